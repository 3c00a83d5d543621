"""Test-session setup. JAX must see 8 simulated CPU devices before its first operation, so the
sharding tests can compare 1 device against 8 in one process. The app-level tests share two
tiny simulated datasets (tests/apphelpers.py), prepared once per session under these roots."""

import os

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")

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
