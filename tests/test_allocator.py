"""The apps' allocator setting (app/allocator.py): the arrays fed to XLA and its buffers reuse
their pages from call to call instead of faulting fresh ones in, and every entry point sets it
before JAX starts."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")

# A jitted program called three times on a fresh 32 MB NumPy array each (as the simulator's
# render is fed its map patches): prints the page faults of the three calls.
_FAULTS = textwrap.dedent(
    """
    import resource, sys, time
    from seglocnet_jax.app import allocator
    if sys.argv[1] == "tuned":
        assert allocator.keep_freed_memory()
    import numpy as np
    import jax
    f = jax.jit(lambda x: (x * 2.0)[::1024].sum())
    source = np.random.default_rng(0).random(1 << 23, dtype=np.float32)
    f(source.copy()).block_until_ready()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(3):
        time.sleep(0.2)  # the previous call's arrays are freed (asynchronously) by then
        f(source.copy()).block_until_ready()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _faults(mode: str) -> int:
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True
    )
    return int(out.stdout.split()[-1])


def test_fed_arrays_reuse_their_pages_once_the_allocator_keeps_freed_memory():
    default, tuned = _faults("default"), _faults("tuned")
    # Each call's copies fault ~8,000 fresh pages in by default (measured: 26,000 in all);
    # kept, the pages are reused (measured: 8,700, the first call's arrays).
    assert default > 20_000, default
    assert tuned < default / 2, (tuned, default)


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
