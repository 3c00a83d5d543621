"""Several hypotheses: a bank of windows per drive, weighted by their evidence.

One window of ``N x N`` cells holds the truth only while the truth stays within ``N / 2``
cells of the window's mode. The first frame of a drive is where that fails: its posterior is
the frame's likelihood over the whole prior box, and when its strongest peak is a look-alike
street at the far side of the box, the window re-centres there and the truth's cells are gone
for good (docs/sequential.md). With ``TrackerConfig.hypotheses`` > 1 the first frame's
posterior is split instead among windows that cover its strongest modes
(:func:`split_modes`: the first is the single window's, the others take what it leaves out).
The belief is then the mixture ``sum_i w_i b_i`` of the windows' beliefs ``b_i`` (each
normalized over its own cells), and the weights follow Bayes' rule exactly:

* predict: ``w_i *= 1 - dropped_i`` (the mass that left window ``i``);
* update: ``w_i *= sum_cells b_i * exp(log_lik_i)`` (``update``'s ``log_evidence``: the
  windows' score volumes are one frame's scores on one map, so they are comparable);
* the weights are renormalized; a window more than ``hypothesis_prune`` nats below the best
  is dropped (:func:`prune_and_merge`), and two windows whose modes meet are merged (their
  weights added, the lighter one's cells dropped: they describe the same place).

The filter's estimate is the mode of the heaviest window; the credible regions are the
mixture's (:func:`mixture_readout`). A window whose update detects a track loss is re-widened
by ``update`` as a single window would be; its weight takes the evidence of the prior it had.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.tracking.belief import Belief, TrackerConfig
from seglocnet_jax.tracking.motion import recentre


@jax.jit
def _peak_map(prob):
    """``max_k prob[k]``: ``(N, N)``."""
    return prob.max(axis=0)


@jax.jit
def _masked(prob, mask):
    """``prob * mask`` over (x, y) and its mass (per slice first: XLA CPU)."""
    part = prob * mask[None]
    return part, part.sum(axis=(1, 2)).sum()


def split_modes(belief: Belief, cfg: TrackerConfig) -> list[tuple[Belief, float]]:
    """The belief split into up to ``cfg.hypotheses`` windows that cover it greedily.

    The first window is centred on the belief's mode (the strongest (x, y) cell over yaw) and
    takes every cell it covers: it is the one window a single-window filter would move to.
    Each next window is centred on the strongest cell no window covers yet and takes the
    uncovered cells it covers. The parts partition the belief (no cell is in two windows);
    cells left over once ``cfg.hypotheses`` windows are placed are dropped, and so is a part
    more than ``cfg.hypothesis_prune`` nats lighter than the first. Returns ``(belief, log
    weight)`` per window, the first first: the weight is the part's mass.
    """
    n, c = cfg.size, cfg.centre
    peak = np.array(jax.device_get(_peak_map(belief.prob)), np.float64)  # (N, N)
    covered = np.zeros((n, n), bool)
    out = []
    while len(out) < cfg.hypotheses:
        work = np.where(covered, 0.0, peak)
        if work.max() <= 0.0:
            break
        h, w = divmod(int(np.argmax(work)), n)
        mask = np.zeros((n, n), bool)
        mask[max(0, h - c) : h + c + 1, max(0, w - c) : w + c + 1] = True  # its window
        mask &= ~covered
        covered |= mask
        part, mass = _masked(belief.prob, jnp.asarray(mask, jnp.float32))
        mass = float(mass)
        if mass <= 0.0 or (out and math.log(mass) < out[0][1] - cfg.hypothesis_prune):
            continue
        piece, _ = recentre(belief._replace(prob=part / mass), (h - c, w - c), cfg)
        out.append((piece, math.log(mass)))  # the part lies inside the new window
    return out


def normalize(log_w) -> np.ndarray:
    """Log weights minus their log-sum-exp (float64)."""
    log_w = np.asarray(log_w, np.float64)
    top = log_w.max()
    return log_w - (top + np.log(np.exp(log_w - top).sum()))


def prune_and_merge(log_w, map_poses, cfg: TrackerConfig) -> tuple[list[int], np.ndarray]:
    """Which windows to keep, heaviest first, and their normalized log weights.

    Args:
      log_w: ``(M,)`` log weights.
      map_poses: ``(M, 3)`` world ``(x, y, yaw)`` of each window's mode.

    A window ``hypothesis_prune`` nats or more below the heaviest is dropped. A window whose
    mode lies within ``peak_radius`` m (per axis) and two yaw bins of a heavier one's is
    merged into it (its weight added): both hold the same place.
    """
    log_w = normalize(log_w)
    poses = np.asarray(map_poses, np.float64).reshape(len(log_w), 3)
    order = np.argsort(-log_w, kind="stable")
    bin_width = 2 * math.pi / cfg.num_rotations
    kept: list[int] = []
    merged: dict[int, list[float]] = {}
    for i in order:
        if log_w[i] < log_w[order[0]] - cfg.hypothesis_prune:
            continue
        into = next(
            (
                j
                for j in kept
                if np.abs(poses[i, :2] - poses[j, :2]).max() <= cfg.peak_radius
                and abs(float(geometry.wrap_angle(poses[i, 2] - poses[j, 2]))) <= 2 * bin_width
            ),
            None,
        )
        if into is None:
            kept.append(int(i))
            merged[int(i)] = [log_w[i]]
        else:
            merged[into].append(log_w[i])
    new = np.array([np.logaddexp.reduce(merged[i]) for i in kept])
    return kept, normalize(new)


@functools.partial(jax.jit, static_argnames="cfg")
def _gt_prob(belief: Belief, gt_cell, cfg: TrackerConfig):
    """The belief at the GT cell ``(k, h, w)`` (int; 0 outside the window), and whether inside."""
    n = cfg.size
    inside = (gt_cell[1] >= 0) & (gt_cell[1] < n) & (gt_cell[2] >= 0) & (gt_cell[2] < n)
    p = belief.prob[
        gt_cell[0] % cfg.num_rotations,
        jnp.clip(gt_cell[1], 0, n - 1),
        jnp.clip(gt_cell[2], 0, n - 1),
    ]
    return jnp.where(inside, p, 0.0), inside


@jax.jit
def _mass_above(prob, threshold):
    """Mass of the cells strictly more probable than ``threshold``."""
    return jnp.sum(jnp.where(prob > threshold, prob, 0.0))


def mixture_readout(beliefs, log_w, gt_cells, cfg: TrackerConfig, floor: float):
    """The mixture ``sum_i w_i b_i`` at the GT: ``(above, log_p)``.

    ``above``: the mixture's mass of the cells more probable than the GT's (the GT is in the
    credible region of mass ``m`` iff ``above < m``; inf when no window holds the GT);
    ``log_p``: log of the mixture at the GT cell (``log floor`` at the least, and when no
    window holds it). ``gt_cells``: per window, the GT's rounded cell ``(k, h, w)``.
    Overlapping windows are summed as they are (a cell held by two windows counts twice).
    """
    w = np.exp(normalize(log_w))
    probs, inside = zip(
        *(
            _gt_prob(b, jnp.asarray(c, jnp.int32), cfg)
            for b, c in zip(beliefs, gt_cells, strict=True)
        ),
        strict=False,
    )
    if not any(bool(v) for v in inside):
        return math.inf, math.log(floor)
    p = float(sum(wi * float(pi) for wi, pi in zip(w, probs, strict=True)))
    above = sum(
        # a threshold above 1 (a light window): no cell of it is above; min() keeps float32 finite
        wi * float(_mass_above(b.prob, np.float32(min(p / wi, 2.0))))
        for wi, b in zip(w, beliefs, strict=True)
        if wi > 0
    )
    return above, math.log(max(p, floor))
