"""The experiment config: every component's frozen config in one tree, built from a plain dict
(a resolved Hydra config) with clear errors for unknown keys and bad values."""

from __future__ import annotations

import dataclasses
import os

from seglocnet_jax import solver
from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.data import prepare as prepare_lib
from seglocnet_jax.data.variants import VariantConfig
from seglocnet_jax.evaluation import EvalConfig
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.training.checkpoint import CheckpointConfig
from seglocnet_jax.training.state import OptimConfig


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Attributes:
    seed: model initialization, dropout and data order seed.
    batch_size: global batch (sharded over the "data" mesh axis).
    num_steps: optimizer steps (the cosine schedule spans them).
    num_devices: devices in the mesh (None: all).
    log_every, eval_every: periods in steps (eval_every 0: validate only at the end).
    val_batches: validation batches per periodic evaluation (None: the whole split).
    """

    seed: int = 0
    batch_size: int = 8
    num_steps: int = 2000
    num_devices: int | None = None
    log_every: int = 20
    eval_every: int = 500
    val_batches: int | None = 20
    optim: dict = dataclasses.field(default_factory=dict)
    checkpoint: CheckpointConfig = CheckpointConfig()

    def __post_init__(self):
        if self.num_steps < 1:
            raise ValueError(f"train.num_steps must be >= 1, got {self.num_steps}")
        if self.batch_size < 1:
            raise ValueError(f"train.batch_size must be >= 1, got {self.batch_size}")
        if self.log_every < 1:
            raise ValueError(f"train.log_every must be >= 1, got {self.log_every}")
        self.optim_config()  # validates train.optim.*

    def optim_config(self) -> OptimConfig:
        section = dict(self.optim)
        section.setdefault("total_steps", self.num_steps)
        if section.get("warmup_steps") is None:  # default: 5% of the run, at most 100 steps
            section["warmup_steps"] = min(100, self.num_steps // 20)
        return from_dict(OptimConfig, section, "train.optim")


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    name: str
    data: prepare_lib.PrepareConfig
    variant: VariantConfig
    loader: loader_lib.LoaderConfig
    model: ModelConfig
    solver: solver.SolverConfig
    train: TrainConfig
    eval: EvalConfig


def build_experiment(tree: dict) -> ExperimentConfig:
    """``tree``: the resolved Hydra config as a dict (keys: name, data, map, loader, model,
    solver, train, eval)."""
    tree = dict(tree)
    known = {"name", "data", "map", "loader", "model", "solver", "train", "eval"}
    unknown = sorted(set(tree) - known)
    if unknown:
        raise ConfigError(f"unknown top-level config key(s) {unknown}; expected {sorted(known)}")
    map_section = dict(tree.get("map") or {})
    variant = from_dict(
        VariantConfig,
        {k: map_section[k] for k in ("kind", "road_width", "channels") if k in map_section},
        "map",
    )
    data = from_dict(prepare_lib.PrepareConfig, tree.get("data"), "data")
    # The run's map variant is rasterized with the sensors (never re-simulated for a new one).
    data = dataclasses.replace(data, map_variants=(dataclasses.asdict(variant),))
    return ExperimentConfig(
        name=str(tree.get("name") or "experiment"),
        data=data,
        variant=variant,
        loader=from_dict(loader_lib.LoaderConfig, tree.get("loader"), "loader"),
        model=from_dict(ModelConfig, tree.get("model"), "model"),
        solver=from_dict(solver.SolverConfig, tree.get("solver"), "solver"),
        train=from_dict(TrainConfig, tree.get("train"), "train"),
        eval=from_dict(EvalConfig, tree.get("eval"), "eval"),
    )


def prepare_dataset(cfg: ExperimentConfig) -> str:
    """Prepares the experiment's data if its shards are missing (progress shown); returns the
    dataset directory. Real-data experiments need their converted directory to exist."""
    source = getattr(cfg.data, "source", "sim")
    if source != "sim":
        path = os.path.join(cfg.data.root, cfg.data.name)
        if not os.path.isdir(path):
            raise FileNotFoundError(
                f"data directory {path!r} for experiment {cfg.name!r} does not exist: convert the "
                f"dataset first (README, 'Using real data')"
            )
    return prepare_lib.prepare(cfg.data)
