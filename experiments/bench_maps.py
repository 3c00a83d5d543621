"""Map timings on this machine: read + project Helsinki, rasterize it (SD, both channels), cut
tiles and GT BEVs. ``python experiments/bench_maps.py [--repeats N]``; JSON on the last line."""

import argparse
import json
import time

import numpy as np
from tqdm import tqdm

from seglocnet_jax import maps


def timed(fn, repeats: int):
    """``(result, best seconds)`` over ``repeats`` calls (best of: least disturbed by the other
    processes sharing the CPU)."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--city", default="helsinki")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--queries", type=int, default=2000)
    args = parser.parse_args()

    city, t_read = timed(lambda: maps.load_city(args.city), args.repeats)
    cfg = maps.MapConfig(kind="sd", road_width=10.0)
    raster, t_raster = timed(lambda: maps.rasterize(city, cfg), args.repeats)

    rng = np.random.default_rng(0)
    x0, y0, x1, y1 = raster.grid.bounds
    xy = rng.uniform([x0, y0], [x1, y1], size=(args.queries, 2))
    t = time.perf_counter()
    for x, y in tqdm(xy, desc="tiles", leave=False):
        raster.tile(float(x), float(y))
    t_tile = (time.perf_counter() - t) / args.queries

    poses = np.concatenate([xy[:200], rng.uniform(-np.pi, np.pi, (200, 1))], axis=1)
    t = time.perf_counter()
    for pose in tqdm(poses, desc="bevs", leave=False):
        raster.cut_bev(pose)
    t_bev = (time.perf_counter() - t) / len(poses)
    _, t_bevs = timed(lambda: raster.cut_bevs(poses[:64]), args.repeats)

    result = {
        "city": city.name,
        "roads": len(city.roads),
        "buildings": len(city.buildings),
        "raster_shape": list(raster.mask.shape),
        "read_project_s": round(t_read, 4),
        "rasterize_sd_s": round(t_raster, 4),
        "tile_ms": round(t_tile * 1e3, 4),
        "cut_bev_ms": round(t_bev * 1e3, 4),
        "cut_bevs_64_ms": round(t_bevs * 1e3, 3),
    }
    print(
        f"read+project {t_read:.3f} s, rasterize SD {t_raster:.3f} s (target < 2 s), "
        f"tile {t_tile * 1e3:.4f} ms (target < 1 ms), cut_bev {t_bev * 1e3:.3f} ms"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
