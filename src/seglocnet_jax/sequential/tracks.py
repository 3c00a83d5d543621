"""Tracking the drives of a split (:mod:`.drives`) in lockstep through the filter and the
localize step (see the package docstring)."""

from __future__ import annotations

import collections
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import geometry, solver, tracking
from seglocnet_jax.evaluation import LocalizeStep
from seglocnet_jax.sequential.config import road_channels
from seglocnet_jax.sequential.drives import Drive, DriveSplit, drive_seed
from seglocnet_jax.tracking import hypotheses
from seglocnet_jax.tracking import odometry as odometry_lib

WARMUP_STEPS = 2  # lockstep steps left out of the per-frame timings (compilation)
# The log posterior of the GT cell is clamped here (and is this outside the window): ~12 nats
# below a uniform belief over the 4.3 M cells, so that one frame off the window does not
# dominate a mean over a drive.
LOG_P_FLOOR_P = 1e-12
LOG_P_FLOOR = float(np.log(LOG_P_FLOOR_P))
# A drive down to one window narrows to the tracking window once the box around the mode has
# held this much of the belief for this many frames in a row (one confident frame may be
# confidently wrong).
NARROW_MASS = 0.99
NARROW_FRAMES = 3


class CompileClock:
    """Seconds JAX spends compiling (tracing, lowering to MLIR, XLA's compile) while it is
    entered, from ``jax.monitoring``'s duration events: the lockstep loop times them apart,
    since a kernel compiles again for each new static shape (the prediction's tap widths,
    one program per width: a drive meets new ones long after its first frames)."""

    EVENTS = (
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "/jax/core/compile/backend_compile_duration",
    )

    def __init__(self):
        self.seconds = 0.0

    def __call__(self, event: str, duration: float, **kwargs) -> None:
        if event in self.EVENTS:
            self.seconds += duration

    def __enter__(self) -> CompileClock:
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc) -> None:
        jax.monitoring.unregister_event_duration_listener(self)


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
def _readout(belief: tracking.Belief, map_cell, cfg: tracking.TrackerConfig):
    """The posterior mode ``map_cell`` refined to sub-cell (the solver's parabolas on the log
    posterior), as a world pose."""
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
    return tracking.cell_to_world(belief, cell, cfg)


@functools.partial(jax.jit, static_argnames="cfg")
def _gt_cell_kernel(belief: tracking.Belief, gt_pose, cfg: tracking.TrackerConfig):
    return jnp.round(tracking.world_to_cell(belief, gt_pose, cfg)).astype(jnp.int32)


def _gt_cell(belief: tracking.Belief, gt_pose, cfg: tracking.TrackerConfig) -> np.ndarray:
    """The GT's rounded window cell ``(k, h, w)`` (outside ``[0, N)`` beyond the window): one
    program (eager, its dozen small ops cost more than the rest of the read-out)."""
    return np.asarray(_gt_cell_kernel(belief, jnp.asarray(gt_pose, jnp.float32), cfg), np.int64)


@jax.jit
def _log_likelihood(volume, temperature, road=None, off_road=0.0):
    """``volume / T``: ``log_softmax(volume / T)`` up to a constant per frame, which the
    update drops anyway (it subtracts the maximum); with ``road`` (``(..., T, T)``, the tiles'
    road channels) plus the on-road prior (:func:`tracking.road_log_prior`, ``-off_road``
    nats off the road)."""
    if road is None:
        return volume / temperature
    return volume / temperature + tracking.road_log_prior(road, off_road)[..., None, :, :]


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
    narrowed: np.ndarray  # (T,) bool, this frame was tracked in the tracking window
    hypotheses: np.ndarray  # (T,) int, windows tracked after this frame (tracking.hypotheses)
    scale: np.ndarray  # (T,) the odometry distance scale estimated after this frame


