"""The network trained and run end to end: network + solver compile once and are deterministic,
every parameter group learns in every modality mode (and SegLocNet-NM), and the tiny preset
overfits a few synthetic samples."""

from __future__ import annotations

import dataclasses
import threading

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from seglocnet_jax import evaluation, losses, solver
from seglocnet_jax.model import api, synthetic
from seglocnet_jax.model.config import preset

# Small inputs keep compilation short; the architecture is the tiny preset's. Parameters do not
# depend on H, W, the camera count or the point count.
HW, CAMS, POINTS = (32, 64), 2, 2048
TINY = preset("tiny")
MAX_STEPS = 200


def _batch(seed, size=2):
    return synthetic.make_batch(seed, size, num_cams=CAMS, image_hw=HW, num_points=POINTS)


def _key(seed):
    # XLA's RngBitGenerator compiles in about half the time of threefry on CPU, and `init` is
    # compiled once per configuration here; the model code is the same for any key type.
    return jax.random.key(seed, impl="rbg")


@pytest.fixture(scope="module")
def tiny_params():
    """Tiny-preset (fused, seg) parameters, initialized once for the whole module."""
    return api.init(_key(0), _batch(0), TINY)


def test_network_and_solver_compile_once_and_are_deterministic(tiny_params):
    # The one localize step every evaluation uses (evaluation.make_localize_step).
    solver_cfg = solver.SolverConfig(num_rotations=64)
    step = evaluation.make_localize_step(TINY, solver_cfg, "model")
    keys = [(TINY, solver_cfg, "model", p) for p in ("network", True)]  # its two programs
    before = [evaluation.TRACE_COUNTS.get(key, 0) for key in keys]
    a = jax.device_get(step(tiny_params, _batch(1), figures=True))
    b = jax.device_get(step(tiny_params, _batch(1), figures=True))
    c = jax.device_get(step(tiny_params, _batch(2), figures=True))  # new contents, same shapes
    for key, n in zip(keys, before, strict=True):
        assert evaluation.TRACE_COUNTS[key] - n == 1, f"{key[-1]} traced more than once"
    assert evaluation.make_localize_step(TINY, solver_cfg, "model") is step  # cached
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert a["probs"].shape == (2, 2, 128, 128) and a["likelihood"].shape == (2, 129, 129)
    assert a["pose_tile"].shape == (2, 3) and a["inter"].shape == (2, 2)
    assert not np.array_equal(a["probs"], c["probs"])


def test_the_solver_threads_give_the_one_program_outputs(tiny_params, monkeypatch):
    """On CPU the localize step solves a batch's rows in parts side by side (a host thread per
    core): the poses, IoU counts, figure maps and volumes equal those of one program run on
    the whole batch, for uneven parts, for gathered BEV rows and for the first (compiling)
    call as for later ones."""
    solver_cfg = solver.SolverConfig(num_rotations=16)
    step = evaluation.make_localize_step(TINY, solver_cfg, "model")
    assert step.threads == evaluation.solver_threads() >= 1
    batch = _batch(3, size=3)
    bev = step.network(tiny_params, batch)
    rows = np.array([2, 0, 2, 1, 1])
    tiles = {"tile": jnp.concatenate([batch["tile"], batch["tile"][::-1][:2]])}

    names = []
    run = evaluation.LocalizeStep._run

    def recorded(*args):
        names.append(threading.current_thread().name)
        return run(*args)

    monkeypatch.setattr(evaluation.LocalizeStep, "_run", staticmethod(recorded))

    def outputs(threads):
        step.threads = threads
        out = [step(tiny_params, batch, figures=True), step(tiny_params, batch, volume=True)]
        out.append(step.solve(tiny_params, bev, tiles, rows, volume=True))
        return jax.device_get(out)

    try:
        one = outputs(1)
        for _ in range(2):  # compiling the parts, then running them in threads
            for a, b in zip(one, outputs(3), strict=True):
                assert a.keys() == b.keys()
                for k in a:
                    np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    finally:
        step.threads = evaluation.solver_threads()
    assert any(name.startswith("parts") for name in names)  # the later calls: in threads


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
def test_every_parameter_group_gets_a_gradient(modality, variant, tiny_params):
    if (modality, variant) == ("fused", "seg"):
        cfg, params = TINY, tiny_params
    else:
        cfg = dataclasses.replace(
            TINY, modality=modality, variant=variant, nm_num_rotations=8, transformer_layers=1
        )
        params = api.init(_key(1), _batch(0), cfg)
    grads = jax.jit(jax.grad(lambda p, b: api.loss_fn(p, b, cfg)[0]))(params, _batch(3))
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
        norm = float(sum(np.abs(np.asarray(g)).sum() for g in jax.tree.leaves(tree)))
        assert np.isfinite(norm), f"{modality}/{variant}: non-finite gradient in {name}"
        assert norm > 0, f"{modality}/{variant}: parameter group {name} gets no gradient"


