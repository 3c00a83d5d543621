"""Per-city similarity correction of OSM against a dataset's HD drivable area.

OSM projected into a dataset's map frame (nuScenes: topocentric about the map origin) can be off
by metres, a fraction of a degree and a small scale (survey, projection and map-making
differences). The published corrections (BLOS-BEV) are not public, so we fit one per city:

    p_dataset = centre + scale * R(rotation) @ (p_osm - centre) + shift

by correlating the dataset's drivable-area raster (the template) with the OSM road raster (the
tile), warped by each candidate rotation and scale, with the project's solver
(:func:`solver.score_volume`: one exhaustive shift search per candidate). The best candidate's
peak is refined to sub-pixel (and sub-step for rotation) by parabola fits.

The template is ``2 * drivable - 1`` (like the solver's GT logits) restricted to a band around
the drivable area, so OSM roads outside the dataset's mapped region cost nothing.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage
from tqdm.auto import tqdm

from seglocnet_jax import geometry


@dataclasses.dataclass(frozen=True)
class AlignConfig:
    """The ``dataset.convert.align`` config.

    Attributes:
      enabled: fit a correction (else the identity is used and reported).
      resolution: working resolution, metres per pixel (rasters are block-averaged to it).
      max_shift: search radius per axis, metres.
      max_rotation_deg, rotation_step_deg: rotations searched, degrees (symmetric about 0).
      scales: scales searched (1.0 must be among them to allow "no scale error").
      band: template band around the drivable area, metres.
      road_width: width (m) the OSM centrelines are buffered to for the fit.
      max_template: largest template side in working pixels (centre crop beyond it).
    """

    enabled: bool = True
    resolution: float = 2.0
    max_shift: float = 48.0
    max_rotation_deg: float = 2.0
    rotation_step_deg: float = 0.25
    scales: tuple[float, ...] = (0.99, 0.995, 1.0, 1.005, 1.01)
    band: float = 20.0
    road_width: float = 10.0
    max_template: int = 1024

    def __post_init__(self):
        if min(self.resolution, self.max_shift, self.road_width) <= 0 or self.band < 0:
            raise ValueError(
                "dataset.convert.align.resolution, max_shift and road_width must be > 0, band >= 0"
            )
        if self.rotation_step_deg <= 0 or self.max_rotation_deg < 0:
            raise ValueError(
                "dataset.convert.align.rotation_step_deg must be > 0, max_rotation_deg >= 0"
            )
        if not self.scales or min(self.scales) <= 0:
            raise ValueError(f"dataset.convert.align.scales must be positive, got {self.scales}")


@dataclasses.dataclass(frozen=True)
class Similarity:
    """``p' = centre + scale * R(rotation) (p - centre) + shift`` in world metres / radians."""

    shift: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    scale: float = 1.0
    centre: tuple[float, float] = (0.0, 0.0)
    score: float = float("nan")  # normalized peak (fraction of the template's weight), report

    def matrix(self) -> np.ndarray:
        """``(3, 3)`` homogeneous world transform."""
        c, s = math.cos(self.rotation) * self.scale, math.sin(self.rotation) * self.scale
        a = np.array([[c, -s], [s, c]])
        centre = np.asarray(self.centre, np.float64)
        out = np.eye(3)
        out[:2, :2] = a
        out[:2, 2] = centre - a @ centre + np.asarray(self.shift, np.float64)
        return out

    def apply(self, xy) -> np.ndarray:
        """Transforms world points ``(..., 2)``."""
        m = self.matrix()
        xy = np.asarray(xy, np.float64)
        return xy @ m[:2, :2].T + m[:2, 2]

    def shapely_params(self) -> list[float]:
        """``[a, b, d, e, xoff, yoff]`` for ``shapely.affinity.affine_transform``."""
        m = self.matrix()
        return [m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[0, 2], m[1, 2]]

    def as_dict(self) -> dict:
        """JSON-able report: shift (m), rotation (deg), scale, centre (m), score."""
        return {
            "shift_m": [float(v) for v in self.shift],
            "rotation_deg": math.degrees(self.rotation),
            "scale": float(self.scale),
            "centre_m": [float(v) for v in self.centre],
            "score": float(self.score),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Similarity:
        return cls(
            shift=tuple(d["shift_m"]),
            rotation=math.radians(d["rotation_deg"]),
            scale=float(d["scale"]),
            centre=tuple(d["centre_m"]),
            score=float(d.get("score", float("nan"))),
        )


def _downsample(mask: np.ndarray, grid: geometry.RasterGrid, factor: int):
    h, w = (mask.shape[0] // factor) * factor, (mask.shape[1] // factor) * factor
    if h == 0 or w == 0:
        raise ValueError(f"raster {mask.shape} is smaller than the alignment factor {factor}")
    small = mask[:h, :w].astype(np.float32)
    small = small.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))
    return small, geometry.RasterGrid(
        grid.x_min, grid.y_max, h // factor, w // factor, grid.resolution * factor
    )


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


