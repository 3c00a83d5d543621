"""Drive splits of a simulated dataset: whole continuous drives for sequential localization.

* ``drives``: ``num_drives`` drives of ``drive_length_m`` metres in the test city (never trained
  on), a frame every ``drive_spacing_m`` metres. A drive that gets stuck before its full length
  (a one-way road that ends: :func:`sim.trajectory.route`) is drawn again from another start.
* ``drives_val``: ``num_val_drives`` drives in the main city whose every frame is more than
  ``2 * BEV_RADIUS + split.margin`` from every train frame (no BEV overlaps training data):
  candidate routes of ``VAL_ROUTE_FACTOR * drive_length_m`` metres are cut into maximal
  contiguous runs of clear frames, and the longest run of each route is kept if it spans at
  least ``min_val_drive_m`` (cut to its first ``drive_length_m``). They may overlap val / test
  frames (they only must stay clear of train).
* ``drives_val_unseen``: ``num_unseen_val_drives`` drives in the test city, chosen the same way
  but clear of every frame of ``drives`` and of the test city's single-frame split: validation
  drives in a city the model was never trained on, for the sequential settings that a
  training-city validation cannot decide (the first lock of a model that has not seen the city).
  They share the city with the test drives, not a place: no frame's BEV overlaps a test frame's.

Records of a drive split are ordered by drive, then frame; drive ``d`` is the sequence
``"{city}-{split}-d{d:03d}"`` with frames ``frame_index`` 0..n-1 (``sample_id``
``"{city}-{split}-d{d:03d}-{i:06d}"``) and ``timestamp`` = distance from the drive's first frame
/ ``sim.NOMINAL_SPEED_MPS``. Every frame gets a seeded prior (``priors.seeded_priors``; stream 4
for ``drives``, 5 for ``drives_val``): the first frame's is the drive's coarse start prior, and
the others let single-frame localization run on the same frames.

Each drive draws from its own random stream (``[seed, city, drive or candidate, attempt, tag]``),
separate from the pool of the train / val / test / test-city splits, so adding drives changes no
other split's frames. A frame source provides ``route(rng, length_m, spacing_m)`` returning an
object with ``poses`` ``(n, 3)`` and ``timestamps`` ``(n,)`` seconds (``sim.Trajectory``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from seglocnet_jax.data.priors import seeded_priors
from seglocnet_jax.data.simulated import splits as sp

DRIVES, VAL_DRIVES, UNSEEN_VAL_DRIVES = "drives", "drives_val", "drives_val_unseen"
# seeded_priors streams (0-3: the other splits)
DRIVE_STREAMS = {DRIVES: 4, VAL_DRIVES: 5, UNSEEN_VAL_DRIVES: 6}
MAX_STARTS = 50  # starts tried per test-city drive before giving up
VAL_ROUTE_FACTOR = 2.0  # candidate drives_val routes are this many drive lengths long
VAL_ROUTES_PER_DRIVE = 100  # candidate routes tried per requested drives_val drive


def drive_frames(length_m: float, spacing_m: float) -> int:
    """Frames of a full drive: one every ``spacing_m`` over ``length_m`` metres, both ends."""
    return int(np.floor(length_m / spacing_m + 1e-9)) + 1


def _route(source, rng, length_m: float, spacing_m: float, city: str):
    route = getattr(source, "route", None)
    if route is None:
        raise TypeError(
            f"the frame source of {city!r} ({type(source).__name__}) has no route(rng, "
            "length_m, spacing_m) method, which the drive splits need; set data.num_drives=0 "
            "and data.num_val_drives=0"
        )
    traj = route(rng, length_m, spacing_m)
    poses = np.asarray(traj.poses, np.float64).reshape(-1, 3)
    stamps = np.asarray(traj.timestamps, np.float64).reshape(-1)
    if len(stamps) != len(poses) or not np.all(np.isfinite(poses)):
        raise ValueError(f"frame source route() returned {poses.shape} poses, {stamps.shape} times")
    return poses, stamps


def _plan(name: str, city: str, drives: list, seed: int) -> sp.SplitPlan:
    """The split plan of ``drives`` (``[(poses (n, 3), timestamps (n,))]``), drive by drive."""
    poses = np.concatenate([p for p, _ in drives])
    seq, index, stamps, ids = [], [], [], []
    for d, (p, t) in enumerate(drives):
        seq += [f"{city}-{name}-d{d:03d}"] * len(p)
        index.append(np.arange(len(p), dtype=np.int64))
        stamps.append(t - t[0])
        ids += [f"{city}-{name}-d{d:03d}-{i:06d}" for i in range(len(p))]
    return sp.SplitPlan(
        name,
        city,
        poses,
        seeded_priors(poses[:, :2], seed, DRIVE_STREAMS[name]),
        sequence_ids=np.array(seq, dtype=object),
        frame_index=np.concatenate(index),
        timestamps=np.concatenate(stamps),
        sample_ids=tuple(ids),
    )


def plan_drives(source, cfg, city: str) -> sp.SplitPlan:
    """``cfg.num_drives`` full-length drives in the test city ``city`` (a city key)."""
    want = drive_frames(cfg.drive_length_m, cfg.drive_spacing_m)
    drives = []
    for d in range(cfg.num_drives):
        for attempt in range(MAX_STARTS):
            rng = np.random.default_rng([cfg.seed, 1, d, attempt, 0xD51])
            poses, stamps = _route(source, rng, cfg.drive_length_m, cfg.drive_spacing_m, city)
            if len(poses) >= want:
                drives.append((poses[:want], stamps[:want]))
                break
        else:
            raise sp.SplitError(
                f"{city}: drive {d} got stuck (a one-way dead end) before "
                f"data.drive_length_m={cfg.drive_length_m:g} m from {MAX_STARTS} starts; lower "
                "data.drive_length_m or data.num_drives"
            )
    return _plan(DRIVES, city, drives, cfg.seed)


def clear_runs(ok: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``[(start, stop)]`` of consecutive True in the boolean ``ok`` ``(n,)``."""
    edges = np.diff(np.concatenate([[0], np.asarray(ok, np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def plan_val_drives(
    source, cfg, city: str, train_xy: np.ndarray, *, name: str = VAL_DRIVES
) -> sp.SplitPlan:
    """Validation drives in ``city`` clear of every frame in ``train_xy`` (``(n, 2)`` world
    metres): ``cfg.num_val_drives`` of them in the main city clear of train (``name`` =
    ``drives_val``), or ``cfg.num_unseen_val_drives`` in the test city clear of its test frames
    (``drives_val_unseen``); see the module docstring."""
    count, key, tag = {
        VAL_DRIVES: (cfg.num_val_drives, "num_val_drives", 0xD52),
        UNSEEN_VAL_DRIVES: (cfg.num_unseen_val_drives, "num_unseen_val_drives", 0xD53),
    }[name]
    what = "train" if name == VAL_DRIVES else "test"
    spacing, cap = cfg.drive_spacing_m, drive_frames(cfg.drive_length_m, cfg.drive_spacing_m)
    need = drive_frames(cfg.min_val_drive_m, spacing)
    clearance = 2 * sp.BEV_RADIUS + cfg.split.margin
    tree = cKDTree(np.asarray(train_xy, np.float64).reshape(-1, 2))
    drives, longest = [], 0
    tries = VAL_ROUTES_PER_DRIVE * count
    for attempt in range(tries):
        rng = np.random.default_rng([cfg.seed, 0, attempt, tag])
        poses, stamps = _route(source, rng, VAL_ROUTE_FACTOR * cfg.drive_length_m, spacing, city)
        dist, _ = tree.query(poses[:, :2], k=1)
        runs = clear_runs(dist > clearance)
        if not runs:
            continue
        a, b = max(runs, key=lambda r: r[1] - r[0])  # the first of the longest
        longest = max(longest, b - a)
        if b - a >= need:
            b = min(b, a + cap)
            drives.append((poses[a:b], stamps[a:b]))
            if len(drives) == count:
                return _plan(name, city, drives, cfg.seed)
    longest_m = max(longest - 1, 0) * spacing
    raise sp.SplitError(
        f"{city}: found {len(drives)} of data.{key}={count} {name} "
        f"drives of >= data.min_val_drive_m={cfg.min_val_drive_m:g} m whose frames all stay "
        f"> {clearance:.1f} m from every {what} frame, in {tries} candidate routes (longest clear "
        f"run {longest_m:g} m); lower data.min_val_drive_m or data.{key}"
        + (
            ", or give the val / test regions more room (data.num_val, data.num_test)"
            if name == VAL_DRIVES
            else ", data.num_drives or data.num_test_city"
        )
        + f", or set data.{key}=0"
    )
