"""Real-data conversion throughput: records/s of ``real_convert.convert`` at 1, 2, ... workers.

    python experiments/bench_convert.py                       # 48 frames, 1 and 2 workers
    python experiments/bench_convert.py --frames 96 --workers 1,2,4

Builds a nuScenes-format fixture in a temporary directory with the tests' writers
(``tests/fixtures_real.py``), scaled to dataset-like sizes: ``--frames`` keyframes in one scene,
six ``--src-hw`` textured JPEG cameras and ``--points`` LiDAR points per frame. Each worker
count converts the sensors (no map variants) into its own directory, from a cold start (the
worker pool's start-up is included; ``cpu_s``, the CPU time of all its processes, shows the
workers' own overhead where other work shares the cores and wall times mislead), and the shards
and manifests are compared byte for byte.
The figures depend on the record encoding of the code under test, not on this script. The last
line of the output is JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import tempfile
import time
import zlib

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import fixtures_real as fx  # noqa: E402  (the tests' dataset writers)
from seglocnet_jax.data.real import convert as rconv  # noqa: E402
from seglocnet_jax.data.real import nuscenes as nu  # noqa: E402


def textured_jpg(seed: int):
    """A replacement for the fixture's solid-colour camera images: smooth random texture plus
    sensor noise at ``fx.IMAGE_HW`` (compresses like a camera frame, unlike a flat colour)."""

    def write(path: str, colour) -> None:
        h, w = fx.IMAGE_HW
        rng = np.random.default_rng([seed, zlib.crc32(path.encode())])
        base = rng.uniform(0, 255, (h // 16 + 1, w // 16 + 1, 3)).astype(np.uint8)
        img = np.asarray(Image.fromarray(base).resize((w, h), Image.Resampling.BICUBIC), float)
        img = 0.7 * img + 0.3 * np.asarray(colour, float) + rng.normal(0, 3, img.shape)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        Image.fromarray(np.clip(img, 0, 255).astype(np.uint8)).save(path, quality=90)

    return write


def cpu_seconds() -> float:
    """User + system CPU time of this process and its finished children (the workers)."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        r = resource.getrusage(who)
        total += r.ru_utime + r.ru_stime
    return total


def build_fixture(root: str, frames: int, src_hw: tuple[int, int], points: int) -> None:
    """The nuScenes fixture with ``frames`` samples per scene, big textured images and LiDAR."""
    lidar_points = fx.lidar_points
    fx.NUS_SAMPLES_PER_SCENE = frames
    fx.IMAGE_HW = src_hw
    fx._write_jpg = textured_jpg(0)
    fx.lidar_points = lambda seed, n=points: lidar_points(seed, n)
    fx.write_nuscenes(root)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48, help="keyframes converted")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--src-hw", default="900,1600", help="fixture camera image H,W")
    ap.add_argument("--out-hw", default="320,800", help="stored image H,W (reader image_size)")
    ap.add_argument("--points", type=int, default=34720, help="LiDAR points per frame")
    ap.add_argument("--shard-size", type=int, default=4)
    args = ap.parse_args()
    workers = [int(w) for w in args.workers.split(",")]
    src_hw = tuple(int(v) for v in args.src_hw.split(","))
    out_hw = tuple(int(v) for v in args.out_hw.split(","))

    results = []
    with tempfile.TemporaryDirectory(prefix="bench_convert_") as tmp:
        root = os.path.join(tmp, "nuscenes")
        t0 = time.perf_counter()
        build_fixture(root, args.frames, src_hw, args.points)
        print(
            f"fixture: {args.frames} frames, 6 x {src_hw} JPEG cameras, {args.points} points "
            f"per frame ({time.perf_counter() - t0:.1f} s)",
            flush=True,
        )
        reader = nu.NuScenesReader(
            nu.NuScenesConfig(dataroot=root, version="v1.0-mini", image_size=out_hw)
        )
        base = rconv.ConvertConfig(
            root=os.path.join(tmp, "out"),
            shard_size=args.shard_size,
            splits={"train": "mini_train"},
        )
        outputs = {}
        for run, w in enumerate(workers):  # a fresh directory per run: nothing to resume
            cfg = dataclasses.replace(base, name=f"run{run}-w{w}", num_workers=w)
            t, c = time.perf_counter(), cpu_seconds()
            ddir = rconv.convert(reader, cfg, variants=False)
            dt, cpu = time.perf_counter() - t, cpu_seconds() - c
            files = {}
            for dirpath, _, names in os.walk(ddir):
                for n in names:
                    p = os.path.join(dirpath, n)
                    with open(p, "rb") as f:
                        files[os.path.relpath(p, ddir)] = f.read()
            outputs[run] = files
            mb = sum(len(v) for k, v in files.items() if k.endswith(".array_record")) / 1e6
            results.append(
                {
                    "workers": w,
                    "seconds": round(dt, 2),
                    "records_per_s": round(args.frames / dt, 2),
                    "cpu_s": round(cpu, 2),  # this process and its workers
                    "shard_mb": round(mb, 1),
                }
            )
            print(
                f"workers={w}: {args.frames} records in {dt:.2f} s = "
                f"{args.frames / dt:.2f} records/s, {cpu:.1f} CPU s ({mb:.1f} MB of shards)",
                flush=True,
            )
        identical = all(o == outputs[0] for o in outputs.values())
        print(f"shards and manifest identical across worker counts: {identical}")
    print(
        json.dumps(
            {
                "bench": "convert",
                "frames": args.frames,
                "src_hw": list(src_hw),
                "out_hw": list(out_hw),
                "points": args.points,
                "shard_size": args.shard_size,
                "cpus": len(os.sched_getaffinity(0)),
                "identical": identical,
                "results": results,
            }
        )
    )


if __name__ == "__main__":
    main()
