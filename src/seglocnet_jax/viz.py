"""Figures a person looks at: BEV segmentation, map tile, likelihood map, GT vs predicted pose;
and for sequential localization a drive over the city map, error against distance driven and
the calibration (reliability) curve.

All inputs are NumPy arrays in the conventions of :mod:`seglocnet_jax.geometry`; the sample
figure's poses are given in the tile frame ``(dx east, dy north, yaw)`` relative to the tile
centre, the drive figures' in the world frame.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")  # files only; never opens a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from seglocnet_jax import fileio, geometry  # noqa: E402
from seglocnet_jax.maps.render import COLOURS  # noqa: E402


def color_mask(mask: np.ndarray, channels=("road", "building")) -> np.ndarray:
    """``(C, H, W)`` values in [0, 1] (labels or probabilities) to an ``(H, W, 3)`` float image
    on white in the project's mask palette (:data:`seglocnet_jax.maps.render.COLOURS`); later
    channels are drawn over earlier ones. An unknown channel name raises ``KeyError``."""
    rgb = np.ones(mask.shape[1:] + (3,), np.float32)
    for c, name in enumerate(channels):
        if name not in COLOURS:
            raise KeyError(f"no colour for channel {name!r}; known channels: {sorted(COLOURS)}")
        alpha = np.clip(np.asarray(mask[c], np.float32), 0, 1)[..., None]
        color = np.asarray(COLOURS[name], np.float32) / 255.0
        rgb = rgb * (1 - alpha) + color * alpha
    return rgb


def _tile_pixel(dx: float, dy: float, res: float, tile_size: int):
    """Tile-frame metres to display ``(col, row)``."""
    return tile_size / 2 + dx / res, tile_size / 2 - dy / res


def _arrow(ax, pose, color, label, res, tile_size, length_m=8.0):
    col, row = _tile_pixel(pose[0], pose[1], res, tile_size)
    dcol = math.cos(pose[2]) * length_m / res
    drow = -math.sin(pose[2]) * length_m / res
    ax.annotate(
        "",
        xy=(col + dcol, row + drow),
        xytext=(col, row),
        arrowprops=dict(arrowstyle="-|>", color=color, lw=2),
    )
    ax.plot([col], [row], "o", color=color, ms=4, label=label)


def sample_figure(
    path: str,
    *,
    tile: np.ndarray,  # (C, 256, 256) {0, 1}
    bev_pred: np.ndarray,  # (C, 128, 128) probabilities
    bev_gt: np.ndarray,  # (C, 128, 128) {0, 1}
    likelihood: np.ndarray,  # (129, 129) max over rotations (any monotone score)
    pose_gt: np.ndarray,  # (3,) tile frame
    pose_pred: np.ndarray,  # (3,) tile frame
    images: np.ndarray | None = None,  # (N, H, W, 3) uint8
    channels=("road", "building"),
    title: str = "",
    resolution: float = geometry.RESOLUTION,
) -> str:
    """Writes one sample's figure (camera images; predicted and GT BEV; tile with GT (green) and
    predicted (red) pose; likelihood map) to ``path`` (PNG); returns the path."""
    n_img = 0 if images is None else len(images)
    ncols = 4
    fig = plt.figure(figsize=(16, 9.5 if n_img else 4.2), dpi=80)
    if n_img:
        top, bottom = fig.subfigures(2, 1, height_ratios=(1.2, 1))
        img_cols = (n_img + 1) // 2
        img_axes = top.subplots(2, img_cols, squeeze=False).reshape(-1)
        for i, ax in enumerate(img_axes):
            if i < n_img:
                ax.imshow(images[i])
            ax.set_axis_off()
    else:
        bottom = fig
    axes = bottom.subplots(1, ncols)
    tile_size = tile.shape[-1]
    panels = [
        ("predicted BEV", color_mask(bev_pred, channels)),
        ("GT BEV", color_mask(bev_gt, channels)),
    ]
    for ax, (name, img) in zip(axes[:2], panels, strict=True):
        ax.imshow(img)
        ax.plot([img.shape[1] / 2 - 0.5], [img.shape[0] / 2 - 0.5], "k^", ms=6)
        ax.set_title(name)
        ax.set_axis_off()
    ax = axes[2]
    ax.imshow(color_mask(tile, channels))
    _arrow(ax, pose_gt, "limegreen", "GT", resolution, tile_size)
    _arrow(ax, pose_pred, "crimson", "predicted", resolution, tile_size)
    err = math.hypot(pose_pred[0] - pose_gt[0], pose_pred[1] - pose_gt[1])
    ax.set_title(f"map tile (error {err:.1f} m)")
    ax.legend(loc="lower right", fontsize=7)
    ax.set_axis_off()
    ax = axes[3]
    half = (likelihood.shape[0] - 1) / 2  # cells span tile corners centre +- half
    lo, hi = tile_size / 2 - half - 0.5, tile_size / 2 + half + 0.5
    ax.imshow(likelihood, cmap="magma", extent=(lo, hi, hi, lo))
    _arrow(ax, pose_gt, "limegreen", "GT", resolution, tile_size)
    _arrow(ax, pose_pred, "cyan", "predicted", resolution, tile_size)
    ax.set_xlim(0, tile_size)
    ax.set_ylim(tile_size, 0)
    ax.set_title("likelihood (max over rotations)")
    ax.set_axis_off()
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def _save(fig, path: str) -> str:
    try:
        with fileio.atomic_path(path) as tmp:  # keeps the .png suffix: savefig's format
            fig.savefig(tmp)
    finally:
        plt.close(fig)
    return path


def _ellipse(mean, cov, mass: float, n: int = 48) -> np.ndarray:
    """``(n, 2)`` outline of the Gaussian ellipse of ``mass`` (chi-square, 2 dof)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov, np.float64))
    radius = np.sqrt(-2.0 * math.log(1.0 - mass) * np.clip(vals, 0.0, None))
    a = np.linspace(0.0, 2 * math.pi, n)
    circle = np.stack([np.cos(a), np.sin(a)], axis=1) * radius
    return np.asarray(mean[:2]) + circle @ vecs.T


