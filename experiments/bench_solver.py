"""Benchmarks the score volume at paper sizes (C=2, 128x128 BEV, 256x256 tile, K=256).

For each batch size: milliseconds per sample of the "fft" and "conv" methods (compile
excluded, median of the repeats), their ratio and the largest absolute difference of the two
volumes. Progress goes to stderr; the last stdout line is JSON.

    python experiments/bench_solver.py [--batch 1 8] [--repeats 3] [--conv-repeats 1]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np

from seglocnet_jax import geometry, solver


def _time(fn, repeats: int) -> tuple[float, jax.Array]:
    out = jax.block_until_ready(fn())  # compile and warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def bench(batch: int, repeats: int, conv_repeats: int, num_rotations: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    bevs = rng.normal(size=(batch, 2, geometry.BEV_SIZE, geometry.BEV_SIZE)).astype(np.float32)
    tiles = rng.random((batch, 2, geometry.TILE_SIZE, geometry.TILE_SIZE)) < 0.3
    tiles = tiles.astype(np.float32)
    result = {"batch": batch, "num_rotations": num_rotations}
    volumes = {}
    for method, reps in (("fft", repeats), ("conv", conv_repeats)):
        print(f"batch {batch}: {method} x{reps} (+1 warm-up) ...", file=sys.stderr, flush=True)
        seconds, volumes[method] = _time(
            lambda m=method: solver.score_volume_batch(bevs, tiles, num_rotations, m), reps
        )
        result[f"{method}_ms_per_sample"] = round(1000 * seconds / batch, 2)
        print(f"  {result[f'{method}_ms_per_sample']} ms/sample", file=sys.stderr, flush=True)
    result["conv_over_fft"] = round(result["conv_ms_per_sample"] / result["fft_ms_per_sample"], 1)
    diff = np.abs(np.asarray(volumes["fft"]) - np.asarray(volumes["conv"]))
    result["max_abs_diff"] = float(diff.max())
    result["max_abs_score"] = float(np.abs(np.asarray(volumes["conv"])).max())
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of fft")
    parser.add_argument("--conv-repeats", type=int, default=1, help="timed runs of conv")
    parser.add_argument("--num-rotations", type=int, default=geometry.NUM_ROTATIONS)
    args = parser.parse_args(argv)
    print(f"devices: {jax.devices()}", file=sys.stderr)
    rows = [bench(b, args.repeats, args.conv_repeats, args.num_rotations) for b in args.batch]
    print(json.dumps({"device": str(jax.devices()[0].platform), "results": rows}))


if __name__ == "__main__":
    main()
