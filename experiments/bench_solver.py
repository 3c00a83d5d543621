"""Benchmarks the score volume at paper sizes (C=2, 128x128 BEV, 256x256 tile, K=256).

For each batch size: milliseconds per sample of the "fft" method beside its bare-FFT reference,
timed in alternation in one run (compile excluded; medians and minima over the repetitions),
the 1-minute load average before and after (other jobs share the cores), and, up to
``--conv-max-batch``, of the "conv" method, with the largest difference of the fft and conv
volumes (absolute, and relative to the largest score).

The bare-FFT reference (``bare_fft_volume``) makes exactly the XLA FFT calls of the fft path's
schedule (same transforms, shapes, counts, per-sample and per-chunk loops, one after the other)
and nothing else: each call transforms its own previous output, so there are no pads, crops,
transposes, BEV rotation, spectrum products or output assembly. ``fft_over_bare`` (ratio of the
medians; ``fft_over_bare_cpu`` of the process CPU times, steadier on shared cores) is what the
solver costs over its FFTs alone. ``step_ms_per_sample`` is the apps' path on the same inputs:
the localize step's solver (``evaluation.make_localize_step``, decoded poses), which on CPU
solves a batch's rows in ``step_threads`` parts side by side (a host thread per core: one
solver program runs on one core).
The process runs with the allocator setting of the apps that call the solver (train, evaluate:
``app.allocator.keep_freed_memory``, so that each call's 17 MB volume per sample reuses freed
pages instead of faulting fresh ones in); ``--default-allocator`` times it with glibc's defaults.
``--profile`` adds where the time goes (``profile``: JAX's profiler over a few more runs of each,
milliseconds per sample in XLA's FFT calls, in the other XLA ops, the largest of those by name,
and the run's wall time): the gap between the fft path and the bare reference split into FFT
calls that run slower inside the solver and the solver's own elementwise work.
Progress goes to stderr; the last stdout line is JSON.

    python experiments/bench_solver.py [--batch 1 8] [--repeats 9] [--conv-repeats 1]
                                       [--conv-max-batch 1] [--default-allocator] [--profile]
"""

from __future__ import annotations

import argparse
import collections
import functools
import glob
import gzip
import json
import math
import os
import sys
import tempfile
import time

from seglocnet_jax.app import allocator

if "--default-allocator" not in sys.argv:
    allocator.keep_freed_memory()  # before JAX starts, as the apps do

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import evaluation, geometry, solver
from seglocnet_jax.model.config import preset

BARE_FFT = (
    "XLA FFT calls alone: the fft path's transforms (tile fft2 once per sample; per chunk of "
    "rotations one forward fft2 of the templates and one inverse fft2 of the quarter pairs), "
    "same shapes, counts, loops and order, each fed its own previous output; no padding, "
    "rotation, products, crops or output assembly"
)


def _chunks(num_rotations: int, rotation_chunk: int) -> tuple[int, int]:
    """``(chunk, number of chunks)`` of the fft path's loop over the K/4 angles."""
    quarter = num_rotations // 4
    chunk = math.gcd(quarter, rotation_chunk) if rotation_chunk else quarter
    return chunk, quarter // chunk


def _bare_sample(bufs, t0, num_rotations: int, rotation_chunk: int):
    """One sample's FFT calls of ``solver._score_fft``. ``bufs``: inputs of the two transforms
    of a chunk, ``(chunk, C/2, T, T)`` and ``(chunk, 2, T, T)``; ``t0 (C, T, T)``: the tile
    side's."""
    n_chunks = _chunks(num_rotations, rotation_chunk)[1]
    t_hat = jnp.fft.fft2(t0)

    def chunk_calls(bufs, forward: bool):  # the two calls of one chunk
        # Directions alternate from chunk to chunk so that the data stay in range; a forward
        # and an inverse transform cost the same. (XLA:CPU runs independent FFTs one after the
        # other, as a profile shows, so none overlaps another.)
        fwd, inv = (jnp.fft.fft2, jnp.fft.ifft2) if forward else (jnp.fft.ifft2, jnp.fft.fft2)
        return tuple(fn(x) for fn, x in zip((fwd, inv), bufs, strict=True))

    bufs = jax.lax.fori_loop(
        0, n_chunks // 2, lambda i, b: chunk_calls(chunk_calls(b, True), False), bufs
    )
    if n_chunks % 2:
        bufs = chunk_calls(bufs, True)
    return bufs, t_hat


