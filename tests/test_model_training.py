"""The network trained and run end to end: network + solver compile once and are deterministic,
every parameter group learns in every modality mode (and SegLocNet-NM), and the tiny preset
overfits a few synthetic samples."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from seglocnet_jax import solver
from seglocnet_jax.model import api, synthetic
from seglocnet_jax.model.config import preset

# Small inputs keep compilation short; the architecture is the tiny preset's.
HW, CAMS, POINTS = (32, 64), 2, 2048
TINY = preset("tiny")


def _batch(seed, size=2):
    return synthetic.make_batch(seed, size, num_cams=CAMS, image_hw=HW, num_points=POINTS)


def test_network_and_solver_compile_once_and_are_deterministic():
    cfg = TINY
    solver_cfg = solver.SolverConfig(num_rotations=64)
    params = api.init(jax.random.key(0), _batch(0), cfg)
    traces = []

    @jax.jit
    def localize(params, batch):
        traces.append(1)  # runs only while tracing
        return api.localize(params, batch, cfg, solver_cfg)

    a = jax.device_get(localize(params, _batch(1)))
    b = jax.device_get(localize(params, _batch(1)))
    c = jax.device_get(localize(params, _batch(2)))  # new contents, same shapes
    assert len(traces) == 1
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert a["bev_logits"].shape == (2, 2, 128, 128)
    assert a["pose_tile"].shape == (2, 3)
    assert not np.array_equal(a["bev_logits"], c["bev_logits"])


def _groups(grads):
    """Parameter groups: each top-level module's direct submodules (or itself if a leaf)."""
    out = {}
    for top, sub in grads.items():
        if isinstance(sub, dict) and all(isinstance(v, dict) for v in sub.values()):
            for name, tree in sub.items():
                out[f"{top}/{name}"] = tree
        else:
            out[top] = sub
    return out


@pytest.mark.parametrize(
    "modality,variant",
    [("fused", "seg"), ("camera", "seg"), ("lidar", "seg"), ("fused", "nm")],
)
def test_every_parameter_group_gets_a_gradient(modality, variant):
    cfg = dataclasses.replace(
        TINY, modality=modality, variant=variant, nm_num_rotations=8, transformer_layers=1
    )
    batch = _batch(3)
    params = api.init(jax.random.key(1), batch, cfg)
    grads = jax.jit(jax.grad(lambda p: api.loss_fn(p, batch, cfg)[0]))(params)
    expected = {"decoder", "fusion"}
    expected |= {"camera"} if modality != "lidar" else set()
    expected |= {"lidar"} if modality != "camera" else set()
    expected |= {"neural_map", "bev_match", "match_scale"} if variant == "nm" else set()
    assert expected <= set(grads), f"missing parameter groups {expected - set(grads)}"
    if modality == "camera":
        assert "lidar" not in grads
    if modality == "lidar":
        assert "camera" not in grads
    for name, tree in _groups(grads).items():
        norm = float(sum(jnp.sum(jnp.abs(g)) for g in jax.tree.leaves(tree)))
        assert np.isfinite(norm), f"{modality}/{variant}: non-finite gradient in {name}"
        assert norm > 0, f"{modality}/{variant}: parameter group {name} gets no gradient"


@pytest.mark.slow
def test_tiny_model_overfits_eight_samples():
    cfg = TINY
    batch = jax.tree.map(jnp.asarray, _batch(4, size=8))
    params = api.init(jax.random.key(2), batch, cfg)
    opt = optax.adamw(3e-3, weight_decay=0.0)
    opt_state = opt.init(params)
    loss_fn = api.make_loss_fn(cfg)

    @jax.jit
    def step(params, opt_state):
        (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch, None)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, metrics

    # Stops once the loss has fallen 10x and both classes are segmented (IoU > 0.5): a falling
    # focal loss alone could be the background bias being learnt.
    losses = []
    for _ in range(MAX_STEPS):
        params, opt_state, loss, metrics = step(params, opt_state)
        losses.append(float(loss))
        assert np.isfinite(losses[-1]), f"loss {losses[-1]} at step {len(losses)}"
        ious = [float(metrics[f"iou_c{i}"]) for i in range(cfg.num_classes)]
        if losses[-1] <= losses[0] / 10 and min(ious) > 0.5:
            break
    first, last = losses[0], losses[-1]
    assert last <= first / 10, (
        f"focal loss fell only {first / last:.1f}x in {MAX_STEPS} steps: {first:.4f} -> {last:.4f}"
    )
    assert min(ious) > 0.5, f"training IoUs {ious} after {MAX_STEPS} steps"
    print(f"focal loss {first:.4f} -> {last:.4f}, IoU {ious} in {len(losses)} steps")


MAX_STEPS = 200
