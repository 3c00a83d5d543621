"""Every config key is live: one source of defaults (each default group's YAML equals its
dataclass), unknown or ignored keys stop `train` and `evaluate` naming them, the simulator
presets are a selectable group, and values that can be checked without data fail up front."""

from __future__ import annotations

import dataclasses
import json

import pytest
from hydra import compose, initialize_config_dir

from seglocnet_jax import maps, sim, solver, tracking
from seglocnet_jax.app import hydra_glue
from seglocnet_jax.app.schema import TrainConfig, build_experiment
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.data import loader
from seglocnet_jax.data.simulated.config import PrepareConfig
from seglocnet_jax.model.config import TINY
from seglocnet_jax.sequential import config as seq_config


def _compose(overrides=(), name="config"):
    hydra_glue.register_resolvers()
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        return hydra_glue.to_tree(compose(config_name=name, overrides=list(overrides)))


def _plain(obj):
    return json.loads(json.dumps(dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj))


@pytest.mark.parametrize(
    "section, default, derived",
    [
        ("map", maps.MapConfig(), ()),
        ("loader", loader.LoaderConfig(), ()),
        ("model", TINY, ("num_classes",)),  # null: follows map.channels
        ("solver", solver.SolverConfig(), ()),
        ("train", TrainConfig(), ()),
        ("eval", seq_config.EvalConfig(), ()),
        ("data", PrepareConfig(), ("name", "sim")),  # name: per sim preset; sim: group
    ],
)
def test_default_group_yaml_equals_dataclass(section, default, derived):
    yaml = _compose()[section]
    want = _plain(default)
    for key in derived:
        yaml.pop(key, None)
        want.pop(key, None)
    if section == "data":
        yaml["map_variants"] = [_plain(maps.MapConfig(**v)) for v in yaml["map_variants"]]
        want["map_variants"] = [_plain(maps.MapConfig(**v)) for v in want["map_variants"]]
    assert yaml == want


@pytest.mark.parametrize(
    "section, default",
    [
        ("tracker", seq_config.TrackerSettings()),
        ("odometry", tracking.OdometryConfig()),
    ],
)
def test_sequential_sections_equal_their_one_dataclass(section, default):
    # eval.tracker is the filter's settings with one set of defaults (sequential.config), not
    # a schema generated from the filter's own config; eval.odometry is the odometry model's.
    yaml = _compose()["eval"][section]
    assert yaml == _plain(default)
    if section == "tracker":
        assert len(yaml) <= 14, sorted(yaml)
        # every setting reaches the filter's config (K, window, noise: derived)
        cfg = seq_config.tracker_config(seq_config.EvalConfig(), 64, ("road", "building"))
        for key, value in yaml.items():
            want = seq_config.OFF_ROAD_NATS if value is None else value
            assert getattr(cfg, key) == want, key


def test_sim_cpu_preset_equals_simulator_defaults():
    tree = _compose()
    assert tree["sim"]["name"] == "cpu" and tree["data"]["name"] == "sim_quick_cpu"
    for section, default in (("world", sim.WorldConfig()), ("sensors", sim.SensorConfig())):
        want = _plain(default)
        for key, value in tree["sim"][section].items():  # the preset lists the main knobs
            assert value == want[key], f"sim.{section}.{key}"


def test_sim_group_is_selectable_and_reaches_the_dataset():
    exp = build_experiment(_compose(["sim=paper"]))
    assert exp.data.name == "sim_quick_paper"  # its own dataset directory
    assert exp.data.sim["sensors"]["image_height"] == 320
    assert "name" not in exp.data.sim
    with pytest.raises(ConfigError, match="data.sim"):
        build_experiment(_compose(["+data.sim={spacing_m: 3.0}"]))


def test_map_variants_are_honoured_with_the_runs_map():
    exp = build_experiment(
        _compose(["map=sd", "map.road_width=5", "data.map_variants=[{kind: sd, road_width: 2.5}]"])
    )
    assert [maps.MapConfig(**v).name for v in exp.data.map_variants] == ["sd_w2.5_road-building"]
    assert exp.map.name == "sd_w5_road-building"


@pytest.mark.parametrize(
    "override, key",
    [
        ("+map.city=kouvola", "map.city"),  # the city is data.city: map.city is gone
        ("+map.resolution=0.25", "map.resolution"),
        ("+solver.return_volume=true", "solver.return_volume"),
        ("+train.bogus=1", "train.bogus"),
        ("+eval.bogus=1", "eval.bogus"),
        ("+loader.bogus=1", "loader.bogus"),
        ("+sim.world.bogus=1", "sim.world.bogus"),
        ("+bogus=1", "bogus"),
    ],
)
@pytest.mark.parametrize("app", ["config", "evaluate"])
def test_unknown_key_stops_train_and_evaluate(app, override, key):
    tree = _compose([override], name=app)
    tree.pop("checkpoint", None)  # the evaluate app's own key
    with pytest.raises(ConfigError) as err:
        build_experiment(tree)
    assert key.split(".")[-1] in str(err.value)


@pytest.mark.parametrize(
    "override, key",
    [
        ("train.checkpoint.every_steps=0", "train.checkpoint.every_steps"),
        ("train.eval_every=-1", "train.eval_every"),
        ("train.val_batches=0", "train.val_batches"),
        ("train.optim.learning_rate=nan", "train.optim.learning_rate"),
        ("eval.splits=[test,kouvla]", "eval.splits"),
        ("train.checkpoint.best_metric=R@5", "train.checkpoint.best_metric"),
        ("train.checkpoint.best_metric=APE", "train.checkpoint.best_mode"),
        ("map.channels=[sky]", "map.channels"),
        ("data.map_variants=[{kind: sd, road_width: 0}]", "road_width"),
        ("eval.bev_source=gt|model.variant=nm", "eval.bev_source"),
        ("sim.sensors.max_range=300", "sim.sensors.max_range"),
        ("sim.spacing_m=0", "sim.spacing_m"),
        ("data.num_val_drives=-1", "data.num_val_drives"),
        ("data.min_val_drive_m=5000", "data.min_val_drive_m"),
    ],
)
def test_bad_values_fail_before_any_work(override, key):
    with pytest.raises((ConfigError, ValueError)) as err:
        build_experiment(_compose(override.split("|")))
    assert key in str(err.value)


def test_drive_splits_can_be_evaluated_when_the_dataset_has_them():
    exp = build_experiment(_compose(["eval.splits=[drives,drives_val]"]))
    assert list(exp.eval.splits) == ["drives", "drives_val"]
    for override in ("data.num_drives=0", "data.test_city=null"):  # no drives split then
        with pytest.raises(ConfigError, match=r"\['drives'\] not in the dataset's splits"):
            build_experiment(_compose(["eval.splits=[drives,drives_val]", override]))


def test_iou_metric_can_select_the_best_checkpoint():
    exp = build_experiment(_compose(["train.checkpoint.best_metric=IoU_road"]))
    assert exp.train.checkpoint.best_metric == "IoU_road"
