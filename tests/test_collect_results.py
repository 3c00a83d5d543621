"""experiments/collect_results.py turns a sweep's job directories into one ablation table."""

import importlib.util
import json
import os

import pytest

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "experiments", "collect_results.py")


def _load():
    spec = importlib.util.spec_from_file_location("collect_results", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _result(r5):
    keys = ["R@1m", "R@2m", "R@5m", "R@10m", "R@1deg", "R@2deg", "R@5deg", "R@10deg"]
    res = {k: r5 for k in keys}
    res.update(APE=3.0, AOE=1.5, count=10)
    return res


def _job(root, name, overrides, r5):
    job = os.path.join(root, name)
    os.makedirs(os.path.join(job, ".hydra"))
    with open(os.path.join(job, ".hydra", "overrides.yaml"), "w") as f:
        f.write("".join(f"- {o}\n" for o in overrides))
    with open(os.path.join(job, "results.json"), "w") as f:
        json.dump({"splits": {"test": _result(r5)}}, f)


def test_sweep_directories_become_one_row_each(tmp_path):
    root = str(tmp_path / "multirun")
    _job(root, "map.road_width=2.5", ["+exp=sim_helsinki_sd", "map.road_width=2.5"], 40.0)
    _job(root, "map.road_width=10", ["+exp=sim_helsinki_sd", "map.road_width=10"], 61.25)
    caption, blank, *table = _load().collect(root, "test").splitlines()
    assert caption == "Split test; every job: +exp=sim_helsinki_sd" and blank == ""
    assert len(table) == 4  # header, separator, two jobs
    rows = {line.split("|")[1].strip(): line for line in table[2:]}
    assert set(rows) == {"map.road_width=2.5", "map.road_width=10"}
    assert "61.2" in rows["map.road_width=10"] and "40.0" in rows["map.road_width=2.5"]


def test_empty_directory_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no results.json"):
        _load().collect(str(tmp_path), "test")
