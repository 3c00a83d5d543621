"""Tracking the drives of a split (:mod:`.drives`) in lockstep: each drive a
:class:`~.drive_filter.DriveFilter`, frame ``t`` of every drive in flight in one batch of the
localize step (see the package docstring). The network runs once per frame
(:meth:`~seglocnet_jax.evaluation.LocalizeStep.network`); the solver matches that BEV against
the tile of every window of the drive and against the frame's stored prior tile (the
single-frame pose); a frame's window tiles a few cells apart (the temperature candidates')
are solved as one slightly larger tile, each window's volume a crop of it (:func:`_volumes`).
The loop only feeds frames, batches the localizations and collects the tracks; the timing
lives in :class:`_StepTimer`."""

from __future__ import annotations

import collections
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import geometry, solver, tracking
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.evaluation import LocalizeStep
from seglocnet_jax.sequential.config import road_channels
from seglocnet_jax.sequential.drive_filter import DriveFilter, Track
from seglocnet_jax.sequential.drives import Drive, DriveSplit, drive_seed
from seglocnet_jax.tracking import odometry as odometry_lib

WARMUP_STEPS = 2  # lockstep steps left out of the per-frame timings (compilation)
# Distinct tiles of one frame within this many pixels of each other (per axis) are solved as
# one tile this much larger (256 + 32 = 288 = 2^5 3^2 points: a fast FFT size), ~1.3x the
# work of one 256 tile: the temperature candidates' windows usually lie a few cells apart.
UNION_SPAN = 32


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


class _StepTimer:
    """Seconds per stage of the lockstep steps (``data``, ``filter``, ``score``,
    ``localize``), each without the compilations inside it (``compile``, timed apart by the
    :class:`CompileClock`), summed over the steps after the first ``WARMUP_STEPS``."""

    STAGES = ("localize", "filter", "score", "compile", "data")

    def __init__(self, clock: CompileClock):
        self.clock, self.steps = clock, 0
        self.totals = {f"{k}_s": 0.0 for k in self.STAGES} | {"frames": 0}

    def begin(self) -> None:
        self.step = collections.Counter()
        self.mark = (time.perf_counter(), self.clock.seconds)

    def lap(self, stage: str) -> None:
        """The time since the last lap goes to ``stage`` (its compilations to ``compile``)."""
        now = (time.perf_counter(), self.clock.seconds)
        wall, compiled = now[0] - self.mark[0], now[1] - self.mark[1]
        self.step[stage] += wall - compiled
        self.step["compile"] += compiled
        self.mark = now

    def end(self, frames: int) -> None:
        self.steps += 1
        if self.steps > WARMUP_STEPS:  # the first lockstep steps compile the programs
            for k in self.STAGES:
                self.totals[f"{k}_s"] += self.step[k]
            self.totals["frames"] += frames


@jax.jit
def _log_likelihood(volume, temperature, road=None, off_road=0.0):
    """``volume / T`` (``temperature (B,)``: a ``T`` per row of ``volume (B, K, N, N)``):
    ``log_softmax(volume / T)`` up to a constant per frame, which the update drops anyway (it
    subtracts the maximum); with ``road`` (``(B, T, T)``, the tiles' road channels) plus the
    on-road prior (:func:`tracking.road_log_prior`, ``-off_road`` nats off the road)."""
    scaled = volume / temperature[:, None, None, None]
    if road is None:
        return scaled
    return scaled + tracking.road_log_prior(road, off_road)[..., None, :, :]


