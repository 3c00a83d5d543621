"""Spinning LiDAR returns from ray hits (:func:`render.march`): range noise, dropout and
intensity by material, as ego-frame ``(x, y, z, intensity)`` float32."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from seglocnet_jax.sim import classes as cl
from seglocnet_jax.sim.render import GROUND, SKY, THING


def returns(
    hits: dict,
    points_ego,
    sensor_pos,
    key,
    *,
    range_noise: float,
    dropout: float,
    intensity_noise: float,
    max_range: float,
) -> dict:
    """LiDAR returns of one sweep.

    Args:
      hits: :func:`render.march` output for the LiDAR columns, (C, R) arrays.
      points_ego: (C, R, 3) exact ego-frame hit points.
      sensor_pos: (3,) LiDAR position in the ego frame.
      key: PRNG key (noise and dropout).

    Returns:
      ``points`` (C*R, 4) float32 (x, y, z m ego frame, intensity in [0, 1]), ``valid``
      (C*R,) bool, ``thing`` (C*R,) int32 object class of the hit (0 for ground / no hit).
    """
    k_range, k_drop, k_int = jax.random.split(key, 3)
    kind, cls, d = hits["kind"], hits["cls"], hits["d"]
    offset = points_ego - sensor_pos  # (C, R, 3)
    rng = jnp.linalg.norm(offset, axis=-1)
    noisy = rng + range_noise * jax.random.normal(k_range, rng.shape)
    pts = sensor_pos + offset * (noisy / jnp.maximum(rng, 1e-6))[..., None]

    refl = jnp.where(
        kind == THING,
        jnp.asarray(cl.THING_INTENSITY)[jnp.clip(cls, 0, len(cl.Thing) - 1)],
        jnp.asarray(cl.SURFACE_INTENSITY)[jnp.clip(cls, 0, len(cl.Surface) - 1)],
    )
    intensity = refl * (1.0 - 0.3 * d / max_range)
    intensity = intensity + intensity_noise * jax.random.normal(k_int, d.shape)
    intensity = jnp.clip(intensity, 0.0, 1.0)
    # Dark, far returns drop out more often.
    p_drop = dropout * (1.0 + (1.0 - refl) * d / max_range)
    valid = (kind != SKY) & (jax.random.uniform(k_drop, d.shape) >= p_drop) & (rng < max_range)
    valid = valid & ((kind == GROUND) | (kind == THING))
    out = jnp.concatenate([pts, intensity[..., None]], axis=-1).reshape(-1, 4)
    thing = jnp.where(kind == THING, cls, 0).reshape(-1)
    return {
        "points": out.astype(jnp.float32),
        "valid": valid.reshape(-1),
        "thing": thing.astype(jnp.int32),
    }
