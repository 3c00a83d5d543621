"""Figures a person looks at: BEV segmentation, map tile, likelihood map, GT vs predicted pose.

All inputs are NumPy arrays in the conventions of :mod:`seglocnet_jax.geometry`; poses are given
in the tile frame ``(dx east, dy north, yaw)`` relative to the tile centre.
"""

from __future__ import annotations

import math
import os

import matplotlib

matplotlib.use("Agg")  # files only; never opens a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from seglocnet_jax import geometry  # noqa: E402
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
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path
