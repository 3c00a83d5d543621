"""Benchmarks the sequential filter (``seglocnet_jax.tracking``): one frame at paper sizes, and
whole drives with the tiny network.

The filter is the one the app runs: its config is built from ``conf/`` (the ``eval`` group's
``tracker`` and ``odometry`` of the default config, the map's channels) by the app's own builder,
:func:`sequential.tracker_config`; only K (``--num-rotations``) and, when given,
``--track-size`` / ``--hypotheses`` replace what the config says.

A frame is predict (motion, blur, window re-centring) + update (one score volume's
log-likelihood over the window's cells; it returns the posterior's estimate too) on a
``(K, N, N)`` belief (K = 256 by default) tracking a synthetic drive (a peaked likelihood at
the true cell plus distractors and noise; making it is not timed, and it is a buffer XLA
wrote, as the app's volume over T is). ``--window tracking`` (the
default): the tracking window a locked drive runs in (``cfg.tracking_window()``, its size
``eval.tracker.track_size``, 65; started on the truth: the app narrows a locked window; its
update takes the centre of the full window's volume and the log mean over it:
:func:`tracking.update_tracking_window`, the app's step); ``--window full``: the full
129 x 129 window (a drive's first frames, its bank of windows, the frames after a loss).
Predict gets the MAP cell of the estimate the previous update returned, as a filter loop
has it (``--map-cell computed``: predict finds it itself, one more pass over the volume).

The whole-drive rate (``--drives N``, 0: skip): N synthetic drives of ``--drive-frames`` frames
(5 m apart over a random 2-channel city raster) through :func:`sequential.track_split`, the
lockstep loop ``evaluate eval.mode=sequential`` runs: per frame the tiny network's localize step
returns the score volume of the tile cut around the filter's estimate (``--batch`` drives per
step), and the filter predicts and updates. The network is the main job's preset (``tiny``,
fused, seg) at the simulator's sizes (6 x 64 x 160 images, 32,768 LiDAR points), its weights
random (the cost does not depend on them; the likelihood is then noise, so the filter may take
its loss path more often than with a trained model: ``drive_losses`` counts it; and a bank of
windows, the app's default, keeps more windows alive than on real drives:
``drive_windows_per_frame`` reports it, ``--hypotheses 1`` measures one window). Sensor frames
cycle through 8 synthetic ones. Reported: frames per second of the vehicle's loop, and its
localize / filter / data milliseconds per frame (the loop's own timing, which leaves out its
first 2 steps: compilation); ``drive_score_ms_per_frame``, the GT's read-out the evaluation's
metrics need, and ``drive_compile_ms_per_frame``, the later steps' compilations (a new kernel
width), are timed apart and not in the rate.

Milliseconds per frame (compile excluded; median and best over the frames) and per stage
(``estimate_ms``: a standalone :func:`tracking.estimate`, not part of the frame), wall clock
and CPU time of this process (all its threads: on a loaded machine the wall clock also counts
the time other processes held the cores). The 1-minute load average is recorded because the
figure depends on what else runs on the CPU. Progress goes to stderr; the last stdout line is
JSON.

    python experiments/bench_tracking.py [--num-rotations 256] [--frames 20] [--map-cell given]
        [--window tracking|full] [--track-size 65] [--drives 4] [--drive-frames 24]
        [--batch 4] [--hypotheses H]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import evaluation, geometry, maps, sequential, solver, tracking
from seglocnet_jax.app import hydra_glue
from seglocnet_jax.app.schema import ExperimentConfig, build_experiment
from seglocnet_jax.data.schema import BATCH_METADATA_KEYS as HOST_ONLY_KEYS
from seglocnet_jax.model import api, synthetic
from seglocnet_jax.model.config import preset


def _likelihood(cfg: tracking.TrackerConfig, belief, pose, rng) -> jax.Array:
    """A frame's log-likelihood: a blob at the true cell, 3 distractor blobs and noise."""
    k0, h0, w0 = np.asarray(tracking.world_to_cell(belief, pose, cfg))
    h = np.arange(cfg.size)[:, None]
    w = np.arange(cfg.size)[None, :]
    ll = rng.normal(0.0, 0.5, (cfg.num_rotations, cfg.size, cfg.size)).astype(np.float32)
    k = np.arange(cfg.num_rotations)
    dk = np.minimum(np.abs(k - k0), cfg.num_rotations - np.abs(k - k0))[:, None, None]
    ll += 20.0 * np.exp(-0.5 * (((h - h0) ** 2 + (w - w0) ** 2) / 4.0 + dk**2 / 4.0))
    for _ in range(3):
        hd, wd, kd = rng.integers(0, cfg.size, 2).tolist() + [rng.integers(cfg.num_rotations)]
        dk = np.minimum(np.abs(k - kd), cfg.num_rotations - np.abs(k - kd))[:, None, None]
        ll += 10.0 * np.exp(-0.5 * (((h - hd) ** 2 + (w - wd) ** 2) / 4.0 + dk**2 / 4.0))
    # As the app's likelihood: a buffer XLA wrote (the volume program's output over T), not
    # host memory on loan: the update reads what a filter loop would read.
    return _block(_over_temperature(jnp.asarray(ll), jnp.float32(1.0)))


