"""Frames, poses and raster indexing: the only owner of the project's conventions.

Every other module asks this one how metres map to pixels and how solver cells map to poses.
The conventions (pinned by ``tests/test_geometry.py``):

* World frame: local metric east-north-up per city, metres. ``x`` east, ``y`` north.
* Pose: ``(x, y, yaw)``; yaw is the vehicle's forward axis counterclockwise from east, radians,
  wrapped to ``(-pi, pi]``.
* Ego frame: ``x`` forward, ``y`` left, ``z`` up (ISO 8855, nuScenes/Argoverse), metres.
* Surround cameras: a six-camera rig (the simulator's, nuScenes') stores its images in
  ``CAMERA_NAMES`` order, nuScenes' channels clockwise from the front.
* Rasters: ``(C, H, W)`` at ``RESOLUTION`` m/px, row 0 at the north edge, column 0 at the west
  edge. Continuous pixel coordinates ``(row, col)`` put integer values on pixel *corners*; the
  centre of pixel ``[r, c]`` is ``(r + 0.5, c + 0.5)``.
* BEV: ``BEV_SIZE`` square in the ego frame, forward = up (row 0 is the far front), the vehicle's
  right = increasing column; the ego sits on the corner shared by the four central pixels.
* Map tile: ``TILE_SIZE`` square whose central pixel corner is the prior snapped to the grid.
* Solver: rotation ``k`` turns the BEV image counterclockwise (as displayed north-up) by
  ``2 pi k / K`` about the ego point, so it shows the scene of a vehicle with
  ``yaw = pi/2 + 2 pi k / K`` (k = 0: the BEV as it is, i.e. heading north). Score cell
  ``(h, w)`` puts the BEV's top-left pixel on tile pixel ``(h, w)``; the ego point then lies at
  tile corner ``(h + BEV_SIZE/2, w + BEV_SIZE/2)``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

RESOLUTION = 0.5  # metres per pixel, BEV and maps
BEV_SIZE = 128  # pixels, 64 m
TILE_SIZE = 256  # pixels, 128 m
SCORE_SIZE = TILE_SIZE - BEV_SIZE + 1  # 129 valid correlation offsets per axis
PRIOR_RANGE = 32.0  # metres: prior = GT + U[-PRIOR_RANGE, PRIOR_RANGE] per axis
NUM_ROTATIONS = 256  # paper's K
# The six surround cameras in record order: nuScenes' channel names, clockwise from the front.
CAMERA_NAMES = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_FRONT_LEFT",
)


# Functions that take arrays dispatch on their type (one function, no NumPy/JAX twins): JAX
# arrays (and tracers, so they jit) stay in jax.numpy and its dtypes; everything else is NumPy
# in float64.


def _xp(*arrays):
    """``jax.numpy`` if any of ``arrays`` is a JAX array or tracer, else ``numpy``."""
    for a in arrays:
        if type(a).__module__.startswith("jax"):
            import jax.numpy as jnp

            return jnp
    return np


def _float(a, xp):
    """``a`` as a float array: float64 NumPy, or JAX's default float (float32 without x64)."""
    if xp is np:
        return np.asarray(a, np.float64)
    a = xp.asarray(a)
    return a if xp.issubdtype(a.dtype, xp.floating) else a.astype(float)


def wrap_angle(a):
    """Wraps radians to ``(-pi, pi]`` (NumPy or JAX arrays, or floats)."""
    xp = _xp(a)
    w = xp.mod(a + math.pi, 2 * math.pi) - math.pi  # [-pi, pi)
    return xp.where(w == -math.pi, math.pi, w)


def angle_error(a, b):
    """Absolute wrapped difference of two angles, radians in ``[0, pi]``."""
    return _xp(a, b).abs(wrap_angle(a - b))


def sample_priors(xy, rng: np.random.Generator, prior_range: float = PRIOR_RANGE) -> np.ndarray:
    """Coarse position priors: ``xy + U[-prior_range, prior_range]`` per axis, metres, of the
    shape of ``xy`` (``(2,)`` or ``(N, 2)``); draws ``xy.size`` uniforms from ``rng``."""
    xy = np.asarray(xy, np.float64)
    return xy + rng.uniform(-prior_range, prior_range, size=xy.shape)


# --------------------------------------------------------------------------- raster grids


