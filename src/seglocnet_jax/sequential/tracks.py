"""Drives of a split and tracking them in lockstep through the filter and the localize step
(see the package docstring)."""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import time
import zlib

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import geometry, solver, tracking
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.data.manifest import read_manifest, split_files
from seglocnet_jax.evaluation import TRACKER_MOTION_FIELDS, EvalConfig, LocalizeStep
from seglocnet_jax.tracking import odometry as odometry_lib

WARMUP_STEPS = 2  # lockstep steps left out of the per-frame timings (compilation)
# The log posterior of the GT cell is clamped here (and is this outside the window): ~12 nats
# below a uniform belief over the 4.3 M cells, so that one frame off the window does not
# dominate a mean over a drive.
LOG_P_FLOOR_P = 1e-12
LOG_P_FLOOR = float(np.log(LOG_P_FLOOR_P))


def tracker_config(eval_cfg: EvalConfig, num_rotations: int) -> tracking.TrackerConfig:
    """The filter's config: ``eval.tracker`` with its null motion-noise fields derived from
    ``eval.odometry`` (:func:`tracking.odometry.tracker_noise` for frames 0.5 s apart: the
    simulator's 5 m at 10 m/s, nuScenes keyframes at 2 Hz), the solver's K and the geometry's
    window (129 cells at 0.5 m). One config per run: the kernels compile once."""
    section = dataclasses.asdict(eval_cfg.tracker)
    derived = odometry_lib.tracker_noise(eval_cfg.odometry)
    for key in TRACKER_MOTION_FIELDS:
        if section[key] is None:
            section[key] = float(derived[key])
    return tracking.TrackerConfig(num_rotations=num_rotations, **section)


def drive_seed(odometry_seed: int, sequence_id: str) -> int:
    """The odometry seed of one drive: independent of which other drives are tracked."""
    crc = zlib.crc32(sequence_id.encode())
    return int(np.random.SeedSequence([int(odometry_seed), crc]).generate_state(1)[0])


@dataclasses.dataclass
class Drive:
    """One sequence of a split, in ``frame_index`` order.

    Attributes:
      sequence_id, city: the sequence and its city key.
      records: ``(T,)`` record indices in the split (file order).
      frame_index: ``(T,)``; timestamps: ``(T,)`` seconds.
      poses: ``(T, 3)`` GT world poses (scoring and the odometry simulation only).
      priors: ``(T, 2)`` stored priors (frame 0's starts the filter; each one the single-frame
        protocol).
    """

    sequence_id: str
    city: str
    records: np.ndarray
    frame_index: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    priors: np.ndarray

    def __len__(self) -> int:
        return len(self.records)

    def distance(self) -> np.ndarray:
        """``(T,)`` metres driven (GT) up to each frame."""
        steps = np.hypot(*np.diff(self.poses[:, :2], axis=0).T)
        return np.concatenate([[0.0], np.cumsum(steps)])


class DriveSplit:
    """Random access to the frames of a split, grouped into :class:`Drive` s."""

    def __init__(self, dataset_dir: str, split: str, map_variant: str, loader_cfg, *, threads=1):
        man = read_manifest(dataset_dir)
        self.name = split
        self.source = loader_lib.ShardSource(split_files(man, dataset_dir, split))
        cities = sorted(man["splits"][split]["cities"])
        self.rasters = loader_lib.load_rasters(dataset_dir, map_variant, cities)
        self.transform = loader_lib.FrameTransform(self.rasters, loader_cfg.max_points, train=False)
        self.pool = concurrent.futures.ThreadPoolExecutor(max(1, threads))
        self.drives = self._index()

    def _index(self) -> list[Drive]:
        groups: dict[str, list] = collections.OrderedDict()
        n = len(self.source)
        for i, s in enumerate(self.pool.map(self.source.__getitem__, range(n))):
            row = (i, int(s["frame_index"]), float(s["timestamp"]), s["pose"], s["prior"])
            groups.setdefault((str(s["sequence_id"]), str(s["city"])), []).append(row)
        drives = []
        for (sid, city), rows in groups.items():
            rows.sort(key=lambda r: r[1])
            drives.append(
                Drive(
                    sequence_id=sid,
                    city=city,
                    records=np.array([r[0] for r in rows], np.int64),
                    frame_index=np.array([r[1] for r in rows], np.int64),
                    timestamps=np.array([r[2] for r in rows], np.float64),
                    poses=np.stack([np.asarray(r[3], np.float64) for r in rows]),
                    priors=np.stack([np.asarray(r[4], np.float64) for r in rows]),
                )
            )
        return drives

    def rows(self, indices) -> list[dict]:
        """Batch rows (the loader's, tile around the stored prior) of the given records."""
        return list(self.pool.map(lambda i: self.transform(self.source[int(i)]), indices))

    def close(self) -> None:
        self.pool.shutdown()


