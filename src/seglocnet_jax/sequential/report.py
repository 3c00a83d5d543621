"""A split's numbers, per-frame arrays and figures from its tracks (definitions: the package
docstring)."""

from __future__ import annotations

import math
import os
import re

import numpy as np

from seglocnet_jax import fileio, metrics, viz
from seglocnet_jax.sequential.drive_filter import Track
from seglocnet_jax.sequential.drives import DriveSplit

TRACKED_M = 5.0  # m: a frame is tracked when the filtered error is at most this, else lost
CONVERGED_M = 2.0  # m: converged / recovered when the error is at most this
MAX_LOST_RUN = 10  # frames: a drive is "never lost" without a longer run of lost frames
RECOVERY_FRAMES = 10  # frames after a detected loss within which it must be recovered
MASSES = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)  # credible masses of the calibration curve
ELLIPSE_EVERY = 10  # frames between the uncertainty ellipses of a drive figure
FIGURE_MARGIN_M = 40.0  # m of map around a drive's bounding box in its figure


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` of the maximal runs of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _ellipse_d2(track: Track) -> np.ndarray:
    """Squared Mahalanobis distance of the GT (x, y) to the posterior mean and covariance."""
    err = track.drive.poses[:, :2] - track.mean[:, :2]
    cov = track.cov_xy + np.eye(2) * 1e-9
    return np.einsum("ti,tij,tj->t", err, np.linalg.inv(cov), err)


def drive_summary(track: Track) -> dict:
    """One drive's numbers (see the module docstring for the definitions)."""
    pos, yaw = metrics.pose_errors(track.filtered, track.drive.poses)
    lost = pos > TRACKED_M
    settled = np.flatnonzero(pos > CONVERGED_M)
    converge = 0 if settled.size == 0 else int(settled[-1]) + 1
    converge = converge if converge < len(pos) else None
    detected = np.flatnonzero(track.lost)
    recovered = sum(bool((pos[i : i + RECOVERY_FRAMES + 1] <= CONVERGED_M).any()) for i in detected)
    episodes = _runs(lost)
    flagged = sum(bool(track.lost[a : b + 1].any()) for a, b in episodes)
    dist = track.drive.distance()
    return {
        "sequence_id": track.drive.sequence_id,
        "frames": len(pos),
        "length_m": float(dist[-1]),
        "APE": float(pos.mean()),
        "AOE": float(yaw.mean()),
        "single_APE": float(metrics.pose_errors(track.single, track.drive.poses)[0].mean()),
        "tracked_pct": float(100.0 * np.mean(~lost)),
        "frames_to_converge": converge,
        "metres_to_converge": None if converge is None else float(dist[converge]),
        "losses_detected": int(detected.size),
        "losses_recovered": int(recovered),
        "lost_episodes": len(episodes),
        "lost_episodes_detected": int(flagged),
        "longest_lost_run": int(max((b - a for a, b in episodes), default=0)),
        "frames_narrowed": int(np.sum(track.narrowed)),
        "frames_multi_hypothesis": int(np.sum(track.hypotheses > 1)),
        "odometry_scale": float(track.scale[-1]),  # the filter's estimate at the last frame
    }


def _pct(x) -> float:
    x = np.asarray(x)
    return float(100.0 * x.mean()) if x.size else math.nan


def summarize(tracks: list[Track], masses=MASSES) -> dict:
    """A split's numbers (module docstring): pooled over frames, per drive under ``per_drive``."""
    gt = np.concatenate([t.drive.poses for t in tracks])
    per_drive = [drive_summary(t) for t in tracks]
    above = np.concatenate([t.above for t in tracks])
    d2 = np.concatenate([_ellipse_d2(t) for t in tracks])
    pos = metrics.pose_errors(np.concatenate([t.filtered for t in tracks]), gt)[0]
    converged = [d["frames_to_converge"] for d in per_drive if d["frames_to_converge"] is not None]
    metres = [d["metres_to_converge"] for d in per_drive if d["metres_to_converge"] is not None]
    out = {
        "drives": len(tracks),
        "frames": int(len(gt)),
        "filtered": metrics.evaluate_poses(np.concatenate([t.filtered for t in tracks]), gt),
        "single": metrics.evaluate_poses(np.concatenate([t.single for t in tracks]), gt),
        "tracked_pct": _pct(pos <= TRACKED_M),
        "drives_never_lost_pct": _pct([d["longest_lost_run"] <= MAX_LOST_RUN for d in per_drive]),
        "frames_to_converge": float(np.median(converged)) if converged else None,
        "metres_to_converge": float(np.median(metres)) if metres else None,
        "drives_not_converged": len(per_drive) - len(converged),
        "losses_detected": sum(d["losses_detected"] for d in per_drive),
        "losses_recovered": sum(d["losses_recovered"] for d in per_drive),
        "lost_episodes": sum(d["lost_episodes"] for d in per_drive),
        "lost_episodes_detected": sum(d["lost_episodes_detected"] for d in per_drive),
        # HPD region of mass m holds the GT iff the mass above the GT cell is below m.
        "coverage": {f"{m:g}": _pct(above < m) for m in masses},
        # chi-square with 2 dof: the ellipse of mass m is d^2 <= -2 ln(1 - m).
        "ellipse_coverage": {f"{m:g}": _pct(d2 <= -2 * math.log(1 - m)) for m in masses},
    }
    out["coverage_90"] = _pct(above < 0.9)
    out["narrowed_pct"] = _pct(np.concatenate([t.narrowed for t in tracks]))
    # Windows tracked per frame (tracking.hypotheses; 1 without a bank).
    out["hypotheses_mean"] = float(np.concatenate([t.hypotheses for t in tracks]).mean())
    # The filter's log score: mean log posterior of the GT cell (nats; clamped, see tracks).
    out["mean_log_p_gt"] = float(np.concatenate([t.log_p_gt for t in tracks]).mean())
    out["per_drive"] = per_drive
    return out


SCALARS = (
    "tracked_pct",
    "drives_never_lost_pct",
    "frames_to_converge",
    "losses_detected",
    "losses_recovered",
    "coverage_90",
    "mean_log_p_gt",
    "temperature",
    "filter_ms_per_frame",
    "score_ms_per_frame",
)


def scalars(summary: dict) -> dict:
    """The numbers of a split summary worth a metrics log row (filtered / single-frame metrics
    nested, None skipped by the logger)."""
    return {
        "filtered": summary["filtered"],
        "single": summary["single"],
        **{k: summary.get(k) for k in SCALARS},
    }


# --------------------------------------------------------------------------- figures


def _crop_extent(raster, poses: np.ndarray, margin: float):
    """The raster window around ``poses`` grown by ``margin`` m: ``(mask (C, h, w), extent)``."""
    grid = raster.grid
    lo, hi = poses[:, :2].min(0) - margin, poses[:, :2].max(0) + margin
    row0, col0 = (int(math.floor(v)) for v in grid.world_to_pixel(lo[0], hi[1]))
    row1, col1 = (int(math.ceil(v)) for v in grid.world_to_pixel(hi[0], lo[1]))
    row0, col0 = max(row0, 0), max(col0, 0)
    row1, col1 = min(row1, grid.height), min(col1, grid.width)
    x0, y1 = grid.pixel_to_world(row0, col0)
    x1, y0 = grid.pixel_to_world(row1, col1)
    return raster.mask[:, row0:row1, col0:col1], (float(x0), float(x1), float(y0), float(y1))


def _file_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)


def write_figures(
    tracks: list[Track], split: DriveSplit, figure_dir: str, *, num_drives: int, channels
) -> list[str]:
    """The first ``num_drives`` drives over the map and the error-vs-distance figure."""
    os.makedirs(figure_dir, exist_ok=True)
    paths = []
    for track in tracks[:num_drives]:
        d = track.drive
        mask, extent = _crop_extent(split.rasters[d.city], d.poses, FIGURE_MARGIN_M)
        summary = drive_summary(track)
        paths.append(
            viz.drive_figure(
                os.path.join(figure_dir, f"{split.name}_{_file_name(d.sequence_id)}.png"),
                mask=mask,
                extent=extent,
                channels=channels,
                gt=d.poses,
                single=track.single,
                filtered=track.filtered,
                mean=track.mean,
                cov_xy=track.cov_xy,
                lost=np.flatnonzero(track.lost),
                every=ELLIPSE_EVERY,
                mass=0.9,
                title=(
                    f"{d.sequence_id}: {len(d)} frames, {summary['length_m']:.0f} m; APE "
                    f"filtered {summary['APE']:.2f} m, single-frame {summary['single_APE']:.2f} m"
                ),
            )
        )
    curves = []
    for track in tracks:
        err_f = metrics.pose_errors(track.filtered, track.drive.poses)[0]
        err_s = metrics.pose_errors(track.single, track.drive.poses)[0]
        curves.append((track.drive.distance(), err_f, err_s))
    paths.append(
        viz.error_distance_figure(
            os.path.join(figure_dir, f"{split.name}_error_vs_distance.png"),
            curves,
            title=f"{split.name}: position error along the drives ({len(tracks)} drives)",
        )
    )
    return paths


def write_arrays(tracks: list[Track], path: str) -> str:
    """Per-frame arrays of a split (``.npz``): ids, GT, single-frame and filtered poses, the
    posterior mean and covariance, the mass above the GT cell, its log posterior, the
    detected losses, the frames tracked in the tracking window and the windows tracked after
    each frame."""
    cat = {
        "sequence_id": np.concatenate([[t.drive.sequence_id] * len(t.drive) for t in tracks]),
        "frame_index": np.concatenate([t.drive.frame_index for t in tracks]),
        "timestamp": np.concatenate([t.drive.timestamps for t in tracks]),
        "gt": np.concatenate([t.drive.poses for t in tracks]),
    }
    for key in (
        "single",
        "filtered",
        "mean",
        "cov_xy",
        "above",
        "log_p_gt",
        "lost",
        "narrowed",
        "hypotheses",
        "scale",
    ):
        cat[key] = np.concatenate([getattr(t, key) for t in tracks])
    with fileio.atomic_path(path) as tmp:  # keeps the .npz suffix (savez adds none then)
        np.savez_compressed(tmp, **cat)
    return path
