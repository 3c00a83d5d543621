"""The model's functional API: ``init``, ``forward`` and ``loss_fn`` (localization: the one
localize step, :func:`seglocnet_jax.evaluation.make_localize_step`).

Pure functions of ``params`` (flax.linen, parameters only: GroupNorm, no batch statistics), to
be jitted once and sharded by the caller. ``cfg`` (a frozen, hashable :class:`ModelConfig`) is
closed over or passed as a static argument. Initialization is from scratch.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from seglocnet_jax import geometry, losses, solver
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.model.neural_map import NeuralMapEncoder
from seglocnet_jax.model.seglocnet import NM_MAP_KEY, SegLocNet, check_batch, required_keys


@functools.lru_cache(maxsize=32)
def build(cfg: ModelConfig) -> SegLocNet:
    """The flax module for ``cfg`` (cached: one module object per config)."""
    return SegLocNet(cfg)


def _model_inputs(batch: dict, cfg: ModelConfig, map_side: bool = True) -> dict:
    check_batch(batch, cfg, map_side)
    return {k: batch[k] for k in required_keys(cfg, map_side)}


def init(key: jax.Array, batch: dict, cfg: ModelConfig) -> dict:
    """Fresh parameters from ``key``, shaped by one sample of ``batch`` (any batch size works
    afterwards; H, W, N and P fix nothing in the parameters)."""
    inputs = jax.tree.map(lambda x: x[:1], _model_inputs(batch, cfg))
    variables = jax.jit(build(cfg).init)({"params": key}, inputs)
    return variables["params"]


def forward(
    params: dict,
    batch: dict,
    cfg: ModelConfig,
    *,
    train: bool = False,
    rng: jax.Array | None = None,
    map_side: bool = True,
) -> tuple[jax.Array, dict]:
    """``(bev_logits (B, C, 128, 128), aux)``; see :class:`SegLocNet` for ``aux``.

    ``train`` enables dropout (``rng`` required when ``cfg.dropout > 0``). ``map_side=False``:
    the NM map side (``aux["map_match"]``) left out, for :func:`encode_map` per tile.
    """
    deterministic = not train or cfg.dropout == 0.0
    if not deterministic and rng is None:
        raise ValueError("forward(train=True) with model.dropout > 0 needs an rng key")
    rngs = None if deterministic else {"dropout": rng}
    inputs = _model_inputs(batch, cfg, map_side)
    return build(cfg).apply(
        {"params": params}, inputs, deterministic=deterministic, rngs=rngs, map_side=map_side
    )


def encode_map(params: dict, batch: dict, cfg: ModelConfig) -> jax.Array:
    """The NM map side alone: ``batch["nm_tile"]`` (``(B, C_osm, 256, 256)``, the OSM class
    tiles) -> ``map_match (B, D', 256, 256)``, as :func:`forward` computes it (the same module
    and parameters)."""
    if cfg.variant != "nm":
        raise ValueError(f"encode_map needs model.variant=nm, got {cfg.variant!r}")
    if NM_MAP_KEY not in batch:  # names it (the sensors are the network's side, not read here)
        check_batch({k: None for k in required_keys(cfg, map_side=False)}, cfg)
    out = NeuralMapEncoder(cfg).apply({"params": params["neural_map"]}, batch[NM_MAP_KEY])
    return jnp.moveaxis(out, -1, 1)


def nm_log_likelihood(aux: dict, num_rotations: int) -> jax.Array:
    """Log-probabilities ``(B, K, 129, 129)`` of the NM score volume of ``forward``'s aux."""
    volume = solver.score_volume_batch(
        aux["bev_match"], aux["map_match"], num_rotations, "fft", rotation_chunk=2, batch_chunk=1
    )
    return solver.log_softmax_volume(volume * aux["match_scale"])


def _check_labels(batch: dict, cfg: ModelConfig):
    if "bev_gt" not in batch:
        raise KeyError("batch lacks key 'bev_gt' needed by the focal loss")
    shape = tuple(batch["bev_gt"].shape)
    want = (cfg.num_classes, geometry.BEV_SIZE, geometry.BEV_SIZE)
    if shape[1:] != want:
        raise ValueError(
            f"batch['bev_gt'] has shape {shape}, expected (B, {want[0]}, {want[1]}, "
            f"{want[2]}) for model.num_classes={cfg.num_classes}"
        )
    if cfg.variant == "nm" and "pose_tile" not in batch:
        raise KeyError("batch lacks key 'pose_tile' needed by the NM pose loss")


def loss_fn(params: dict, batch: dict, cfg: ModelConfig, rng: jax.Array | None = None):
    """Scalar training loss and metrics.

    ``seg``: mean over classes of the per-class focal loss. ``nm``: ``seg_weight * focal +
    nm_weight * NLL`` of the GT pose cell over all ``nm_num_rotations x 129 x 129`` cells.
    Fused, both add ``camera_aux_weight`` times the focal loss of the camera latent's own
    logits (``aux["camera_aux_logits"]``, 16x16) against the GT averaged over each latent cell.
    Metrics: ``focal``, ``focal_c{i}``, ``iou_c{i}`` (threshold 0.5, pooled over the batch),
    ``camera_aux_focal`` when that term is on, and for NM ``pose_nll`` and ``match_scale``.
    """
    _check_labels(batch, cfg)
    logits, aux = forward(params, batch, cfg, train=True, rng=rng)
    labels = batch["bev_gt"].astype(jnp.float32)
    per_class = losses.sigmoid_focal_loss(logits, labels, cfg.focal_alpha, cfg.focal_gamma)
    focal = per_class.mean()
    pred = (logits > 0).astype(jnp.float32)
    inter = jnp.sum(pred * labels, axis=(0, 2, 3))
    union = jnp.sum(jnp.maximum(pred, labels), axis=(0, 2, 3))
    iou = inter / jnp.maximum(union, 1.0)
    metrics = {"focal": focal}
    for i in range(cfg.num_classes):
        metrics[f"focal_c{i}"] = per_class[i]
        metrics[f"iou_c{i}"] = iou[i]
    camera_term = 0.0
    if cfg.camera_aux:
        cam_logits = aux["camera_aux_logits"]  # (B, C, n, n): the GT's mean over each cell
        b, c, n = labels.shape[0], labels.shape[1], cam_logits.shape[-1]
        cell = labels.shape[-1] // n
        pooled = labels.reshape(b, c, n, cell, n, cell).mean(axis=(3, 5))
        cam_focal = losses.sigmoid_focal_loss(
            cam_logits, pooled, cfg.focal_alpha, cfg.focal_gamma
        ).mean()
        metrics["camera_aux_focal"] = cam_focal
        camera_term = cfg.camera_aux_weight * cam_focal
    if cfg.variant != "nm":
        return focal + camera_term, metrics
    log_probs = nm_log_likelihood(aux, cfg.nm_num_rotations)  # (B, K, 129, 129)
    cells = losses.gt_cells(batch["pose_tile"], cfg.nm_num_rotations, log_probs.shape[-1])
    nll = losses.pose_nll(log_probs, cells).mean()
    metrics.update(pose_nll=nll, match_scale=aux["match_scale"])
    return cfg.seg_weight * focal + cfg.nm_weight * nll + camera_term, metrics


def make_loss_fn(cfg: ModelConfig):
    """``(params, batch, rng) -> (loss, metrics)`` for the training step."""
    return functools.partial(_bound_loss, cfg=cfg)


def _bound_loss(params, batch, rng, *, cfg):
    return loss_fn(params, batch, cfg, rng)