@jax.jit
def _over_temperature(volume, temperature):
    return volume / temperature


def _block(tree):
    return jax.block_until_ready(tree)


WINDOWS = ("tracking", "full")


def app_config(overrides=()) -> ExperimentConfig:
    """The experiment the app would run with ``overrides`` (Hydra syntax) on ``conf/``."""
    from hydra import compose, initialize_config_dir

    hydra_glue.register_resolvers()
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        tree = hydra_glue.to_tree(compose("config", overrides=list(overrides)))
    return build_experiment(tree)


def app_tracker(num_rotations: int, track_size=None, hypotheses=None) -> tracking.TrackerConfig:
    """The filter's config as the app builds it from ``conf/`` (:func:`app_config`), with K
    ``num_rotations`` and, when given, the tracking window's size and the windows per drive."""
    overrides = [f"solver.num_rotations={num_rotations}"]
    if track_size is not None:
        overrides.append(f"eval.tracker.track_size={track_size}")
    if hypotheses is not None:
        overrides.append(f"eval.tracker.hypotheses={hypotheses}")
    exp = app_config(overrides)
    return sequential.tracker_config(exp.eval, exp.solver.num_rotations, exp.map.channels)


def bench(
    app: tracking.TrackerConfig,
    frames: int,
    seed: int = 0,
    map_cell: str = "given",
    window="tracking",
) -> dict:
    """One frame of the filter ``app`` (the app's config) at a time (module docstring)."""
    num_rotations = app.num_rotations
    full = app  # the window the likelihood volume covers
    cfg = app.tracking_window() if window == "tracking" else full
    rng = np.random.default_rng(seed)
    step = np.array([2.0, 0.1, 0.02])  # m forward, m left, rad per frame
    pose = np.array([500.0, 500.0, 0.3])
    if cfg is full:
        belief = tracking.init_belief(cfg, pose[:2] + 5.0)
    else:  # the app narrows a locked window: start on the truth, as one
        belief = tracking.init_belief(cfg, pose[:2], sigma=1.0, yaw=pose[2], yaw_sigma=0.05)
    stages = ("predict", "update", "estimate", "frame")
    wall = {key: [] for key in stages}
    cpu = {key: [] for key in stages}
    cell = None
    clock = lambda: (time.perf_counter(), time.process_time())  # noqa: E731
    for i in range(frames + 2):  # the first two frames compile (update's reset path too)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * step[0] - s * step[1], s * step[0] + c * step[1], step[2]])
        t0 = clock()
        belief, _ = _block(tracking.predict(belief, step, cfg, map_cell=cell))
        t1 = clock()
        ll = _likelihood(full, belief, pose, rng)  # not timed: the network's job
        t2 = clock()
        if cfg is full:
            belief, info = _block(tracking.update(belief, ll, cfg))
        else:  # as the tracker runs it: the volume's centre, the loss test against its mean
            belief, info, now_in = tracking.update_tracking_window(belief, ll, cfg, full)
            _block((belief, info))
            if now_in is not cfg:  # reset in the full window: the figure would mix windows
                raise RuntimeError(f"frame {i}: the tracking window lost the synthetic drive")
        t3 = clock()
        _block(tracking.estimate(belief, cfg))
        t4 = clock()
        est = info["estimate"]
        cell = est["map_cell"] if map_cell == "given" else None
        if i >= 2:
            for key, (a, b) in (
                ("predict", (t0, t1)),
                ("update", (t2, t3)),
                ("estimate", (t3, t4)),
            ):
                wall[key].append(1000 * (b[0] - a[0]))
                cpu[key].append(1000 * (b[1] - a[1]))
            wall["frame"].append(wall["predict"][-1] + wall["update"][-1])
            cpu["frame"].append(cpu["predict"][-1] + cpu["update"][-1])
        err = float(np.hypot(*(np.asarray(est["map_pose"][:2]) - pose[:2])))
        ms = 1000 * ((t1[0] - t0[0]) + (t3[0] - t2[0]))
        print(f"frame {i}: {ms:.1f} ms, error {err:.2f} m", file=sys.stderr, flush=True)
    result = {"num_rotations": num_rotations, "window": window, "size": cfg.size, "frames": frames}
    result["map_cell"] = map_cell
    for key in stages:
        result[f"{key}_ms"] = round(float(np.median(wall[key])), 2)
    for key in stages:
        result[f"{key}_cpu_ms"] = round(float(np.median(cpu[key])), 2)
    result["frame_ms_best"] = round(float(np.min(wall["frame"])), 2)
    result["frame_cpu_ms_best"] = round(float(np.min(cpu["frame"])), 2)
    result["final_error_m"] = round(err, 3)
    return result


