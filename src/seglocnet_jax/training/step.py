"""The one jitted train step, sharded over a device mesh (batch on "data", params replicated).

The same code runs on one device, on N simulated CPU devices and on many hosts: only the mesh
changes. ``jax.pmap`` is not used (legacy in JAX >= 0.8).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from seglocnet_jax.data.schema import BATCH_METADATA_KEYS
from seglocnet_jax.training.state import TrainState

# (params, batch, rng) -> (scalar loss, dict of scalar metrics)
LossFn = Callable[[dict, dict, jax.Array], tuple[jax.Array, dict]]


def make_mesh(num_devices: int | None = None) -> jax.sharding.Mesh:
    """A 1-D ("data",) mesh over the first ``num_devices`` devices (all by default)."""
    devices = jax.devices()
    n = len(devices) if num_devices is None else num_devices
    if not 1 <= n <= len(devices):
        raise ValueError(f"train.num_devices={n} but {len(devices)} devices are available")
    return jax.make_mesh((n,), ("data",), axis_types=(AxisType.Auto,), devices=devices[:n])


def evaluation_mesh(mesh: jax.sharding.Mesh) -> jax.sharding.Mesh:
    """The mesh evaluation places its batches on: ``mesh``, except on CPU devices in one
    process, where it is the first device alone. There the localize step splits a batch
    among host threads (``evaluation.solver_threads``); a program sharded over several CPU
    devices, launched from several threads at once, deadlocks in its collectives, and the
    partitioner does not split the solver's per-sample loop (the devices share the cores)."""
    devices = list(mesh.devices.flat)
    if len(devices) == 1 or devices[0].platform != "cpu" or jax.process_count() > 1:
        return mesh
    return jax.make_mesh((1,), ("data",), axis_types=(AxisType.Auto,), devices=devices[:1])


def cpu_devices(batch_size: int, cores: int) -> int:
    """XLA CPU devices for a run whose global batch is ``batch_size`` on ``cores`` usable
    cores: one per core, down to the largest count that divides the batch."""
    return max(d for d in range(1, max(cores, 1) + 1) if batch_size % d == 0)


def batch_shard(mesh: jax.sharding.Mesh) -> tuple[int, int]:
    """``(shard_index, shard_count)`` of this process's rows of a global batch on ``mesh``.

    The batch is split along the mesh's devices in order, so this process's devices must form
    one contiguous run of them: its rows are block ``shard_index`` of ``shard_count`` equal
    blocks, what ``data.loader.make_loader(shard_options=ShardOptions(*batch_shard(mesh)))``
    reads. ``(jax.process_index(), jax.process_count())`` on a mesh over all devices in their
    usual order; ``(0, 1)`` in one process."""
    devices = list(mesh.devices.flat)
    mine = [i for i, d in enumerate(devices) if d.process_index == jax.process_index()]
    if not mine:
        raise ValueError(f"process {jax.process_index()} has no device in the mesh")
    first, m = mine[0], len(mine)
    if mine != list(range(first, first + m)) or first % m or len(devices) % m:
        raise ValueError(
            f"process {jax.process_index()} holds mesh positions {mine} of {len(devices)}: "
            "a process's devices must be one contiguous, equally sized block of the mesh"
        )
    return first // m, len(devices) // m


def device_batch(batch: dict, mesh: jax.sharding.Mesh, *, process_local: bool = True) -> dict:
    """Puts the device part of a host batch on the mesh, sharded along its leading axis.

    ``process_local=True`` (training): ``batch`` is this process's rows of the global batch
    (its loader reads shard :func:`batch_shard` of every batch), and the global array is built
    from every process's part (``jax.make_array_from_process_local_data``); in one process that
    is the whole batch, placed as it is. ``process_local=False``: ``batch`` is the whole global
    batch (every process's loader yields the same one) and each process places only the slices
    of its own devices."""
    sharding = NamedSharding(mesh, P("data"))
    n = mesh.devices.size
    _, count = batch_shard(mesh) if process_local else (0, 1)
    out = {}
    for key, value in batch.items():
        if key in BATCH_METADATA_KEYS:  # float64 world coordinates, strings: host only
            continue
        value = np.asarray(value)
        rows = value.shape[0] * count  # the global batch size
        if rows % n:
            raise ValueError(
                f"batch size {rows} (key {key!r}) is not divisible by the "
                f"{n} devices of the mesh; set train.batch_size to a multiple of {n}"
            )
        if process_local:
            out[key] = jax.make_array_from_process_local_data(
                sharding, value, (rows, *value.shape[1:])
            )
        else:
            out[key] = jax.make_array_from_callback(
                value.shape, sharding, lambda index, v=value: v[index]
            )
    return out


def make_train_step(loss_fn: LossFn, optimizer: optax.GradientTransformation, mesh):
    """Returns ``train_step(state, batch) -> (state, metrics)``, jitted once, state donated."""
    replicated = NamedSharding(mesh, P())

    def train_step(state: TrainState, batch: dict):
        rng = jax.random.fold_in(jax.random.wrap_key_data(state.rng), state.step)  # typed key
        (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, batch, rng)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, loss=loss, grad_norm=optax.tree.norm(grads))
        new_state = state.replace(step=state.step + 1, params=params, opt_state=opt_state)
        return new_state, metrics

    return jax.jit(train_step, donate_argnums=(0,), out_shardings=(replicated, replicated))


def replicate(tree, mesh):
    """Places a pytree (params, state) replicated on every device of the mesh."""
    return jax.device_put(tree, NamedSharding(mesh, P()))


def to_host(metrics: dict) -> dict[str, float]:
    return {k: float(np.asarray(v)) for k, v in jax.device_get(metrics).items()}


def tree_all_finite(tree) -> bool:
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
