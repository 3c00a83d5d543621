"""The training and evaluation apps end to end on a tiny simulated dataset: train + evaluate with
figures, the GT upper bound, bit-identical reruns, kill-and-resume, and config errors."""

import json
import os

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from apphelpers import TINY, app_tree
from seglocnet_jax import evaluation, maps
from seglocnet_jax.app import eval_run, train_run
from seglocnet_jax.app.schema import build_experiment
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import step as step_lib


@pytest.fixture(scope="module")
def data_root(tiny_data_root):
    return tiny_data_root


def _tree(data_root, **train):
    return app_tree(
        data_root,
        "app_test",
        TINY,
        train={"num_steps": 4, "optim": {"warmup_steps": 1, "learning_rate": 1e-3}, **train},
        eval_={
            "mode": "single",  # no drive splits here: tests/test_sequential.py tracks drives
            "splits": ["test"],
            "num_figures": 1,
            "batch_size": 4,
            "max_batches": 1,
        },
    )


def _final_params(workdir):
    mngr = ocp.CheckpointManager(os.path.join(workdir, "checkpoints", "last"))
    step = mngr.latest_step()
    tree = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))
    mngr.close()
    return step, tree["state"]["params"]


def test_train_evaluate_gt_and_figures(data_root, tmp_path, capsys):
    cfg = build_experiment(_tree(data_root, eval_every=2))
    workdir = str(tmp_path / "run")
    results = train_run.train_and_evaluate(cfg, workdir)
    out = capsys.readouterr().out
    assert "| app_test [hd_road-building, tiny-seg] test |" in out  # the paper-style table
    assert "[seglocnet] time: data preparation" in out
    timing = json.load(open(os.path.join(workdir, "results.json")))["time"]
    assert f"(single-frame {timing['single_frame_s']:.0f} s), total" in out  # no drives here
    assert results["test"]["count"] == 4  # one batch of 4 (eval.max_batches=1)
    # The simulator's records know their lighting: each condition's frames are also summarized.
    by_lighting = results["test"]["lighting"]
    assert set(by_lighting) <= {"day", "dusk", "night"}
    assert sum(sub["count"] for sub in by_lighting.values()) == 4
    if len(by_lighting) > 1:  # the table's rows of each condition
        assert all(
            f"test, {name} frames only ({sub['count']})" in out for name, sub in by_lighting.items()
        )
    else:  # one condition: its rows would repeat the split's
        assert "frames only" not in out
    saved = json.load(open(os.path.join(workdir, "results.json")))
    assert saved["splits"]["test"]["APE"] == pytest.approx(results["test"]["APE"])
    assert os.listdir(os.path.join(workdir, "figures", "test"))
    assert any(f.startswith("events") for f in os.listdir(os.path.join(workdir, "tb")))
    lines = [json.loads(ln) for ln in open(os.path.join(workdir, "metrics.jsonl"))]
    assert {"train", "val", "test"} <= {ln["split"] for ln in lines}

    # evaluate app from the run's checkpoint reproduces the run's test numbers.
    ev = eval_run.run_evaluation(cfg, workdir, str(tmp_path / "eval"))
    assert ev["test"]["APE"] == pytest.approx(results["test"]["APE"], abs=1e-6)

    # GT-segmentation upper bound: no checkpoint, same code path, near-perfect localization.
    gt_cfg = build_experiment(
        {
            **_tree(data_root),
            "eval": {
                "bev_source": "gt",
                "mode": "single",
                "splits": ["test", "val"],
                "num_figures": 1,
                "batch_size": 4,
            },
        }
    )
    gt = eval_run.run_evaluation(gt_cfg, None, str(tmp_path / "gt"))
    assert gt["test"]["count"] == 8 and gt["val"]["count"] == 8
    assert gt["test"]["R@5m"] >= 75.0 and gt["val"]["R@5m"] >= 75.0
    assert os.listdir(tmp_path / "gt" / "figures" / "val")


def test_missing_checkpoint_is_reported(data_root, tmp_path):
    cfg = build_experiment(_tree(data_root))
    with pytest.raises(ckpt_lib.CheckpointError, match="required"):
        eval_run.run_evaluation(cfg, None, str(tmp_path / "e"))
    with pytest.raises(ckpt_lib.CheckpointError, match="does not exist"):
        eval_run.run_evaluation(cfg, str(tmp_path / "nowhere"), str(tmp_path / "e"))