class _SyntheticSplit:
    """What :func:`sequential.track_split` reads of a split: the city rasters and the loader's
    rows (sensor inputs, the tile around the stored prior, the GT pose) by record index."""

    def __init__(self, raster, drives: list, sensors: dict):
        self.rasters = {raster.name: raster}
        self.nm_rasters = None  # a seg model: no OSM class rasters
        self.drives = {int(r): (d, t) for d in drives for t, r in enumerate(d.records)}
        self.sensors = sensors
        self.pool = len(next(iter(sensors.values())))

    def rows(self, indices) -> list[dict]:
        out = []
        for i in indices:
            drive, t = self.drives[int(i)]
            raster = self.rasters[drive.city]
            tile, centre = raster.tile(*drive.priors[t])
            pose = drive.poses[t]
            row = {k: v[int(i) % self.pool] for k, v in self.sensors.items()}
            row.update(
                tile=tile.astype(np.float32),
                tile_center=np.asarray(centre, np.float64),
                pose_tile=np.array([*(pose[:2] - centre), pose[2]], np.float32),
                pose=pose,
                frame_index=np.int64(t),
            )
            out.append(row)
        return out


def _synthetic_drives(num: int, frames: int, raster, rng) -> list:
    """``num`` gently curving drives, 5 m between frames, inside the raster; each frame's
    stored prior within +-20 m of the truth."""
    drives, grid = [], raster.grid
    x_max, y_min = grid.x_min + grid.width * 0.5, grid.y_max - grid.height * 0.5
    for d in range(num):
        yaw, rate = rng.uniform(-np.pi, np.pi), rng.uniform(-0.02, 0.02)
        yaws = yaw + rate * np.arange(frames)
        steps = 5.0 * np.stack([np.cos(yaws), np.sin(yaws)], 1)
        xy = np.cumsum(steps, 0) - steps[0]
        xy += [(grid.x_min + x_max) / 2, (grid.y_max + y_min) / 2] - xy.mean(0)
        poses = np.concatenate([xy, yaws[:, None]], 1)
        drives.append(
            sequential.Drive(
                sequence_id=f"bench-d{d:03d}",
                city=raster.name,
                records=np.arange(frames) + d * frames,
                frame_index=np.arange(frames),
                timestamps=np.arange(frames) * 0.5,
                poses=poses,
                priors=xy + rng.uniform(-20.0, 20.0, (frames, 2)),
            )
        )
    return drives