@dataclasses.dataclass(frozen=True)
class RasterGrid:
    """A north-up raster's placement in the world frame.

    Attributes:
      x_min: world x (m) of the west edge (left edge of column 0).
      y_max: world y (m) of the north edge (top edge of row 0).
      height, width: raster size in pixels.
      resolution: metres per pixel.
    """

    x_min: float
    y_max: float
    height: int
    width: int
    resolution: float = RESOLUTION

    @classmethod
    def covering(cls, bounds, resolution: float = RESOLUTION, margin: float = 0.0) -> RasterGrid:
        """The smallest grid with corners on multiples of ``resolution`` covering
        ``bounds = (x_min, y_min, x_max, y_max)`` grown by ``margin`` metres."""
        x0, y0, x1, y1 = bounds
        x0 = math.floor((x0 - margin) / resolution) * resolution
        y0 = math.floor((y0 - margin) / resolution) * resolution
        x1 = math.ceil((x1 + margin) / resolution) * resolution
        y1 = math.ceil((y1 + margin) / resolution) * resolution
        width = int(round((x1 - x0) / resolution))
        height = int(round((y1 - y0) / resolution))
        return cls(x_min=x0, y_max=y1, height=height, width=width, resolution=resolution)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` in metres."""
        return (
            self.x_min,
            self.y_max - self.height * self.resolution,
            self.x_min + self.width * self.resolution,
            self.y_max,
        )

    def world_to_pixel(self, x, y):
        """World metres to continuous ``(row, col)``; integers are pixel corners."""
        col = (np.asarray(x) - self.x_min) / self.resolution
        row = (self.y_max - np.asarray(y)) / self.resolution
        return row, col

    def pixel_to_world(self, row, col):
        """Continuous ``(row, col)`` to world ``(x, y)`` metres."""
        x = self.x_min + np.asarray(col) * self.resolution
        y = self.y_max - np.asarray(row) * self.resolution
        return x, y

    def snap_to_corner(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """The pixel corner nearest to world ``(x, y)``: ``(row, col)`` integers."""
        row, col = self.world_to_pixel(x, y)
        return np.round(row).astype(np.int64), np.round(col).astype(np.int64)

    def affine(self):
        """The rasterio/GDAL-style affine ``(a, b, c, d, e, f)``: x = a*col + b*row + c, etc."""
        r = self.resolution
        return (r, 0.0, self.x_min, 0.0, -r, self.y_max)


def tile_window(grid: RasterGrid, x, y, size: int = TILE_SIZE):
    """Where the tile centred on world ``(x, y)`` lies in ``grid``.

    The centre is snapped to the nearest pixel corner. Returns ``(row0, col0, cx, cy)``: the
    tile's top-left pixel in the grid (may be out of range: outside is zero) and the snapped
    centre in world metres.
    """
    row_c, col_c = grid.snap_to_corner(x, y)
    cx, cy = grid.pixel_to_world(row_c, col_c)
    return row_c - size // 2, col_c - size // 2, cx, cy


def crop(array: np.ndarray, row0: int, col0: int, size: int) -> np.ndarray:
    """The ``size x size`` window of ``array (..., H, W)`` whose top-left pixel is ``(row0,
    col0)`` (a copy, ``(..., size, size)``); zero where the window leaves the array."""
    row0, col0 = int(row0), int(col0)
    h, w = array.shape[-2:]
    r0, r1 = max(row0, 0), min(row0 + size, h)
    c0, c1 = max(col0, 0), min(col0 + size, w)
    if (r0, c0, r1, c1) == (row0, col0, row0 + size, col0 + size):
        return array[..., r0:r1, c0:c1].copy()
    out = np.zeros((*array.shape[:-2], size, size), array.dtype)
    if r1 > r0 and c1 > c0:
        out[..., r0 - row0 : r1 - row0, c0 - col0 : c1 - col0] = array[..., r0:r1, c0:c1]
    return out


# --------------------------------------------------------------------------- poses and frames


def ego_to_world(pose, points):
    """Ego-frame points ``(..., 2)`` (forward, left) of ``pose`` to world ``(..., 2)`` (NumPy
    or JAX)."""
    xp = _xp(pose, points)
    pose, points = _float(pose, xp), _float(points, xp)
    c, s = xp.cos(pose[2]), xp.sin(pose[2])
    f, l = points[..., 0], points[..., 1]
    return xp.stack([pose[0] + c * f - s * l, pose[1] + s * f + c * l], axis=-1)


def world_to_ego(pose, points):
    """World points ``(..., 2)`` to the ego frame ``(..., 2)`` (forward, left) of ``pose``
    (NumPy or JAX)."""
    xp = _xp(pose, points)
    pose, points = _float(pose, xp), _float(points, xp)
    c, s = xp.cos(pose[2]), xp.sin(pose[2])
    dx, dy = points[..., 0] - pose[0], points[..., 1] - pose[1]
    return xp.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def pose_from_matrix(world_from_ego) -> np.ndarray:
    """``(x, y, yaw)`` of a ``(4, 4)`` (or ``(3, 3)`` 2-D) world-from-ego transform.

    The yaw is the ego forward axis (first column of the rotation) projected on the ground plane,
    counterclockwise from east, wrapped; roll and pitch are dropped.
    """
    t = np.asarray(world_from_ego, np.float64)
    n = t.shape[0] - 1  # 3 for SE(3), 2 for SE(2)
    return np.array([t[0, n], t[1, n], float(wrap_angle(math.atan2(t[1, 0], t[0, 0])))])


def bev_cell_centers_ego(size: int = BEV_SIZE, resolution: float = RESOLUTION) -> np.ndarray:
    """Ego-frame ``(forward, left)`` metres of each BEV pixel centre, shape ``(size, size, 2)``."""
    idx = (size / 2 - np.arange(size) - 0.5) * resolution  # row i -> forward, col j -> left
    fwd = np.broadcast_to(idx[:, None], (size, size))
    left = np.broadcast_to(idx[None, :], (size, size))
    return np.stack([fwd, left], axis=-1)


def ego_to_bev_pixel(points, size: int = BEV_SIZE, resolution: float = RESOLUTION):
    """Ego ``(..., 2)`` (forward, left) metres to continuous BEV ``(row, col)`` (NumPy or JAX)."""
    xp = _xp(points)
    points = xp.asarray(points)
    row = size / 2 - points[..., 0] / resolution
    col = size / 2 - points[..., 1] / resolution
    return row, col


# --------------------------------------------------------------------------- solver cells


def rotation_angle(k, num_rotations: int):
    """Counterclockwise turn (radians) that solver rotation ``k`` applies to the BEV image."""
    xp = _xp(k)
    return 2 * math.pi * _float(k, xp) / num_rotations


def yaw_from_rotation(k, num_rotations: int):
    """The vehicle yaw (radians, wrapped) that solver rotation index ``k`` (may be fractional)
    stands for."""
    return wrap_angle(math.pi / 2 + rotation_angle(k, num_rotations))


def rotation_from_yaw(yaw, num_rotations: int):
    """Continuous rotation index in ``[0, K)`` for a vehicle yaw; round it for the GT bin."""
    xp = _xp(yaw)
    k = (_float(yaw, xp) - math.pi / 2) / (2 * math.pi) * num_rotations
    return xp.mod(k, num_rotations)


def cell_to_tile_offset(
    h, w, resolution: float = RESOLUTION, bev_size: int = BEV_SIZE, tile_size: int = TILE_SIZE
):
    """Score cell ``(h, w)`` (may be fractional) to the ego position relative to the tile
    centre, ``(dx east, dy north)`` metres."""
    xp = _xp(h, w)
    centre = (tile_size - bev_size) / 2  # the cell whose ego point is the tile centre (64)
    dx = (_float(w, xp) - centre) * resolution
    dy = -(_float(h, xp) - centre) * resolution
    return dx, dy


def tile_offset_to_cell(
    dx, dy, resolution: float = RESOLUTION, bev_size: int = BEV_SIZE, tile_size: int = TILE_SIZE
):
    """Inverse of :func:`cell_to_tile_offset`: continuous ``(h, w)``."""
    xp = _xp(dx, dy)
    centre = (tile_size - bev_size) / 2
    w = _float(dx, xp) / resolution + centre
    h = -_float(dy, xp) / resolution + centre
    return h, w


def cell_to_pose(cell, num_rotations: int, size: int = SCORE_SIZE, bev_size: int = BEV_SIZE):
    """``(..., 3)`` score cells ``(k, h, w)`` (may be fractional) of a ``(K, size, size)``
    volume to tile-frame poses ``(dx, dy, yaw)`` (m, m, rad); NumPy or JAX (jit-friendly)."""
    xp = _xp(cell)
    cell = _float(cell, xp)
    tile_size = size - 1 + bev_size
    dx, dy = cell_to_tile_offset(cell[..., 1], cell[..., 2], bev_size=bev_size, tile_size=tile_size)
    yaw = yaw_from_rotation(cell[..., 0], num_rotations)
    return xp.stack([dx, dy, yaw], axis=-1)


def pose_to_cell(pose_tile, num_rotations: int, size: int = SCORE_SIZE, bev_size: int = BEV_SIZE):
    """Inverse of :func:`cell_to_pose`: continuous ``(..., 3)`` cells ``(k in [0, K), h, w)``;
    round for the GT cell."""
    xp = _xp(pose_tile)
    pose_tile = _float(pose_tile, xp)
    tile_size = size - 1 + bev_size
    h, w = tile_offset_to_cell(
        pose_tile[..., 0], pose_tile[..., 1], bev_size=bev_size, tile_size=tile_size
    )
    k = rotation_from_yaw(pose_tile[..., 2], num_rotations)
    return xp.stack([k, h, w], axis=-1)
