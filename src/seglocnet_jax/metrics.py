"""Localization metrics in the paper's layout: recalls at position / orientation thresholds,
APE (mean position error, m) and AOE (mean orientation error, deg).

Poses are ``(x, y, yaw)`` in metres and radians in any common frame (world or tile). Position
error is the Euclidean distance; orientation error is the wrapped absolute yaw difference
(:func:`geometry.angle_error`). Recalls count errors strictly below the threshold (``<``), in %.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seglocnet_jax import geometry


@dataclasses.dataclass(frozen=True)
class MetricsConfig:
    """Recall thresholds (paper: 1, 2, 5, 10 m and 1, 2, 5, 10 degrees)."""

    position_thresholds: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0)  # metres
    yaw_thresholds: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0)  # degrees


def _fmt(t: float) -> str:
    return f"{t:g}"


def position_key(t: float) -> str:
    """Result key of the position recall at ``t`` metres, e.g. ``"R@1m"``."""
    return f"R@{_fmt(t)}m"


def yaw_key(t: float) -> str:
    """Result key of the orientation recall at ``t`` degrees, e.g. ``"R@1deg"``."""
    return f"R@{_fmt(t)}deg"


def pose_errors(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample errors of ``(N, 3)`` poses: position (m) and wrapped yaw (deg), each ``(N,)``."""
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != 2 or pred.shape[-1] != 3:
        raise ValueError(f"pose_errors expects two (N, 3) arrays, got {pred.shape} and {gt.shape}")
    pos = np.hypot(pred[:, 0] - gt[:, 0], pred[:, 1] - gt[:, 1])
    yaw = np.degrees(geometry.angle_error(pred[:, 2], gt[:, 2]))
    return pos, yaw


def recall(errors, threshold: float) -> float:
    """Percentage of ``errors`` strictly below ``threshold``."""
    errors = np.asarray(errors, np.float64)
    if errors.size == 0:
        return math.nan
    return float(np.mean(errors < threshold) * 100.0)


def position_summary(pos_err, cfg: MetricsConfig = MetricsConfig()) -> dict:
    """Position recalls and APE of a method without a heading (e.g. the prior alone); the
    orientation keys are None (a table shows them as "–")."""
    pos_err = np.asarray(pos_err, np.float64)
    out = {position_key(t): recall(pos_err, t) for t in cfg.position_thresholds}
    out.update({yaw_key(t): None for t in cfg.yaw_thresholds})
    out.update(APE=float(np.mean(pos_err)) if pos_err.size else math.nan, AOE=None)
    out["count"] = int(pos_err.size)
    return out


def summarize(pos_err, yaw_err, cfg: MetricsConfig = MetricsConfig()) -> dict[str, float]:
    """The paper's numbers from per-sample errors (m, deg): recalls in %, APE (m), AOE (deg),
    and ``count``. Empty inputs give NaN metrics and count 0."""
    pos_err = np.asarray(pos_err, np.float64).reshape(-1)
    yaw_err = np.asarray(yaw_err, np.float64).reshape(-1)
    if pos_err.shape != yaw_err.shape:
        raise ValueError(f"summarize: {pos_err.size} position but {yaw_err.size} yaw errors")
    out = {position_key(t): recall(pos_err, t) for t in cfg.position_thresholds}
    out |= {yaw_key(t): recall(yaw_err, t) for t in cfg.yaw_thresholds}
    out["APE"] = float(pos_err.mean()) if pos_err.size else math.nan
    out["AOE"] = float(yaw_err.mean()) if yaw_err.size else math.nan
    out["count"] = int(pos_err.size)
    return out


def evaluate_poses(pred, gt, cfg: MetricsConfig = MetricsConfig()) -> dict[str, float]:
    """:func:`summarize` of the errors of ``(N, 3)`` predicted against ground-truth poses."""
    return summarize(*pose_errors(pred, gt), cfg=cfg)


class MetricAccumulator:
    """Collects per-sample errors over batches; :meth:`result` gives the paper's numbers.

    Usage::

        acc = MetricAccumulator()
        for batch in ...:
            acc.update(pred_pose, gt_pose)  # (B, 3) each
        row = acc.result()
    """

    def __init__(self, cfg: MetricsConfig = MetricsConfig()):
        self.cfg = cfg
        self._pos: list[np.ndarray] = []
        self._yaw: list[np.ndarray] = []

    def update(self, pred, gt) -> None:
        """Adds a batch of ``(B, 3)`` predicted and ground-truth poses."""
        pos, yaw = pose_errors(pred, gt)
        self._pos.append(pos)
        self._yaw.append(yaw)

    def errors(self) -> tuple[np.ndarray, np.ndarray]:
        """All errors so far: position (m) and yaw (deg), each ``(N,)``."""
        if not self._pos:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(self._pos), np.concatenate(self._yaw)

    def result(self) -> dict[str, float]:
        return summarize(*self.errors(), cfg=self.cfg)

    def __len__(self) -> int:
        return sum(p.size for p in self._pos)


# --------------------------------------------------------------------------- markdown


def table_header(cfg: MetricsConfig = MetricsConfig(), name: str = "Method") -> str:
    """Markdown header and separator lines in the paper's column order."""
    cols = [f"R@{_fmt(t)}m" for t in cfg.position_thresholds]
    cols += [f"R@{_fmt(t)}°" for t in cfg.yaw_thresholds]
    cols += ["APE (m)", "AOE (°)"]
    head = "| " + " | ".join([name] + cols) + " |"
    sep = "|" + "|".join(["---"] + ["---:"] * len(cols)) + "|"
    return head + "\n" + sep


def table_row(name: str, result: dict, cfg: MetricsConfig = MetricsConfig()) -> str:
    """One markdown row: recalls in % with 2 decimals, APE / AOE with 2 decimals ("–" for a
    None value: a metric the method does not have)."""
    keys = [position_key(t) for t in cfg.position_thresholds]
    keys += [yaw_key(t) for t in cfg.yaw_thresholds]
    missing = [k for k in keys + ["APE", "AOE"] if k not in result]
    if missing:
        raise KeyError(f"table_row({name!r}): result lacks {missing}")
    cells = ["–" if result[k] is None else f"{result[k]:.2f}" for k in keys + ["APE", "AOE"]]
    return "| " + " | ".join([name] + cells) + " |"


def markdown_table(results, cfg: MetricsConfig = MetricsConfig(), name: str = "Method") -> str:
    """A markdown table of ``{name: result}`` (or ``[(name, result), ...]``) rows."""
    items = results.items() if isinstance(results, dict) else results
    return "\n".join([table_header(cfg, name)] + [table_row(n, r, cfg) for n, r in items])