def test_the_camera_aux_loss_is_the_focal_loss_of_the_camera_latent_alone():
    """``model.camera_aux_weight``: the loss adds that weight times the focal loss of the
    camera latent's own 16x16 logits against the GT's mean over each 8x8-pixel cell, a term
    whose gradient reaches the camera branch and its head only."""
    assert TINY.camera_aux_weight == 1.0 and preset("paper").camera_aux_weight == 0.0
    cfg = dataclasses.replace(TINY, camera_aux_weight=0.5, transformer_layers=1)
    batch = _batch(3)
    params = api.init(_key(2), batch, cfg)
    assert params["camera_aux"]["kernel"].shape == (1, 1, cfg.embed_dim, cfg.num_classes)

    def run(p, b):
        camera_term = jax.grad(lambda q: api.loss_fn(q, b, cfg)[1]["camera_aux_focal"])(p)
        return api.loss_fn(p, b, cfg), api.forward(p, b, cfg)[1]["camera_aux_logits"], camera_term

    (loss, metrics), logits, grads = jax.jit(run)(params, batch)
    labels = np.asarray(batch["bev_gt"], np.float32)
    cells = sum(labels[:, :, i::8, j::8] for i in range(8) for j in range(8)) / 64.0
    want = losses.sigmoid_focal_loss(logits, jnp.asarray(cells)).mean()
    np.testing.assert_allclose(metrics["camera_aux_focal"], want, rtol=1e-5)
    np.testing.assert_allclose(loss, metrics["focal"] + 0.5 * want, rtol=1e-5)
    for group, tree in grads.items():
        norm = float(sum(np.abs(np.asarray(g)).sum() for g in jax.tree.leaves(tree)))
        assert (norm > 0) == (group in ("camera", "camera_aux")), f"{group}: gradient {norm}"
    assert not dataclasses.replace(cfg, modality="camera").camera_aux  # fused only
    with pytest.raises(ValueError, match="camera_aux_weight"):
        dataclasses.replace(TINY, camera_aux_weight=-1.0)


def _best_constant_focal(labels: np.ndarray, alpha: float, gamma: float) -> float:
    """Smallest mean focal loss of a predictor that outputs one logit per class everywhere
    (the per-class bias alone), by a dense search over the logit."""
    z = np.linspace(-10.0, 10.0, 4001)[:, None]
    p = 1 / (1 + np.exp(-z))
    prevalence = labels.mean(axis=(0, 2, 3))[None]  # (1, C)
    pos = alpha * np.log1p(np.exp(-z)) * (1 - p) ** gamma
    neg = (1 - alpha) * np.log1p(np.exp(z)) * p**gamma
    per_class = prevalence * pos + (1 - prevalence) * neg  # (Z, C)
    return float(per_class.min(axis=0).mean())


@pytest.mark.slow
def test_tiny_model_overfits_eight_samples(tiny_params):
    cfg = TINY
    batch = _batch(4, size=8)
    opt = optax.adamw(3e-3, weight_decay=0.0)
    loss_fn = api.make_loss_fn(cfg)

    @jax.jit
    def step(params, opt_state, batch):
        (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch, None)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, metrics

    # A falling focal loss alone could be the per-class bias being learnt: the loss must also
    # end well below the best constant predictor's, and the road (the larger class) be found.
    constant = _best_constant_focal(batch["bev_gt"], cfg.focal_alpha, cfg.focal_gamma)
    params, opt_state = tiny_params, opt.init(tiny_params)
    losses = []
    for _ in range(MAX_STEPS):
        params, opt_state, loss, metrics = step(params, opt_state, batch)
        losses.append(float(loss))
        assert np.isfinite(losses[-1]), f"loss {losses[-1]} at step {len(losses)}"
        road_iou = float(metrics["iou_c0"])
        if losses[-1] <= min(losses[0] / 10, constant / 2) and road_iou > 0.5:
            break
    first, last = losses[0], losses[-1]
    assert last <= first / 10, (
        f"focal loss fell only {first / last:.1f}x in {MAX_STEPS} steps: {first:.4f} -> {last:.4f}"
    )
    assert last <= constant / 2, f"focal loss {last:.4f} vs best constant logits {constant:.4f}"
    assert road_iou > 0.5, f"road IoU {road_iou:.2f} after {len(losses)} steps"
    print(f"focal loss {first:.4f} -> {last:.4f} (constant {constant:.4f}) in {len(losses)} steps")
