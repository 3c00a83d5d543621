"""The data presets compose into valid typed configs; bad keys and values are named."""

import os

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.data.simulated.config import PrepareConfig

CONF = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "conf"))


def _data(preset):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        tree = OmegaConf.to_container(compose("config", [f"data={preset}"]), resolve=True)
    return tree["data"]  # data.name interpolates the sim preset's name


def test_presets_compose_and_full_is_ten_times_quick():
    quick = from_dict(PrepareConfig, _data("quick"), "data")
    full = from_dict(PrepareConfig, _data("full"), "data")
    assert (quick.num_train, quick.num_val, quick.num_test, quick.num_test_city) == (
        2000,
        300,
        300,
        300,
    )
    for key in ("num_train", "num_val", "num_test", "num_test_city"):
        assert getattr(full, key) >= 10 * getattr(quick, key), key
    assert quick.identity() != full.identity() and full.name != quick.name
    assert quick.name == "sim_quick_cpu" and full.name == "sim_full_cpu"
    assert [v["kind"] for v in quick.map_variants] == ["hd"]  # the run adds its own map


def test_unknown_key_and_bad_variant_are_named():
    data = _data("quick")
    data["num_trian"] = 5
    with pytest.raises(ConfigError, match="data.num_trian"):
        from_dict(PrepareConfig, data, "data")
    data = _data("quick")
    data["map_variants"] = [{"kind": "xd"}]
    with pytest.raises(ConfigError, match=r"data.map_variants\[0\]"):
        from_dict(PrepareConfig, data, "data")
