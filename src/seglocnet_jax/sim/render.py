"""Column ray marching of the 2.5D world raster in JAX (cameras and LiDAR share it).

A *column* is a vertical fan of rays from one sensor position along one horizontal azimuth: an
image column of a level camera, or one azimuth step of the spinning LiDAR. The world is sampled
once per column at horizontal distances ``d_s`` (gathers), then each ray (slope ``m``, metres up
per horizontal metre) hits the first sample whose object interval ``[bottom, top]`` contains its
height ``z0 + m d_s``, or the ground plane at ``z0 / -m``, or nothing (sky).

Coordinates inside the compiled functions are *patch-local*: ``(e, n)`` metres east / north of
the patch's north-west corner (``n <= 0`` inside the patch), so float32 stays exact to
millimetres. ``cell0 = (row0, col0)`` is the patch's offset in the world raster (texture hashes
use global cells, so textures do not swim between frames).
"""

from __future__ import annotations

import jax.numpy as jnp

from seglocnet_jax import geometry

SKY, GROUND, THING = 0, 1, 2
TOP, X_FACE, Y_FACE = 0, 1, 2  # which face of a cell a ray entered (roof / east-west / n-s)


def hash01(a, b, c=0):
    """Deterministic integer hash of int32 arrays to float32 in [0, 1)."""
    x = (
        (jnp.asarray(a, jnp.uint32) * jnp.uint32(73856093))
        ^ (jnp.asarray(b, jnp.uint32) * jnp.uint32(19349663))
        ^ (jnp.asarray(c, jnp.uint32) * jnp.uint32(83492791))
    )
    x = (x ^ (x >> 13)) * jnp.uint32(1274126177)
    x = x ^ (x >> 16)
    return (x >> 8).astype(jnp.float32) / jnp.float32(1 << 24)


