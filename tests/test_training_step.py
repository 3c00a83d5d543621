"""The sharded train step, checkpoints and resume, on a small regression model."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from seglocnet_jax.training import checkpoint as ckpt
from seglocnet_jax.training import state as st
from seglocnet_jax.training import step as stp


def _loss_fn(params, batch, rng):
    noise = 0.01 * jax.random.normal(rng, batch["x"].shape)
    pred = jnp.tanh((batch["x"] + noise) @ params["w1"]) @ params["w2"]
    loss = jnp.mean((pred - batch["y"]) ** 2)
    return loss, {"mse": loss}


def _batch(i, b=16):
    r = np.random.default_rng(i)
    x = r.normal(size=(b, 4)).astype(np.float32)
    return {"x": x, "y": np.sin(x[:, :1]).astype(np.float32)}


def _init(seed=0):
    k1, k2 = jax.random.split(jax.random.key(seed))
    return {"w1": jax.random.normal(k1, (4, 8)), "w2": jax.random.normal(k2, (8, 1))}


CFG = st.OptimConfig(learning_rate=1e-2, warmup_steps=1, total_steps=10)


def _run(num_devices, steps, state=None, start=0):
    mesh = stp.make_mesh(num_devices)
    opt = st.make_optimizer(CFG)
    if state is None:
        state = st.TrainState.create(_init(), opt, jax.random.key(1))
    state = stp.replicate(state, mesh)
    step_fn = stp.make_train_step(_loss_fn, opt, mesh)
    losses = []
    for i in range(start, start + steps):
        state, m = step_fn(state, stp.device_batch(_batch(i), mesh))
        losses.append(float(m["loss"]))
    return state, losses, step_fn


def test_one_vs_eight_devices_agree():
    assert len(jax.devices()) == 8, "conftest must configure 8 CPU devices"
    s1, l1, _ = _run(1, 3)
    s8, l8, _ = _run(8, 3)
    np.testing.assert_allclose(l1, l8, rtol=1e-5, atol=1e-6)
    for a, b in zip(jax.tree.leaves(s1.params), jax.tree.leaves(s8.params), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


def test_same_seed_bit_identical_and_no_retrace():
    s_a, l_a, fn = _run(2, 3)
    s_b, l_b, _ = _run(2, 3)
    assert l_a == l_b
    for a, b in zip(jax.tree.leaves(s_a), jax.tree.leaves(s_b), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert fn._cache_size() == 1  # one compilation across all steps


def test_resume_equals_uninterrupted(tmp_path):
    full, l_full, _ = _run(1, 4)
    half, l_half, _ = _run(1, 2)
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig())
    ck.save(2, jax.device_get(half), {"next_index": 2})
    ck.close()
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig())
    target = st.TrainState.create(_init(), st.make_optimizer(CFG), jax.random.key(1))
    restored, data_state, step = ck.restore_latest(target)
    assert step == 2 and data_state == {"next_index": 2}
    resumed, l_rest, _ = _run(1, 2, state=restored, start=data_state["next_index"])
    assert l_half + l_rest == l_full
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_corrupt_latest_checkpoint_falls_back(tmp_path, capsys):
    s1, _, _ = _run(1, 1)
    s2, _, _ = _run(1, 2)
    ck = ckpt.Checkpointer(str(tmp_path), ckpt.CheckpointConfig(keep_last=3))
    ck.save(1, jax.device_get(s1), {"i": 1})
    ck.save(2, jax.device_get(s2), {"i": 2})
    # Cut the latest checkpoint's array data, as a crash mid-write would.
    state_dir = os.path.join(ck.last_dir, "2", "state")
    for root, _, files in os.walk(state_dir):
        for f in files:
            if f not in ("_METADATA", "_sharding", "commit_success.txt"):
                open(os.path.join(root, f), "wb").close()
    target = st.TrainState.create(_init(), st.make_optimizer(CFG), jax.random.key(1))
    _, data_state, step = ck.restore_latest(target)
    assert step == 1 and data_state == {"i": 1}
    assert "is corrupt or incomplete" in capsys.readouterr().out


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(ckpt.CheckpointError, match="does not exist"):
        ckpt.restore_params(str(tmp_path / "nope"), None)


def test_batch_not_divisible_by_devices():
    mesh = stp.make_mesh(8)
    with pytest.raises(ValueError, match="not divisible"):
        stp.device_batch(_batch(0, b=6), mesh)


def test_tiny_model_one_vs_eight_devices_agree():
    """The real network (fused tiny preset) under the sharded step: the batch split over 8
    devices gives the single device's loss and parameters after 3 steps."""
    import dataclasses

    from seglocnet_jax.model import api, synthetic
    from seglocnet_jax.model.config import preset

    cfg = dataclasses.replace(preset("tiny"), transformer_layers=1)
    batches = [
        synthetic.make_batch(i, 8, num_cams=1, image_hw=(32, 64), num_points=2048) for i in range(3)
    ]
    # The paper's lr. Adam moves every parameter by ~lr per step whatever its gradient's size, so
    # a near-zero gradient summed in another order can differ by O(lr) there: 1e-4 keeps 1e-5.
    opt = st.make_optimizer(st.OptimConfig(learning_rate=1e-4, warmup_steps=1, total_steps=10))
    params0 = jax.device_get(api.init(jax.random.key(0), batches[0], cfg))  # step donates

    def run(num_devices):
        mesh = stp.make_mesh(num_devices)
        state = stp.replicate(st.TrainState.create(params0, opt, jax.random.key(1)), mesh)
        step_fn = stp.make_train_step(api.make_loss_fn(cfg), opt, mesh)
        losses = []
        for b in batches:
            state, m = step_fn(state, stp.device_batch(b, mesh))
            losses.append(float(m["loss"]))
        return jax.device_get(state.params), losses

    p1, l1 = run(1)
    p8, l8 = run(8)
    np.testing.assert_allclose(l1, l8, rtol=1e-5)
    assert l1[-1] != l1[0]  # the steps did change the parameters
    for (path, a), b in zip(
        jax.tree_util.tree_leaves_with_path(p1), jax.tree.leaves(p8), strict=True
    ):
        np.testing.assert_allclose(a, b, atol=1e-5, err_msg=jax.tree_util.keystr(path))


