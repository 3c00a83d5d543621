"""The one seam to Hydra: config location, resolvers, DictConfig -> plain dict, distributed init.

Only the app floor and the ``__main__`` entry points import this; the library never does.
"""

from __future__ import annotations

import os
import pathlib
import re

from omegaconf import DictConfig, OmegaConf


def conf_dir() -> str:
    """The repository's ``conf/`` (override with ``SEGLOCNET_CONF``)."""
    env = os.environ.get("SEGLOCNET_CONF")
    if env:
        return os.path.abspath(env)
    for parent in pathlib.Path(__file__).resolve().parents:
        if (parent / "conf" / "config.yaml").exists():
            return str(parent / "conf")
    raise FileNotFoundError(
        "cannot find conf/config.yaml above the package; set SEGLOCNET_CONF to the conf directory"
    )


def safe_dirname(name: str) -> str:
    """A Hydra ``override_dirname`` usable as a run directory: list values lose their brackets
    (orbax cannot restore from a path with ``[``/``]``), ``map.channels=[road,building]`` ->
    ``map.channels=road+building``."""
    return re.sub(r"\[([^\]]*)\]", lambda m: m.group(1).replace(",", "+"), name).translate(
        {ord("["): None, ord("]"): None}
    )


def map_dir(kind: str, road_width, channels) -> str:
    """The map part of a run directory's name: ``hd_road-building`` (HD maps ignore the road
    width), ``sd_w10.0_road-building``."""
    width = f"_w{road_width}" if kind == "sd" else ""
    return f"{kind}{width}_{'-'.join(str(c) for c in channels)}"


def eval_source(bev_source: str, checkpoint) -> str:
    """What an evaluation localizes with, for its directory's name: ``gt``, or the checkpoint
    step it restores, ``<run directory name>-step<N>`` (verified: the step the evaluation will
    restore, :func:`seglocnet_jax.training.checkpoint.resolve`). A missing or unusable
    checkpoint exits with its message."""
    if bev_source == "gt":
        return "gt"
    from seglocnet_jax.training import checkpoint as ckpt_lib

    # Hydra resolves the run directory before the app starts and cannot format an error raised
    # here: the message and exit status 1 instead of a traceback through Hydra's internals.
    if not checkpoint:
        raise SystemExit(
            "error: checkpoint=PATH is required with eval.bev_source=model (a run directory, "
            "its checkpoints/best, or one step directory); eval.bev_source=gt needs none"
        )
    try:
        return ckpt_lib.resolve(str(checkpoint)).name
    except ckpt_lib.CheckpointError as err:
        raise SystemExit(f"error: {err}") from None


def register_resolvers() -> None:
    if not OmegaConf.has_resolver("join"):
        OmegaConf.register_new_resolver("join", lambda xs: "-".join(str(x) for x in xs))
    if not OmegaConf.has_resolver("dirname"):
        OmegaConf.register_new_resolver("dirname", safe_dirname)
    if not OmegaConf.has_resolver("map_dir"):
        OmegaConf.register_new_resolver("map_dir", map_dir)
    if not OmegaConf.has_resolver("eval_source"):
        OmegaConf.register_new_resolver("eval_source", eval_source, use_cache=True)


def to_tree(cfg: DictConfig) -> dict:
    """The resolved config without Hydra's own node."""
    tree = OmegaConf.to_container(cfg, resolve=True)
    tree.pop("hydra", None)
    return tree


def quiet_library_logs() -> None:
    """Hydra sets the root logger to INFO; orbax (absl) and tensorboardX then flood the console
    with per-save chatter. Our own progress goes through tqdm and ``[seglocnet]`` lines."""
    import logging

    for name in ("absl", "tensorboardX", "orbax", "jax._src"):
        logging.getLogger(name).setLevel(logging.WARNING)


def maybe_initialize_distributed() -> None:
    """Multi-host: ``jax.distributed.initialize()`` when the environment asks for it (a
    coordinator address, or a cluster JAX auto-detects such as SLURM / TPU pods)."""
    import jax

    if _distributed():
        jax.distributed.initialize()


def _distributed() -> bool:
    """The environment asks for several processes (see :func:`maybe_initialize_distributed`)."""
    return bool(
        os.environ.get("JAX_COORDINATOR_ADDRESS") or os.environ.get("SEGLOCNET_DISTRIBUTED")
    )


def cpu_device_per_core(batch_size) -> int | None:
    """Before JAX starts: XLA's CPU devices, one per usable core down to a divisor of the
    training batch (``training.step.cpu_devices``), so that the train step sharded over them
    runs each device's rows on its own core (one device's intra-op threads leave the second
    core half idle: README, figures); says so on stdout. Left as it is (None returned) when
    the user chose the count (``JAX_NUM_CPU_DEVICES``, ``--xla_force_host_platform_device_count``
    in ``XLA_FLAGS``), runs several processes, or ``batch_size`` is not a positive integer
    (the config check that follows names it). Evaluation stays on one CPU device
    (``training.step.evaluation_mesh``)."""
    import jax

    from seglocnet_jax.training import step as step_lib

    chosen = "JAX_NUM_CPU_DEVICES" in os.environ
    chosen |= "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "")
    if (
        chosen
        or _distributed()
        or isinstance(batch_size, bool)
        or not isinstance(batch_size, int)
        or batch_size < 1
    ):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    n = step_lib.cpu_devices(batch_size, cores or 1)
    jax.config.update("jax_num_cpu_devices", n)  # raises once JAX has started
    print(
        f"[seglocnet] {n} XLA CPU device(s): one per usable core, dividing train.batch_size="
        f"{batch_size} (JAX_NUM_CPU_DEVICES chooses another count)",
        flush=True,
    )
    return n
