"""The evaluate app writes one consistent set from verified data: two checkpoints get two
directories (and a rerun into one never leaves the other's figures), another mode replaces the
whole set, a killed re-evaluation leaves the previous complete set (or a directory that says it
is incomplete, which the collectors refuse), and damaged drive shards stop the evaluation before
any work."""

import glob
import importlib.util
import json
import os
import shutil
import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from apphelpers import DRIVES_EVAL, TINY_DRIVES, app_tree
from seglocnet_jax.app import eval_run, evalset, hydra_glue, runs, train_run
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.schema import build_experiment
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records

EXPERIMENTS = os.path.join(os.path.dirname(__file__), "..", "experiments")


def _tree(root, *, train=None, **eval_):
    ev = {"mode": "single", "splits": ["test"], "batch_size": 2, "num_figures": 0, **DRIVES_EVAL}
    return app_tree(root, "evalrun", TINY_DRIVES, train=train, eval_={**ev, **eval_})


def _cfg(root, **eval_):
    return build_experiment(_tree(root, **eval_))


def _script(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXPERIMENTS, f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _aside(workdir):
    return sorted(glob.glob(os.path.join(workdir, "evaluation.discarded-*")))


def _figures(workdir, split="test"):
    path = os.path.join(workdir, "figures", split)
    return sorted(os.listdir(path)) if os.path.isdir(path) else []


@pytest.fixture(scope="module")
def run_a(drives_data_root, tmp_path_factory):
    """A tiny training run with checkpoints at steps 2 and 4 (best: 4)."""
    workdir = str(tmp_path_factory.mktemp("evalrun") / "run_a")
    train = {"num_steps": 4, "checkpoint": {"every_steps": 2, "keep_last": 2}}
    tree = _tree(drives_data_root, train=train, max_batches=1)
    train_run.train_and_evaluate(build_experiment(tree), workdir)
    return workdir


def _eval_dir(*overrides, app="evaluate"):
    hydra_glue.register_resolvers()
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        cfg = compose(app, list(overrides), return_hydra_config=True)
        return str(OmegaConf.select(cfg, "hydra.run.dir"))


def test_two_checkpoints_get_two_directories_and_never_share_a_set(
    drives_data_root, run_a, tmp_path, capsys
):
    # The default directory names the checkpoint (run and step) and what changes the numbers.
    run_b = str(tmp_path / "run_b")
    shutil.copytree(run_a, run_b)  # another run directory (same parameters)
    last = os.path.join(run_a, "checkpoints", "last")
    dirs = {
        "a": _eval_dir(f"checkpoint={run_a}"),
        "a2": _eval_dir(f"checkpoint={os.path.join(last, '2')}"),
        "b": _eval_dir(f"checkpoint={run_b}"),
        "a_seq": _eval_dir(f"checkpoint={run_a}", "eval.mode=sequential"),
        "gt": _eval_dir("eval.bev_source=gt"),
        "gt_sd": _eval_dir("eval.bev_source=gt", "map=sd"),
    }
    assert len(set(dirs.values())) == len(dirs)
    assert os.path.basename(dirs["a"]).startswith("eval_run_a-step4_both_")
    assert "eval_run_a-step2_both_" in dirs["a2"] and "eval_run_b-step4_both_" in dirs["b"]
    assert "_sequential_" in dirs["a_seq"]
    assert os.path.basename(dirs["gt"]).startswith("eval_gt_both_")
    assert "_hd_road-building_" in dirs["gt"] and "_sd_w10.0_road-building_" in dirs["gt_sd"]
    # Training runs too: HD maps ignore the road width, so HD names carry none.
    assert "_hd_road-building_" in _eval_dir("map.road_width=5", app="config")
    assert "_sd_w5_road-building_" in _eval_dir("map=sd", "map.road_width=5", app="config")

    # Two checkpoints into one directory: the second set replaces the first whole.
    workdir = str(tmp_path / "eval")
    eval_run.run_evaluation(_cfg(drives_data_root, num_figures=2), os.path.join(last, "4"), workdir)
    assert len(_figures(workdir)) == 2
    first = json.load(open(os.path.join(workdir, "config.json")))
    eval_run.run_evaluation(_cfg(drives_data_root, num_figures=1), os.path.join(last, "2"), workdir)
    out = capsys.readouterr().out
    assert len(_figures(workdir)) == 1  # none of the step-4 figures is left beside it
    saved = json.load(open(os.path.join(workdir, "results.json")))
    assert saved["step"] == 2
    ident = json.load(open(os.path.join(workdir, "config.json")))
    ck = ident["evaluation"]["checkpoint"]
    assert ck["step"] == 2 and ck["run_dir"] == run_a and ck["checksum"].startswith("sha256:")
    assert ck["checksum"] != first["evaluation"]["checkpoint"]["checksum"]
    assert ident["config"]["eval"]["num_figures"] == 1
    assert "checkpoint.step: 4 -> 2" in out and "eval.num_figures: 2 -> 1" in out
    (old,) = _aside(workdir)
    assert f"moved the previous evaluation set of {workdir} to {old}" in out
    assert len(_figures(old)) == 2
    assert json.load(open(os.path.join(old, "results.json")))["step"] == 4
    # A training run's directory is not an evaluation's.
    with pytest.raises(ConfigError, match="training run's directory"):
        eval_run.run_evaluation(_cfg(drives_data_root), run_a, run_a)


def test_another_mode_replaces_the_whole_set(drives_data_root, tmp_path):
    workdir = str(tmp_path / "gt")
    single = _cfg(drives_data_root, bev_source="gt", num_figures=2)
    eval_run.run_evaluation(single, None, workdir, ["eval.bev_source=gt"])
    assert len(_figures(workdir)) == 2
    seq = _cfg(
        drives_data_root,
        bev_source="gt",
        mode="sequential",
        temperature=50.0,
        num_figures=1,
        max_drives=1,
    )
    eval_run.run_evaluation(seq, None, workdir, ["eval.mode=sequential"])
    saved = json.load(open(os.path.join(workdir, "results.json")))
    assert saved["splits"] == {} and set(saved["sequential"]) == {"drives_val"}
    assert _figures(workdir) == []  # the single-frame figures went with their set
    assert os.listdir(os.path.join(workdir, "figures", "sequential"))
    (old,) = _aside(workdir)
    assert len(_figures(old)) == 2 and not os.path.exists(os.path.join(old, "sequential"))
    assert set(json.load(open(os.path.join(old, "results.json")))["splits"]) == {"test"}
    # The set's own overrides name its row (Hydra's .hydra/ is rewritten by any later command).
    assert _script("collect_results")._overrides(workdir) == ["eval.mode=sequential"]


def _consistent(workdir):
    """results.json and the per-frame arrays beside it describe the same run."""
    s = json.load(open(os.path.join(workdir, "results.json")))["sequential"]["drives_val"]
    arrays = np.load(os.path.join(workdir, "sequential", "drives_val.npz"))
    assert s["mean_log_p_gt"] == pytest.approx(float(arrays["log_p_gt"].mean()), rel=1e-6)
    err = np.hypot(*(arrays["filtered"][:, :2] - arrays["gt"][:, :2]).T)
    assert s["filtered"]["APE"] == pytest.approx(float(err.mean()), rel=1e-4, abs=1e-6)
    return s


def test_a_killed_reevaluation_leaves_a_complete_set_or_says_it_is_incomplete(
    drives_data_root, tmp_path, monkeypatch, capsys
):
    workdir = str(tmp_path / "seq")
    fixed = dict(bev_source="gt", mode="sequential", num_figures=1, temperature_drives=None)
    fixed.update(max_drives=1, max_batches=1)  # one drive; the fit on one batch of val
    eval_run.run_evaluation(_cfg(drives_data_root, temperature=50.0, **fixed), None, workdir)
    assert _consistent(workdir)["temperature"] == 50.0
    before = sorted(os.listdir(workdir))

    # Killed (kill -9: nothing cleans up) after the arrays and figures, before results.json.
    def killed(*args, **kwargs):
        raise KeyboardInterrupt("killed")

    fitted = _cfg(drives_data_root, **fixed)
    with monkeypatch.context() as m:
        m.setattr(runs, "write_results", killed)
        m.setattr(evalset.OutputSet, "abandon", lambda self: None)
        with pytest.raises(KeyboardInterrupt):
            eval_run.run_evaluation(fitted, None, workdir)
    (staging,) = glob.glob(os.path.join(workdir, "evaluation.staging-*"))
    assert os.path.exists(os.path.join(staging, "sequential", "drives_val.npz"))
    assert sorted(os.listdir(workdir)) == sorted([*before, os.path.basename(staging)])
    assert _consistent(workdir)["temperature"] == 50.0  # the previous set, whole

    # Killed while moving its set in: the directory says it is incomplete; readers refuse it.
    moves = []

    def cut(src, dst):
        moves.append(src)
        if len(moves) == 6:  # the old set is aside, part of the new one is in
            raise KeyboardInterrupt("killed")
        os.rename(src, dst)

    with monkeypatch.context() as m:
        m.setattr(evalset, "_move", cut)
        m.setattr(evalset.OutputSet, "abandon", lambda self: None)
        with pytest.raises(KeyboardInterrupt):
            eval_run.run_evaluation(fitted, None, workdir)
    out = capsys.readouterr().out
    assert "removed evaluation.staging-" in out  # the first kill's leftovers
    marker = os.path.join(workdir, evalset.INCOMPLETE)
    assert os.path.exists(marker) and not os.path.exists(os.path.join(workdir, "results.json"))
    text, failed = _script("collect_results").collect_jobs(str(tmp_path), "drives_val")
    assert [(job, marker in reason) for job, reason in failed] == [(workdir, True)]
    assert "FAILED" in text
    paper = _script("paper_tables")
    with pytest.raises(ValueError, match=marker):
        paper.store_result(paper.BY_NAME["gt_hd"], "cpu", workdir, str(tmp_path / "store"))

    # The next evaluation moves the partial set aside and writes a whole one.
    eval_run.run_evaluation(fitted, None, workdir)
    assert "was cut off while moving its files in" in capsys.readouterr().out
    assert not os.path.exists(marker) and _consistent(workdir)["temperature_fit"] is not None
    assert not glob.glob(os.path.join(workdir, "evaluation.staging-*"))
    assert len(_aside(workdir)) == 2  # the T = 50 set, then the partial one
    assert _script("collect_results")._failure(workdir) is None  # no longer refused


@pytest.fixture(scope="module")
def prepared(drives_data_root):
    return prepare_dataset(_cfg(drives_data_root))


def _reverse_first_shard(man, dataset_dir):
    """Shard 0 of drives_val replaced by another of the same record count (manifest untouched)."""
    path = os.path.join(dataset_dir, man["splits"]["drives_val"]["shards"][0]["file"])
    reader = records.ArrayRecordReader(path)
    recs = list(reader.read_all())
    reader.close()
    records.write_shard(path, recs[::-1])
    return "SHA-256"


def _edit_checksum(man, dataset_dir):
    shard = man["splits"]["drives_val"]["shards"][0]
    shard["sha256"] = "0" * 64
    mf.write_manifest(dataset_dir, man)
    return "SHA-256"


def _edit_count(man, dataset_dir):
    man["splits"]["drives_val"]["count"] -= 1
    mf.write_manifest(dataset_dir, man)
    return "split 'drives_val' records count"


@pytest.mark.parametrize("damage", [_reverse_first_shard, _edit_checksum, _edit_count])
def test_damaged_drive_shards_stop_the_evaluation_before_any_work(
    prepared, tmp_path, damage, capsys
):
    root = str(tmp_path / "data")
    dataset_dir = os.path.join(root, TINY_DRIVES["name"])
    shutil.copytree(prepared, dataset_dir)
    want = damage(mf.read_manifest(dataset_dir), dataset_dir)
    workdir = str(tmp_path / "e")
    cfg = _cfg(root, bev_source="gt", mode="sequential", temperature_drives=None)
    with pytest.raises((records.RecordError, mf.ManifestError), match=want) as err:
        eval_run.run_evaluation(cfg, None, workdir)
    assert "drives_val" in str(err.value)
    assert "temperature fit" not in capsys.readouterr().err  # before the fit on val
    assert os.listdir(workdir) == [".lock"]  # nothing written, no staging left
