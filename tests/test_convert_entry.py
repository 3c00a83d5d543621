"""The conversion entry points compose their Hydra configs (conf/dataset/*.yaml) into typed
configs and convert the fixtures."""

import dataclasses
import importlib.util
import json
import os
import pathlib

import pytest

import fixtures_real as fx
from seglocnet_jax import maps
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.real.common import RealDataError

REPO = pathlib.Path(__file__).resolve().parents[1]
FAST = [
    "dataset.convert.align.resolution=1.0",
    "dataset.convert.align.max_shift=8.0",
    "dataset.convert.align.max_rotation_deg=0.5",
    "dataset.convert.align.rotation_step_deg=0.5",
    "dataset.convert.align.scales=[1.0]",
    "dataset.reader.image_size=[12,20]",
    "dataset.convert.shard_size=4",
]


def _entry(name):
    spec = importlib.util.spec_from_file_location(name, REPO / "data_prep" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def test_convert_nuscenes_entry_point(tmp_path, capsys):
    root = tmp_path / "nus"
    fx.write_nuscenes(str(root))
    osm = tmp_path / "boston.osm"
    fx.write_osm(str(osm), maps.Projection.topocentric(*nu.MAP_ORIGINS["boston-seaport"]).to_lonlat)
    _entry("convert_nuscenes")(
        [
            f"dataset.reader.dataroot={root}",
            "dataset.reader.version=v1.0-mini",
            f"dataset.convert.root={tmp_path}",
            "dataset.convert.name=nus_mini",
            "dataset.convert.splits={train: mini_train, val: mini_val}",
            f"+dataset.convert.osm.boston-seaport={osm}",
            *FAST,
        ]
    )
    out = capsys.readouterr().out
    assert "split val: 3 frames {'boston-seaport': 3}" in out
    assert "OSM correction boston-seaport: shift (+0.00, +0.00) m" in out  # OSM written aligned
    assert "poses on the road of hd_road-building: 100.0%" in out
    assert "poses on the road of sd_w10_road-building: 100.0%" in out
    man = mf.read_manifest(tmp_path / "nus_mini")
    assert man["config"]["reader"]["image_size"] == [12, 20]


def test_convert_argoverse_entry_point_presets(tmp_path, capsys):
    root = tmp_path / "av2"
    fx.write_argoverse(str(root))
    osm = tmp_path / "pit.osm"
    lat, lon = av.CITY_FRAMES["PIT"][1]
    fx.write_osm(str(osm), maps.Projection.utm(17, origin_latlon=(lat, lon)).to_lonlat)
    _entry("convert_argoverse")(
        [
            "--preset",
            "argo_pit",
            f"dataset.reader.dataroot={root}",
            f"dataset.convert.root={tmp_path}",
            "~dataset.convert.splits.val",
            f"+dataset.convert.osm.PIT={osm}",
            *FAST,
        ]
    )
    assert "split train: 2 frames {'PIT': 2}" in capsys.readouterr().out
    man = json.loads((tmp_path / "argo_pit" / "manifest.json").read_text())
    assert man["config"]["reader"]["cities"] == ["PIT"]
    assert sorted(man["map_variants"]) == ["hd_road-building", "sd_w10_road-building"]
    with pytest.raises(Exception, match="dataset.reader.dataroot"):
        _entry("convert_argoverse")([f"dataset.convert.root={tmp_path}"])  # ??? is mandatory
    assert os.path.isdir(tmp_path / "argo_pit" / "sensors" / "train")


def test_from_tree_names_bad_keys_and_training_adds_a_variant(tmp_path):
    from seglocnet_jax.config_util import ConfigError
    from seglocnet_jax.data.real import convert as rconv
    from seglocnet_jax.maps import MapConfig

    with pytest.raises(ConfigError, match="dataset.source must be one of"):
        rconv.from_tree({"source": "kitti"})
    with pytest.raises(ConfigError, match=r"dataset\.reader\.cams"):
        rconv.from_tree({"source": "av2", "reader": {"dataroot": "x", "cams": []}})
    root = tmp_path / "av2"
    fx.write_argoverse(str(root))
    reader, cfg = rconv.from_tree(
        {
            "source": "av2",
            "reader": {"dataroot": str(root), "cities": ["MIA"], "image_size": [12, 20]},
            "convert": {
                "root": str(tmp_path),
                "name": "mia",
                "map_variants": [{"kind": "hd", "channels": ["road"]}],
                "align": {"enabled": False},
            },
        }
    )
    ddir, name = rconv.convert_for_training(reader, cfg, MapConfig("hd", channels=("road",)))
    assert name == "hd_road"
    reader.load = lambda frame: pytest.fail("sensors read again")
    sd = MapConfig("sd", road_width=5.0, channels=("road",))
    with pytest.raises(RealDataError, match=r"needs OSM: set dataset\.convert\.osm\.MIA"):
        rconv.convert_for_training(reader, cfg, sd)
    osm = tmp_path / "mia.osm"
    lat, lon = av.CITY_FRAMES["MIA"][1]
    fx.write_osm(str(osm), maps.Projection.utm(17, origin_latlon=(lat, lon)).to_lonlat)
    with_osm = dataclasses.replace(cfg, osm={"MIA": str(osm)})
    assert rconv.convert_for_training(reader, with_osm, sd) == (ddir, "sd_w5_road")
    assert set(mf.read_manifest(ddir)["map_variants"]) == {"hd_road", "sd_w5_road"}