def march(
    patch: dict,
    pose,
    col_pos,
    col_az,
    slopes,
    dists,
    steps,
    max_range: float,
    resolution: float,
    refine: int = 2,
) -> dict:
    """Ray hits of a fan of columns from one vehicle pose.

    Args:
      patch: ``surface``, ``thing``, ``colour`` (P, P) int32 and ``top``, ``bottom`` (P, P)
        float32 metres.
      pose: (3,) patch-local ``(e, n, yaw)`` of the vehicle.
      col_pos: (C, 3) ego-frame sensor position per column; col_az: (C,) ego azimuth (rad).
      slopes: (C, R) ray slopes; dists, steps: (S,) sample distances and spacing.
      max_range: horizontal metres beyond which nothing is hit.
      resolution: metres per raster cell.
      refine: bisection steps locating an object's surface between two samples.

    Returns a dict of (C, R) arrays: ``kind`` (SKY / GROUND / THING), ``d`` horizontal
    distance, ``z`` hit height above ground, ``e``, ``n`` patch-local hit position, ``cls``
    (surface class for ground hits, thing class for objects), ``colour``, ``face``, and the
    hit cell ``row``, ``col`` (patch cells).
    """
    size = patch["thing"].shape[0]
    sensor = geometry.ego_to_world(pose, col_pos[:, :2])  # (C, 2) patch-local (e, n)
    e0, n0 = sensor[:, 0], sensor[:, 1]  # (C,)
    z0 = col_pos[:, 2]
    theta = pose[2] + col_az
    ce, cn = jnp.cos(theta), jnp.sin(theta)

    def cell(e, n):
        col = jnp.clip(jnp.floor(e / resolution).astype(jnp.int32), 0, size - 1)
        row = jnp.clip(jnp.floor(-n / resolution).astype(jnp.int32), 0, size - 1)
        return row, col

    row_s, col_s = cell(e0[:, None] + dists * ce[:, None], n0[:, None] + dists * cn[:, None])
    flat = row_s * size + col_s  # (C, S)
    thing_s = patch["thing"].reshape(-1)[flat]
    top_s = jnp.where(thing_s > 0, patch["top"].reshape(-1)[flat], -1.0)  # (C, S)
    bot_s = patch["bottom"].reshape(-1)[flat]

    z_ray = z0[:, None, None] + slopes[:, :, None] * dists[None, None, :]  # (C, R, S) fused
    hit = (z_ray <= top_s[:, None, :]) & (z_ray >= bot_s[:, None, :])
    num = dists.shape[0]
    first = jnp.min(jnp.where(hit, jnp.arange(num, dtype=jnp.int32), num), axis=-1)  # (C, R)
    any_hit = first < num
    first_c = jnp.minimum(first, num - 1)
    # The surface lies between the previous sample and this one: bisect ``refine`` times
    # (each halves the error), then report the midpoint.
    lo, hi = dists[first_c] - steps[first_c], dists[first_c]  # (C, R)
    for _ in range(refine):
        mid = 0.5 * (lo + hi)
        r_m, c_m = cell(e0[:, None] + mid * ce[:, None], n0[:, None] + mid * cn[:, None])
        f_m = r_m * size + c_m
        z_m = z0[:, None] + slopes * mid
        inside = (
            (patch["thing"].reshape(-1)[f_m] > 0)
            & (z_m <= patch["top"].reshape(-1)[f_m])
            & (z_m >= patch["bottom"].reshape(-1)[f_m])
        )
        hi, lo = jnp.where(inside, mid, hi), jnp.where(inside, lo, mid)
    d_thing = 0.5 * (lo + hi)
    d_ground = jnp.where(slopes < 0, z0[:, None] / jnp.maximum(-slopes, 1e-6), jnp.inf)
    is_thing = any_hit & (d_thing < d_ground)
    is_ground = ~is_thing & (d_ground <= max_range)
    d = jnp.where(is_thing, d_thing, jnp.where(is_ground, d_ground, max_range))
    e = e0[:, None] + d * ce[:, None]
    n = n0[:, None] + d * cn[:, None]
    z = jnp.where(is_ground, 0.0, z0[:, None] + slopes * d)

    row_g, col_g = cell(e, n)
    # The object's cell is the one at ``hi`` (inside); the ray came from the cell at ``lo``.
    row_t, col_t = cell(e0[:, None] + hi * ce[:, None], n0[:, None] + hi * cn[:, None])
    row_p, _ = cell(e0[:, None] + lo * ce[:, None], n0[:, None] + lo * cn[:, None])
    top_hit = patch["top"].reshape(-1)[row_t * size + col_t]
    z_prev = z0[:, None] + slopes * lo
    face = jnp.where(z_prev > top_hit, TOP, jnp.where(row_p == row_t, X_FACE, Y_FACE))
    row = jnp.where(is_thing, row_t, row_g)
    col = jnp.where(is_thing, col_t, col_g)
    flat_hit = row * size + col
    cls = jnp.where(
        is_thing, patch["thing"].reshape(-1)[flat_hit], patch["surface"].reshape(-1)[flat_hit]
    )
    kind = jnp.where(is_thing, THING, jnp.where(is_ground, GROUND, SKY))
    return {
        "kind": kind,
        "d": d,
        "z": z,
        "e": e,
        "n": n,
        "cls": cls,
        "colour": patch["colour"].reshape(-1)[flat_hit],
        "face": face,
        "row": row,
        "col": col,
    }


def hit_points_ego(hits: dict, col_pos, col_az, slopes):
    """Ego-frame ``(C, R, 3)`` points of the hits (sensor position + ray to the hit)."""
    d = hits["d"]
    x = col_pos[:, 0:1] + d * jnp.cos(col_az)[:, None]
    y = col_pos[:, 1:2] + d * jnp.sin(col_az)[:, None]
    z = col_pos[:, 2:3] + d * slopes
    return jnp.stack([x, y, z], axis=-1)