def bench_drives(
    num_drives: int, frames: int, batch_size: int, seed: int = 0, hypotheses: int | None = None
) -> dict:
    """Whole drives through the lockstep loop with the tiny network (see the module docstring);
    the filter the app's (``conf/``), ``hypotheses``: windows per drive (None: the app's,
    ``eval.tracker.hypotheses``)."""
    rng = np.random.default_rng(seed)
    side = 1600  # pixels: an 800 m city
    mask = (rng.random((2, side // 8, side // 8)) > 0.6).repeat(8, 1).repeat(8, 2)
    grid = geometry.RasterGrid(x_min=0.0, y_max=side * 0.5, height=side, width=side)
    raster = maps.CityRaster(mask.astype(np.uint8), grid, ("road", "building"), "bench-city")
    sensors = synthetic.make_batch(seed, 8, image_hw=(64, 160), num_points=32768)
    sensors = {
        k: v
        for k, v in sensors.items()
        if k not in HOST_ONLY_KEYS + ("tile", "nm_tile", "pose_tile")
    }
    model_cfg = preset("tiny")
    example = {k: v[:1] for k, v in sensors.items()}
    example["tile"] = np.zeros((1, 2, geometry.TILE_SIZE, geometry.TILE_SIZE), np.float32)
    example["pose_tile"] = np.zeros((1, 3), np.float32)
    params = api.init(jax.random.key(seed), example, model_cfg)
    step = evaluation.make_localize_step(model_cfg, solver.SolverConfig())

    def place(batch):
        return {k: jnp.asarray(v) for k, v in batch.items() if k not in HOST_ONLY_KEYS}

    drives = _synthetic_drives(num_drives, frames, raster, rng)
    overrides = ["solver.num_rotations=" + str(geometry.NUM_ROTATIONS)]
    if hypotheses is not None:
        overrides.append(f"eval.tracker.hypotheses={hypotheses}")
    exp = app_config(overrides)
    cfg = sequential.tracker_config(exp.eval, exp.solver.num_rotations, raster.channels)
    t0 = time.perf_counter()
    tracks, timing = sequential.track_split(
        step,
        params,
        _SyntheticSplit(raster, drives, sensors),
        drives,
        cfg=cfg,
        odometry_cfg=exp.eval.odometry,
        odometry_seed=seed,
        temperature=346.0,  # the main job's filter temperature (docs/sequential.md)
        batch_size=batch_size,
        place=place,
        desc="drives",
        single=False,
    )
    wall = time.perf_counter() - t0
    n = timing["frames"]
    # the vehicle's loop: the GT's read-out for the metrics (score) is reported on its own
    per_frame = {k: 1000 * timing[f"{k}_s"] / n for k in ("localize", "filter", "data")}
    return {
        "drives": num_drives,
        "drive_frames": frames,
        "drive_batch": batch_size,
        "drive_timed_frames": n,
        "drive_frames_per_s": round(1000 / sum(per_frame.values()), 2),
        **{f"drive_{k}_ms_per_frame": round(v, 1) for k, v in per_frame.items()},
        "drive_score_ms_per_frame": round(1000 * timing["score_s"] / n, 1),
        "drive_compile_ms_per_frame": round(1000 * timing["compile_s"] / n, 1),
        "drive_wall_s_with_compile": round(wall, 1),
        "drive_losses": int(sum(t.lost.sum() for t in tracks)),
        "drive_hypotheses": cfg.hypotheses,
        "drive_windows_per_frame": round(float(np.mean([t.hypotheses.mean() for t in tracks])), 2),
        "drive_track_size": cfg.track_size,
        "drive_narrowed_pct": round(float(100 * np.mean([t.narrowed.mean() for t in tracks])), 1),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-rotations", type=int, default=256)
    parser.add_argument("--frames", type=int, default=20, help="timed frames")
    parser.add_argument(
        "--map-cell",
        choices=("given", "computed"),
        default="given",
        help="predict gets the previous estimate's MAP cell, or computes it",
    )
    parser.add_argument(
        "--window",
        choices=WINDOWS,
        default="tracking",
        help="the tracking window (eval.tracker.track_size cells: a locked drive's) or the "
        "full 129-cell window",
    )
    parser.add_argument(
        "--track-size",
        type=int,
        default=None,
        help="cells of the tracking window (default: the app's eval.tracker.track_size)",
    )
    parser.add_argument(
        "--drives", type=int, default=4, help="synthetic drives for the whole-drive rate (0: skip)"
    )
    parser.add_argument("--drive-frames", type=int, default=24, help="frames per drive")
    parser.add_argument("--batch", type=int, default=4, help="drives per localize step")
    parser.add_argument(
        "--hypotheses", type=int, default=None, help="windows per drive (default: the app's)"
    )
    args = parser.parse_args(argv)
    if args.drives and args.drive_frames * args.drives <= 2 * args.batch:
        parser.error("--drives x --drive-frames must exceed the 2 compiling steps' frames")
    print(f"devices: {jax.devices()}", file=sys.stderr)
    load_before = os.getloadavg()[0]
    app = app_tracker(args.num_rotations, track_size=args.track_size)
    if args.window == "tracking" and not app.track_size:
        parser.error("--window tracking needs --track-size (the app has no tracking window)")
    result = bench(app, args.frames, map_cell=args.map_cell, window=args.window)
    if args.drives:
        result.update(
            bench_drives(args.drives, args.drive_frames, args.batch, hypotheses=args.hypotheses)
        )
    result.update(
        device=str(jax.devices()[0].platform),
        cpu_count=os.cpu_count(),
        load_avg_1min=round((load_before + os.getloadavg()[0]) / 2, 2),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        target_ms=10.0,
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
