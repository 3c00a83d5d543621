"""Every experiment in conf/exp composes into a valid typed config; the real-data experiments
name their missing data directory, convert on first use and then reuse the conversion."""

from __future__ import annotations

import glob
import os
import shutil

import pytest
from hydra import compose, initialize_config_dir

import fixtures_real as fx
from seglocnet_jax import maps
from seglocnet_jax.app import hydra_glue
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.schema import build_experiment
from seglocnet_jax.data.loader import make_loader
from seglocnet_jax.data.real import nuscenes as nu

EXPS = sorted(
    os.path.splitext(os.path.basename(p))[0]
    for p in glob.glob(os.path.join(hydra_glue.conf_dir(), "exp", "*.yaml"))
)
REAL = {"nusc_hd": "nuscenes", "nusc_sd": "nuscenes", "argo_mia": "av2", "argo_pit": "av2"}


def _compose(overrides):
    hydra_glue.register_resolvers()
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        return hydra_glue.to_tree(compose(config_name="config", overrides=overrides))


def test_every_paper_experiment_exists():
    assert set(REAL) | {"sim_helsinki", "sim_helsinki_sd", "sim_generalization"} <= set(EXPS)


@pytest.mark.parametrize("name", EXPS)
def test_experiment_composes_and_builds(name):
    exp = build_experiment(_compose([f"+exp={name}"]))
    assert exp.name == name
    assert (exp.dataset is not None) == (name in REAL)
    if name in REAL:
        assert exp.dataset["source"] == REAL[name]
    assert exp.map.kind == ("sd" if name.endswith("_sd") or name == "sim_generalization" else "hd")


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_experiment_names_the_missing_data_directory(name, tmp_path):
    missing = str(tmp_path / "no_such_dataroot")
    exp = build_experiment(
        _compose(
            [
                f"+exp={name}",
                f"dataset.reader.dataroot={missing}",
                f"dataset.convert.root={tmp_path / 'out'}",
            ]
        )
    )
    with pytest.raises(FileNotFoundError, match="no_such_dataroot.*dataset.reader.dataroot"):
        prepare_dataset(exp)


def test_real_experiment_unknown_dataset_key_is_named():
    with pytest.raises(Exception, match="dataset.reader.bogus"):
        build_experiment(_compose(["+exp=nusc_hd", "+dataset.reader.bogus=1"]))


def test_nuscenes_experiment_converts_then_reuses(tmp_path):
    root = str(tmp_path / "nuscenes")
    fx.write_nuscenes(root)
    osm = str(tmp_path / "boston.osm")
    fx.write_osm(osm, maps.Projection.topocentric(*nu.MAP_ORIGINS["boston-seaport"]).to_lonlat)
    overrides = [
        "+exp=nusc_sd",
        "model=tiny",
        f"dataset.reader.dataroot={root}",
        "dataset.reader.version=v1.0-mini",
        "dataset.reader.image_size=[16,32]",
        f"dataset.convert.root={tmp_path / 'out'}",
        "dataset.convert.shard_size=2",
        "dataset.convert.splits={train: mini_train, val: mini_val}",
        f"+dataset.convert.osm.boston-seaport={osm}",
        "dataset.convert.map_variants=[{kind: hd}]",
        "dataset.convert.align.enabled=false",
        "map.road_width=8.0",
    ]
    exp = build_experiment(_compose(overrides))
    ddir = prepare_dataset(exp)  # converts sensors, the listed HD variant and the run's SD one
    batch = next(iter(make_loader(ddir, "val", exp.map.name, 1, 0, train=False)))
    assert batch["tile"].shape[1:] == (2, 256, 256)
    assert batch["images"].shape[2:4] == (16, 32)
    shutil.rmtree(root)  # converted: the raw data is no longer needed
    assert prepare_dataset(exp) == ddir


def test_model_classes_follow_map_channels():
    exp = build_experiment(_compose(["map.channels=[road]"]))
    assert exp.model.num_classes == 1 and exp.map.channels == ("road",)
    with pytest.raises(Exception, match="model.num_classes=2 but map.channels"):
        build_experiment(_compose(["map.channels=[building]", "model.num_classes=2"]))
