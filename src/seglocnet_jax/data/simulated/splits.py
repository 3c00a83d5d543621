"""Spatially disjoint train / val / test splits and seeded evaluation priors.

A frame's BEV (64 m square, ego at the centre) lies within ``BEV_RADIUS = 32 * sqrt(2)`` m of its
pose, so two BEVs cannot overlap when the poses are more than ``2 * BEV_RADIUS`` apart. Splits
are contiguous regions (stripes across the city, test at one seeded end, then val, then train,
sized by frame counts); then frames are dropped by priority: every test frame is kept, a val
frame only if more than ``2 * BEV_RADIUS + margin`` from every test frame, a train frame only if
that far from every kept val/test frame. So each border costs one ~91 m band;
:func:`check_disjoint` verifies the result directly.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial import cKDTree

from seglocnet_jax import geometry

BEV_RADIUS = geometry.BEV_SIZE * geometry.RESOLUTION / 2 * math.sqrt(2)  # 45.25 m


@dataclasses.dataclass(frozen=True)
class SplitPlan:
    """Frames of one split (world metres / radians), in record order.

    Attributes:
      poses: ``(n, 3)`` GT poses.
      priors: ``(n, 2)`` seeded evaluation priors.
      sequence_ids: ``(n,)`` str (object array): each frame's sequence (route or drive).
      frame_index: ``(n,)`` int64 position of each frame in its sequence.
      timestamps: ``(n,)`` float64 seconds.
      sample_ids: one per frame; None: ``"{city}-{name}-{i:06d}"``.
    """

    name: str
    city: str
    poses: np.ndarray
    priors: np.ndarray
    sequence_ids: np.ndarray
    frame_index: np.ndarray
    timestamps: np.ndarray
    sample_ids: tuple[str, ...] | None = None

    def sample_id(self, i: int) -> str:
        if self.sample_ids is not None:
            return self.sample_ids[i]
        return f"{self.city}-{self.name}-{i:06d}"


class SplitError(ValueError):
    """Split assignment failed or violated disjointness; the message says which splits."""


@dataclasses.dataclass(frozen=True)
class SplitConfig:
    """Stripe-based split assignment.

    Attributes:
      stripe_width: width of the assignment stripes across the pool's longer axis, metres.
      margin: extra clearance beyond ``2 * BEV_RADIUS`` between frames of two splits, metres.
    """

    stripe_width: float = 20.0
    margin: float = 1.0

    def __post_init__(self):
        if self.stripe_width <= 0 or self.margin < 0:
            raise ValueError(
                f"split.stripe_width must be > 0 and split.margin >= 0, got "
                f"{self.stripe_width}, {self.margin}"
            )


def assign_stripes(xy: np.ndarray, want: dict[str, int], cfg: SplitConfig, seed: int) -> np.ndarray:
    """Split name per frame before clearance, ``(N,)`` object array.

    The pool's longer axis is cut into stripes ``cfg.stripe_width`` wide; walking from one end
    (seeded), stripes go to the splits in reverse order of ``want`` (test, val, then train) so
    that each split gets a contiguous region holding its share ``want[s] / sum(want)`` of the
    pool's frames. Contiguous regions keep the clearance bands (see :func:`assign_frames`) few.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    names = list(want)[::-1]
    shares = np.array([want[n] for n in names], np.float64)
    if len(xy) == 0 or shares.min() <= 0:
        raise SplitError(f"need frames and positive split sizes, got {len(xy)} frames, {want}")
    axis = int(np.ptp(xy[:, 1]) > np.ptp(xy[:, 0]))  # 0: stripes across east, 1: north
    sign = 1.0 if np.random.default_rng([seed, 0x5B1]).random() < 0.5 else -1.0
    coord = sign * xy[:, axis]
    stripe = np.floor((coord - coord.min()) / cfg.stripe_width).astype(np.int64)  # (N,)
    per_stripe = np.bincount(stripe).astype(np.float64)
    middle = (np.cumsum(per_stripe) - per_stripe / 2) / len(xy)  # frame fraction at the middle
    bounds = np.cumsum(shares / shares.sum())[:-1]
    stripe_split = np.searchsorted(bounds, middle, side="right")  # (num_stripes,)
    return np.array(names, dtype=object)[stripe_split[stripe]]


def assign_frames(
    xy: np.ndarray, labels: np.ndarray, order: list[str], cfg: SplitConfig
) -> np.ndarray:
    """Drops frames for clearance: ``labels`` with ``None`` where a frame is dropped.

    Splits later in ``order`` win: every frame of the last split is kept; a frame of an earlier
    split is kept only if more than ``2 * BEV_RADIUS + margin`` from every kept frame of a later
    split. ``xy`` ``(N, 2)`` world metres.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    out = np.array(labels, dtype=object)
    min_distance = 2 * BEV_RADIUS + cfg.margin
    kept_later = np.zeros((0, 2))
    for name in reversed(order):
        mine = np.flatnonzero(out == name)
        if len(kept_later) and len(mine):
            dist, _ = cKDTree(kept_later).query(xy[mine], k=1)
            out[mine[dist <= min_distance]] = None
            mine = mine[dist > min_distance]
        kept_later = np.concatenate([kept_later, xy[mine]])
    return out


def check_disjoint(xy_by_split: dict[str, np.ndarray], min_distance: float = 2 * BEV_RADIUS):
    """Raises :class:`SplitError` if frames of two different splits are within
    ``min_distance`` metres (i.e. their BEVs could overlap)."""
    names = sorted(xy_by_split)
    for a_i, a in enumerate(names):
        xa = np.asarray(xy_by_split[a], np.float64).reshape(-1, 2)
        if not len(xa):
            continue
        tree = cKDTree(xa)
        for b in names[a_i + 1 :]:
            xb = np.asarray(xy_by_split[b], np.float64).reshape(-1, 2)
            if not len(xb):
                continue
            dist, idx = tree.query(xb, k=1)
            worst = int(np.argmin(dist))
            if dist[worst] <= min_distance:
                raise SplitError(
                    f"splits {a!r} and {b!r} overlap: {b} frame {worst} at {xb[worst]} is "
                    f"{dist[worst]:.1f} m from {a} frame {int(idx[worst])} "
                    f"(need > {min_distance:.1f} m)"
                )


def select_evenly(n_available: int, n: int) -> np.ndarray:
    """``n`` indices spread evenly over ``range(n_available)`` (deterministic)."""
    if n > n_available:
        raise SplitError(f"requested {n} frames but only {n_available} are available")
    return np.floor(np.arange(n) * (n_available / max(n, 1))).astype(np.int64)
