"""The unified binary map: a city's roads and buildings as a ``(C, H, W)`` uint8 mask.

HD and SD maps share this representation (DESIGN): the road channel is the HD drivable area
(supplied by the caller: the simulator's world or a dataset's HD map) or the OSM centrelines
buffered to a fixed width (SD); the building channel is OSM building footprints. The one seam to
rasterio. Tiles and GT BEV labels are cut from the cached raster (slice / nearest neighbour).
"""

from __future__ import annotations

import dataclasses
import numbers
import os

import numpy as np
import rasterio.features
import shapely
from rasterio.transform import Affine

from seglocnet_jax import geometry as g
from seglocnet_jax.maps.osm import CityGeometry, MapError

CHANNELS = ("road", "building")
KINDS = ("hd", "sd")


class MapConfigError(ValueError):
    """A map config value is invalid; the message names the config key and the bad value."""


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """How a city becomes a binary map.

    Attributes:
      kind: ``"hd"`` (caller's drivable area + OSM buildings) or ``"sd"`` (OSM centrelines
        buffered to ``road_width`` + OSM buildings).
      road_width: SD road width in metres (paper: 10; ablation 2.5 / 5 / 10).
      channels: raster channels, in order; each ``"road"`` or ``"building"``.
      resolution: metres per pixel.
    """

    kind: str = "hd"
    road_width: float = 10.0
    channels: tuple[str, ...] = CHANNELS
    resolution: float = g.RESOLUTION

    def __post_init__(self):
        if self.kind not in KINDS:
            raise MapConfigError(f"map.kind must be one of {KINDS}, got {self.kind!r}")
        channels = tuple(self.channels) if not isinstance(self.channels, str) else (self.channels,)
        object.__setattr__(self, "channels", channels)
        if not channels:
            raise MapConfigError("map.channels must name at least one of ('road', 'building')")
        for c in channels:
            if c not in CHANNELS:
                raise MapConfigError(f"map.channels has unknown channel {c!r}; known: {CHANNELS}")
        if len(set(channels)) != len(channels):
            raise MapConfigError(f"map.channels repeats a channel: {channels!r}")
        for key, unit in (("road_width", "metres"), ("resolution", "m/px")):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0:
                raise MapConfigError(f"map.{key} must be a number > 0 {unit}, got {value!r}")
            object.__setattr__(self, key, float(value))


def rasterize_geometries(geoms, grid: g.RasterGrid) -> np.ndarray:
    """Burns shapely geometries (or a list of them) into a ``(H, W)`` uint8 {0, 1} mask on
    ``grid``. A pixel is 1 when its centre lies inside a polygon (GDAL rule)."""
    if isinstance(geoms, shapely.Geometry):
        geoms = [geoms]
    geoms = [x for x in geoms if x is not None and not x.is_empty]
    if not geoms:
        return np.zeros((grid.height, grid.width), np.uint8)
    return rasterio.features.rasterize(
        ((x, 1) for x in geoms),
        out_shape=(grid.height, grid.width),
        transform=Affine(*grid.affine()),
        fill=0,
        dtype=np.uint8,
        all_touched=False,
    )


def buffer_roads(city: CityGeometry, road_width: float) -> np.ndarray:
    """SD road polygons: each centreline buffered by ``road_width / 2`` metres on both sides.

    Round caps and joins: OSM splits a street into ways at junctions and attribute changes, so
    consecutive ways meet end to end at an angle; round caps close the wedge that flat caps leave
    there, and the w/2 overshoot at a dead end is within what the road surface itself occupies.
    """
    lines = np.array([r.geometry for r in city.roads], dtype=object)
    return shapely.buffer(lines, road_width / 2, quad_segs=4, cap_style="round", join_style="round")


