"""Evaluation, in one home: the jitted localize step and the split evaluation built on it.

:func:`make_localize_step` builds, once per ``(model config, solver config, BEV source)``, one
jitted program ``network (or GT labels) -> solver -> decoded pose``. Every evaluation goes through
it: periodic validation, best-checkpoint selection, the final tables, the figures, the
``evaluate`` app and the benchmarks. What it matches depends on the variant:

- ``seg`` models: the BEV logits ``(B, C, 128, 128)`` against the ``{0, 1}`` map tile.
- ``nm`` models (SegLocNet-NM): the BEV matching features against the neural map the network
  computes from the tile (``aux["bev_match"]`` vs ``aux["map_match"]``).
- ``bev_source="gt"`` (the GT-segmentation upper bound): the GT BEV labels as +-1 logits
  (:func:`solver.labels_to_logits`) against the tile; no network, no parameters.

Only decoded poses, peak scores and per-class IoU counts come back to the host; the likelihood
map (score volume maximized over rotations) and BEV probabilities are returned only by the
figure variant of the program, used for the batches that get figures, and the whole score volume
``(B, K, 129, 129)`` only by the volume variant (left on the device: the sequential filter's
likelihood and the temperature fit, :mod:`seglocnet_jax.sequential`). The ``eval`` group's
settings are :class:`seglocnet_jax.sequential.config.EvalConfig` (with the filter's: the
evaluation floor below it does not know the filter).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import metrics, solver, viz
from seglocnet_jax.model import api as model_api
from seglocnet_jax.model.config import ModelConfig

BEV_SOURCES = ("model", "gt")

# How many times each localize program was traced, keyed by the builder's arguments and the
# program: ``figures`` False (poses), True (figure maps) or "volume" (the score volume). Pinned
# by a test so that validation rounds never recompile.
TRACE_COUNTS: dict[tuple, int] = {}


def _match_inputs(params, batch, model_cfg: ModelConfig, bev_source: str):
    """``(template (B, C', 128, 128), tile (B, C', 256, 256), bev logits or None)``."""
    tile = batch["tile"].astype(jnp.float32)
    if bev_source == "gt":
        return solver.labels_to_logits(batch["bev_gt"].astype(jnp.float32)), tile, None
    logits, aux = model_api.forward(params, batch, model_cfg)
    if model_cfg.variant == "nm":
        return aux["bev_match"], aux["map_match"], logits
    return logits, tile, logits


def _localize(params, batch, *, model_cfg, solver_cfg, bev_source, figures, key):
    TRACE_COUNTS[key] = TRACE_COUNTS.get(key, 0) + 1  # runs only while tracing
    template, tile, logits = _match_inputs(params, batch, model_cfg, bev_source)
    out = solver.localize(template, tile, solver_cfg, return_volume=bool(figures))
    result = {"pose_tile": out["pose_tile"], "score": out["score"]}  # (B, 3), (B,)
    labels = batch["bev_gt"].astype(jnp.float32)  # (B, C, 128, 128)
    if logits is not None:
        pred = (logits > 0).astype(jnp.float32)
        result["inter"] = jnp.sum(pred * labels, axis=(2, 3))  # (B, C)
        result["union"] = jnp.sum(jnp.maximum(pred, labels), axis=(2, 3))  # (B, C)
    if figures == "volume":
        result["volume"] = out["volume"]  # (B, K, 129, 129)
    elif figures:
        result["likelihood"] = out["volume"].max(axis=1)  # (B, 129, 129)
        result["probs"] = labels if logits is None else jax.nn.sigmoid(logits)
    return result


LocalizeStep = Callable[..., dict]


@functools.lru_cache(maxsize=16)
def make_localize_step(
    model_cfg: ModelConfig, solver_cfg: solver.SolverConfig, bev_source: str = "model"
) -> LocalizeStep:
    """``step(params, device_batch, figures=False, volume=False) -> dict`` of device arrays:
    ``pose_tile (B, 3)`` (tile frame: dx, dy m, yaw rad), ``score (B,)``, for a network also
    ``inter`` / ``union (B, C)`` pixel counts of the thresholded BEV vs the GT labels; with
    ``figures=True`` also ``likelihood (B, 129, 129)`` and ``probs (B, C, 128, 128)``; with
    ``volume=True`` (not with figures) also the raw score volume ``volume (B, K, 129, 129)``.

    Built once per argument triple (cached); each of the three programs compiles once.
    ``params`` is ignored (pass None) for ``bev_source="gt"``."""
    if bev_source not in BEV_SOURCES:
        raise ValueError(f"bev_source must be one of {BEV_SOURCES}, got {bev_source!r}")
    compiled = {}
    for figures in (False, True, "volume"):
        key = (model_cfg, solver_cfg, bev_source, figures)
        compiled[figures] = jax.jit(
            functools.partial(
                _localize,
                model_cfg=model_cfg,
                solver_cfg=solver_cfg,
                bev_source=bev_source,
                figures=figures,
                key=key,
            )
        )

    def step(params, batch, figures: bool = False, volume: bool = False):
        if volume and figures:
            raise ValueError("a localize step returns either the figure maps or the volume")
        return compiled["volume" if volume else bool(figures)](params, batch)

    return step


def evaluate_split(
    step: LocalizeStep,
    params,
    batches: Iterable[dict],
    *,
    num_batches: int,
    place: Callable[[dict], dict],
    desc: str,
    channels: tuple[str, ...],
    figure_dir: str | None = None,
    num_figures: int = 0,
) -> dict:
    """Localizes every valid sample of the first ``num_batches`` host ``batches`` (``place``
    puts one on the devices) and returns the metric summary: the paper's keys and ``count``,
    ``IoU_<channel>`` (percent, pooled over the split; network only) and ``prior`` (position
    recalls / APE of answering the tile centre). Writes ``num_figures`` figures."""
    acc = metrics.MetricAccumulator()
    prior_err = []
    inter = union = None
    figures = 0
    for i, batch in enumerate(tqdm(batches, total=num_batches, desc=desc, unit="batch")):
        if i >= num_batches:
            break
        valid = np.asarray(batch.get("valid", np.ones(len(batch["pose"]), bool)), bool)
        want = min(num_figures - figures, int(valid.sum())) if figure_dir else 0
        out = jax.device_get(step(params, place(batch), figures=want > 0))
        pose_tile = np.asarray(out["pose_tile"], np.float64)  # (B, 3)
        pred_world = solver.tile_pose_to_world(pose_tile, batch["tile_center"])
        gt_world = np.asarray(batch["pose"], np.float64)[valid]
        acc.update(pred_world[valid], gt_world)
        centre = np.asarray(batch["tile_center"], np.float64)[valid]
        prior_err.append(np.hypot(*(centre - gt_world[:, :2]).T))
        if "inter" in out:
            i_b = np.asarray(out["inter"], np.float64)[valid].sum(0)
            u_b = np.asarray(out["union"], np.float64)[valid].sum(0)
            inter = i_b if inter is None else inter + i_b
            union = u_b if union is None else union + u_b
        for j in np.flatnonzero(valid)[:want]:
            _figure(figure_dir, batch, j, out, pose_tile, channels)
            figures += 1
    result = acc.result()
    if inter is not None:
        for c, name in enumerate(channels):
            result[f"IoU_{name}"] = float(100.0 * inter[c] / max(union[c], 1.0))
    result["prior"] = metrics.position_summary(np.concatenate(prior_err) if prior_err else [])
    return result


def _figure(figure_dir, batch, j, out, pose_tile, channels):
    sid = str(batch["sample_id"][j])
    viz.sample_figure(
        os.path.join(figure_dir, f"{sid}.png"),
        tile=np.asarray(batch["tile"][j]),
        bev_pred=np.asarray(out["probs"][j]),
        bev_gt=np.asarray(batch["bev_gt"][j]),
        likelihood=np.asarray(out["likelihood"][j]),
        pose_gt=np.asarray(batch["pose_tile"][j], np.float64),
        pose_pred=pose_tile[j],
        images=np.asarray(batch["images"][j]) if "images" in batch else None,
        channels=channels,
        title=sid,
    )
