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


def _crashed_job(root, name, overrides, log_lines=None):
    job = os.path.join(root, name)
    os.makedirs(os.path.join(job, ".hydra"))
    with open(os.path.join(job, ".hydra", "overrides.yaml"), "w") as f:
        f.write("".join(f"- {o}\n" for o in overrides))
    if log_lines is not None:
        with open(os.path.join(job, "train.log"), "w") as f:
            f.write("".join(f"{ln}\n" for ln in log_lines))
    return job


def test_job_without_results_is_listed_as_failed_and_fails_the_script(tmp_path, capsys):
    root = str(tmp_path / "multirun")
    _job(root, "map.road_width=10", ["+exp=sim_helsinki_sd", "map.road_width=10"], 61.25)
    crashed = _crashed_job(
        root,
        "map.road_width=2.5",
        ["+exp=sim_helsinki_sd", "map.road_width=2.5"],
        [f"step {i}" for i in range(20)] + ["FloatingPointError: loss is nan at step 140"],
    )
    unfinished = _crashed_job(
        root, "map.road_width=5", ["+exp=sim_helsinki_sd", "map.road_width=5"]
    )
    mod = _load()
    text = mod.collect(root, "test")
    lines = text.splitlines()
    assert lines[0] == "Split test; every job: +exp=sim_helsinki_sd"
    rows = {ln.split("|")[1].strip(): ln for ln in lines if ln.startswith("| map.")}
    assert set(rows) == {
        "map.road_width=10",
        "map.road_width=2.5 (FAILED)",
        "map.road_width=5 (FAILED)",
    }
    assert "61.2" in rows["map.road_width=10"] and "–" in rows["map.road_width=5 (FAILED)"]
    assert f"- {crashed}: no results.json" in text and f"- {unfinished}: no results.json" in text
    assert "train.log: FloatingPointError: loss is nan at step 140" in text
    assert "train.log: step 0" not in text  # only the last lines
    assert "(no log file)" in text
    assert mod.main([root]) == 1
    assert "2 job(s) failed" in capsys.readouterr().err
    assert mod.main([root, "--allow-failed"]) == 0
    assert "map.road_width=5 (FAILED)" in capsys.readouterr().out