@functools.partial(jax.jit, static_argnames=("num_rotations", "rotation_chunk", "batch_chunk"))
def bare_fft_volume(bufs, t0, num_rotations, rotation_chunk, batch_chunk):
    """The bare-FFT reference over a batch, looped like :func:`solver.score_volume_batch`."""
    fn = functools.partial(_bare_sample, num_rotations=num_rotations, rotation_chunk=rotation_chunk)
    if not batch_chunk or batch_chunk >= t0.shape[0]:
        return jax.vmap(fn)(bufs, t0)
    return jax.lax.map(lambda x: fn(*x), (bufs, t0), batch_size=batch_chunk)


def _timed(fn) -> tuple[float, object, float]:
    """Wall seconds, the result, and this process's CPU seconds (all its threads): the CPU
    time moves less than the wall time when other processes share the cores."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out, time.process_time() - c0


def op_profile(fn, batch: int, runs: int = 5, top: int = 6) -> dict:
    """Where ``fn``'s time goes, from a JAX profiler trace of ``runs`` calls (after warm-up):
    ms per sample in XLA's FFT calls (ops named ``fft*``), in every other XLA op (fusions,
    copies, broadcasts; not the loops that contain them), the ``top`` largest of those by
    XLA's name, and the wall time of the traced calls (with the profiler's own cost)."""
    jax.block_until_ready(fn())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(runs):
                jax.block_until_ready(fn())
        wall = time.perf_counter() - t0
        (path,) = glob.glob(os.path.join(tmp, "**", "*.trace.json.gz"), recursive=True)
        with gzip.open(path) as f:
            events = json.load(f)["traceEvents"]
    ops: dict[str, float] = collections.defaultdict(float)
    for event in events:
        name = event.get("name", "")
        # XLA's ops are named like "fft.3" or "add_bitcast_fusion"; the runtime's own events
        # ("ThunkExecutor::Execute", "$api.py:...") and loops ("while.5") contain other events.
        if event.get("ph") != "X" or name.startswith(("$", "while", "end:")) or ":" in name:
            continue
        if "." in name or "fusion" in name or name.startswith(("wrapped_", "copy")):
            ops[name] += event["dur"] / 1000 / runs / batch  # us -> ms per sample
    fft = sum(ms for name, ms in ops.items() if name.startswith("fft"))
    other = {name: ms for name, ms in ops.items() if not name.startswith("fft")}
    largest = sorted(other.items(), key=lambda item: -item[1])[:top]
    return {
        "fft_calls_ms_per_sample": round(fft, 2),
        "other_ops_ms_per_sample": round(sum(other.values()), 2),
        "largest_other_ops": {name: round(ms, 2) for name, ms in largest},
        "traced_wall_ms_per_sample": round(1000 * wall / runs / batch, 2),
    }


def bench(
    batch: int,
    repeats: int,
    conv_repeats: int,
    num_rotations: int,
    seed: int = 0,
    profile: bool = False,
) -> dict:
    cfg = solver.SolverConfig(num_rotations=num_rotations)
    rng = np.random.default_rng(seed)
    c_dim, size, tsize = 2, geometry.BEV_SIZE, geometry.TILE_SIZE
    bevs = jnp.asarray(rng.normal(size=(batch, c_dim, size, size)), jnp.float32)
    tiles = jnp.asarray(rng.random((batch, c_dim, tsize, tsize)) < 0.3, jnp.float32)
    pairs = (c_dim + 1) // 2
    chunk = _chunks(num_rotations, cfg.rotation_chunk)[0]

    def normal(*shape):
        return jnp.asarray(rng.normal(size=(batch,) + shape), jnp.complex64)

    bufs = (normal(chunk, pairs, tsize, tsize), normal(chunk, 2, tsize, tsize))
    t0 = normal(2 * pairs, tsize, tsize)  # the tile side: quarters 0 and 1 of each channel pair
    # The apps' path: the localize step's solver (GT-source step: the BEVs as they are), its
    # rows in parts side by side on CPU (evaluation.solver_threads), decoded to poses.
    step = evaluation.make_localize_step(preset("tiny"), cfg, "gt")
    rows = np.arange(batch)
    runs = {
        "fft": lambda: solver.score_volume_batch(
            bevs, tiles, num_rotations, "fft", cfg.rotation_chunk, cfg.batch_chunk
        ),
        "bare_fft": lambda: bare_fft_volume(
            bufs, t0, num_rotations, cfg.rotation_chunk, cfg.batch_chunk
        ),
        "step": lambda: step.solve(None, {"template": bevs}, {"tile": tiles}, rows),
    }
    print(f"batch {batch}: {', '.join(runs)} x{repeats} in turn ...", file=sys.stderr, flush=True)
    for fn in runs.values():
        jax.block_until_ready(fn())  # compile and warm up
    load_before = os.getloadavg()[0]
    times = {name: [] for name in runs}
    cpu = {name: [] for name in runs}
    for rep in range(repeats):
        for name in list(runs)[:: 1 if rep % 2 else -1]:  # alternate who goes first
            seconds, _, cpu_seconds = _timed(runs[name])
            times[name].append(seconds)
            cpu[name].append(cpu_seconds)
    result = {"batch": batch, "num_rotations": num_rotations, "repeats": repeats}
    result["load_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    for name, ts in times.items():
        result[f"{name}_ms_per_sample"] = round(1000 * float(np.median(ts)) / batch, 2)
        result[f"{name}_min_ms_per_sample"] = round(1000 * float(np.min(ts)) / batch, 2)
        result[f"{name}_cpu_ms_per_sample"] = round(1000 * float(np.median(cpu[name])) / batch, 2)
    result["step_threads"] = min(step.threads, batch)
    for kind in ("", "_cpu"):
        result[f"fft_over_bare{kind}"] = round(
            result[f"fft{kind}_ms_per_sample"] / result[f"bare_fft{kind}_ms_per_sample"], 3
        )
    print(
        f"  fft {result['fft_ms_per_sample']} ms/sample, bare FFTs "
        f"{result['bare_fft_ms_per_sample']}: x{result['fft_over_bare']} "
        f"(cpu x{result['fft_over_bare_cpu']}; load {result['load_1min']}); the localize "
        f"step's solver {result['step_ms_per_sample']} ms/sample in "
        f"{result['step_threads']} thread(s)",
        file=sys.stderr,
        flush=True,
    )
    if profile:
        print(f"batch {batch}: profiling fft and bare_fft ...", file=sys.stderr, flush=True)
        result["profile"] = {name: op_profile(runs[name], batch) for name in ("fft", "bare_fft")}
        print(f"  {json.dumps(result['profile'])}", file=sys.stderr, flush=True)
    if conv_repeats:
        print(f"batch {batch}: conv x{conv_repeats} ...", file=sys.stderr, flush=True)
        conv = functools.partial(solver.score_volume_batch, bevs, tiles, num_rotations, "conv")
        jax.block_until_ready(conv())
        conv_times = []
        for _ in range(conv_repeats):
            seconds, conv_volume, _ = _timed(conv)
            conv_times.append(seconds)
        result["conv_ms_per_sample"] = round(1000 * float(np.median(conv_times)) / batch, 2)
        result["conv_over_fft"] = round(
            result["conv_ms_per_sample"] / result["fft_ms_per_sample"], 1
        )
        diff = np.abs(np.asarray(runs["fft"]()) - np.asarray(conv_volume))
        result["max_abs_diff"] = float(diff.max())
        result["max_abs_score"] = float(np.abs(np.asarray(conv_volume)).max())
        result["max_rel_diff"] = result["max_abs_diff"] / result["max_abs_score"]
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--repeats", type=int, default=9, help="timed runs of fft and bare_fft")
    parser.add_argument("--conv-repeats", type=int, default=1, help="timed runs of conv (0: none)")
    parser.add_argument(
        "--conv-max-batch", type=int, default=1, help="largest batch that also times conv (slow)"
    )
    parser.add_argument("--num-rotations", type=int, default=geometry.NUM_ROTATIONS)
    parser.add_argument(
        "--default-allocator", action="store_true", help="glibc's defaults, not the apps' setting"
    )
    parser.add_argument(
        "--profile", action="store_true", help="also split each run's time by XLA op (profiler)"
    )
    args = parser.parse_args(argv)
    print(f"devices: {jax.devices()}", file=sys.stderr)
    rows = [
        bench(
            b,
            args.repeats,
            args.conv_repeats * (b <= args.conv_max_batch),
            args.num_rotations,
            profile=args.profile,
        )
        for b in args.batch
    ]
    print(
        json.dumps(
            {
                "device": str(jax.devices()[0].platform),
                "allocator": "apps' setting" if allocator.tuned else "default",
                "bare_fft": BARE_FFT,
                "results": rows,
            }
        )
    )


if __name__ == "__main__":
    main()
