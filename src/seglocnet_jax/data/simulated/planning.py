"""Which frames a prepared dataset holds: the driven pool of a city and its split plans
(train / val / test disjoint in the main city, the test city's generalization split), with
seeded priors. Pure functions of the config and the frame source; :mod:`.prepare` writes them."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from seglocnet_jax.data.priors import seeded_priors
from seglocnet_jax.data.simulated import splits as sp
from seglocnet_jax.data.simulated.splits import SplitPlan
from seglocnet_jax.maps import city_key

if TYPE_CHECKING:
    from seglocnet_jax.data.simulated.config import FrameSource, PrepareConfig


def _seed(*parts: int) -> int:
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])


@dataclasses.dataclass(frozen=True)
class Pool:
    """Driven frames: ``poses`` (n, 3) and each frame's sequence metadata (n,)."""

    poses: np.ndarray
    sequence_ids: np.ndarray  # str (object array)
    frame_index: np.ndarray  # int64
    timestamps: np.ndarray  # float64 seconds

    def __add__(self, other: Pool) -> Pool:
        pairs = zip(self.fields(), other.fields(), strict=True)
        return Pool(*(np.concatenate([a, b]) for a, b in pairs))

    def fields(self) -> tuple:
        return self.poses, self.sequence_ids, self.frame_index, self.timestamps

    def take(self, idx: np.ndarray) -> Pool:
        return Pool(*(a[idx] for a in self.fields()))


EMPTY_POOL = Pool(np.zeros((0, 3)), np.zeros(0, object), np.zeros(0, np.int64), np.zeros(0))


def _drive_pool(
    source: FrameSource, seed: int, city_idx: int, round_: int, n: int, city: str
) -> Pool:
    rng = np.random.default_rng([seed, city_idx, round_, 0xD21])
    routes = getattr(source, "drive_routes", None)
    traj = routes(rng, n) if routes is not None else None
    poses = np.asarray(source.drive(rng, n) if traj is None else traj.poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or not np.all(np.isfinite(poses)):
        raise ValueError(f"frame source drive() returned {poses.shape} poses, expected (n, 3)")
    if traj is None:  # no routes known: every frame is a sequence of its own
        seq = [f"{city}-p{round_}-frame{i:06d}" for i in range(len(poses))]
        return Pool(
            poses, np.array(seq, object), np.zeros(len(poses), np.int64), np.zeros(len(poses))
        )
    seq = [f"{city}-p{round_}-route{int(r):05d}" for r in traj.route]
    return Pool(
        poses,
        np.array(seq, object),
        np.asarray(traj.index, np.int64),
        np.asarray(traj.timestamps, np.float64),
    )


def _plan(name: str, city: str, pool: Pool, priors: np.ndarray) -> SplitPlan:
    return SplitPlan(
        name,
        city,
        pool.poses,
        priors,
        sequence_ids=pool.sequence_ids,
        frame_index=pool.frame_index,
        timestamps=pool.timestamps,
    )


def plan_main_city(source: FrameSource, cfg: PrepareConfig) -> list[SplitPlan]:
    """Train / val / test frames of ``cfg.city``: disjoint BEVs, seeded priors."""
    want = {"train": cfg.num_train, "val": cfg.num_val, "test": cfg.num_test}
    names = list(want)
    per_round = int(np.ceil(cfg.pool_factor * sum(want.values())))
    key = city_key(cfg.city)
    pool = EMPTY_POOL
    for round_ in range(cfg.max_rounds):
        pool = pool + _drive_pool(source, cfg.seed, 0, round_, per_round, key)
        labels = sp.assign_stripes(pool.poses[:, :2], want, cfg.split, cfg.seed)
        labels = sp.assign_frames(pool.poses[:, :2], labels, names, cfg.split)
        avail = {n: np.flatnonzero(labels == n) for n in want}
        if all(len(avail[n]) >= want[n] for n in want):
            break
    else:
        have = {n: len(avail[n]) for n in want}
        raise sp.SplitError(
            f"{cfg.city}: after {cfg.max_rounds} rounds of {per_round} poses the splits hold "
            f"{have}, need {want}; raise data.max_rounds / data.pool_factor or lower the counts"
        )
    plans = []
    for stream, name in enumerate(names):
        idx = avail[name][sp.select_evenly(len(avail[name]), want[name])]
        frames = pool.take(idx)
        priors = seeded_priors(frames.poses[:, :2], cfg.seed, stream)
        plans.append(_plan(name, key, frames, priors))
    sp.check_disjoint({p.name: p.poses[:, :2] for p in plans})
    return plans


def plan_test_city(source: FrameSource, cfg: PrepareConfig) -> SplitPlan:
    """The generalization split: ``cfg.num_test_city`` frames spread over one drive."""
    n = cfg.num_test_city
    key = city_key(cfg.test_city)  # split and city named by the key (a path is no name)
    pool = _drive_pool(source, cfg.seed, 1, 0, int(np.ceil(cfg.pool_factor * n)), key)
    frames = pool.take(sp.select_evenly(len(pool.poses), n))
    priors = seeded_priors(frames.poses[:, :2], cfg.seed, 3)
    return _plan(key, key, frames, priors)
