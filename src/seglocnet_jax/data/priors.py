"""Each record's evaluation prior (the ``prior`` field of :mod:`.records`): seeded, so a dataset
evaluates every model from the same coarse starts. Every writer of a dataset draws them here
(:mod:`.writer`, the simulator's plans in :mod:`.simulated`)."""

from __future__ import annotations

import numpy as np

from seglocnet_jax import geometry


def seeded_priors(xy: np.ndarray, seed: int, stream: int) -> np.ndarray:
    """Fixed evaluation priors: ``xy + U[-PRIOR_RANGE, PRIOR_RANGE]`` per axis, metres ``(N, 2)``.

    ``stream`` separates splits (e.g. an index of the split name) so they draw independently.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    return geometry.sample_priors(xy, np.random.default_rng([seed, stream, 0x9A1]))
