"""The C allocator of an app process, set before JAX starts its threads.

Each call of the simulator's render moves about 70 MB per frame of fresh arrays in and out of
XLA (the map patches it is fed, the copies XLA makes of them, its outputs). glibc serves requests
that large with ``mmap`` (or, from XLA's threads, an arena of their own) and gives the pages back
on ``free``, so every call faulted ~17,000 fresh zero pages in per frame: a third of the data
preparation's CPU time went to the kernel. :func:`keep_freed_memory` has glibc serve every
thread from its main heap and keep freed memory there (``mallopt``: one arena, no ``mmap``, no
trimming below 2 GiB): the next call reuses the same pages. The entry points call it first
thing (train, evaluate, the data preparation); the library never does. The difference:
``python experiments/bench_sim.py`` against ``--default-allocator`` (the README's figures).

The process's resident memory then stays at its peak. Only glibc on Linux has ``mallopt``:
elsewhere nothing changes and the function says so by returning False."""

from __future__ import annotations

import ctypes
import sys

# mallopt parameters (glibc's malloc.h)
M_TRIM_THRESHOLD, M_MMAP_MAX, M_ARENA_MAX = -1, -4, -8
SETTINGS = ((M_ARENA_MAX, 1), (M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, 2**31 - 1))

tuned = False  # keep_freed_memory() took effect in this process


def keep_freed_memory() -> bool:
    """Sets :data:`SETTINGS` (glibc): True when all took effect. It must run before anything
    starts JAX's backend (its threads take their arenas then); importing jax is fine."""
    global tuned
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's C library
    except (OSError, AttributeError):  # not glibc (e.g. musl): left as it is
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    tuned = all(mallopt(param, value) == 1 for param, value in SETTINGS)
    return tuned
