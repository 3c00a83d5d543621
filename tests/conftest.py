"""Test-session setup. JAX must see 8 simulated CPU devices before its first operation, so the
sharding tests can compare 1 device against 8 in one process. The app-level tests share two
tiny simulated datasets (tests/apphelpers.py), prepared once per session under these roots.

The session compiles the same small programs many times over (every app run builds its train
and evaluation steps again): a persistent compilation cache, fresh for each session and shared
with the tests' subprocesses and pytest-xdist's workers (``-n 2`` in pyproject's addopts),
compiles each once (the suite: 1,277 s on CI without it)."""

import atexit
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# pytest-xdist's workers inherit the controller's environment: they share its cache.
_CACHE = os.environ.get("SEGLOCNET_TEST_XLA_CACHE")
if _CACHE is None:
    _CACHE = tempfile.mkdtemp(prefix="seglocnet-test-xla-cache-")
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
    os.environ["SEGLOCNET_TEST_XLA_CACHE"] = _CACHE
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"

import jax  # noqa: E402

jax.config.update("jax_num_cpu_devices", 8)


@pytest.fixture(scope="session")
def tiny_data_root(tmp_path_factory):
    """Root of ``apphelpers.TINY`` (prepared by the first app run that uses it)."""
    return str(tmp_path_factory.mktemp("app_data"))


@pytest.fixture(scope="session")
def drives_data_root(tmp_path_factory):
    """Root of ``apphelpers.TINY_DRIVES`` (prepared by the first app run that uses it)."""
    return str(tmp_path_factory.mktemp("seq_data"))
