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
    init_from: checkpoint (run directory or step directory) whose parameters start a new run
      (fine-tuning, e.g. Argoverse from nuScenes); ignored when the run resumes its own.
    """

    seed: int = 0
    batch_size: int = 8
    num_steps: int = 2000
    num_devices: int | None = None
    log_every: int = 20
    eval_every: int = 500
    val_batches: int | None = 20
    init_from: str | None = None
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
    # Real data (conf/dataset/*.yaml: source, reader, convert), None for the simulator. Validated
    # by build_experiment; converted on first use by prepare_dataset.
    dataset: dict | None = None


def build_experiment(tree: dict) -> ExperimentConfig:
    """``tree``: the resolved Hydra config as a dict (keys: name, data, map, loader, model,
    solver, train, eval, and for real data dataset)."""
    tree = dict(tree)
    known = {"name", "data", "map", "loader", "model", "solver", "train", "eval", "dataset"}
    unknown = sorted(set(tree) - known)
    if unknown:
        raise ConfigError(f"unknown top-level config key(s) {unknown}; expected {sorted(known)}")
    map_section = dict(tree.get("map") or {})
    variant = from_dict(
        VariantConfig,
        {k: map_section[k] for k in ("kind", "road_width", "channels") if k in map_section},
        "map",
    )
    dataset = tree.get("dataset")
    if dataset is not None:
        from seglocnet_jax.data import real_convert

        real_convert.parse_tree(dataset)  # unknown keys and bad values fail here, not later
    data = from_dict(prepare_lib.PrepareConfig, tree.get("data"), "data")
    # The run's map variant is rasterized with the sensors (never re-simulated for a new one).
    data = dataclasses.replace(data, map_variants=(dataclasses.asdict(variant),))
    return ExperimentConfig(
        name=str(tree.get("name") or "experiment"),
        data=data,
        variant=variant,
        loader=from_dict(loader_lib.LoaderConfig, tree.get("loader"), "loader"),
        model=_model_config(tree.get("model"), variant),
        solver=from_dict(solver.SolverConfig, tree.get("solver"), "solver"),
        train=from_dict(TrainConfig, tree.get("train"), "train"),
        eval=from_dict(EvalConfig, tree.get("eval"), "eval"),
        dataset=dataset,
    )


def _model_config(section: dict | None, variant: VariantConfig) -> ModelConfig:
    """``model.num_classes`` follows ``map.channels`` (null or absent: derived); a number that
    disagrees is an error naming both keys."""
    section = dict(section or {})
    channels = len(variant.channels)
    if section.get("num_classes") is None:
        section["num_classes"] = channels
    elif section["num_classes"] != channels:
        raise ConfigError(
            f"model.num_classes={section['num_classes']} but map.channels={list(variant.channels)} "
            f"has {channels}; leave model.num_classes null to follow the map"
        )
    return from_dict(ModelConfig, section, "model")


def prepare_dataset(cfg: ExperimentConfig) -> str:
    """Prepares the experiment's data if its shards or map variant are missing (progress
    shown); returns the dataset directory. Real data is converted from
    ``dataset.reader.dataroot`` on first use; a converted directory is used as it is."""
    if cfg.dataset is not None:
        return _prepare_real(cfg)
    return prepare_lib.prepare(cfg.data)


def _prepare_real(cfg: ExperimentConfig) -> str:
    from seglocnet_jax.data import real_convert

    reader_cls, reader_cfg, convert_cfg = real_convert.parse_tree(cfg.dataset)
    dataset_dir = os.path.join(convert_cfg.root, convert_cfg.name)
    if _converted(dataset_dir, cfg.variant):
        return dataset_dir
    dataroot = reader_cfg.dataroot
    if not os.path.isdir(dataroot):
        raise FileNotFoundError(
            f"experiment {cfg.name!r}: data directory {dataroot!r} (dataset.reader.dataroot) "
            f"does not exist and {dataset_dir!r} holds no converted dataset with map variant "
            f"{cfg.variant.name!r}. Put the {cfg.dataset['source']} data there or pass "
            "dataset.reader.dataroot=PATH; the first run converts it (README, 'Using real data')"
        )
    dataset_dir, _ = real_convert.convert_for_training(
        reader_cls(reader_cfg), convert_cfg, cfg.variant
    )
    return dataset_dir


def _converted(dataset_dir: str, variant: VariantConfig) -> bool:
    """Whether ``dataset_dir`` holds a complete conversion with ``variant`` for every city."""
    from seglocnet_jax.data import manifest as mf
    from seglocnet_jax.data.variants import variant_path

    if not os.path.isfile(mf.manifest_path(dataset_dir)):
        return False
    man = mf.read_manifest(dataset_dir)
    if not man.get("complete") or not prepare_lib.all_shards_exist(man, dataset_dir):
        return False
    if variant.name not in man["map_variants"]:
        return False
    cities = {c for sp in man["splits"].values() for c in sp["cities"]}
    return all(os.path.exists(variant_path(dataset_dir, variant.name, c)) for c in cities)
