"""Benchmarks the network per preset and modality: parameter counts, compile time, forward
latency per sample (network alone, and network + solver at K=256 as evaluation runs it), train
step latency, and peak memory: the device's peak bytes in use where the backend reports them
(GPU), else the process's peak RSS so far (CPU), which only grows from one row to the next.

Inputs are synthetic batches in the loader's schema (``model.synthetic``): the tiny preset at the
simulator's CPU sizes (6 x 64 x 160 images, 32,768 LiDAR points), the paper preset at 6 x 320 x
800 (meant for a GPU: on this 2-core CPU it takes minutes). Progress goes to stderr; each
configuration prints one JSON line to stdout, and the last line is a JSON summary.

    python experiments/bench_model.py                          # tiny: fused, camera, lidar, nm
    python experiments/bench_model.py --presets paper --modes fused --batch 1

Target: tiny network + solver <= 0.5 s per sample on the 2-core CPU.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time

import jax
import numpy as np

from seglocnet_jax import evaluation, solver
from seglocnet_jax.model import api, synthetic
from seglocnet_jax.model.config import preset

SIZES = {"tiny": ((64, 160), 32768), "paper": ((320, 800), 32768)}


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _timed(fn, repeats: int) -> tuple[float, float]:
    """(first call incl. compile, median of ``repeats`` later calls), seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def _peak_memory_mb() -> tuple[str, float]:
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return "device_peak", stats["peak_bytes_in_use"] / 2**20
    return "process_peak_rss", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench(name: str, mode: str, batch_size: int, repeats: int, image_hw, points: int) -> dict:
    variant = "nm" if mode == "nm" else "seg"
    modality = "fused" if mode == "nm" else mode
    cfg = dataclasses.replace(preset(name), modality=modality, variant=variant)
    batch = synthetic.make_batch(0, batch_size, image_hw=image_hw, num_points=points)
    batch = {k: v for k, v in batch.items() if k not in ("pose", "tile_center")}
    params = api.init(jax.random.key(0), batch, cfg)
    groups = {k: int(sum(x.size for x in jax.tree.leaves(v))) for k, v in params.items()}
    solver_cfg = solver.SolverConfig()  # K = 256, fft

    forward = jax.jit(lambda p, b: api.forward(p, b, cfg)[0])
    step = evaluation.make_localize_step(cfg, solver_cfg)  # what every evaluation runs

    def localize(p, b):
        return step(p, b)["pose_tile"]

    grad = jax.jit(jax.grad(lambda p, b: api.loss_fn(p, b, cfg, jax.random.key(1))[0]))
    out = {"preset": name, "mode": mode, "batch": batch_size, "image_hw": list(image_hw)}
    out["points"] = points
    out["params_total"] = sum(groups.values())
    out["params_by_group"] = groups
    for key, fn in (("forward", forward), ("forward_solver", localize), ("train_grad", grad)):
        _progress(f"{name}/{mode}: {key} (compile + {repeats} runs) ...")
        first, median = _timed(lambda f=fn: f(params, batch), repeats)
        out[f"{key}_compile_s"] = round(first - median, 2)
        out[f"{key}_s_per_sample"] = round(median / batch_size, 4)
    kind, mb = _peak_memory_mb()
    out[f"{kind}_mb"] = round(mb, 1)
    out["device"] = jax.devices()[0].device_kind
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["tiny"], choices=sorted(SIZES))
    parser.add_argument("--modes", nargs="+", default=["fused", "camera", "lidar", "nm"])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--image-size", type=int, nargs=2, default=None, help="H W override")
    parser.add_argument("--points", type=int, default=None, help="LiDAR points override")
    args = parser.parse_args(argv)
    bad = sorted(set(args.modes) - {"fused", "camera", "lidar", "nm"})
    if bad:
        parser.error(f"--modes: unknown {bad}; choose from fused, camera, lidar, nm")
    rows = []
    for name in args.presets:
        image_hw, points = SIZES[name]
        image_hw = tuple(args.image_size) if args.image_size else image_hw
        points = args.points or points
        for mode in args.modes:
            row = bench(name, mode, args.batch, args.repeats, image_hw, points)
            print(json.dumps(row), flush=True)
            rows.append(row)
    summary = {
        f"{r['preset']}/{r['mode']}": {
            "forward_solver_s_per_sample": r["forward_solver_s_per_sample"],
            "train_grad_s_per_sample": r["train_grad_s_per_sample"],
            "params": r["params_total"],
        }
        for r in rows
    }
    tiny = [r for r in rows if r["preset"] == "tiny" and r["mode"] != "nm"]
    if tiny:
        summary["tiny_target_0.5s_met"] = all(r["forward_solver_s_per_sample"] <= 0.5 for r in tiny)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
