"""The apps' allocator setting (app/allocator.py): large arrays freed between calls of XLA
programs reuse their pages instead of faulting fresh ones in, and every entry point sets it
before JAX starts."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")

# Fresh 64 MB NumPy arrays, freed again, between calls of a jitted program (its threads
# running): prints the page faults of each of eight rounds. 64 MB lies above glibc's largest
# dynamic mmap threshold (32 MB), so by default every array is mapped afresh and returned on
# free; all of it happens on the main thread, in order (no free that may come late).
_FAULTS = textwrap.dedent(
    """
    import resource, sys
    from seglocnet_jax.app import allocator
    if sys.argv[1] == "tuned":
        assert allocator.keep_freed_memory()
    import numpy as np
    import jax
    f = jax.jit(lambda x: (x * 2.0).sum())
    source = np.random.default_rng(0).random(1 << 24, dtype=np.float32)
    faults = []
    for _ in range(8):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        x = source.copy()
        float(f(x[:1024]))
        del x
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    print(*faults)
    """
)


def _faults_per_call(mode: str) -> float:
    """The median page faults of a call after the first (which faults its heap in either way)."""
    # 4 kB pages: NumPy would ask for transparent huge pages, 512 times fewer faults either way
    env = {**os.environ, "NUMPY_MADVISE_HUGEPAGE": "0"}
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True, env=env
    )
    return float(np.median([int(n) for n in out.stdout.split()[-8:][1:]]))


def test_fed_arrays_reuse_their_pages_once_the_allocator_keeps_freed_memory():
    default, tuned = _faults_per_call("default"), _faults_per_call("tuned")
    # Each round's copy faults its 16,384 fresh pages in by default; kept, the heap's pages
    # are reused (measured: 0 per round).
    assert default > 12_000, default
    assert tuned < default / 8, (tuned, default)


def test_every_entry_point_sets_it_before_jax_starts():
    script = textwrap.dedent(
        """
        import runpy, jax
        from jax._src import xla_bridge
        import seglocnet_jax.train, seglocnet_jax.evaluate
        runpy.run_path("data_prep/prepare_sim.py", run_name="not_main")
        from seglocnet_jax.app import allocator
        print(allocator.tuned, bool(xla_bridge._backends))
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-2:] == ["True", "False"], out.stdout
