"""Test-session setup. JAX must see 8 simulated CPU devices before its first operation, so the
sharding tests can compare 1 device against 8 in one process."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_num_cpu_devices", 8)