def drive_figure(
    path: str,
    *,
    mask: np.ndarray,  # (C, h, w) the map around the drive
    extent: tuple[float, float, float, float],  # world (x0, x1, y0, y1) of the mask
    gt: np.ndarray,  # (T, 3) world poses
    single: np.ndarray,  # (T, 3) single-frame estimates
    filtered: np.ndarray,  # (T, 3) filtered estimates
    mean: np.ndarray,  # (T, 3) posterior means (ellipse centres)
    cov_xy: np.ndarray,  # (T, 2, 2) posterior (x, y) covariances, m^2
    lost=(),  # frame indices where the filter detected a track loss
    every: int = 10,
    mass: float = 0.9,
    channels=("road", "building"),
    title: str = "",
) -> str:
    """One drive over the city map: the true trajectory (green), the single-frame estimates
    (red dots), the filtered trajectory (blue) with its ``mass`` uncertainty ellipse every
    ``every`` frames, the start (square) and the detected track losses (black crosses)."""
    x0, x1, y0, y1 = extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-6)
    fig, ax = plt.subplots(figsize=(10, float(np.clip(10 * aspect, 4, 14))), dpi=100)
    ax.imshow(color_mask(mask, channels), extent=extent, interpolation="nearest")
    ax.plot(gt[:, 0], gt[:, 1], "-", color="limegreen", lw=2.5, label="truth")
    ax.plot(single[:, 0], single[:, 1], ".", color="crimson", ms=3, label="single-frame")
    ax.plot(filtered[:, 0], filtered[:, 1], "-", color="royalblue", lw=1.2, label="filtered")
    for t in range(0, len(gt), max(every, 1)):
        ring = _ellipse(mean[t], cov_xy[t], mass)
        ax.plot(ring[:, 0], ring[:, 1], "-", color="navy", lw=0.8, alpha=0.8)
    ax.plot([], [], "-", color="navy", lw=0.8, label=f"{mass:.0%} ellipse every {every} frames")
    ax.plot(gt[:1, 0], gt[:1, 1], "s", color="k", ms=6, label="start")
    lost = np.asarray(lost, np.int64)
    if lost.size:
        ax.plot(filtered[lost, 0], filtered[lost, 1], "x", color="k", ms=7, label="loss detected")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.legend(loc="best", fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def error_distance_figure(path: str, curves, title: str = "") -> str:
    """Position error against distance driven: ``curves`` is ``[(distance (T,), filtered error
    (T,), single-frame error (T,)), ...]`` per drive (m); filtered as lines, single-frame as
    faint dots; log scale."""
    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=100)
    floor = 0.05  # m: the log axis needs positive values
    for i, (dist, err_f, err_s) in enumerate(curves):
        colour = plt.cm.tab10(i % 10)
        ax.plot(dist, np.maximum(err_s, floor), ".", color=colour, ms=2, alpha=0.35)
        ax.plot(dist, np.maximum(err_f, floor), "-", color=colour, lw=1.2)
    ax.plot([], [], "-", color="gray", label="filtered")
    ax.plot([], [], ".", color="gray", label="single-frame")
    for level, style in ((2.0, ":"), (5.0, "--")):
        ax.axhline(level, color="k", lw=0.8, ls=style)
    ax.set_yscale("log")
    ax.set_xlabel("distance driven (m)")
    ax.set_ylabel("position error (m)")
    ax.legend(loc="upper right", fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def reliability_figure(path: str, masses, coverage, ellipse_coverage=None, title: str = "") -> str:
    """The calibration figure: how often the truth falls inside the credible region of each
    nominal mass (``coverage``, %; ``ellipse_coverage``: of the Gaussian (x, y) ellipse) against
    the mass; a calibrated filter lies on the diagonal."""
    masses = 100.0 * np.asarray(masses, np.float64)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=100)
    ax.plot([0, 100], [0, 100], "k--", lw=0.8, label="calibrated")
    ax.plot(masses, coverage, "o-", color="royalblue", label="credible region (pose cells)")
    if ellipse_coverage is not None:
        ax.plot(masses, ellipse_coverage, "s-", color="darkorange", label="(x, y) ellipse")
    lo = max(0.0, float(masses.min()) - 10)
    ax.set_xlim(lo, 100)
    ax.set_ylim(0, 100)
    ax.set_xlabel("nominal mass (%)")
    ax.set_ylabel("truth inside (%)")
    ax.legend(loc="lower right", fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)
