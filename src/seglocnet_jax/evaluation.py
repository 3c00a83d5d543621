"""Evaluation of a prepared split: BEV source -> solver -> metrics, tables and figures.

The network's output and the GT-segmentation upper bound take the same path: a function gives
``(B, C, 128, 128)`` BEV logits for a batch, :func:`seglocnet_jax.solver.localize` turns them into
poses, :class:`seglocnet_jax.metrics.MetricAccumulator` scores them.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable

import jax
import numpy as np
from tqdm import tqdm

from seglocnet_jax import metrics, solver, viz

BEV_SOURCES = ("model", "gt")

# batch (host NumPy dict) -> (bev_logits (B, C, 128, 128), bev_probs (B, C, 128, 128))
BevFn = Callable[[dict], tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Attributes:
    bev_source: "model" (network output) or "gt" (GT-segmentation upper bound: the map cut out
      at the GT pose, as ±1 logits; needs no checkpoint).
    splits: prepared splits evaluated at the end of training / by ``evaluate``.
    num_figures: figures written per split (the first samples).
    max_batches: cap on batches per split (None: the whole split).
    batch_size: evaluation batch size.
    """

    bev_source: str = "model"
    splits: tuple[str, ...] = ("test",)
    num_figures: int = 4
    max_batches: int | None = None
    batch_size: int = 8

    def __post_init__(self):
        if self.bev_source not in BEV_SOURCES:
            raise ValueError(
                f"eval.bev_source must be one of {BEV_SOURCES}, got {self.bev_source!r}"
            )
        if self.batch_size < 1:
            raise ValueError(f"eval.batch_size must be >= 1, got {self.batch_size}")


def gt_bev_fn(batch: dict) -> tuple[np.ndarray, np.ndarray]:
    """The upper bound's BEV: GT labels as confident logits (road on non-road is penalized)."""
    labels = np.asarray(batch["bev_gt"], np.float32)
    return np.asarray(solver.labels_to_logits(labels)), labels


def evaluate_loader(
    batches,
    bev_fn: BevFn,
    solver_cfg: solver.SolverConfig,
    *,
    num_batches: int,
    desc: str,
    figure_dir: str | None = None,
    num_figures: int = 0,
    channels=("road", "building"),
) -> dict:
    """Localizes every valid sample of ``batches`` and returns the metric summary (paper keys
    plus ``count``, and ``prior``: the position recalls / APE of the prior alone, i.e. of
    answering the tile centre). Writes ``num_figures`` figures to ``figure_dir``."""
    acc = metrics.MetricAccumulator()
    prior_err = []
    figures = 0
    for i, batch in enumerate(tqdm(batches, total=num_batches, desc=desc, unit="batch")):
        if i >= num_batches:
            break
        logits, probs = bev_fn(batch)
        out = solver.localize(logits, batch["tile"], solver_cfg)
        pose_tile = np.asarray(out["pose_tile"], np.float64)  # (B, 3)
        pred_world = solver.tile_pose_to_world(pose_tile, batch["tile_center"])
        valid = np.asarray(batch.get("valid", np.ones(len(pose_tile), bool)), bool)
        gt_world = np.asarray(batch["pose"], np.float64)[valid]
        acc.update(pred_world[valid], gt_world)
        centre = np.asarray(batch["tile_center"], np.float64)[valid]
        prior_err.append(np.hypot(*(centre - gt_world[:, :2]).T))
        for j in np.flatnonzero(valid)[: max(num_figures - figures, 0) if figure_dir else 0]:
            _figure(figure_dir, batch, j, logits, probs, pose_tile, solver_cfg, channels)
            figures += 1
    result = acc.result()
    result["prior"] = metrics.position_summary(np.concatenate(prior_err) if prior_err else [])
    return result


def _figure(figure_dir, batch, j, logits, probs, pose_tile, solver_cfg, channels):
    volume = solver.score_volume(
        jax.numpy.asarray(logits[j]),
        jax.numpy.asarray(batch["tile"][j]),
        solver_cfg.num_rotations,
        solver_cfg.method,
    )  # (K, 129, 129)
    likelihood = np.asarray(volume.max(axis=0))  # (129, 129) best score over rotations
    sid = str(batch["sample_id"][j])
    viz.sample_figure(
        os.path.join(figure_dir, f"{sid}.png"),
        tile=np.asarray(batch["tile"][j]),
        bev_pred=np.asarray(probs[j]),
        bev_gt=np.asarray(batch["bev_gt"][j]),
        likelihood=likelihood,
        pose_gt=np.asarray(batch["pose_tile"][j], np.float64),
        pose_pred=pose_tile[j],
        images=np.asarray(batch["images"][j]) if "images" in batch else None,
        channels=channels,
        title=sid,
    )