def filter_tile(raster, belief: tracking.Belief, cfg: tracking.TrackerConfig):
    """The map tile of the belief's window, ``(C, 256, 256)``, and its centre (world m): the
    raster cut around the filter's estimate (equal to ``raster.tile(*centre)``)."""
    tile = geometry.crop(raster.mask, *tracking.tile_corner(belief, cfg), cfg.tile_size)
    return tile, tracking.window_centre(belief, cfg)


def start_belief(raster, prior_xy, cfg: tracking.TrackerConfig) -> tracking.Belief:
    """Frame 0's belief: uniform over the window around the coarse prior (the prior box) and
    over yaw, on the lattice of the raster's pixel corners."""
    grid = raster.grid
    return tracking.init_belief(cfg, prior_xy, origin=(grid.x_min, grid.y_max))


@functools.partial(jax.jit, static_argnames="cfg")
def _readout(belief: tracking.Belief, map_cell, gt_pose, cfg: tracking.TrackerConfig):
    """The posterior mode ``map_cell`` refined to sub-cell (the solver's parabolas on the log
    posterior), as a world pose, and the posterior mass of the cells strictly more probable
    than the GT cell (inf when the GT is outside the window): the GT is in the credible region
    of mass ``m`` iff that mass is below ``m`` (``tracking.in_credible_region`` for every mass
    at once), and the log posterior of the GT cell (:data:`LOG_P_FLOOR` at the least, and
    outside the window)."""
    prob = belief.prob  # (K, N, N)
    k, h, w = map_cell[0], map_cell[1], map_cell[2]
    n_k, n = cfg.num_rotations, cfg.size
    # The 3 x 3 x 3 neighbourhood only (k wraps, h / w clipped: no refinement on the border).
    ks = jnp.mod(k + jnp.arange(-1, 2), n_k)
    hs, ws = jnp.clip(h + jnp.arange(-1, 2), 0, n - 1), jnp.clip(w + jnp.arange(-1, 2), 0, n - 1)
    near = prob[ks[:, None, None], hs[None, :, None], ws[None, None, :]]
    # 1e-30, not 1e-38: XLA on CPU flushes float32 denormals to zero (log 0 = -inf, then NaN).
    offset = solver.refine_cell(jnp.log(jnp.maximum(near, 1e-30)), jnp.array([1, 1, 1]))
    offset = offset - 1.0
    on_border = jnp.stack([False, (h == 0) | (h == n - 1), (w == 0) | (w == n - 1)])
    cell = map_cell.astype(jnp.float32) + jnp.where(on_border, 0.0, offset)
    pose = tracking.cell_to_world(belief, cell, cfg)
    gt = jnp.round(tracking.world_to_cell(belief, gt_pose, cfg)).astype(jnp.int32)
    inside = (gt[1] >= 0) & (gt[1] < n) & (gt[2] >= 0) & (gt[2] < n)
    p = prob[gt[0] % n_k, jnp.clip(gt[1], 0, n - 1), jnp.clip(gt[2], 0, n - 1)]
    above = jnp.sum(jnp.where(prob > p, prob, 0.0))
    log_p = jnp.where(inside, jnp.log(jnp.maximum(p, LOG_P_FLOOR_P)), LOG_P_FLOOR)
    return pose, jnp.where(inside, above, jnp.inf), log_p


@jax.jit
def _log_likelihood(volume, temperature):
    """``volume / T``: ``log_softmax(volume / T)`` up to a constant per frame, which the
    update drops anyway (it subtracts the maximum)."""
    return volume / temperature


@dataclasses.dataclass
class Track:
    """Per-frame outputs of one tracked drive (``T`` frames)."""

    drive: Drive
    filtered: np.ndarray  # (T, 3) world
    single: np.ndarray  # (T, 3) world
    mean: np.ndarray  # (T, 3) posterior (x, y) mean and circular mean yaw
    cov_xy: np.ndarray  # (T, 2, 2) m^2
    above: np.ndarray  # (T,) posterior mass more probable than the GT cell (inf: outside)
    log_p_gt: np.ndarray  # (T,) log posterior of the GT cell (clamped: LOG_P_FLOOR)
    lost: np.ndarray  # (T,) bool, the filter detected a track loss at this frame


