"""GT-segmentation upper bound: localize perfect BEV labels cut from the map itself.

What the solver can do with a flawless network: the BEV is the map raster cut at the GT pose,
entered as +-1 logits (:func:`solver.labels_to_logits`), matched by the same
:func:`solver.localize` the network's evaluation path calls. Failures left are the map's own
ambiguities (a straight road with nothing else in view, repeated blocks) and the solver's
quantization (0.5 m cells, 2 pi / K rotation bins).

The raster is any object with the maps API of :mod:`seglocnet_jax.maps` (``CityRaster``):
``tile(x, y) -> (tile (C, 256, 256), (cx, cy))`` around world ``(x, y)`` and
``cut_bev(pose) -> (C, 128, 128)`` at a world pose.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from tqdm.auto import tqdm

from seglocnet_jax import geometry, metrics, solver


@dataclasses.dataclass(frozen=True)
class UpperBoundResult:
    """Per-sample outcome of :func:`gt_upper_bound`.

    Attributes:
      pred: ``(N, 3)`` predicted world poses (m, m, rad).
      gt: ``(N, 3)`` GT world poses.
      tile_center: ``(N, 2)`` world (x, y) of each tile centre (snapped prior).
      score: ``(N,)`` peak raw scores.
      pos_err: ``(N,)`` position errors (m); yaw_err: ``(N,)`` wrapped yaw errors (deg).
      metrics: the paper's numbers (:func:`metrics.summarize`).
    """

    pred: np.ndarray
    gt: np.ndarray
    tile_center: np.ndarray
    score: np.ndarray
    pos_err: np.ndarray
    yaw_err: np.ndarray
    metrics: dict


def sample_priors(
    poses, rng: np.random.Generator, prior_range: float = geometry.PRIOR_RANGE
) -> np.ndarray:
    """Priors ``(N, 2)``: GT position plus a uniform offset in ``[-range, range]`` m per axis."""
    poses = np.asarray(poses, np.float64)
    return poses[:, :2] + rng.uniform(-prior_range, prior_range, size=(len(poses), 2))


def gt_inputs(raster, poses, priors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GT BEVs ``(N, C, 128, 128)`` (labels), tiles ``(N, C, 256, 256)`` and tile centres
    ``(N, 2)`` for world ``poses (N, 3)`` and ``priors (N, 2)``."""
    poses = np.asarray(poses, np.float64)
    priors = np.asarray(priors, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or priors.shape != (len(poses), 2):
        raise ValueError(
            f"gt_inputs expects poses (N, 3) and priors (N, 2), got "
            f"{poses.shape} and {priors.shape}"
        )
    bevs, tiles, centres = [], [], []
    for pose, prior in zip(poses, priors, strict=True):
        bevs.append(np.asarray(raster.cut_bev(pose), np.float32))
        tile, centre = raster.tile(float(prior[0]), float(prior[1]))
        tiles.append(np.asarray(tile, np.float32))
        centres.append(centre)
    return np.stack(bevs), np.stack(tiles), np.asarray(centres, np.float64)


def gt_upper_bound(
    raster,
    poses,
    priors,
    cfg: solver.SolverConfig | None = None,
    batch_size: int = 8,
    metrics_cfg: metrics.MetricsConfig | None = None,
    progress: bool = True,
) -> UpperBoundResult:
    """Localizes the GT segmentation at each pose against the tile around its prior.

    Args:
      raster: a ``CityRaster`` (see module docstring).
      poses: ``(N, 3)`` GT world poses (m, m, rad).
      priors: ``(N, 2)`` world priors (m); the tile is centred on each, snapped to the grid.
      cfg: solver configuration (same as the network's evaluation); default SolverConfig().
      batch_size: samples per jitted call; the last batch is padded so shapes stay static.
      metrics_cfg: recall thresholds; default MetricsConfig() (the paper's).
      progress: show a tqdm bar.

    Returns:
      :class:`UpperBoundResult` with per-sample poses and errors and the paper's metrics.
    """
    cfg = cfg or solver.SolverConfig()
    metrics_cfg = metrics_cfg or metrics.MetricsConfig()
    if batch_size <= 0:
        raise ValueError(f"gt_upper_bound: batch_size must be positive, got {batch_size}")
    poses = np.asarray(poses, np.float64)
    priors = np.asarray(priors, np.float64)
    n = len(poses)
    preds, centres, scores = [], [], []
    for start in tqdm(
        range(0, n, batch_size), desc="gt upper bound", disable=not progress, unit="batch"
    ):
        stop = min(start + batch_size, n)
        bev, tile, centre = gt_inputs(raster, poses[start:stop], priors[start:stop])
        pad = batch_size - (stop - start)
        if pad:  # repeat the last sample: one compiled shape for every batch
            bev = np.concatenate([bev, np.repeat(bev[-1:], pad, axis=0)])
            tile = np.concatenate([tile, np.repeat(tile[-1:], pad, axis=0)])
        out = solver.localize(solver.labels_to_logits(bev), tile, cfg)
        pose_tile = np.asarray(out["pose_tile"])[: stop - start]
        preds.append(solver.tile_pose_to_world(pose_tile, centre))
        centres.append(centre)
        scores.append(np.asarray(out["score"])[: stop - start])
    pred = np.concatenate(preds) if preds else np.zeros((0, 3))
    pos_err, yaw_err = metrics.pose_errors(pred, poses) if n else (np.zeros(0), np.zeros(0))
    return UpperBoundResult(
        pred=pred,
        gt=poses,
        tile_center=np.concatenate(centres) if centres else np.zeros((0, 2)),
        score=np.concatenate(scores) if scores else np.zeros(0),
        pos_err=pos_err,
        yaw_err=yaw_err,
        metrics=metrics.summarize(pos_err, yaw_err, metrics_cfg),
    )