def _crop_grid(grid: geometry.RasterGrid, row_c: int, col_c: int, size: int):
    x, y = grid.pixel_to_world(row_c - size // 2, col_c - size // 2)
    return geometry.RasterGrid(float(x), float(y), size, size, grid.resolution)


def _parabola(left: float, centre: float, right: float) -> float:
    denom = left - 2 * centre + right
    return float(np.clip(0.5 * (left - right) / denom, -0.5, 0.5)) if denom < 0 else 0.0


def fit_similarity(
    target: np.ndarray,
    source: np.ndarray,
    grid: geometry.RasterGrid,
    cfg: AlignConfig = AlignConfig(),
    progress: bool = True,
) -> Similarity:
    """The similarity that moves ``source`` (OSM roads) onto ``target`` (drivable area).

    Args:
      target: ``(H, W)`` {0, 1} dataset drivable area on ``grid`` (world = dataset frame).
      source: ``(H, W)`` {0, 1} OSM road raster on the same grid, uncorrected.
      grid: placement of both rasters.
      cfg: search ranges.

    Returns:
      :class:`Similarity` about the centre of the drivable area; its ``score`` is the peak
      correlation divided by the template's positive weight (1.0: every drivable pixel is OSM
      road and no OSM road lies in the band off the drivable area).
    """
    from seglocnet_jax import solver  # jax is imported only when a fit runs

    target, source = np.asarray(target), np.asarray(source)
    if target.shape != source.shape or target.shape != (grid.height, grid.width):
        raise ValueError(
            f"target {target.shape} and source {source.shape} must both match the "
            f"grid ({grid.height}, {grid.width})"
        )
    if not np.any(target):
        raise ValueError("the drivable-area raster is empty: nothing to align")
    factor = max(1, round(cfg.resolution / grid.resolution))
    tgt, wgrid = _downsample(target, grid, factor)
    src, _ = _downsample(source, grid, factor)
    rows, cols = np.nonzero(tgt > 0.5)
    if not len(rows):
        rows, cols = np.nonzero(tgt > 0)
    # Template: the drivable area's bounding box (square, even), capped at max_template.
    row_c = (rows.min() + rows.max() + 1) // 2
    col_c = (cols.min() + cols.max() + 1) // 2
    size = int(max(rows.max() - rows.min(), cols.max() - cols.min())) + 2
    size = min(size + size % 2, cfg.max_template - cfg.max_template % 2)
    shift_px = int(math.ceil(cfg.max_shift / wgrid.resolution))
    t_grid = _crop_grid(wgrid, row_c, col_c, size)
    tile_grid = _crop_grid(wgrid, row_c, col_c, size + 2 * shift_px)
    centre = wgrid.pixel_to_world(row_c, col_c)
    identity = Similarity(centre=(float(centre[0]), float(centre[1])))
    tmpl = _warp(tgt, wgrid, t_grid, identity)  # crop with zero fill, (S, S)
    band = ndimage.binary_dilation(
        tmpl > 0.5, iterations=max(1, round(cfg.band / wgrid.resolution))
    )
    tmpl = np.where(band, 2.0 * tmpl - 1.0, 0.0).astype(np.float32)[None]  # (1, S, S)
    weight = float(np.clip(tmpl, 0, None).sum())
    steps = int(math.floor(cfg.max_rotation_deg / cfg.rotation_step_deg + 1e-9))
    angles = np.radians(np.arange(-steps, steps + 1) * cfg.rotation_step_deg)
    scales = np.asarray(sorted(cfg.scales), np.float64)
    peaks = np.full((len(scales), len(angles)), -np.inf)
    best = None
    total = len(scales) * len(angles)
    with tqdm(total=total, desc="align OSM", unit="cand", disable=not progress) as bar:
        for i, s in enumerate(scales):
            for j, a in enumerate(angles):
                cand = dataclasses.replace(identity, rotation=float(a), scale=float(s))
                tile = _warp(src, wgrid, tile_grid, cand)[None]  # (1, T, T)
                vol = np.asarray(solver.score_volume(tmpl, tile, num_rotations=4))[0]
                h, w = np.unravel_index(int(np.argmax(vol)), vol.shape)
                peaks[i, j] = vol[h, w]
                if best is None or vol[h, w] > best[0]:
                    best = (vol[h, w], i, j, vol, h, w)
                bar.update()
    _, i, j, vol, h, w = best
    n = vol.shape[0]
    dh = _parabola(vol[h - 1, w], vol[h, w], vol[h + 1, w]) if 0 < h < n - 1 else 0.0
    dw = _parabola(vol[h, w - 1], vol[h, w], vol[h, w + 1]) if 0 < w < n - 1 else 0.0
    # Refine the rotation between its neighbours (the shift is that of the best candidate).
    da = (
        _parabola(peaks[i, j - 1], peaks[i, j], peaks[i, j + 1]) if 0 < j < len(angles) - 1 else 0.0
    )
    dx, dy = geometry.cell_to_tile_offset(
        h + dh, w + dw, resolution=wgrid.resolution, bev_size=size, tile_size=size + 2 * shift_px
    )
    # Template centre at tile centre + (dx, dy): target(p) ~ warped(p + d), so shift by -d.
    return Similarity(
        shift=(-float(dx), -float(dy)),
        rotation=float(angles[j] + da * math.radians(cfg.rotation_step_deg)),
        scale=float(scales[i]),
        centre=identity.centre,
        score=float(peaks[i, j] / max(weight, 1e-9)),
    )
