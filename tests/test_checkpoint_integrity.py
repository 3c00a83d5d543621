"""Checkpoint integrity: checksums verified on every restore, fallback to the previous good
step, a clear error and an archive when none is usable, corrupt steps replaced, the best
checkpoint recovered on resume, and tree mismatches named."""

import json
import os
import shutil

import jax
import numpy as np
import pytest

from seglocnet_jax.training import checkpoint as ckpt
from seglocnet_jax.training import state as st

OPT = st.make_optimizer(st.OptimConfig(learning_rate=1e-2, warmup_steps=1, total_steps=10))


def _state(seed=0, w1_shape=(4, 8)):
    r = np.random.default_rng(seed)
    params = {
        "w1": r.normal(size=w1_shape).astype(np.float32),
        "w2": r.normal(size=(8, 1)).astype(np.float32),
    }
    return jax.device_get(st.TrainState.create(params, OPT, jax.random.key(seed)))


def _same(a, b):
    return all(
        np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


def _two_steps(tmp_path, **cfg):
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig(keep_last=3, **cfg))
    s1, s2 = _state(1), _state(2)
    ck.save(1, s1, {"i": 1})
    ck.save(2, s2, {"i": 2})
    return ck, s1, s2


def _item_files(step_dir, item):
    out = []
    for root, _, files in os.walk(os.path.join(step_dir, item)):
        out += [os.path.join(root, f) for f in files]
    return sorted(out)


def _flip(path, at=None):
    data = bytearray(open(path, "rb").read())
    at = len(data) // 2 if at is None else at
    data[at] ^= 0x10
    open(path, "wb").write(bytes(data))


def test_bit_flip_in_any_file_is_detected_and_the_previous_step_used(tmp_path, capsys):
    ck, s1, _ = _two_steps(tmp_path)
    step2 = os.path.join(ck.last_dir, "2")
    files = _item_files(step2, "state") + _item_files(step2, "data")
    assert len(files) >= 4
    for path in files:
        original = open(path, "rb").read()
        _flip(path)
        state, data_state, step = ck.restore_latest(_state(0))
        out = capsys.readouterr().out
        assert step == 1 and data_state == {"i": 1} and _same(state, s1), path
        rel = os.path.relpath(path, step2)
        assert f"WARNING: checkpoint {step2} is corrupt" in out and rel in out
        assert "using checkpoint" in out and "(step 1)" in out
        open(path, "wb").write(original)
    assert ck.restore_latest(_state(0))[2] == 2  # restored files: good again


def test_missing_checksum_file_is_corrupt(tmp_path, capsys):
    ck, _, _ = _two_steps(tmp_path)
    os.remove(os.path.join(ck.last_dir, "2", ckpt.CHECKSUM_NAME))
    assert ck.restore_latest(_state(0))[2] == 1
    out = capsys.readouterr().out
    assert os.path.join(ck.last_dir, "2") in out and f"no {ckpt.CHECKSUM_NAME}" in out


def test_no_usable_step_is_an_error_with_the_remedy_and_archive_works(tmp_path, capsys):
    ck, _, _ = _two_steps(tmp_path)
    for step in (1, 2):
        _flip(_item_files(os.path.join(ck.last_dir, str(step)), "state")[-1])
    with pytest.raises(ckpt.CheckpointError) as err:
        ck.restore_latest(_state(0))
    msg = str(err.value)
    assert ck.last_dir in msg
    for step in (1, 2):
        assert os.path.join(ck.last_dir, str(step)) + ": checksum mismatch" in msg
    root = os.path.join(str(tmp_path), "checkpoints")
    assert msg.endswith(
        f"; delete {root} or rerun with train.restart=true (moves the old checkpoints aside)"
    )
    ck.close()
    moved = ckpt.archive_checkpoints(str(tmp_path))
    assert os.path.basename(moved).startswith("checkpoints.discarded-")
    assert os.path.isdir(os.path.join(moved, "last", "2")) and not os.path.exists(root)
    assert ckpt.archive_checkpoints(str(tmp_path)) is None  # nothing left to move
    fresh = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig())
    assert fresh.restore_latest(_state(0)) is None
    fresh.close()