def _stack(rows: list[dict]) -> dict:
    return {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


class _Slot:
    """One drive in flight in the lockstep batch: its windows (one, or with
    ``cfg.hypotheses`` > 1 a bank of them, heaviest first), their log weights and each
    window's own odometry-scale estimate, learned from that window's mode track (a window
    that wins late keeps the scale of its own track, not the one learned on the window that
    led before it); ``cfg`` is the windows' (the tracking window's once narrowed)."""

    def __init__(self, drive: Drive, belief, odometry, cfg):
        self.drive, self.odometry, self.t = drive, odometry, 0
        self.beliefs, self.log_w = [belief], [0.0]
        self.map_cells = [None]  # (3,) of each window's last posterior
        self.infos = [None]  # each window's last update info
        self.cfg = cfg
        self.scales = [odometry_lib.ScaleEstimate(cfg.scale_prior_m)]  # one per window
        self.modes = [None]  # (3,) world, each window's last posterior mode (read out)
        self.held = 0  # consecutive frames the tracking window's box held NARROW_MASS
        self.out = collections.defaultdict(list)

    @property
    def belief(self):
        """The heaviest window's belief."""
        return self.beliefs[0]


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
    all but the first ``WARMUP_STEPS`` lockstep steps, which compile): ``filter_s`` is what a
    vehicle would run (prediction, tile cut, update, windows, read-outs), ``score_s`` the
    GT's read-out the metrics need (its cell's posterior and the mass above it), and
    ``compile_s`` the compilations of the later steps (:class:`CompileClock`: a new kernel
    width, a window's first frame), each left out of the others. Fewer drives than
    ``batch_size``: the batch is that many (no padded rows computed for nothing).

    With a tracking window (``cfg.track_size``) a drive down to one window narrows to it once
    the box around the mode has held :data:`NARROW_MASS` for :data:`NARROW_FRAMES` frames in
    a row (:func:`_next_window`); its frames are localized on ``cfg``'s tile around the window
    centre, and the window's likelihood is the volume's centre."""
    batch_size = max(1, min(batch_size, len(drives)))
    road_of = road_channels(split.rasters, cfg)  # None: no on-road prior
    pending = collections.deque(drives)
    slots: list[_Slot | None] = [None] * batch_size
    done: dict[str, Track] = {}
    timing = {
        "localize_s": 0.0,
        "filter_s": 0.0,
        "score_s": 0.0,
        "compile_s": 0.0,
        "data_s": 0.0,
        "frames": 0,
    }
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
                belief = start_belief(raster, d.priors[0], cfg)
                slots[s] = _Slot(d, belief, np.asarray(odo), cfg)

    def road(rows, active):
        """The rows' road channels ``(B, T, T)`` (None without the on-road prior)."""
        if road_of is None:
            return None
        cities = [slots[s].drive.city for s in active]
        return np.stack([r["tile"][road_of[c]] for r, c in zip(rows, cities, strict=True)])

    def volumes(filter_rows, active):
        """The log-likelihood volume of each row (``active``: its slot): the ``cfg`` tiles in
        padded batches of ``batch_size`` (a tracking window's too: its likelihood is the
        volume's centre); with ``cfg.off_road``, plus the on-road prior of each row's tile."""
        out = {}
        for start in range(0, len(active), batch_size):
            chunk = list(range(start, min(start + batch_size, len(active))))
            chunk_slots = [active[j] for j in chunk]
            rows = [filter_rows[j] for j in chunk]
            rows += [rows[0]] * (batch_size - len(rows))  # static shapes
            chunk_slots += [chunk_slots[0]] * (batch_size - len(chunk_slots))
            vol = step(params, place(_stack(rows)), volume=True)["volume"]
            lik = _log_likelihood(vol, temperature, road(rows, chunk_slots), cfg.off_road)
            out.update({j: lik[i] for i, j in enumerate(chunk)})  # (K, N, N) each
        jax.block_until_ready(out)  # dispatch is asynchronous: time the steps, not the filter
        return out

    with CompileClock() as clock:
        fill()
        while any(slots):
            active = [s for s in range(batch_size) if slots[s] is not None]
            t0 = time.perf_counter()
            rows = split.rows([slots[s].drive.records[slots[s].t] for s in active])
            t1, c1 = time.perf_counter(), clock.seconds
            filter_rows, owners = [], []  # a row per window; owners: (active index, window)
            for j, (s, row) in enumerate(zip(active, rows, strict=True)):
                slot = slots[s]
                for i in range(len(slot.beliefs)):
                    if slot.t:  # the previous estimate's MAP cell saves predict a pass
                        slot.beliefs[i], moved = tracking.predict(
                            slot.beliefs[i],
                            slot.scales[i].apply(slot.odometry[slot.t]),
                            slot.cfg,
                            map_cell=slot.map_cells[i],
                        )
                        if len(slot.beliefs) > 1:  # the mass that left the window
                            slot.log_w[i] = slot.log_w[i] + jnp.log(
                                jnp.maximum(1.0 - moved["dropped"], 1e-30)
                            )
                    # the tracking window's tile is cfg's: its volume's centre is the window
                    tile, centre = filter_tile(split.rasters[slot.drive.city], slot.beliefs[i], cfg)
                    pose = np.asarray(row["pose"], np.float64)
                    filter_rows.append(
                        {
                            **row,
                            "tile": np.asarray(tile, np.float32),
                            "tile_center": centre,
                            "pose_tile": np.array([*(pose[:2] - centre), pose[2]], np.float32),
                        }
                    )
                    owners.append((j, i))
            t2, c2 = time.perf_counter(), clock.seconds
            pad = batch_size - len(active)  # repeat the first row: static shapes
            if single:
                one = step(params, place(_stack(rows + [rows[0]] * pad)))
                pose_tile = np.asarray(jax.device_get(one["pose_tile"]), np.float64)
            else:
                pose_tile = np.full((batch_size, 3), np.nan)
            log_lik = volumes(filter_rows, [active[j] for j, _ in owners])
            t3, c3 = time.perf_counter(), clock.seconds
            for r, (j, i) in enumerate(owners):
                slot = slots[active[j]]
                # The evidence only weighs windows against each other: one window needs none (frame
                # 0's split sets the weights afterwards).
                weigh = len(slot.beliefs) > 1
                if slot.cfg.size < cfg.size:  # the tracking window runs the full window's filter
                    slot.beliefs[i], info, window = tracking.update_tracking_window(
                        slot.beliefs[i], log_lik[r], slot.cfg, cfg
                    )
                    if window is cfg:  # a loss: reset in the full window
                        slot.cfg, slot.held = cfg, 0
                else:
                    slot.beliefs[i], info = tracking.update(
                        slot.beliefs[i], log_lik[r], slot.cfg, evidence=weigh
                    )
                slot.map_cells[i] = info["estimate"]["map_cell"]
                slot.infos[i] = info
                if weigh:
                    slot.log_w[i] = slot.log_w[i] + info["log_evidence"]
            score_s = score_c = 0.0  # the GT's read-out: the evaluation's, not the filter's
            for j, s in enumerate(active):
                slot = slots[s]
                lost = any(bool(info["lost"]) for info in slot.infos)  # in any window
                _weigh_windows(slot, cfg, first=slot.t == 0)
                gt = slot.drive.poses[slot.t]
                if slot.infos[0] is None:  # frame 0's split: the heaviest piece's own estimate
                    est = jax.device_get(tracking.estimate(slot.belief, slot.cfg))
                else:
                    est = jax.device_get(slot.infos[0]["estimate"])
                modes = [
                    np.asarray(_readout(b, jnp.asarray(c), slot.cfg), np.float64)
                    for b, c in zip(slot.beliefs, slot.map_cells, strict=True)
                ]
                t_score, c_score = time.perf_counter(), clock.seconds
                above, log_p = hypotheses.mixture_readout(
                    slot.beliefs,
                    slot.log_w,
                    [_gt_cell(b, gt, slot.cfg) for b in slot.beliefs],
                    slot.cfg,
                    LOG_P_FLOOR_P,
                )
                score_s += time.perf_counter() - t_score
                score_c += clock.seconds - c_score
                for scale, previous, mode in zip(slot.scales, slot.modes, modes, strict=True):
                    if previous is not None:  # each window learns from its own mode track
                        scale.observe(previous, mode, slot.odometry[slot.t])
                slot.modes = modes
                slot.out["filtered"].append(modes[0])
                slot.out["scale"].append(slot.scales[0].scale)  # the heaviest window's
                slot.out["single"].append(
                    solver.tile_pose_to_world(pose_tile[j], rows[j]["tile_center"])
                )
                slot.out["mean"].append(np.asarray(est["mean_pose"], np.float64))
                slot.out["cov_xy"].append(np.asarray(est["cov_xy"], np.float64))
                slot.out["above"].append(float(above))
                slot.out["log_p_gt"].append(float(log_p))
                slot.out["lost"].append(lost)
                slot.out["narrowed"].append(slot.cfg.size < cfg.size)
                slot.out["hypotheses"].append(len(slot.beliefs))
                _next_window(slot, lost, cfg)
                slot.t += 1
                if slot.t == len(slot.drive):
                    done[slot.drive.sequence_id] = Track(
                        slot.drive, **{k: np.asarray(v) for k, v in slot.out.items()}
                    )
                    slots[s] = None
            t4, c4 = time.perf_counter(), clock.seconds
            steps += 1
            if steps > WARMUP_STEPS:  # the first lockstep steps compile the programs
                # later compilations (a new kernel width...) apart: score_s holds score_c
                filter_c = (c2 - c1) + (c4 - c3)
                timing["data_s"] += t1 - t0
                timing["filter_s"] += (t2 - t1) + (t4 - t3) - score_s - (filter_c - score_c)
                timing["score_s"] += score_s - score_c
                timing["localize_s"] += t3 - t2 - (c3 - c2)
                timing["compile_s"] += filter_c + (c3 - c2)
                timing["frames"] += len(active)
            bar.update(len(active))
            fill()
    bar.close()
    return [done[d.sequence_id] for d in drives], timing


def _weigh_windows(slot: _Slot, cfg: tracking.TrackerConfig, *, first: bool) -> None:
    """After a frame's update: with ``cfg.hypotheses`` > 1, frame 0's posterior is split among
    its modes (:func:`tracking.hypotheses.split_modes`); then the windows are pruned and merged
    (:func:`tracking.hypotheses.prune_and_merge`), the heaviest first. Frame 0's pieces each
    start from the scale estimate so far (the prior); a window merged into another leaves the
    survivor's estimate."""
    if cfg.hypotheses <= 1 or (not first and len(slot.beliefs) == 1):
        return  # one window left: nothing to weigh, prune or merge (its weight is 1)
    if first:
        pieces = hypotheses.split_modes(slot.belief, slot.cfg)
        slot.beliefs = [b for b, _ in pieces]
        slot.log_w = [lw for _, lw in pieces]
        slot.map_cells = [None] * len(pieces)
        slot.infos = [None] * len(pieces)
        slot.scales = [dataclasses.replace(slot.scales[0]) for _ in pieces]
        slot.modes = [slot.modes[0]] * len(pieces)
    cells = [
        tracking.estimate(b, slot.cfg)["map_cell"] if c is None else c
        for b, c in zip(slot.beliefs, slot.map_cells, strict=True)
    ]
    poses = [
        tracking.cell_to_world(b, c, slot.cfg) for b, c in zip(slot.beliefs, cells, strict=True)
    ]
    log_w = np.array([float(v) for v in slot.log_w])
    kept, log_w = hypotheses.prune_and_merge(log_w, np.asarray(jax.device_get(poses)), cfg)
    slot.beliefs = [slot.beliefs[i] for i in kept]
    slot.map_cells = [cells[i] for i in kept]
    slot.infos = [slot.infos[i] for i in kept]
    slot.scales = [slot.scales[i] for i in kept]
    slot.modes = [slot.modes[i] for i in kept]
    slot.log_w = list(log_w)


def _next_window(slot: _Slot, lost: bool, cfg) -> None:
    """The window the slot's next frame is tracked in: a drive down to one ``cfg`` window
    narrows to the tracking window once its box around the mode has held :data:`NARROW_MASS`
    for :data:`NARROW_FRAMES` frames in a row (:func:`tracking.narrow`); a detected loss
    restarts the count (the update has reset the belief in the ``cfg`` window already)."""
    track_cfg = cfg.tracking_window()
    if lost:
        slot.held = 0
        return
    if not (slot.cfg is cfg and track_cfg is not None and len(slot.beliefs) == 1):
        return
    belief, kept = tracking.narrow(slot.belief, slot.cfg, track_cfg, map_cell=slot.map_cells[0])
    slot.held = slot.held + 1 if float(kept) >= NARROW_MASS else 0
    if slot.held >= NARROW_FRAMES:
        # the next predict finds the mode in the new window
        slot.beliefs, slot.map_cells, slot.infos = [belief], [None], [None]
        slot.scales, slot.modes = slot.scales[:1], slot.modes[:1]
        slot.cfg, slot.held = track_cfg, 0
