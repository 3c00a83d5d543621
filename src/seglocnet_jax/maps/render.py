"""Binary map rasters as RGB images (north up) and PNG files, for a user to look at."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

from seglocnet_jax.fileio import atomic_path

# The project's one mask palette (previews, contact sheets, evaluation figures): uint8 RGB.
BACKGROUND = (255, 255, 255)
COLOURS = {"road": (110, 110, 110), "building": (214, 96, 60)}  # grey roads, brick buildings


def colorize(mask: np.ndarray, channels) -> np.ndarray:
    """``(C, H, W)`` {0, 1} mask -> ``(H, W, 3)`` uint8 RGB; later channels paint over
    earlier ones, and buildings always paint over roads."""
    if mask.ndim != 3 or mask.shape[0] != len(channels):
        raise ValueError(f"mask shape {mask.shape} does not match channels {tuple(channels)}")
    rgb = np.empty((*mask.shape[1:], 3), np.uint8)
    rgb[:] = BACKGROUND
    order = sorted(range(len(channels)), key=lambda i: channels[i] == "building")
    for i in order:
        rgb[mask[i] > 0] = COLOURS[channels[i]]
    return rgb


def outline(
    rgb: np.ndarray, row0: int, col0: int, size: int, colour=(30, 90, 220), thickness: int = 3
) -> np.ndarray:
    """Draws a ``size`` square frame with top-left pixel ``(row0, col0)`` (clipped) in place."""
    h, w, _ = rgb.shape
    for r0, r1, c0, c1 in (
        (row0, row0 + thickness, col0, col0 + size),  # top
        (row0 + size - thickness, row0 + size, col0, col0 + size),  # bottom
        (row0, row0 + size, col0, col0 + thickness),  # left
        (row0, row0 + size, col0 + size - thickness, col0 + size),  # right
    ):
        rgb[max(r0, 0) : max(min(r1, h), 0), max(c0, 0) : max(min(c1, w), 0)] = colour
    return rgb


def save_png(rgb: np.ndarray, path: str | os.PathLike) -> str:
    """Writes ``(H, W, 3)`` uint8 as PNG atomically; returns the path."""
    path = os.fspath(path)
    with atomic_path(path) as tmp:
        Image.fromarray(rgb).save(tmp, format="PNG")
    return path


def write_preview(raster, out_dir: str | os.PathLike, tile_xy=None, prefix: str | None = None):
    """PNGs of a :class:`~seglocnet_jax.maps.raster.CityRaster`: the whole city (with the tile's
    frame drawn in blue) and one 256x256 tile centred on world ``tile_xy`` metres (default: the
    raster's centre). Returns ``{"city": path, "tile": path}``."""
    from seglocnet_jax import geometry as g

    if tile_xy is None:
        x0, y0, x1, y1 = raster.grid.bounds
        tile_xy = ((x0 + x1) / 2, (y0 + y1) / 2)
    x, y = (float(v) for v in tile_xy)
    tile, _ = raster.tile(x, y)
    row0, col0, _, _ = g.tile_window(raster.grid, x, y)
    prefix = prefix or f"{raster.name}_{'-'.join(raster.channels)}"
    city_rgb = outline(colorize(raster.mask, raster.channels), int(row0), int(col0), g.TILE_SIZE)
    return {
        "city": save_png(city_rgb, os.path.join(out_dir, f"{prefix}_city.png")),
        "tile": save_png(
            colorize(tile, raster.channels), os.path.join(out_dir, f"{prefix}_tile.png")
        ),
    }