def _stack(rows: list[dict]) -> dict:
    return {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


def _window_row(row: dict, tile, centre, nm_rasters=None) -> dict:
    """A window's tile row: its tile, centre and the GT in that tile's frame (``pose_tile``,
    read by nothing the filter runs), with the frame's index and GT pose; with ``nm_rasters``
    (an NM model's OSM class rasters) also the same tile of the row's city's (``nm_tile``)."""
    pose = np.asarray(row["pose"], np.float64)
    out = {
        "tile": np.asarray(tile, np.float32),
        "tile_center": centre,
        "pose_tile": np.array([*(pose[:2] - centre), pose[2]], np.float32),
        "pose": pose,
        "frame_index": row["frame_index"],
    }
    if nm_rasters is not None:
        city = str(row["city"])
        out["nm_tile"] = loader_lib.nm_tile(nm_rasters, city, *centre, f"window of {city!r}")
    return out


def _padded(chunk: list, devices: int) -> list:
    """``chunk`` (row indices) padded with its first row to a multiple of ``devices`` (those
    that ``place`` shards a batch over; on one device: as it is, no row computed for nothing)."""
    return chunk + [chunk[0]] * (-len(chunk) % devices)


def _devices(batch: dict) -> int:
    """The devices a placed batch is sharded over (1 for host arrays)."""
    sharding = getattr(batch["tile"], "sharding", None)
    return len(sharding.device_set) if sharding is not None else 1


def _corner(raster, centre, size: int) -> tuple[int, int]:
    """Top-left pixel ``(row, col)`` of the ``size`` tile of ``raster`` centred on ``centre``
    (world m, a pixel corner of the raster: a window centre)."""
    grid = raster.grid
    col = int(round((centre[0] - grid.x_min) / grid.resolution))
    row = int(round((grid.y_max - centre[1]) / grid.resolution))
    return row - size // 2, col - size // 2


def _groups(corners: list, span: int) -> list[list[int]]:
    """Indices of ``corners`` (the top-left pixels of one frame's distinct tiles) grouped
    greedily in order: a tile joins the first group whose corners, with it, stay within
    ``span`` pixels per axis."""
    groups, boxes = [], []
    for i, (r, c) in enumerate(corners):
        for g, (r0, c0, r1, c1) in enumerate(boxes):
            box = (min(r0, r), min(c0, c), max(r1, r), max(c1, c))
            if box[2] - box[0] <= span and box[3] - box[1] <= span:
                groups[g].append(i)
                boxes[g] = box
                break
        else:
            groups.append([i])
            boxes.append((r, c, r, c))
    return groups


@functools.partial(jax.jit, static_argnames="n")
def _crop(volumes, index, offset, n: int):
    """The ``(K, n, n)`` window of ``volumes[index]`` (a union tile's volume) at ``offset``
    ``(2,)`` cells: the volume of the tile ``offset`` pixels into the union tile."""
    k = volumes.shape[1]
    return jax.lax.dynamic_slice(volumes, (index, 0, offset[0], offset[1]), (1, k, n, n))[0]


def _volumes(
    step,
    params,
    place,
    bev,
    rows,
    owners,
    roads,
    temps,
    *,
    off_road,
    batch_size,
    devices,
    rasters=None,
) -> list:
    """The log-likelihood ``(K, N, N)`` of each window row: the solver's volume program on the
    frame's BEV (``bev``, row ``owners[i]`` for window row ``i``: the network does not run
    again) in batches of up to ``batch_size`` (:func:`_padded` to ``devices``; each size
    compiles once), over the row's temperature ``temps[i]``; with ``roads`` (the rows' road
    channels, or None) plus the on-road prior. Rows of one frame with the same tile centre
    (the temperature candidates' windows often coincide) share one solver volume: it does not
    depend on T. With ``rasters`` (each row's city raster; a seg model's, whose tile the
    solver reads as it is), the distinct tiles of one frame that lie within
    :data:`UNION_SPAN` pixels of each other are solved as one union tile :data:`UNION_SPAN`
    pixels larger, each window's volume a crop of the union's (the candidates' windows
    usually lie a few cells apart)."""
    key_of = [
        (o, np.asarray(r["tile_center"], np.float64).tobytes())
        for o, r in zip(owners, rows, strict=True)
    ]
    first = {}
    for i, key in enumerate(key_of):
        first.setdefault(key, i)
    unique = list(first.values())  # row index of each distinct (frame, tile)

    def solve(tile_rows, frames) -> list:
        """The volume of each tile row against its frame's BEV: ``(volumes, index)`` pairs."""
        out = []
        for start in range(0, len(tile_rows), batch_size):
            take = _padded(list(range(start, min(start + batch_size, len(tile_rows)))), devices)
            batch = place(_stack([tile_rows[i] for i in take]))
            index = np.asarray([frames[i] for i in take])
            vol = step.solve(params, bev, batch, index, volume=True)["volume"]
            out.extend((vol, n) for n in range(min(batch_size, len(tile_rows) - start)))
        return out

    alone, unions = [], []  # unique positions solved as they are / (corner, [(pos, offset)])
    by_owner = collections.defaultdict(list)
    for pos, i in enumerate(unique):
        by_owner[owners[i]].append(pos)
    for positions in by_owner.values():
        if rasters is None:
            alone.extend(positions)
            continue
        size = rows[unique[positions[0]]]["tile"].shape[-1]
        corners = [
            _corner(rasters[unique[p]], rows[unique[p]]["tile_center"], size) for p in positions
        ]
        for group in _groups(corners, UNION_SPAN):
            if len(group) == 1:
                alone.append(positions[group[0]])
                continue
            r0 = min(corners[g][0] for g in group)
            c0 = min(corners[g][1] for g in group)
            members = [(positions[g], (corners[g][0] - r0, corners[g][1] - c0)) for g in group]
            unions.append(((r0, c0), members))
    vols = [None] * len(unique)
    solved = solve([rows[unique[p]] for p in alone], [owners[unique[p]] for p in alone])
    for p, (vol, n) in zip(alone, solved, strict=True):
        vols[p] = vol[n]
    union_rows = []
    for (r0, c0), members in unions:
        i = unique[members[0][0]]
        raster, size = rasters[i], rows[i]["tile"].shape[-1] + UNION_SPAN
        grid = raster.grid
        centre = np.array(
            [
                grid.x_min + (c0 + size // 2) * grid.resolution,
                grid.y_max - (r0 + size // 2) * grid.resolution,
            ]
        )
        union_rows.append(_window_row(rows[i], geometry.crop(raster.mask, r0, c0, size), centre))
    frames = [owners[unique[members[0][0]]] for _, members in unions]
    for (_, members), (vol, n) in zip(unions, solve(union_rows, frames), strict=True):
        for p, offset in members:
            offset = np.asarray(offset, np.int32)
            vols[p] = _crop(vol, np.int32(n), offset, vol.shape[-1] - UNION_SPAN)
    slot = {key: n for n, key in enumerate(first)}
    out = []
    for start in range(0, len(rows), batch_size):
        chunk = list(range(start, min(start + batch_size, len(rows))))
        take = _padded(chunk, devices)
        vol = jnp.stack([vols[slot[key_of[i]]] for i in take])  # (B, K, N, N)
        road = None if roads is None else np.stack([roads[i] for i in take])
        temp = np.asarray([temps[i] for i in take], np.float32)
        lik = _log_likelihood(vol, temp, road, off_road)
        out.extend(lik[i] for i in range(len(chunk)))
    return jax.block_until_ready(out)  # dispatch is asynchronous: time the steps, not the filter


def track_split(
    step: LocalizeStep,
    params,
    split: DriveSplit,
    drives: list[Drive],
    *,
    temperature: float,
    **kwargs,
) -> tuple[list[Track], dict]:
    """:func:`track_candidates` at one temperature: the tracks of ``drives`` and the timings."""
    tracks, timing = track_candidates(
        step, params, split, drives, temperatures=(temperature,), **kwargs
    )
    return tracks[0], timing


def track_candidates(
    step: LocalizeStep,
    params,
    split: DriveSplit,
    drives: list[Drive],
    *,
    cfg: tracking.TrackerConfig,
    odometry_cfg,
    odometry_seed: int,
    temperatures,
    batch_size: int,
    place,
    desc: str,
    single: bool = True,
) -> tuple[list[list[Track]], dict]:
    """Tracks ``drives``, ``batch_size`` of them in lockstep (frame t of each in one batch of
    the localize step; a finished drive's slot takes the next one), each with a filter per
    likelihood temperature of ``temperatures`` (the candidates: one network pass per frame
    for all of them, their windows' tiles in the same solver batches), and localizes the same
    frames single-frame (``single=False``: not; the tracks' ``single`` poses are then NaN).
    Returns the tracks per temperature and timings (seconds, and the drive frames they cover:
    all but the first ``WARMUP_STEPS`` lockstep steps, which compile): ``filter_s`` is what a
    vehicle would run (prediction, tile cut, update, windows, read-outs), ``score_s`` the
    GT's read-out the metrics need (its cell's posterior and the mass above it), and
    ``compile_s`` the compilations of the later steps (:class:`CompileClock`: a new kernel
    width, a window's first frame), each left out of the others. Fewer drives than
    ``batch_size``: the batch is that many (no padded rows computed for nothing)."""
    batch_size = max(1, min(batch_size, len(drives)))
    temperatures = [float(t) for t in temperatures]
    road_of = road_channels(split.rasters, cfg)  # None: no on-road prior
    pending = collections.deque(drives)
    slots: list[list[DriveFilter] | None] = [None] * batch_size  # a filter per temperature
    done: list[dict[str, Track]] = [{} for _ in temperatures]
    bar = tqdm(total=sum(len(d) for d in drives), desc=desc, unit="frame")

    def fill():
        for s in range(batch_size):
            if slots[s] is None and pending:
                d = pending.popleft()
                seed = drive_seed(odometry_seed, d.sequence_id)
                odo = odometry_lib.simulate(d.poses, d.timestamps, odometry_cfg, seed)
                slots[s] = [DriveFilter(d, split.rasters[d.city], odo, cfg) for _ in temperatures]

    with CompileClock() as clock:
        timer = _StepTimer(clock)
        fill()
        while any(slots):
            active = [s for s in range(batch_size) if slots[s] is not None]
            timer.begin()
            rows = split.rows([slots[s][0].drive.records[slots[s][0].t] for s in active])
            timer.lap("data")
            # a row per window of each drive's filter per temperature: (drive row, filter)
            windows = [
                ((j, c), f.tiles()) for j, s in enumerate(active) for c, f in enumerate(slots[s])
            ]
            owners = [key for key, tiles in windows for _ in tiles]
            window_rows = [
                _window_row(rows[j], *tc, split.nm_rasters)
                for (j, _), tiles in windows
                for tc in tiles
            ]
            roads = None
            if road_of is not None:
                cities = [slots[active[j]][0].drive.city for j, _ in owners]
                roads = [r["tile"][road_of[c]] for r, c in zip(window_rows, cities, strict=True)]
            timer.lap("filter")
            frame = place(_stack(rows + [rows[0]] * (batch_size - len(active))))  # static shapes
            bev = step.network(params, frame)  # once per frame: every tile below reuses it
            if single:  # the frame's stored prior tile, of the drives in flight only
                take = _padded(list(range(len(active))), _devices(frame))
                tiles = {k: frame[k][: len(take)] for k in ("tile", "nm_tile") if k in frame}
                one = step.solve(params, bev, tiles, np.asarray(take))
                pose_tile = np.asarray(jax.device_get(one["pose_tile"]), np.float64)
            else:
                pose_tile = np.full((batch_size, 3), np.nan)
            log_lik = _volumes(
                step,
                params,
                place,
                bev,
                window_rows,
                [j for j, _ in owners],
                roads,
                [temperatures[c] for _, c in owners],
                off_road=cfg.off_road,
                batch_size=batch_size,
                devices=_devices(frame),
                # a seg model's tiles (not an NM model's class tiles) unite
                rasters=None
                if split.nm_rasters is not None
                else [split.rasters[slots[active[j]][0].drive.city] for j, _ in owners],
            )
            timer.lap("localize")
            for j, s in enumerate(active):
                one_pose = solver.tile_pose_to_world(pose_tile[j], rows[j]["tile_center"])
                for c, f in enumerate(slots[s]):
                    f.update([lik for lik, o in zip(log_lik, owners, strict=True) if o == (j, c)])
                    readout = f.read_out()
                    timer.lap("filter")
                    above, log_p = f.score()
                    timer.lap("score")
                    track = f.finish(readout, one_pose, above, log_p)
                    if track is not None:
                        done[c][f.drive.sequence_id] = track
                if slots[s][0].t == len(slots[s][0].drive):
                    slots[s] = None
            timer.lap("filter")
            timer.end(len(active))
            bar.update(len(active))
            fill()
    bar.close()
    return [[out[d.sequence_id] for d in drives] for out in done], timer.totals