@dataclasses.dataclass
class CityRaster:
    """A city's binary map, cached once and cut into tiles and BEV labels.

    Attributes:
      mask: ``(C, H, W)`` uint8 {0, 1}, row 0 at the north edge.
      grid: the raster's placement in the world frame.
      channels: channel names in mask order.
      name: city key.
    """

    mask: np.ndarray
    grid: g.RasterGrid
    channels: tuple[str, ...]
    name: str

    def __post_init__(self):
        if self.mask.ndim != 3 or self.mask.shape[1:] != (self.grid.height, self.grid.width):
            raise MapError(
                f"raster {self.name!r}: mask shape {self.mask.shape} does not match "
                f"(C, {self.grid.height}, {self.grid.width})"
            )
        if self.mask.shape[0] != len(self.channels):
            raise MapError(
                f"raster {self.name!r}: {self.mask.shape[0]} mask channels but "
                f"channels={self.channels!r}"
            )

    def tile(self, x: float, y: float, size: int = g.TILE_SIZE):
        """The ``(C, size, size)`` uint8 tile centred on world ``(x, y)`` snapped to the nearest
        pixel corner, zero outside the raster; returns ``(tile, (cx, cy))`` with the snapped
        centre in world metres."""
        row0, col0, cx, cy = g.tile_window(self.grid, x, y, size)
        row0, col0 = int(row0), int(col0)
        c, h, w = self.mask.shape
        r0, r1 = max(row0, 0), min(row0 + size, h)
        c0, c1 = max(col0, 0), min(col0 + size, w)
        if r0 == row0 and c0 == col0 and r1 - r0 == size and c1 - c0 == size:
            return self.mask[:, r0:r1, c0:c1].copy(), (float(cx), float(cy))
        out = np.zeros((c, size, size), self.mask.dtype)
        if r1 > r0 and c1 > c0:
            out[:, r0 - row0 : r1 - row0, c0 - col0 : c1 - col0] = self.mask[:, r0:r1, c0:c1]
        return out, (float(cx), float(cy))

    def cut_bev(self, pose, size: int = g.BEV_SIZE) -> np.ndarray:
        """GT BEV label ``(C, size, size)`` uint8 at world ``pose = (x, y, yaw)``: the map pixel
        under each BEV pixel centre (nearest neighbour), zero outside the raster."""
        return self.cut_bevs(np.asarray(pose, np.float64)[None], size)[0]

    def cut_bevs(self, poses, size: int = g.BEV_SIZE) -> np.ndarray:
        """Batched :meth:`cut_bev`: ``poses (N, 3)`` -> ``(N, C, size, size)`` uint8."""
        poses = np.asarray(poses, np.float64)
        if poses.ndim != 2 or poses.shape[1] != 3:
            raise ValueError(f"poses must have shape (N, 3), got {poses.shape}")
        centres = g.bev_cell_centers_ego(size, self.grid.resolution)  # (S, S, 2)
        # ego_to_world broadcasts over a pose array of shape (3, N, 1, 1).
        world = g.ego_to_world(poses.T[:, :, None, None], centres)  # (N, S, S, 2)
        row, col = self.grid.world_to_pixel(world[..., 0], world[..., 1])
        row = np.floor(row).astype(np.int64)  # the pixel containing the centre
        col = np.floor(col).astype(np.int64)
        _, h, w = self.mask.shape
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)  # (N, S, S)
        flat = np.where(inside, row * w + col, 0)
        out = self.mask.reshape(self.mask.shape[0], -1)[:, flat]  # (C, N, S, S)
        out = out * inside[None].astype(self.mask.dtype)
        return np.ascontiguousarray(out.transpose(1, 0, 2, 3))

    def save(self, path: str | os.PathLike) -> None:
        """Writes a compressed ``.npz`` atomically (temporary name, then ``os.replace``)."""
        path = os.fspath(path)
        tmp = f"{path}.tmp-{os.getpid()}"
        gr = self.grid
        try:
            with open(tmp, "wb") as f:
                np.savez_compressed(
                    f,
                    mask=self.mask,
                    channels=np.array(self.channels),
                    name=np.array(self.name),
                    grid=np.array([gr.x_min, gr.y_max, gr.height, gr.width, gr.resolution]),
                )
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)

    @classmethod
    def load(cls, path: str | os.PathLike) -> CityRaster:
        """Reads a raster written by :meth:`save`; a missing or malformed file raises
        :class:`MapError` naming it."""
        path = os.fspath(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                mask, grid = z["mask"], z["grid"]
                channels = tuple(str(c) for c in z["channels"])
                name = str(z["name"])
        except (OSError, KeyError, ValueError) as err:
            raise MapError(f"{path}: not a city raster written by CityRaster.save ({err})") from err
        if mask.dtype != np.uint8 or grid.shape != (5,):
            raise MapError(
                f"{path}: mask dtype {mask.dtype} / grid {grid.shape}: expected uint8 "
                "and 5 grid values"
            )
        grid = g.RasterGrid(
            x_min=float(grid[0]),
            y_max=float(grid[1]),
            height=int(grid[2]),
            width=int(grid[3]),
            resolution=float(grid[4]),
        )
        return cls(mask, grid, channels, name)


def rasterize(city: CityGeometry, cfg: MapConfig, drivable=None) -> CityRaster:
    """The city's binary map of ``cfg``'s kind and channels.

    Args:
      city: OSM content in world metres (:func:`osm.load_city`).
      cfg: map kind, SD road width, channels, resolution.
      drivable: HD only: the drivable area, a shapely geometry or a list of them (world metres).

    The grid covers everything drawn, corners on multiples of the resolution (so tiles of
    different variants of a city line up pixel for pixel where they overlap).
    """
    road_geoms = None
    if "road" in cfg.channels:
        if cfg.kind == "sd":
            road_geoms = list(buffer_roads(city, cfg.road_width))
        else:
            if drivable is None:
                raise MapError(
                    f"HD map of {city.name!r} needs the drivable area (drivable=...: "
                    "the simulator's world or the dataset's HD map); use kind='sd' "
                    "for OSM roads"
                )
            road_geoms = [drivable] if isinstance(drivable, shapely.Geometry) else list(drivable)
            if not all(isinstance(x, shapely.Geometry) for x in road_geoms):
                raise MapError(f"HD drivable area of {city.name!r} must be shapely geometries")
    building_geoms = [b.geometry for b in city.buildings] if "building" in cfg.channels else None
    drawn = [x for x in (road_geoms or []) + (building_geoms or []) if not x.is_empty]
    bounds = np.array(city.bounds)
    if drawn:
        b = shapely.total_bounds(drawn)
        bounds = np.concatenate([np.minimum(bounds[:2], b[:2]), np.maximum(bounds[2:], b[2:])])
    grid = g.RasterGrid.covering(tuple(bounds), resolution=cfg.resolution)
    layers = {"road": road_geoms, "building": building_geoms}
    mask = np.stack([rasterize_geometries(layers[c], grid) for c in cfg.channels])
    return CityRaster(mask, grid, tuple(cfg.channels), city.name)
