"""Data pipeline benchmark: prepare frames/s and loader records/s (with decoding); the last line
of the output is JSON. (Bytes and decode time per record: ``experiments/bench_records.py``.)

    python experiments/bench_data.py --source synth --frames 200   # prepare + loader rates
    python experiments/bench_data.py --source sim --frames 200     # simulator + map rasters

``synth`` renders random frames of a configurable size (no simulator) and cuts tiles from a
random raster, isolating the pipeline's own cost (PNG, ArrayRecord, grain, tile/BEV cuts).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data.simulated import prepare as pp
from seglocnet_jax.data.simulated import splits
from seglocnet_jax.data.simulated.config import PrepareConfig

CONF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "conf")
QUICK_FRAMES = 2000 + 300 + 300 + 300  # data=quick: train + val + test + kouvola
NUSCENES_TRAINVAL = 34149  # keyframes (samples) of nuScenes v1.0-trainval


# --------------------------------------------------------------------------- pipeline benchmark


class SynthSource:
    """Random frames on a street grid: ``cams`` RGB images of ``hw`` and ``points`` LiDAR."""

    def __init__(self, city: str, cams: int, hw: tuple[int, int], points: int):
        self.city, self.cams, self.hw, self.points = city, cams, hw, points

    def drive(self, rng, n):
        street = rng.integers(0, 13, n) * 100.0
        along = rng.uniform(0, 1200, n)
        east = rng.random(n) < 0.5
        return np.stack(
            [
                np.where(east, along, street),
                np.where(east, street, along),
                np.where(east, 0.0, np.pi / 2),
            ],
            axis=1,
        )

    def render(self, poses, seed):
        rng = np.random.default_rng(seed)
        out = []
        for i, pose in enumerate(poses):
            # Smooth images compress like camera frames, unlike white noise.
            base = rng.integers(0, 256, (self.cams, self.hw[0] // 8, self.hw[1] // 8, 3))
            images = np.repeat(np.repeat(base, 8, 1), 8, 2).astype(np.uint8)
            images += rng.integers(0, 8, images.shape, dtype=np.uint8)
            out.append(
                {
                    "sample_id": str(i),
                    "city": self.city,
                    "sequence_id": f"{self.city}-{seed}",
                    "frame_index": np.int64(i),
                    "timestamp": np.float64(0.0),
                    "lighting": "day",
                    "pose": np.asarray(pose, np.float64),
                    "images": images,
                    "intrinsics": np.tile(np.eye(3, dtype=np.float32), (self.cams, 1, 1)),
                    "cam_to_ego": np.tile(np.eye(4, dtype=np.float32), (self.cams, 1, 1)),
                    "lidar": rng.normal(size=(self.points, 4)).astype(np.float32),
                }
            )
        return out


class SynthRaster:
    """Random (2, H, W) raster with the maps API (slice tile, nearest-neighbour BEV)."""

    def __init__(self, size_m=1400.0):
        self.grid = geometry.RasterGrid.covering((-100.0, -100.0, size_m, size_m))
        rng = np.random.default_rng(0)
        self.mask = (rng.random((2, self.grid.height, self.grid.width)) < 0.3).astype(np.uint8)
        self._centres = geometry.bev_cell_centers_ego()  # (128, 128, 2)

    def tile(self, x, y):
        r0, c0, cx, cy = geometry.tile_window(self.grid, x, y)
        return geometry.crop(self.mask, r0, c0, geometry.TILE_SIZE), (float(cx), float(cy))

    def cut_bev(self, pose):
        w = geometry.ego_to_world(pose, self._centres)
        r, c = self.grid.world_to_pixel(w[..., 0], w[..., 1])
        r = np.clip(np.floor(r).astype(int), 0, self.grid.height - 1)
        c = np.clip(np.floor(c).astype(int), 0, self.grid.width - 1)
        return self.mask[:, r, c]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", choices=["synth", "sim"], default="synth")
    ap.add_argument("--frames", type=int, default=200, help="train frames to prepare")
    ap.add_argument("--cams", type=int, default=6)
    ap.add_argument("--height", type=int, default=160)
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--points", type=int, default=30000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--root", default=None, help="output root (default: a temp dir)")
    pipeline_benchmark(ap.parse_args())


def pipeline_benchmark(args):
    root = args.root or tempfile.mkdtemp(prefix="bench_data_")
    n_eval = max(args.frames // 8, args.batch)
    cfg = PrepareConfig(
        name=f"bench_{args.source}",
        root=root,
        num_train=args.frames,
        num_val=n_eval,
        num_test=n_eval,
        num_test_city=n_eval,
        split=splits.SplitConfig(stripe_width=25.0),
    )
    factory = None
    if args.source == "synth":

        def factory(city):
            return SynthSource(city, args.cams, (args.height, args.width), args.points)

    t0 = time.perf_counter()
    ddir = pp.prepare(cfg, factory, variants=() if args.source == "synth" else None)
    prep_s = time.perf_counter() - t0
    frames = args.frames + 3 * n_eval
    size = sum(
        os.path.getsize(os.path.join(d, f))
        for d, _, fs in os.walk(os.path.join(ddir, "sensors"))
        for f in fs
    )
    if args.source == "synth":
        rasters = {"helsinki": SynthRaster(), "kouvola": SynthRaster()}
        variant = None
    else:
        rasters, variant = None, cfg.map_variants[0]
        from seglocnet_jax.maps import MapConfig

        variant = MapConfig(**variant).name
    lcfg = ld.LoaderConfig(num_threads=args.threads, prefetch=2 * max(args.threads, 1))
    loader = ld.make_loader(
        ddir, "train", variant, args.batch, 0, True, config=lcfg, rasters=rasters
    )
    it = iter(loader)
    next(it)  # warm-up
    t0 = time.perf_counter()
    for _ in range(args.batches):
        next(it)
    load_s = time.perf_counter() - t0
    raster = rasters["helsinki"] if rasters else None
    tile_ms = None
    if raster is not None:
        t0 = time.perf_counter()
        for i in range(200):
            raster.tile(100.0 + i, 200.0)
            raster.cut_bev(np.array([100.0 + i, 200.0, 0.3]))
        tile_ms = (time.perf_counter() - t0) / 200 * 1e3
    print(
        json.dumps(
            {
                "source": args.source,
                "frames": frames,
                "prepare_frames_per_s": frames / prep_s,
                "bytes_per_frame": size / frames,
                "loader_records_per_s": args.batches * args.batch / load_s,
                "threads": args.threads,
                "tile_plus_bev_ms": tile_ms,
                "image": [args.cams, args.height, args.width],
                "points": args.points,
            }
        )
    )


if __name__ == "__main__":
    main()
