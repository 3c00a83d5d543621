"""Benchmarks one frame of the sequential filter (``seglocnet_jax.tracking``) at paper sizes.

A frame is predict (motion, blur, window re-centring) + update (one score volume's
log-likelihood, a full ``(K, 129, 129)`` volume every frame; it returns the posterior's
estimate too) on a ``(K, 129, 129)`` belief (K = 256 by default) tracking a synthetic drive (a
peaked likelihood at the true cell plus distractors and noise; making it is not timed).
Predict gets the MAP cell of the estimate the previous update returned, as a filter loop
has it (``--map-cell computed``: predict finds it itself, one more pass over the volume).
``--window acquisition``: the same frame on the acquisition window
(``TrackerConfig(acquire_size=257).acquisition()``, 257 x 257 cells: the first frames of a drive
and those after a loss), plus the :func:`tracking.narrow` test every such frame runs
(``narrow_ms``, not part of the frame).

Milliseconds per frame (compile excluded; median and best over the frames) and per stage
(``estimate_ms``: a standalone :func:`tracking.estimate`, not part of the frame), wall clock
and CPU time of this process (all its threads: on a loaded machine the wall clock also counts
the time other processes held the cores). The 1-minute load average is recorded because the
figure depends on what else runs on the CPU. Progress goes to stderr; the last stdout line is
JSON.

    python experiments/bench_tracking.py [--num-rotations 256] [--frames 20] [--map-cell given]
        [--window tracking|acquisition]
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

from seglocnet_jax import tracking


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
    return jnp.asarray(ll)


def _block(tree):
    return jax.block_until_ready(tree)


def bench(
    num_rotations: int, frames: int, seed: int = 0, map_cell: str = "given", window="tracking"
) -> dict:
    wide = 2 * tracking.TrackerConfig().size - 1 if window == "acquisition" else 0  # 257
    base = tracking.TrackerConfig(num_rotations=num_rotations, acquire_size=wide)
    cfg = base.acquisition() if window == "acquisition" else base
    rng = np.random.default_rng(seed)
    step = np.array([2.0, 0.1, 0.02])  # m forward, m left, rad per frame
    pose = np.array([500.0, 500.0, 0.3])
    belief = tracking.init_belief(cfg, pose[:2] + 5.0)
    stages = ("predict", "update", "estimate", "frame") + (("narrow",) if cfg is not base else ())
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
        ll = _likelihood(cfg, belief, pose, rng)  # not timed: the network's job
        t2 = clock()
        belief, info = _block(tracking.update(belief, ll, cfg))
        t3 = clock()
        _block(tracking.estimate(belief, cfg))
        t4 = clock()
        if cfg is not base:  # as the tracker runs it: with the mode update returned
            _block(tracking.narrow(belief, cfg, base, map_cell=info["estimate"]["map_cell"]))
        t5 = clock()
        est = info["estimate"]
        cell = est["map_cell"] if map_cell == "given" else None
        if i >= 2:
            for key, (a, b) in (
                ("predict", (t0, t1)),
                ("update", (t2, t3)),
                ("estimate", (t3, t4)),
            ) + ((("narrow", (t4, t5)),) if cfg is not base else ()):
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
        choices=("tracking", "acquisition"),
        default="tracking",
        help="the 129-cell tracking window or the 257-cell acquisition window",
    )
    args = parser.parse_args(argv)
    print(f"devices: {jax.devices()}", file=sys.stderr)
    load_before = os.getloadavg()[0]
    result = bench(args.num_rotations, args.frames, map_cell=args.map_cell, window=args.window)
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
