"""The unified binary map: a city's roads and buildings as a ``(C, H, W)`` uint8 mask.

HD and SD maps share this representation (DESIGN): the road channel is the HD drivable area
(supplied by the caller: the simulator's world or a dataset's HD map) or the OSM centrelines
buffered to a fixed width (SD); the building channel is OSM building footprints. The neural map's
input, the multi-class OSM raster (:func:`rasterize_osm_classes`, channels
:data:`.osm_classes.OSM_CLASSES`), is a :class:`CityRaster` too. The one seam to rasterio. Tiles
and GT BEV labels are cut from the cached raster (slice / nearest neighbour).
"""

from __future__ import annotations

import dataclasses
import numbers
import os
import zipfile
import zlib

import numpy as np
import rasterio.features
import shapely
from rasterio.transform import Affine

from seglocnet_jax import fileio
from seglocnet_jax import geometry as g
from seglocnet_jax.maps.osm import CityGeometry, MapError
from seglocnet_jax.maps.osm_classes import OSM_CLASS_NAMES, OSM_CLASSES, line_class

CHANNELS = ("road", "building")
KINDS = ("hd", "sd")


class MapConfigError(ValueError):
    """A map config value is invalid; the message names the config key and the bad value."""


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """One map variant: how a city becomes a binary map (the ``map`` config section's raster
    keys). The one map-variant config of the project: the rasterizer, the prepared datasets'
    ``maps/<name>/`` directories and the manifest's ``map_variants`` all use it.

    Rasters are always at :data:`seglocnet_jax.geometry.RESOLUTION` (0.5 m/px, DESIGN): the BEV,
    the tiles, the simulator and the solver's decoding all assume it.

    Attributes:
      kind: ``"hd"`` (caller's drivable area + OSM buildings) or ``"sd"`` (OSM centrelines
        buffered to ``road_width`` + OSM buildings).
      road_width: SD road width in metres (paper: 10; ablation 2.5 / 5 / 10); HD maps ignore it
        (it is kept so that a sweep can set it for either kind).
      channels: raster channels, in order; each one of :data:`CHANNELS`, no repeats.
    """

    kind: str = "hd"
    road_width: float = 10.0
    channels: tuple[str, ...] = CHANNELS

    def __post_init__(self):
        if self.kind not in KINDS:
            raise MapConfigError(f"map.kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        allowed = ", ".join(CHANNELS)
        channels = self.channels
        if isinstance(channels, str):
            channels = (channels,)
        try:
            channels = tuple(channels)
        except TypeError:
            raise MapConfigError(
                f"map.channels must be a list of channel names ({allowed}), got {self.channels!r}"
            ) from None
        object.__setattr__(self, "channels", channels)
        if not channels:
            raise MapConfigError(f"map.channels must name at least one channel of: {allowed}")
        for c in channels:
            if c not in CHANNELS:
                raise MapConfigError(f"map.channels has unknown channel {c!r}; allowed: {allowed}")
        if len(set(channels)) != len(channels):
            raise MapConfigError(
                f"map.channels repeats a channel: {list(channels)!r}; each of {allowed} "
                "at most once"
            )
        value = self.road_width
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0:
            raise MapConfigError(f"map.road_width must be a number > 0 metres, got {value!r}")
        object.__setattr__(self, "road_width", float(value))

    @property
    def name(self) -> str:
        """Directory name of the variant, e.g. ``hd_road-building`` or ``sd_w5_road-building``
        (HD names carry no width: HD maps do not depend on it)."""
        width = f"_w{self.road_width:g}" if self.kind == "sd" else ""
        return f"{self.kind}{width}_{'-'.join(self.channels)}"

    def to_dict(self) -> dict:
        """Plain JSON-able form (``channels`` a list), as the manifest records it."""
        return {"kind": self.kind, "road_width": self.road_width, "channels": list(self.channels)}

    def same_map(self, other: MapConfig) -> bool:
        """Whether ``other`` draws the same raster (equal, or both HD and differing only in
        the ``road_width`` that HD ignores)."""
        if self.kind == other.kind == "hd":
            return self.channels == other.channels
        return self == other


def rasterize_geometries(
    geoms, grid: g.RasterGrid, values=None, *, dtype=np.uint8, all_touched: bool = False
) -> np.ndarray:
    """Burns shapely geometries into a zero ``(H, W)`` raster of ``dtype`` on ``grid``.

    Args:
      geoms: a shapely geometry or an iterable of them; ``None`` / empty ones are skipped.
      grid: the raster's placement.
      values: one value per geometry (an iterable as long as ``geoms``, paired before skipping);
        default 1 for all, i.e. a {0, 1} mask. Later geometries win where they overlap.
      dtype: output dtype.
      all_touched: burn every pixel a geometry touches (thin lines); default: a pixel is burnt
        when its centre lies inside (GDAL rule).
    """
    if isinstance(geoms, shapely.Geometry):
        geoms = [geoms]
    geoms = list(geoms)
    values = [1] * len(geoms) if values is None else list(values)
    if len(values) != len(geoms):
        raise ValueError(f"rasterize_geometries: {len(geoms)} geometries but {len(values)} values")
    shapes = [
        (x, v) for x, v in zip(geoms, values, strict=True) if x is not None and not x.is_empty
    ]
    if not shapes:
        return np.zeros((grid.height, grid.width), dtype)
    return rasterio.features.rasterize(
        shapes,
        out_shape=(grid.height, grid.width),
        transform=Affine(*grid.affine()),
        fill=0,
        dtype=dtype,
        all_touched=all_touched,
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
        return g.crop(self.mask, row0, col0, size), (float(cx), float(cy))

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
        """Writes a compressed ``.npz`` atomically (:func:`seglocnet_jax.fileio.atomic_path`);
        creates the parent directory."""
        gr = self.grid
        with fileio.atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(
                f,
                mask=self.mask,
                channels=np.array(self.channels),
                name=np.array(self.name),
                grid=np.array([gr.x_min, gr.y_max, gr.height, gr.width, gr.resolution]),
            )
            f.flush()
            os.fsync(f.fileno())

    @classmethod
    def load(cls, path: str | os.PathLike) -> CityRaster:
        """Reads a raster written by :meth:`save`; a missing, truncated or malformed file raises
        :class:`MapError` naming it."""
        path = os.fspath(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                mask, grid = z["mask"], z["grid"]
                channels = tuple(str(c) for c in z["channels"])
                name = str(z["name"])
        except FileNotFoundError as err:
            raise MapError(f"{path}: city raster file does not exist") from err
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            raise MapError(
                f"{path}: corrupt or not a city raster written by CityRaster.save "
                f"({type(err).__name__}: {err})"
            ) from err
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
      cfg: map kind, SD road width, channels.
      drivable: HD only: the drivable area, a shapely geometry or a list of them (world metres).

    The grid (at :data:`geometry.RESOLUTION`) covers everything drawn, corners on multiples of
    the resolution (so tiles of different variants of a city line up pixel for pixel where they
    overlap).
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
    grid = g.RasterGrid.covering(tuple(bounds), resolution=g.RESOLUTION)
    layers = {"road": road_geoms, "building": building_geoms}
    mask = np.stack([rasterize_geometries(layers[c], grid) for c in cfg.channels])
    return CityRaster(mask, grid, tuple(cfg.channels), city.name)


def rasterize_osm_classes(city: CityGeometry) -> CityRaster:
    """The multi-class OSM raster of ``city``: channels :data:`.osm_classes.OSM_CLASS_NAMES`,
    ``(9, H, W)`` uint8 {0, 1}, from OSM alone (roads and other ways: centrelines buffered to
    their class's width; buildings and areas: filled).

    The grid covers the city's bounds and its roads and buildings (not the areas, which are
    clipped to it: a forest polygon may reach far beyond the streets), corners on multiples of
    the resolution like :func:`rasterize`'s, so that a tile around the same prior is centred on
    the same point in both.
    """
    layers: dict[str, list] = {name: [] for name in OSM_CLASS_NAMES}
    width = {c.name: c.width for c in OSM_CLASSES}
    for road in city.roads:
        layers[line_class(road.highway).name].append(road.geometry)
    for way in city.ways:
        layers[line_class(way.highway).name].append(way.geometry)
    for name in layers:
        if width[name] is not None and layers[name]:
            lines = np.array(layers[name], dtype=object)
            layers[name] = list(
                shapely.buffer(lines, width[name] / 2, quad_segs=4, cap_style="round")
            )
    layers["building"] = [b.geometry for b in city.buildings]
    for area in city.areas:
        layers[area.kind].append(area.geometry)
    drawn = [r.geometry for r in city.roads] + layers["building"]
    bounds = np.array(city.bounds)
    if drawn:
        b = shapely.total_bounds(drawn)
        bounds = np.concatenate([np.minimum(bounds[:2], b[:2]), np.maximum(bounds[2:], b[2:])])
    grid = g.RasterGrid.covering(tuple(bounds), resolution=g.RESOLUTION)
    mask = np.stack([rasterize_geometries(layers[name], grid) for name in OSM_CLASS_NAMES])
    return CityRaster(mask, grid, OSM_CLASS_NAMES, city.name)