def test_checkpoint_path_with_brackets_is_refused_up_front(tmp_path):
    with pytest.raises(ckpt.CheckpointError, match=r"contains '\[' or '\]'"):
        ckpt.Checkpointer(str(tmp_path / "eval.splits=[test]"), ckpt.CheckpointConfig())


def test_sweep_directory_names_drop_brackets():
    from seglocnet_jax.app.hydra_glue import safe_dirname

    name = "eval.splits=[test],map.channels=[road,building],map.road_width=5"
    assert safe_dirname(name) == "eval.splits=test,map.channels=road+building,map.road_width=5"


def test_batch_shard_of_one_process_is_everything():
    for n in (1, 8):
        assert stp.batch_shard(stp.make_mesh(n)) == (0, 1)


def test_process_local_placement_equals_global_placement_in_one_process():
    mesh = stp.make_mesh(8)
    batch = _batch(0)
    local = stp.device_batch(batch, mesh)  # process_local=True: this process holds all rows
    whole = stp.device_batch(batch, mesh, process_local=False)
    for key in batch:
        assert local[key].sharding == whole[key].sharding
        np.testing.assert_array_equal(np.asarray(local[key]), batch[key])
        np.testing.assert_array_equal(np.asarray(whole[key]), batch[key])


_TWO_PROCESS_WORKER = """
import json, os, sys
pid, port, tests = int(sys.argv[1]), sys.argv[2], sys.argv[3]
import jax
jax.config.update("jax_num_cpu_devices", 4)
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(f"localhost:{port}", num_processes=2, process_id=pid)
import numpy as np
from jax.experimental import multihost_utils
sys.path.insert(0, tests)
import test_training_step as t
from seglocnet_jax.training import state as st
from seglocnet_jax.training import step as stp

mesh = stp.make_mesh(8)
index, count = stp.batch_shard(mesh)
opt = st.make_optimizer(t.CFG)
state = stp.replicate(st.TrainState.create(t._init(), opt, jax.random.key(1)), mesh)
step_fn = stp.make_train_step(t._loss_fn, opt, mesh)
losses, same = [], True
for i in range(3):
    full = t._batch(i)
    b = len(full["x"]) // count
    local = {k: v[index * b : (index + 1) * b] for k, v in full.items()}  # this process's rows
    placed = stp.device_batch(local, mesh)
    for k, v in placed.items():  # the global array is the whole batch
        same &= bool(np.array_equal(multihost_utils.process_allgather(v, tiled=True), full[k]))
    state, m = step_fn(state, placed)
    losses.append(float(m["loss"]))
print("RESULT " + json.dumps({"shard": [index, count], "losses": losses, "same": same}))
"""


