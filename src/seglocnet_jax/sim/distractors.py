"""Things no map has: parked cars, trees, poles and pedestrians beside the world's roads.

Placed by a seeded Poisson process along both sides of every road (world metres), then dropped
where they would touch the drivable area or a building. Each object is one or two shapely
footprints with a height interval ``[bottom, top]`` (metres above ground), a class and a colour.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import shapely

from seglocnet_jax.sim.classes import TRUNK_COLOUR, Thing


@dataclasses.dataclass(frozen=True)
class Distractors:
    """Object parts, in rasterization order (later parts overwrite earlier ones).

    Attributes:
      geoms: (M,) shapely footprints, world metres.
      thing: (M,) ``Thing`` class; top, bottom: (M,) metres; colour: (M,) colour id.
    """

    geoms: np.ndarray
    thing: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    colour: np.ndarray


def _along(roads, rng, per_100m: float):
    """Random stations on road sides: (centre xy (n, 2), tangent (n, 2), side (n,), road idx)."""
    xy, tan, side, idx = [], [], [], []
    for i, road in enumerate(roads):
        c = road.centerline
        seg = np.diff(c, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        for s in (-1.0, 1.0):
            n = rng.poisson(cum[-1] / 100.0 * per_100m)
            if n == 0:
                continue
            st = rng.uniform(0, cum[-1], n)
            k = np.clip(np.searchsorted(cum, st) - 1, 0, len(seg) - 1)
            t = seg[k] / np.maximum(seg_len[k], 1e-9)[:, None]
            frac = ((st - cum[k]) / np.maximum(seg_len[k], 1e-9))[:, None]
            xy.append(c[k] + frac * seg[k])
            tan.append(t)
            side.append(np.full(n, s))
            idx.append(np.full(n, i))
    if not xy:
        z = np.zeros((0, 2))
        return z, z, np.zeros(0), np.zeros(0, np.int64)
    return np.concatenate(xy), np.concatenate(tan), np.concatenate(side), np.concatenate(idx)


def _offset(roads, xy, tan, side, idx, lateral):
    half = np.array([roads[i].width / 2 for i in idx])
    normal = np.stack([-tan[:, 1], tan[:, 0]], axis=1)  # left of the way direction
    return xy + (side * (half + lateral))[:, None] * normal


def _boxes(centre, tan, length, width):
    """Oriented rectangles (n,) from centres, unit tangents and sizes (metres)."""
    n = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    corners = [(1, 1), (1, -1), (-1, -1), (-1, 1), (1, 1)]
    pts = np.stack(
        [centre + a * tan * length[:, None] / 2 + b * n * width[:, None] / 2 for a, b in corners],
        axis=1,
    )  # (n, 5, 2)
    return shapely.polygons(pts)


def place(roads, drivable, buildings, rng: np.random.Generator, cfg) -> Distractors:
    """Seeded distractors for the world's ``roads`` (``cfg``: a ``WorldConfig``)."""
    min_r = 0.6 * cfg.resolution  # thinner objects would not cover a raster cell centre
    parts: list[tuple] = []  # (geoms, thing, top, bottom, colour)

    xy, tan, side, idx = _along(roads, rng, cfg.cars_per_100m)
    n = len(xy)
    if n:
        width = rng.uniform(1.7, 1.95, n)
        centre = _offset(roads, xy, tan, side, idx, width / 2 + rng.uniform(0.2, 0.5, n))
        van = rng.uniform(size=n) < 0.15
        parts.append(
            (
                _boxes(centre, tan, rng.uniform(4.0, 4.9, n) + van * 1.0, width),
                Thing.CAR,
                rng.uniform(1.4, 1.7, n) + van * 0.7,
                np.zeros(n),
                rng.integers(0, 256, n),
            )
        )

    xy, tan, side, idx = _along(roads, rng, cfg.trees_per_100m)
    n = len(xy)
    if n:
        centre = _offset(roads, xy, tan, side, idx, cfg.sidewalk_width + rng.uniform(1.0, 3.0, n))
        radius = rng.uniform(1.5, 3.0, n)
        top = rng.uniform(6.0, 12.0, n)
        pts = shapely.points(centre)
        parts.append(
            (
                shapely.buffer(pts, radius),
                Thing.TREE,
                top,
                rng.uniform(2.0, 3.0, n),
                rng.integers(0, TRUNK_COLOUR, n),
            )
        )
        parts.append(
            (
                shapely.buffer(pts, max(0.25, min_r)),
                Thing.TREE,
                top,
                np.zeros(n),
                np.full(n, TRUNK_COLOUR),
            )
        )

    xy, tan, side, idx = _along(roads, rng, cfg.poles_per_100m)
    n = len(xy)
    if n:
        centre = _offset(roads, xy, tan, side, idx, rng.uniform(0.4, 0.7, n))
        parts.append(
            (
                shapely.buffer(shapely.points(centre), max(0.12, min_r)),
                Thing.POLE,
                rng.uniform(4.5, 8.0, n),
                np.zeros(n),
                np.zeros(n, np.int64),
            )
        )

    xy, tan, side, idx = _along(roads, rng, cfg.pedestrians_per_100m)
    n = len(xy)
    if n:
        centre = _offset(
            roads, xy, tan, side, idx, rng.uniform(0.8, max(1.0, cfg.sidewalk_width - 0.3), n)
        )
        parts.append(
            (
                shapely.buffer(shapely.points(centre), max(0.28, min_r)),
                Thing.PEDESTRIAN,
                rng.uniform(1.5, 1.95, n),
                np.zeros(n),
                rng.integers(0, 256, n),
            )
        )

    if not parts:
        e = np.zeros(0)
        return Distractors(np.zeros(0, object), e.astype(np.uint8), e, e, e.astype(np.uint8))
    geoms = np.concatenate([p[0] for p in parts])
    thing = np.concatenate([np.full(len(p[0]), int(p[1])) for p in parts]).astype(np.uint8)
    top = np.concatenate([p[2] for p in parts])
    bottom = np.concatenate([p[3] for p in parts])
    colour = np.concatenate([p[4] for p in parts]).astype(np.uint8)
    obstacles = list(shapely.get_parts(drivable)) + list(buildings)
    # The tree holds the small objects and the obstacles query it: the predicate then runs on
    # each (prepared) obstacle once instead of on the whole drivable area per object (same
    # pairs, ~50x faster).
    hit = np.unique(shapely.STRtree(geoms).query(obstacles, predicate="intersects")[1])
    keep = np.ones(len(geoms), bool)
    keep[hit] = False
    # A trunk goes with its canopy: drop both if either is dropped.
    is_tree = thing == Thing.TREE
    if is_tree.any():
        t_idx = np.flatnonzero(is_tree)
        half = len(t_idx) // 2
        pair = keep[t_idx[:half]] & keep[t_idx[half:]]
        keep[t_idx[:half]] = pair
        keep[t_idx[half:]] = pair
    return Distractors(geoms[keep], thing[keep], top[keep], bottom[keep], colour[keep])
