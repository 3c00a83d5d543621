"""Simulator throughput: frames/s (6 cameras + LiDAR) for a sensor preset in a real OSM city.

    python experiments/bench_sim.py --city helsinki --preset cpu --frames 64 [--consistency]

Builds the world, drives poses, renders once to compile, then times ``Simulator.render`` in
batches of ``--batch`` frames (as the data pipeline calls it), with the allocator setting of
the apps (``app.allocator.keep_freed_memory``; ``--default-allocator``: without it, for the
difference; also the page faults and system CPU time per frame). ``--consistency`` adds how far
the world is from its maps: the share of elevated building LiDAR returns within 0.5 m of an OSM
building outline, the HD-vs-SD road IoU, and the world-vs-OSM road centre offset. The last line
is JSON.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time

from seglocnet_jax.app import allocator

if "--default-allocator" not in sys.argv:
    allocator.keep_freed_memory()  # before JAX starts, as the apps do

import jax
import numpy as np
import shapely

from seglocnet_jax import geometry
from seglocnet_jax.sim import SensorConfig, Simulator, WorldConfig, build_world, drive
from seglocnet_jax.sim.classes import Thing


def consistency(world, sim, poses) -> dict:
    """How the simulated world differs from the OSM maps (see the module docstring)."""
    from seglocnet_jax.maps import MapConfig, load_city, rasterize

    city = load_city(world.name)
    walls = shapely.union_all([shapely.boundary(b.geometry) for b in city.buildings])
    arrays = sim.render_arrays(poses, seed=0, diagnostics=True)
    dist = []
    for i, pose in enumerate(poses):
        sel = arrays["lidar_valid"][i] & (arrays["lidar_thing"][i] == Thing.BUILDING)
        pts = arrays["lidar"][i][sel]
        pts = pts[pts[:, 2] > 0.5]
        dist.append(
            shapely.distance(walls, shapely.points(geometry.ego_to_world(pose, pts[:, :2])))
        )
    dist = np.concatenate(dist)
    hd = rasterize(city, MapConfig(kind="hd", channels=("road",)), drivable=world.drivable)
    sd = rasterize(city, MapConfig(kind="sd", channels=("road",)))
    hd_mask = hd.mask[0].astype(bool)
    # Align SD to HD by world coordinates: both grids have corners on the same lattice.
    r0, c0 = hd.grid.world_to_pixel(*sd.grid.pixel_to_world(0, 0))
    sd_full = np.zeros_like(hd_mask)
    r0, c0 = int(round(float(r0))), int(round(float(c0)))
    h, w = sd.mask.shape[1:]
    rr = slice(max(r0, 0), min(r0 + h, hd_mask.shape[0]))
    cc = slice(max(c0, 0), min(c0 + w, hd_mask.shape[1]))
    sd_full[rr, cc] = sd.mask[0, rr.start - r0 : rr.stop - r0, cc.start - c0 : cc.stop - c0] > 0
    offsets = np.concatenate(
        [np.linalg.norm(r.centerline - r.osm_centerline, axis=1) for r in world.roads]
    )
    return {
        "lidar_building_returns": int(len(dist)),
        "lidar_within_0.5m_of_osm_walls": round(float(np.mean(dist < 0.5)), 4),
        "hd_sd10_road_iou": round(float((hd_mask & sd_full).sum() / (hd_mask | sd_full).sum()), 4),
        "centre_offset_mean_m": round(float(offsets.mean()), 3),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--city", default="helsinki")
    ap.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--consistency", action="store_true")
    ap.add_argument("--default-allocator", action="store_true", help="glibc's defaults")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    world = build_world(args.city, WorldConfig(), args.seed)
    t_world = time.perf_counter() - t0
    cfg = SensorConfig.preset(args.preset)
    sim = Simulator(world, cfg)
    poses = drive(world, np.random.default_rng(args.seed), args.frames + args.batch, 4.0)
    t0 = time.perf_counter()
    sim.render(poses[: args.batch], seed=0)  # compile + first batch
    t_first = time.perf_counter() - t0
    points = []
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    for start in range(args.batch, args.batch + args.frames, args.batch):
        for s in sim.render(poses[start : start + args.batch], seed=start):
            points.append(len(s["lidar"]))
    seconds = time.perf_counter() - t0
    usage = resource.getrusage(resource.RUSAGE_SELF)
    result = {
        "bench": "sim",
        "city": args.city,
        "preset": args.preset,
        "frames": len(points),
        "seconds": round(seconds, 3),
        "fps": round(len(points) / seconds, 2),
        "first_batch_s": round(t_first, 2),
        "allocator_tuned": allocator.tuned,
        "page_faults_per_frame": round((usage.ru_minflt - usage0.ru_minflt) / len(points)),
        "system_cpu_ms_per_frame": round(1e3 * (usage.ru_stime - usage0.ru_stime) / len(points), 1),
        "user_cpu_ms_per_frame": round(1e3 * (usage.ru_utime - usage0.ru_utime) / len(points), 1),
        "world_build_s": round(t_world, 2),
        "images": [6, cfg.image_height, cfg.image_width],
        "lidar_points_mean": int(np.mean(points)),
        "backend": jax.default_backend(),
        "world_cells": int(world.surface.size),
    }
    if args.consistency:
        result.update(consistency(world, sim, poses[args.batch :]))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