@pytest.mark.slow
def test_two_processes_read_their_halves_and_train_like_one(tmp_path):
    """Two jax.distributed CPU processes (4 devices each): each places only its half of every
    batch (``device_batch`` of process-local rows, shard ``batch_shard``); the global arrays are
    the whole batches and the losses those of one process with 8 devices."""
    import json
    import socket
    import subprocess
    import sys

    script = tmp_path / "worker.py"
    script.write_text(_TWO_PROCESS_WORKER)
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    tests = os.path.dirname(os.path.abspath(__file__))
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(i), str(port), tests],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        for i in range(2)
    ]
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=240)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    results = []
    for p, out in zip(procs, outs, strict=True):
        assert p.returncode == 0, out[-3000:]
        results.append(json.loads(out.split("RESULT ", 1)[1].splitlines()[0]))
    assert [r["shard"] for r in results] == [[0, 2], [1, 2]]
    assert all(r["same"] for r in results)
    assert results[0]["losses"] == results[1]["losses"]
    _, l8, _ = _run(8, 3)
    np.testing.assert_allclose(results[0]["losses"], l8, rtol=1e-5, atol=1e-6)


def test_the_cpu_device_count_divides_the_batch_and_evaluation_stays_on_one_device():
    assert [stp.cpu_devices(8, cores) for cores in (1, 2, 3, 4, 6, 16)] == [1, 2, 2, 4, 4, 8]
    assert stp.cpu_devices(6, 4) == 3
    mesh = stp.make_mesh()  # the tests' 8 CPU devices
    one = stp.evaluation_mesh(mesh)
    assert one.devices.size == 1 and one.devices.flat[0] == mesh.devices.flat[0]
    single = stp.make_mesh(1)
    assert stp.evaluation_mesh(single) is single


@pytest.mark.parametrize("chosen", [None, "1"])
def test_the_train_entry_sets_a_cpu_device_per_core_unless_the_user_chose(chosen, tmp_path):
    """``python -m seglocnet_jax.train`` (a fresh process) makes one CPU device per usable
    core for the batch of 8 before anything starts JAX (a bad config value stops it right
    after, naming the key), or keeps the user's JAX_NUM_CPU_DEVICES."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    if chosen:
        env["JAX_NUM_CPU_DEVICES"] = chosen
    out = subprocess.run(
        [sys.executable, "-m", "seglocnet_jax.train", "train.num_steps=-1",
         f"hydra.run.dir={tmp_path}"],
        env=env, capture_output=True, text=True, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 1 and "train.num_steps" in out.stdout + out.stderr
    cores = stp.cpu_devices(8, len(os.sched_getaffinity(0)))
    line = f"[seglocnet] {cores} XLA CPU device(s): one per usable core"
    assert (line in out.stdout) == (chosen is None), out.stdout