def test_rerun_is_bit_identical_and_resume_equals_uninterrupted(data_root, tmp_path, monkeypatch):
    cfg = build_experiment(_tree(data_root))
    train_run.train_and_evaluate(cfg, str(tmp_path / "a"))
    train_run.train_and_evaluate(cfg, str(tmp_path / "b"))
    step_a, params_a = _final_params(str(tmp_path / "a"))
    step_b, params_b = _final_params(str(tmp_path / "b"))
    assert step_a == step_b == 4
    for x, y in zip(jax.tree.leaves(params_a), jax.tree.leaves(params_b), strict=True):
        np.testing.assert_array_equal(x, y)

    # Kill during step 3 (after the step-2 checkpoint), then run again: it resumes.
    real_make = step_lib.make_train_step

    def killing_make(*args, **kwargs):
        fn = real_make(*args, **kwargs)
        calls = {"n": 0}

        def step(state, batch):
            calls["n"] += 1
            if calls["n"] == 3:
                raise KeyboardInterrupt("simulated kill")
            return fn(state, batch)

        return step

    monkeypatch.setattr(step_lib, "make_train_step", killing_make)
    with pytest.raises(KeyboardInterrupt):
        train_run.train_and_evaluate(cfg, str(tmp_path / "c"))
    monkeypatch.setattr(step_lib, "make_train_step", real_make)
    assert _final_params(str(tmp_path / "c"))[0] == 2
    train_run.train_and_evaluate(cfg, str(tmp_path / "c"))
    step_c, params_c = _final_params(str(tmp_path / "c"))
    assert step_c == 4
    for x, y in zip(jax.tree.leaves(params_a), jax.tree.leaves(params_c), strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize(
    "override, key",
    [
        ({"train": {"bogus": 1}}, "train.bogus"),
        ({"train": {"batch_size": 0}}, "train.batch_size"),
        ({"train": {"optim": {"learning_rate": -1.0}}}, "train.optim.learning_rate"),
        ({"eval": {"bev_source": "oracle"}}, "eval.bev_source"),
        ({"map": {"kind": "xd"}}, "map"),
        ({"solver": {"num_rotations": 30}}, "solver.num_rotations"),
        ({"model": {"modality": "radar"}}, "model"),
        ({"bogus_section": {}}, "bogus_section"),
    ],
)
def test_bad_config_names_the_key(data_root, override, key):
    tree = _tree(data_root)
    for section, values in override.items():
        if section in tree and isinstance(tree[section], dict):
            merged = dict(tree[section])
            for k, v in values.items():
                merged[k] = {**merged[k], **v} if isinstance(v, dict) and k in merged else v
            tree[section] = merged
        else:
            tree[section] = values
    with pytest.raises((ConfigError, ValueError), match=key.split(".")[0]) as err:
        build_experiment(tree)
    assert key in str(err.value)


def _with(tree, **sections):
    out = dict(tree)
    for section, values in sections.items():
        out[section] = {**out.get(section, {}), **values}
    return out


def test_nm_is_evaluated_with_its_neural_map(data_root, tmp_path, capsys, monkeypatch):
    """model.variant=nm: the dataset gets its OSM class rasters, training, validation and the
    evaluate app localize with the BEV matching features against the neural map of the OSM
    class tile; changing only the neural-map parameters changes the evaluated poses; a
    validation IoU under the threshold is a printed warning naming the class, not an error."""
    cfg = build_experiment(
        _with(_tree(data_root, num_steps=2), model={"variant": "nm"}, eval={"num_figures": 0})
    )
    workdir = str(tmp_path / "nm")
    monkeypatch.setattr(train_run, "NM_MIN_IOU", 101.0)  # every IoU is "collapsed"
    results = train_run.train_and_evaluate(cfg, workdir)
    assert results["test"]["count"] == 4
    assert "IoU_road" in results["test"] and "IoU_building" in results["test"]
    out = capsys.readouterr().out
    warning = next(line for line in out.splitlines() if "warning: NM model at step 2" in line)
    assert "validation IoU road " in warning and ", building " in warning and "< 101 %" in warning

    mesh = step_lib.make_mesh(1)
    evaluator = train_run.Evaluator(cfg, os.path.join(data_root, "tiny"), mesh, str(tmp_path))
    batch = next(iter(evaluator.loader("test")))
    assert batch["nm_tile"].shape[1:] == (len(maps.OSM_CLASSES), 256, 256)
    example = step_lib.device_batch(batch, mesh)
    state, _ = train_run.init_state(cfg, example)
    target = jax.device_get(state)
    restored, _ = ckpt_lib.restore_params(workdir, target)
    params = restored.params
    base = evaluator.step(params, example)
    bent = dict(params)
    bent["neural_map"] = jax.tree.map(lambda x: -x + 0.3, params["neural_map"])
    moved = evaluator.step(bent, example)
    assert not np.allclose(np.asarray(base["pose_tile"]), np.asarray(moved["pose_tile"]))
    # ... while a seg model ignores a parameter group of that name entirely: it has none.
    assert (
        "neural_map"
        not in train_run.init_state(build_experiment(_tree(data_root)), example)[0].params
    )


def test_collapsed_nm_segmentation_is_a_warning_line_naming_each_class(capsys):
    nm = build_experiment(_with(_tree("/nowhere"), model={"variant": "nm"}))
    seg = build_experiment(_tree("/nowhere"))
    threshold = train_run.NM_MIN_IOU
    assert threshold == 5.0
    msg = train_run.warn_collapsed_segmentation(nm, {"IoU_road": 0.1, "R@1m": 80.0}, 7)
    assert msg.startswith("[seglocnet] warning: NM model at step 7: validation IoU road 0.1 %")
    assert "collapsed for this class" in msg
    assert msg in capsys.readouterr().out
    # A healthy road channel does not hide a collapsed building channel (the NM row of the
    # tables at 2685693: road 26 %, building 0.3 % on validation).
    msg = train_run.warn_collapsed_segmentation(nm, {"IoU_road": 26.2, "IoU_building": 0.3}, 9)
    assert "validation IoU building 0.3 % < 5 %" in msg and "road" not in msg.split("<")[0]
    both = train_run.warn_collapsed_segmentation(nm, {"IoU_road": 1.0, "IoU_building": 2.0}, 9)
    assert "IoU road 1.0 %, building 2.0 % < 5 %" in both and "these classes" in both
    capsys.readouterr()
    for cfg, val in [
        (nm, {"IoU_road": threshold, "IoU_building": threshold}),  # at the threshold: healthy
        (nm, {"R@1m": 0.0}),  # no IoU measured
        (seg, {"IoU_road": 0.1}),  # a seg model's IoU is its own table's business
    ]:
        assert train_run.warn_collapsed_segmentation(cfg, val, 1) is None
    assert capsys.readouterr().out == ""


def test_validation_rounds_never_recompile(data_root, tmp_path):
    cfg = build_experiment(
        _tree(data_root, num_steps=4, eval_every=1, checkpoint={"every_steps": 4})
    )
    key = (cfg.model, cfg.solver, "model", False)
    before = evaluation.TRACE_COUNTS.get(key, 0)
    train_run.train_and_evaluate(cfg, str(tmp_path / "v"))  # 4 validation rounds + test
    assert evaluation.TRACE_COUNTS[key] - before <= 1


def test_rerun_with_another_config_is_refused_not_relabelled(data_root, tmp_path):
    workdir = str(tmp_path / "run")
    cfg = build_experiment(_tree(data_root))
    train_run.train_and_evaluate(cfg, workdir)
    first = json.load(open(os.path.join(workdir, "results.json")))
    assert first["config"]["train"]["seed"] == 0
    for change in (
        {"train": {"seed": 1}},
        {"train": {"optim": {"warmup_steps": 1, "learning_rate": 0.05}}},
        {"model": {"modality": "camera"}},
    ):
        tree = _tree(data_root)
        for section, values in change.items():
            tree[section] = {**tree[section], **values}
        with pytest.raises(ConfigError, match="train.restart=true") as err:
            train_run.train_and_evaluate(build_experiment(tree), workdir)
        key = next(iter(change)) + "." + next(iter(next(iter(change.values()))))
        assert key in str(err.value)
    # Nothing was overwritten: the results still describe the seed-0 model.
    assert json.load(open(os.path.join(workdir, "results.json"))) == first
    # Operational keys may change: a rerun with another log period resumes the finished run.
    train_run.train_and_evaluate(build_experiment(_tree(data_root, log_every=2)), workdir)
    # train.restart=true keeps the old checkpoints aside and starts over.
    tree = _tree(data_root, seed=1, restart=True)
    train_run.train_and_evaluate(build_experiment(tree), workdir)
    assert json.load(open(os.path.join(workdir, "results.json")))["config"]["train"]["seed"] == 1
    (old,) = [d for d in os.listdir(workdir) if d.startswith("checkpoints.discarded-")]
    kept = json.load(open(os.path.join(workdir, old, "run_files", "results.json")))
    assert kept["splits"] == first["splits"]  # the seed-0 run's numbers are kept, not relabelled


def test_evaluating_with_another_model_config_names_the_keys(data_root, tmp_path):
    workdir = str(tmp_path / "run")
    train_run.train_and_evaluate(build_experiment(_tree(data_root)), workdir)
    other = build_experiment(_with(_tree(data_root), model={"modality": "camera"}))
    with pytest.raises(ConfigError, match="model.modality"):
        eval_run.run_evaluation(other, workdir, str(tmp_path / "e"))


def test_a_second_process_on_the_run_directory_is_refused(data_root, tmp_path):
    import subprocess
    import sys

    from seglocnet_jax import fileio

    workdir = tmp_path / "locked"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from seglocnet_jax import fileio; "
            f"fileio.DirLock({str(workdir)!r}, 'training run').acquire(); "
            "print('held', flush=True); "
            "time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(fileio.LockError, match=f"pid {holder.pid}"):
            train_run.train_and_evaluate(build_experiment(_tree(data_root)), str(workdir))
    finally:
        holder.kill()
        holder.wait()
    # The holder died without releasing: the lock is taken over.
    with fileio.DirLock(str(workdir), "test") as lock:
        assert lock.previous["pid"] == holder.pid
