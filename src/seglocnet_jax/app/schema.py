"""The experiment schema: every component's frozen config in one tree, built from a plain dict
(a resolved Hydra config), with every value that can be checked without data checked here,
before any work: unknown keys, bad values, periods and counts, the evaluation splits against
the splits the dataset will have, the best-checkpoint metric against the metric names.

The YAML files under ``conf/`` and the dataclass defaults are one truth: ``tests/test_config.py``
holds every default group's YAML against its dataclass.
"""

from __future__ import annotations

import dataclasses
import math

from seglocnet_jax import maps, metrics, solver
from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.data.simulated.config import PrepareConfig
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.sequential.config import EvalConfig
from seglocnet_jax.training.checkpoint import CheckpointConfig
from seglocnet_jax.training.state import OptimConfig

SECTIONS = ("name", "data", "sim", "map", "loader", "model", "solver", "train", "eval", "dataset")


@dataclasses.dataclass(frozen=True)
class OptimSection:
    """``train.optim``: AdamW with linear warmup and cosine decay over ``train.num_steps``.

    Attributes:
      learning_rate: peak learning rate (CPU budget 2e-3, chosen on validation at 1,000 steps;
          paper 1e-4, ``train=paper``).
      weight_decay: decoupled weight decay.
      warmup_steps: linear warmup (None: 5% of the run, at most 100 steps).
      final_lr_ratio: the cosine decays to ``learning_rate * final_lr_ratio``.
      grad_clip: global-norm clip (<= 0 disables).
    """

    learning_rate: float = 2e-3
    weight_decay: float = 0.01
    warmup_steps: int | None = None
    final_lr_ratio: float = 0.01
    grad_clip: float = 1.0

    def __post_init__(self):
        for key in ("learning_rate", "weight_decay", "final_lr_ratio", "grad_clip"):
            if not math.isfinite(getattr(self, key)):
                raise ValueError(f"train.optim.{key} must be finite, got {getattr(self, key)}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """``train``. Attributes:
    seed: model initialization, dropout and data order seed.
    batch_size: global batch (sharded over the "data" mesh axis).
    num_steps: optimizer steps (the cosine schedule spans them).
    num_devices: devices in the mesh (None: all).
    log_every: logging period in steps.
    eval_every: validation period in steps (0: validate only at the end).
    val_batches: validation batches per evaluation (None: the whole split).
    init_from: checkpoint (run directory or step directory) whose parameters start a new run
      (fine-tuning, e.g. Argoverse from nuScenes); ignored when the run resumes its own.
    restart: move this run directory's checkpoints aside (``checkpoints.discarded-<time>``)
      and start from step 0 instead of refusing a changed config or unusable checkpoints.
    optim: :class:`OptimSection`; checkpoint: :class:`CheckpointConfig`.
    """

    seed: int = 0
    batch_size: int = 8
    num_steps: int = 1000
    num_devices: int | None = None
    log_every: int = 20
    eval_every: int = 250
    val_batches: int | None = 10
    init_from: str | None = None
    restart: bool = False
    optim: OptimSection = OptimSection()
    checkpoint: CheckpointConfig = CheckpointConfig()

    def __post_init__(self):
        for key in ("num_steps", "batch_size", "log_every"):
            if getattr(self, key) < 1:
                raise ValueError(f"train.{key} must be >= 1, got {getattr(self, key)}")
        if self.eval_every < 0:
            raise ValueError(
                f"train.eval_every must be >= 0 (0: only at the end), got {self.eval_every}"
            )
        if self.val_batches is not None and self.val_batches < 1:
            raise ValueError(
                f"train.val_batches must be >= 1 or null (the whole split), got {self.val_batches}"
            )
        if self.num_devices is not None and self.num_devices < 1:
            raise ValueError(f"train.num_devices must be >= 1 or null, got {self.num_devices}")
        self.optim_config()  # validates train.optim against num_steps

    def optim_config(self) -> OptimConfig:
        o = self.optim
        warmup = min(100, self.num_steps // 20) if o.warmup_steps is None else o.warmup_steps
        return from_dict(
            OptimConfig,
            {
                "learning_rate": o.learning_rate,
                "weight_decay": o.weight_decay,
                "warmup_steps": warmup,
                "total_steps": self.num_steps,
                "final_lr_ratio": o.final_lr_ratio,
                "grad_clip": o.grad_clip,
            },
            "train.optim",
        )


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    """The whole run. ``data`` is the simulator's dataset (None for real data, which ``dataset``
    describes: ``conf/dataset/*.yaml``, validated by ``data.real.convert.parse_tree``)."""

    name: str
    data: PrepareConfig | None
    map: maps.MapConfig
    loader: loader_lib.LoaderConfig
    model: ModelConfig
    solver: solver.SolverConfig
    train: TrainConfig
    eval: EvalConfig
    dataset: dict | None = None


def build_experiment(tree: dict) -> ExperimentConfig:
    """``tree``: the resolved Hydra config as a dict (sections :data:`SECTIONS`)."""
    tree = dict(tree)
    unknown = sorted(set(tree) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"unknown top-level config key(s) {unknown}; expected {list(SECTIONS)}")
    map_cfg = from_dict(maps.MapConfig, tree.get("map"), "map")
    dataset = tree.get("dataset")
    data = _data_config(tree, dataset, map_cfg)
    cfg = ExperimentConfig(
        name=str(tree.get("name") or "experiment"),
        data=data,
        map=map_cfg,
        loader=from_dict(loader_lib.LoaderConfig, tree.get("loader"), "loader"),
        model=_model_config(tree.get("model"), map_cfg),
        solver=from_dict(solver.SolverConfig, tree.get("solver"), "solver"),
        train=from_dict(TrainConfig, tree.get("train"), "train"),
        eval=from_dict(EvalConfig, tree.get("eval"), "eval"),
        dataset=dataset,
    )
    _check_cross(cfg)
    return cfg


def _data_config(tree: dict, dataset, map_cfg) -> PrepareConfig | None:
    if dataset is not None:
        from seglocnet_jax.data.real import convert as real_convert

        real_convert.parse_tree(dataset)  # unknown keys and bad values fail here, not later
        for section in ("data", "sim"):
            if tree.get(section):
                raise ConfigError(
                    f"{section}.* configures the simulator dataset, but this experiment reads "
                    f"real data (dataset.source={dataset.get('source')!r}); set its options "
                    f"under dataset.reader / dataset.convert (got {section}: "
                    f"{sorted(tree[section])})"
                )
        return None
    data = dict(tree.get("data") or {})
    sim = tree.get("sim")
    if sim is not None:
        if data.get("sim"):
            raise ConfigError(
                "data.sim and the sim group are both set; use sim=cpu|paper and "
                "sim.* overrides only"
            )
        sim = dict(sim)
        sim.pop("name", None)  # the preset's name: part of data.name through the YAML
        data["sim"] = sim
    prep = from_dict(PrepareConfig, data, "data")
    if prep.source == "sim":
        from seglocnet_jax.data.simulated.source import parse_sim_config

        parse_sim_config(prep.sim, "sim")  # before any simulation
    return prep


def _model_config(section: dict | None, map_cfg: maps.MapConfig) -> ModelConfig:
    """``model.num_classes`` follows ``map.channels`` (null or absent: derived); a number that
    disagrees is an error naming both keys."""
    section = dict(section or {})
    channels = len(map_cfg.channels)
    if section.get("num_classes") is None:
        section["num_classes"] = channels
    elif section["num_classes"] != channels:
        raise ConfigError(
            f"model.num_classes={section['num_classes']} but map.channels={list(map_cfg.channels)} "
            f"has {channels}; leave model.num_classes null to follow the map"
        )
    return from_dict(ModelConfig, section, "model")


def metric_names(channels) -> list[str]:
    """Names a validation result holds (``train.checkpoint.best_metric`` must be one)."""
    cfg = metrics.MetricsConfig()
    names = [metrics.position_key(t) for t in cfg.position_thresholds]
    names += [metrics.yaw_key(t) for t in cfg.yaw_thresholds]
    return names + ["APE", "AOE"] + [f"IoU_{c}" for c in channels]


LOWER_IS_BETTER = ("APE", "AOE")


def dataset_splits(cfg: ExperimentConfig) -> list[str] | None:
    """The splits the prepared dataset will have (None: known only from its manifest)."""
    if cfg.data is None:
        from seglocnet_jax.data.real import convert as real_convert

        _, _, convert_cfg = real_convert.parse_tree(cfg.dataset)
        return sorted(convert_cfg.splits)
    return cfg.data.split_names()  # + the test city's split and the drives, when configured


def _check_sequential_splits(ev, splits: list[str]) -> None:
    """eval.mode=sequential|both: every split it reads must be one the dataset will have."""
    wanted = [("eval.sequential_splits", s) for s in ev.sequential_splits]
    if ev.calibration_split:
        wanted.append(("eval.calibration_split", ev.calibration_split))
    if ev.temperature is None:
        wanted.append(("eval.temperature_split", ev.temperature_split))
        if ev.temperature_drives:
            wanted.append(("eval.temperature_drives", ev.temperature_drives))
    for key, split in wanted:
        if split not in splits:
            raise ConfigError(
                f"{key}: split {split!r} (eval.mode={ev.mode}) is not in the dataset's splits "
                f"{splits}; name one of them, or set eval.mode=single"
                + ("" if not key.startswith("eval.temperature") else " or a fixed eval.temperature")
            )


def _check_cross(cfg: ExperimentConfig) -> None:
    ck = cfg.train.checkpoint
    names = metric_names(cfg.map.channels)
    if ck.best_metric not in names:
        raise ConfigError(
            f"train.checkpoint.best_metric={ck.best_metric!r} is not a validation metric; "
            f"choose one of {names}"
        )
    want = "min" if ck.best_metric in LOWER_IS_BETTER else "max"
    if ck.best_mode != want:
        raise ConfigError(
            f"train.checkpoint.best_mode={ck.best_mode!r} with best_metric={ck.best_metric!r}: "
            f"{ck.best_metric} is better when {'lower' if want == 'min' else 'higher'}; use "
            f"best_mode={want}"
        )
    splits = dataset_splits(cfg)
    if splits is not None:
        missing = [s for s in cfg.eval.splits if s not in splits]
        if missing:
            raise ConfigError(
                f"eval.splits={list(cfg.eval.splits)}: {missing} not in the dataset's splits "
                f"{splits}"
            )
        for need in ("train", "val"):
            if need not in splits:
                raise ConfigError(f"the dataset has no {need!r} split (splits: {splits})")
        if cfg.eval.sequential:
            _check_sequential_splits(cfg.eval, splits)
    if cfg.eval.sequential:
        from seglocnet_jax import sequential

        try:  # the filter's config, as the evaluation will build it
            sequential.tracker_config(cfg.eval, cfg.solver.num_rotations, cfg.map.channels)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"eval.tracker / eval.odometry: {err}") from err
        off_road = cfg.eval.tracker.off_road
        if off_road is not None and off_road > 0 and "road" not in cfg.map.channels:
            raise ConfigError(
                f"eval.tracker.off_road={cfg.eval.tracker.off_road} reads the map's road channel, "
                f"but map.channels={list(cfg.map.channels)} has none; set eval.tracker.off_road=0"
            )
    if cfg.eval.bev_source == "gt" and cfg.model.variant == "nm":
        raise ConfigError(
            "eval.bev_source=gt localizes the GT labels against the binary map: it has no neural "
            "map; use model.variant=seg (the model is not used) for the upper bound"
        )