def _stack(rows: list[dict]) -> dict:
    return {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


class _Slot:
    """One drive in flight in the lockstep batch."""

    def __init__(self, drive: Drive, belief, odometry):
        self.drive, self.belief, self.odometry, self.t = drive, belief, odometry, 0
        self.map_cell = None  # (3,) of the last posterior
        self.out = collections.defaultdict(list)


def track_split(
    step: LocalizeStep,
    params,
    split: DriveSplit,
    drives: list[Drive],
    *,
    cfg: tracking.TrackerConfig,
    odometry_cfg,
    odometry_seed: int,
    temperature: float,
    batch_size: int,
    place,
    desc: str,
    single: bool = True,
) -> tuple[list[Track], dict]:
    """Tracks ``drives``, ``batch_size`` of them in lockstep (frame t of each in one batch of
    the localize step; a finished drive's slot takes the next one), and localizes the same
    frames single-frame (``single=False``: not; the tracks' ``single`` poses are then NaN).
    Returns the tracks and timings (seconds, and the frames they cover:
    all but the first ``WARMUP_STEPS`` lockstep steps, which compile). Fewer drives than
    ``batch_size``: the batch is that many (no padded rows computed for nothing)."""
    batch_size = max(1, min(batch_size, len(drives)))
    pending = collections.deque(drives)
    slots: list[_Slot | None] = [None] * batch_size
    done: dict[str, Track] = {}
    timing = {"localize_s": 0.0, "filter_s": 0.0, "data_s": 0.0, "frames": 0}
    steps = 0
    bar = tqdm(total=sum(len(d) for d in drives), desc=desc, unit="frame")

    def fill():
        for s in range(batch_size):
            if slots[s] is None and pending:
                d = pending.popleft()
                raster = split.rasters[d.city]
                odo = odometry_lib.simulate(
                    d.poses, d.timestamps, odometry_cfg, drive_seed(odometry_seed, d.sequence_id)
                )
                slots[s] = _Slot(d, start_belief(raster, d.priors[0], cfg), np.asarray(odo))

    fill()
    while any(slots):
        active = [s for s in range(batch_size) if slots[s] is not None]
        t0 = time.perf_counter()
        rows = split.rows([slots[s].drive.records[slots[s].t] for s in active])
        t1 = time.perf_counter()
        filter_rows = []
        for s, row in zip(active, rows, strict=True):
            slot = slots[s]
            if slot.t:  # the previous estimate's MAP cell saves predict a pass
                slot.belief, _ = tracking.predict(
                    slot.belief, slot.odometry[slot.t], cfg, map_cell=slot.map_cell
                )
            tile, centre = filter_tile(split.rasters[slot.drive.city], slot.belief, cfg)
            pose = np.asarray(row["pose"], np.float64)
            filter_rows.append(
                {
                    **row,
                    "tile": np.asarray(tile, np.float32),
                    "tile_center": centre,
                    "pose_tile": np.array([*(pose[:2] - centre), pose[2]], np.float32),
                }
            )
        t2 = time.perf_counter()
        pad = batch_size - len(active)  # repeat the first row: static shapes
        if single:
            one = step(params, place(_stack(rows + [rows[0]] * pad)))
            pose_tile = np.asarray(jax.device_get(one["pose_tile"]), np.float64)
        else:
            pose_tile = np.full((batch_size, 3), np.nan)
        volume = step(params, place(_stack(filter_rows + [filter_rows[0]] * pad)), volume=True)
        log_lik = _log_likelihood(volume["volume"], temperature)  # (B, K, 129, 129)
        log_lik.block_until_ready()  # (dispatch is asynchronous: time the steps, not the filter)
        t3 = time.perf_counter()
        for j, s in enumerate(active):
            slot = slots[s]
            slot.belief, info = tracking.update(slot.belief, log_lik[j], cfg)
            gt = slot.drive.poses[slot.t]
            est = info["estimate"]
            slot.map_cell = est["map_cell"]
            mode, above, log_p = _readout(
                slot.belief, est["map_cell"], jnp.asarray(gt, jnp.float32), cfg
            )
            est = jax.device_get(est)
            slot.out["filtered"].append(np.asarray(mode, np.float64))
            slot.out["single"].append(
                solver.tile_pose_to_world(pose_tile[j], rows[j]["tile_center"])
            )
            slot.out["mean"].append(np.asarray(est["mean_pose"], np.float64))
            slot.out["cov_xy"].append(np.asarray(est["cov_xy"], np.float64))
            slot.out["above"].append(float(above))
            slot.out["log_p_gt"].append(float(log_p))
            slot.out["lost"].append(bool(info["lost"]))
            slot.t += 1
            if slot.t == len(slot.drive):
                done[slot.drive.sequence_id] = Track(
                    slot.drive, **{k: np.asarray(v) for k, v in slot.out.items()}
                )
                slots[s] = None
        t4 = time.perf_counter()
        steps += 1
        if steps > WARMUP_STEPS:  # the first lockstep steps compile the programs
            timing["data_s"] += t1 - t0
            timing["filter_s"] += (t2 - t1) + (t4 - t3)
            timing["localize_s"] += t3 - t2
            timing["frames"] += len(active)
        bar.update(len(active))
        fill()
    bar.close()
    return [done[d.sequence_id] for d in drives], timing
