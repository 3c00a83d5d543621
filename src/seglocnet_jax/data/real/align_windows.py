"""Windows on the data for the OSM alignment: where the windows go (:func:`place_windows`: on
clusters of frames), their grids at the working resolution (:func:`window_grids`) and the raster
operations the fit runs in them (downsampling, warping by a similarity, the band template).
The fit is :mod:`seglocnet_jax.data.real.align_fit`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from seglocnet_jax import geometry
from seglocnet_jax.data.real.alignment import AlignConfig, Similarity


def downsample(mask: np.ndarray, grid: geometry.RasterGrid, factor: int):
    """Block mean by ``factor``: ``(small, small_grid)`` (edges that do not fill a block drop)."""
    h, w = (mask.shape[0] // factor) * factor, (mask.shape[1] // factor) * factor
    if h == 0 or w == 0:
        raise ValueError(f"raster {mask.shape} is smaller than the alignment factor {factor}")
    small = mask[:h, :w].astype(np.float32)
    small = small.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))
    return small, geometry.RasterGrid(
        grid.x_min, grid.y_max, h // factor, w // factor, grid.resolution * factor
    )


def fine_factor(cfg: AlignConfig) -> int:
    """Rasters are drawn at ``cfg.resolution / fine_factor`` (<= ~0.5 m) and block-averaged."""
    return max(1, round(cfg.resolution / geometry.RESOLUTION))


def _index_from_world(grid: geometry.RasterGrid) -> np.ndarray:
    """Homogeneous ``(3, 3)``: world ``(x, y, 1)`` -> ndimage index ``(row, col, 1)`` (pixel
    centres at integers)."""
    r = grid.resolution
    return np.array(
        [[0, -1 / r, grid.y_max / r - 0.5], [1 / r, 0, -grid.x_min / r - 0.5], [0, 0, 1.0]]
    )


def _warp(source: np.ndarray, src_grid, out_grid, sim: Similarity) -> np.ndarray:
    """``source`` resampled on ``out_grid`` after moving it by ``sim`` (bilinear, zero fill)."""
    world_from_out = np.linalg.inv(_index_from_world(out_grid))
    m = _index_from_world(src_grid) @ np.linalg.inv(sim.matrix()) @ world_from_out
    return ndimage.affine_transform(
        source,
        m[:2, :2],
        offset=m[:2, 2],
        output_shape=(out_grid.height, out_grid.width),
        order=1,
        mode="constant",
        cval=0.0,
    )


def _shift_px(cfg: AlignConfig, res: float) -> int:
    return int(math.ceil(cfg.max_shift / res - 1e-9))


def window_grids(centre, cfg: AlignConfig, resolution: float | None = None, origin=(0.0, 0.0)):
    """``(template_grid, tile_grid, source_grid)`` of a window around ``centre``.

    The template is ``window`` metres square (even pixels) with corners on ``origin + k *
    resolution``; the tile grows it by ``max_shift``; the source grid grows the tile by what the
    candidate rotations and scales move its corners (plus 2 pixels).
    """
    r = float(resolution or cfg.resolution)
    n = max(8, int(round(cfg.window / r)))
    n += n % 2
    k = _shift_px(cfg, r)
    x0 = origin[0] + round((centre[0] - n * r / 2 - origin[0]) / r) * r
    y1 = origin[1] + round((centre[1] + n * r / 2 - origin[1]) / r) * r
    template = geometry.RasterGrid(float(x0), float(y1), n, n, r)
    tile = geometry.RasterGrid(float(x0 - k * r), float(y1 + k * r), n + 2 * k, n + 2 * k, r)
    reach = (n / 2 + k) * r * math.sqrt(2)
    spread = math.radians(cfg.max_rotation_deg) + max(abs(1 / s - 1) for s in cfg.scales)
    m = int(math.ceil(reach * spread * 1.05 / r)) + 2
    source = geometry.RasterGrid(
        float(x0 - (k + m) * r), float(y1 + (k + m) * r), n + 2 * (k + m), n + 2 * (k + m), r
    )
    return template, tile, source


def place_windows(points, cfg: AlignConfig) -> tuple[list[tuple[tuple[float, float], int]], int]:
    """Windows on the clusters of ``points (N, 2)`` (frame positions, metres).

    Clusters: points binned into cells of ``window / 2``, cells joined with their 8 neighbours
    (clusters closer than that share windows).
    A cluster that spans at most ``window`` gets one window centred on its bounding box; a
    larger one is cut into ``ceil(span / window)`` equal blocks per axis, one window centred on
    the points of each occupied block. Returns ``([(centre, frames), ...]`` (most frames first,
    at most ``max_windows``), ``frames left unchecked)``.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        return [], 0
    side = cfg.window
    cells, inverse = np.unique(
        np.floor(pts / (side / 2)).astype(np.int64), axis=0, return_inverse=True
    )
    inverse = inverse.reshape(-1)
    index = {tuple(c): i for i, c in enumerate(cells.tolist())}
    label = np.full(len(cells), -1)
    for start in range(len(cells)):  # connected components of occupied cells
        if label[start] >= 0:
            continue
        label[start], stack = start, [start]
        while stack:
            cx, cy = cells[stack.pop()]
            for nb in ((cx + a, cy + b) for a in (-1, 0, 1) for b in (-1, 0, 1)):
                j = index.get(nb)
                if j is not None and label[j] < 0:
                    label[j] = start
                    stack.append(j)
    out = []
    point_label = label[inverse]
    for lab in np.unique(label):
        mine = pts[point_label == lab]
        lo, hi = mine.min(axis=0), mine.max(axis=0)
        blocks = np.maximum(1, np.ceil((hi - lo) / side - 1e-9)).astype(np.int64)
        size = np.where(blocks > 1, (hi - lo) / blocks, 1.0)
        block = np.minimum(np.floor((mine - lo) / size).astype(np.int64), blocks - 1)
        keys, which = np.unique(block, axis=0, return_inverse=True)
        which = which.reshape(-1)
        for b in range(len(keys)):
            part = mine[which == b]
            c = (part.min(axis=0) + part.max(axis=0)) / 2
            out.append(((float(c[0]), float(c[1])), len(part)))
    out.sort(key=lambda item: (-item[1], item[0]))
    kept = out[: cfg.max_windows]
    return kept, int(sum(c for _, c in out[cfg.max_windows :]))


def _template(target: np.ndarray, cfg: AlignConfig, res: float) -> np.ndarray:
    band = ndimage.binary_dilation(target > 0.5, iterations=max(1, round(cfg.band / res)))
    return np.where(band, 2.0 * target - 1.0, 0.0).astype(np.float32)