def test_corrupt_step_is_replaced_when_saved_again(tmp_path, capsys):
    ck, _, s2 = _two_steps(tmp_path)
    _flip(_item_files(os.path.join(ck.last_dir, "2"), "state")[-1])
    ck.save(2, s2, {"i": 2})
    assert "replacing it" in capsys.readouterr().out
    state, data_state, step = ck.restore_latest(_state(0))
    assert step == 2 and data_state == {"i": 2} and _same(state, s2)
    assert "WARNING" not in capsys.readouterr().out


def test_resume_offers_the_restored_step_to_best(tmp_path):
    cfg = ckpt.CheckpointConfig(best_metric="R@5m")
    ck = ckpt.Checkpointer(str(tmp_path), cfg)
    s1, s2 = _state(1), _state(2)
    ck.save(1, s1, {"i": 1}, metrics={"R@5m": 10.0})
    ck.save(2, s2, {"i": 2}, metrics={"R@5m": 50.0, "prior": {"APE": np.float64(3.0)}})
    ck.close()
    # A kill between the `last` and the `best` save of step 2.
    shutil.rmtree(os.path.join(ck.best_dir, "2"))
    ck = ckpt.Checkpointer(str(tmp_path), cfg)
    assert ck.restore_latest(_state(0))[2] == 2
    assert ck.best.all_steps() == [2]
    ck.save(3, _state(3), {"i": 3}, metrics={"R@5m": 20.0})  # worse: not written to best
    assert ck.best.all_steps() == [2] and not os.path.exists(os.path.join(ck.best_dir, "3"))
    ck.close()
    with open(os.path.join(ck.last_dir, "2", ckpt.CHECKSUM_NAME)) as f:
        assert json.load(f)["metrics"]["R@5m"] == 50.0  # validation metrics kept with `last`
    state, step = ckpt.restore_params(os.path.join(str(tmp_path), "checkpoints", "best"), _state(0))
    assert step == 2 and _same(state, s2)


def test_restore_params_verifies_and_falls_back_to_last(tmp_path, capsys):
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig())
    s1 = _state(1)
    ck.save(1, s1, {"i": 1}, metrics={"R@5m": 1.0})
    ck.close()
    best1 = os.path.join(ck.best_dir, "1")
    _flip(_item_files(best1, "state")[-1])
    with pytest.raises(ckpt.CheckpointError, match=f"{best1}: checksum mismatch"):
        ckpt.restore_params(best1, _state(0))
    state, step = ckpt.restore_params(str(tmp_path), _state(0))  # the run dir: best, then last
    out = capsys.readouterr().out
    assert step == 1 and _same(state, s1)
    assert f"WARNING: checkpoint {best1} is corrupt" in out
    assert f"using checkpoint {os.path.join(ck.last_dir, '1')} (step 1)" in out


def test_restore_params_into_another_model_names_the_parameters(tmp_path):
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig())
    ck.save(3, _state(1), {"i": 3})
    ck.close()
    step_dir = os.path.join(ck.last_dir, "3")
    with pytest.raises(ckpt.CheckpointError) as err:
        ckpt.restore_params(step_dir, _state(0, w1_shape=(4, 9)))
    msg = str(err.value)
    assert step_dir in msg and "params.w1: checkpoint (4, 8) float32, model (4, 9)" in msg
    assert "tree structures" not in msg
    bigger = _state(0)
    bigger = bigger.replace(params={**bigger.params, "w3": np.zeros(3, np.float32)})
    with pytest.raises(ckpt.CheckpointError, match="params.w3: not in the checkpoint"):
        ckpt.restore_params(str(tmp_path), bigger)


def test_every_steps_must_be_positive():
    with pytest.raises(ValueError, match="train.checkpoint.every_steps"):
        ckpt.CheckpointConfig(every_steps=0)
