"""The simulated world of one city: a 2.5D height + class raster built from real OSM.

The world is what the sensors see; the maps are what OSM says. They differ the way real OSM
differs from the street: road centres are offset from the OSM centrelines (see :mod:`.roads`),
a few buildings are missing, extra or shifted, and parked cars, trees, poles and pedestrians
exist that no map has.

Raster layout (north-up, row 0 north, :class:`geometry.RasterGrid` at ``cfg.resolution``):
``surface`` (H, W) uint8 ground class; per cell at most one object occupying heights
``[bottom, top]`` metres above ground: ``thing`` (H, W) uint8 object class (0 none), ``top`` /
``bottom`` (H, W) float16 metres, ``colour`` (H, W) uint8 colour id (per building / car / ...).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import shapely
from tqdm.auto import tqdm

from seglocnet_jax.geometry import RasterGrid
from seglocnet_jax.maps import osm
from seglocnet_jax.maps.raster import rasterize_geometries
from seglocnet_jax.sim import distractors as dis
from seglocnet_jax.sim import roads as rd
from seglocnet_jax.sim.classes import Surface, Thing


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    """How a city's world is built (all lengths metres).

    Attributes:
      resolution: metres per cell of the world raster.
      margin: world extent beyond the city bounds (sensors see past the edge).
      offset_min, offset_max, offset_wavelength: world road centre offset from the OSM
        centreline: magnitude range and spatial wavelength of its smooth variation.
      sidewalk_width: sidewalk band beside non-motorway carriageways.
      level_height: storey height for ``building:levels``; ``default_levels`` (min, max) is the
        seeded range for untagged buildings.
      missing_buildings, extra_buildings, shifted_buildings: fractions of OSM buildings absent
        from the world, added to it (not in OSM), and moved by up to ``shift_max`` (a moved
        building never covers the road).
      passage_clearance: where an OSM building covers a road (passages, covered roads) its
        world counterpart starts this high above the road.
      cars_per_100m, trees_per_100m, poles_per_100m, pedestrians_per_100m: distractor densities
        per 100 m of road side.
    """

    resolution: float = 0.25
    margin: float = 80.0
    offset_min: float = 0.5
    offset_max: float = 1.5
    offset_wavelength: float = 250.0
    sidewalk_width: float = 3.0
    level_height: float = 3.2
    default_levels: tuple[int, int] = (2, 7)
    missing_buildings: float = 0.03
    extra_buildings: float = 0.03
    shifted_buildings: float = 0.05
    shift_max: float = 2.5
    passage_clearance: float = 4.5
    cars_per_100m: float = 3.0
    trees_per_100m: float = 2.0
    poles_per_100m: float = 2.0
    pedestrians_per_100m: float = 1.5

    def __post_init__(self):
        if not 0.05 <= self.resolution <= 1.0:
            raise ValueError(f"WorldConfig.resolution={self.resolution}: expected 0.05..1.0 m")
        if not 0 <= self.offset_min <= self.offset_max:
            raise ValueError("WorldConfig.offset_min/offset_max: expected 0 <= min <= max")


@dataclasses.dataclass
class World:
    """A city's simulated world (see the module docstring for the raster layout).

    Attributes:
      name: city key.
      grid: placement of the rasters in the world frame.
      surface, thing, top, bottom, colour: the rasters, (H, W).
      drivable: shapely (Multi)Polygon, world metres: the HD map's drivable area.
      roads: the world's drivable roads (routing and trajectories).
      buildings: world building footprints (shapely), as built (after discrepancies).
      building_heights: (Nb,) metres.
      osm_buildings_kept: indices of the OSM buildings present in the world (shifted or not).
      cfg, seed: how it was built.
      graph: the directed road graph (:func:`trajectory.graph_of` builds it on first use).
    """

    name: str
    grid: RasterGrid
    surface: np.ndarray
    thing: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    colour: np.ndarray
    drivable: object
    roads: list
    buildings: list
    building_heights: np.ndarray
    osm_buildings_kept: np.ndarray
    cfg: WorldConfig
    seed: int
    graph: object = dataclasses.field(default=None, repr=False)


def building_height(building, rng: np.random.Generator, cfg: WorldConfig) -> float:
    """Metres from the OSM tags (:func:`seglocnet_jax.maps.osm.building_height`), else a
    seeded number of ``cfg.default_levels``."""
    h = osm.building_height(building, cfg.level_height)
    if h is None:
        levels = rng.integers(cfg.default_levels[0], cfg.default_levels[1] + 1)
        h = osm.levels_height(levels, cfg.level_height)
    return h


def _world_buildings(city_buildings, drivable, rng, cfg: WorldConfig):
    """Applies the map-versus-world discrepancies; returns (polygons, heights, kept indices)."""
    polys, heights, kept = [], [], []
    for i, feat in enumerate(city_buildings):
        geom = feat.geometry
        h = building_height(feat, rng, cfg)
        u = rng.uniform()
        if geom is None or geom.is_empty or u < cfg.missing_buildings:
            continue
        if u < cfg.missing_buildings + cfg.shifted_buildings:
            d = rng.uniform(0.5, cfg.shift_max) * np.exp(1j * rng.uniform(0, 2 * np.pi))
            geom = shapely.affinity.translate(geom, d.real, d.imag).difference(drivable)
            if geom.is_empty:
                continue
        polys.append(geom)
        heights.append(h)
        kept.append(i)
    n_extra = int(round(cfg.extra_buildings * len(city_buildings)))
    if n_extra and polys:
        occupied = shapely.union_all([drivable.buffer(4.0)] + polys)
        x0, y0, x1, y1 = occupied.bounds
        added, tries = 0, 0
        while added < n_extra and tries < 50 * n_extra:
            tries += 1
            c = rng.uniform([x0, y0], [x1, y1])
            w, l_ = rng.uniform(8, 25, size=2)
            box = shapely.affinity.rotate(
                shapely.box(c[0] - w / 2, c[1] - l_ / 2, c[0] + w / 2, c[1] + l_ / 2),
                rng.uniform(0, 180),
            )
            if occupied.intersects(box):
                continue
            polys.append(box)
            heights.append(osm.levels_height(rng.integers(*cfg.default_levels), cfg.level_height))
            occupied = occupied.union(box)
            added += 1
    return polys, np.asarray(heights, np.float64), np.asarray(kept, np.int64)


def build_world_from_city(name: str, city, cfg: WorldConfig, seed: int) -> World:
    """Builds the world of ``city`` (a :class:`seglocnet_jax.maps.CityGeometry`, or an object
    with its ``roads`` (``geometry``, ``highway``, ``lanes``, ``width``, ``oneway``),
    ``buildings`` (``geometry``, ``height``, ``levels``) and ``bounds``), seeded by
    ``(seed, name)``."""
    rng = np.random.default_rng([seed, *name.encode()])
    field = rd.OffsetField(rng, cfg.offset_min, cfg.offset_max, cfg.offset_wavelength)
    steps = tqdm(total=6, desc=f"world {name}", unit="step", leave=False)
    roads = rd.build_roads(city.roads, field)
    if not roads:
        raise ValueError(
            f"city {name!r}: no drivable roads (highway in {sorted(osm.DRIVABLE_HIGHWAYS)})"
        )
    drivable = rd.drivable_area(roads)
    steps.update()
    polys, heights, kept = _world_buildings(city.buildings, drivable, rng, cfg)
    steps.update()
    grid = RasterGrid.covering(city.bounds, cfg.resolution, cfg.margin)

    sidewalk = rd.sidewalk_area(roads, cfg.sidewalk_width)
    marks = [ln for r in roads for ln in rd.marking_lines(r, rng)]
    surface = np.full((grid.height, grid.width), Surface.OTHER, np.uint8)
    surface[rasterize_geometries(sidewalk, grid) > 0] = Surface.SIDEWALK
    surface[rasterize_geometries(drivable, grid) > 0] = Surface.ROAD
    if marks:  # paint stays on the carriageway
        paint = shapely.buffer(np.array(marks, dtype=object), 0.08, cap_style="flat")
        painted = rasterize_geometries(paint, grid, all_touched=True) > 0
        surface[painted & (surface == Surface.ROAD)] = Surface.MARKING
    steps.update()

    objs = dis.place(roads, drivable, polys, rng, cfg)
    steps.update()
    # One id raster: buildings 1..Nb, distractor parts after them.
    n_b = len(polys)
    shapes = [*polys, *objs.geoms]
    ids = rasterize_geometries(shapes, grid, values=range(1, len(shapes) + 1), dtype=np.int32)
    steps.update()
    palette_ids = rng.integers(0, 256, size=n_b)
    lut_thing = np.concatenate([[0], np.full(n_b, Thing.BUILDING), objs.thing]).astype(np.uint8)
    lut_top = np.concatenate([[0.0], heights, objs.top]).astype(np.float16)
    lut_bottom = np.concatenate([[0.0], np.zeros(n_b), objs.bottom]).astype(np.float16)
    lut_colour = np.concatenate([[0], palette_ids, objs.colour]).astype(np.uint8)
    thing, top, bottom = lut_thing[ids], lut_top[ids], lut_bottom[ids]
    # OSM roads through buildings (passages, covered roads): the building floats above the
    # road at ``passage_clearance`` (or is cut away where it is too low for that).
    over = (thing == Thing.BUILDING) & ((surface == Surface.ROAD) | (surface == Surface.MARKING))
    low = over & (top < cfg.passage_clearance + 2.0)
    thing[low], top[low] = Thing.NONE, 0
    bottom[over & ~low] = cfg.passage_clearance
    world = World(
        name=name,
        grid=grid,
        surface=surface,
        thing=thing,
        top=top,
        bottom=bottom,
        colour=lut_colour[ids],
        drivable=drivable,
        roads=roads,
        buildings=polys,
        building_heights=heights,
        osm_buildings_kept=kept,
        cfg=cfg,
        seed=seed,
    )
    steps.update()
    steps.close()
    return world


def build_world(city, cfg: WorldConfig | None = None, seed: int = 0) -> World:
    """The world of a city: ``city`` is a city key / OSM path for
    :func:`seglocnet_jax.maps.load_city`, or an already loaded city geometry."""
    cfg = cfg or WorldConfig()
    if isinstance(city, str):
        from seglocnet_jax.maps import load_city

        return build_world_from_city(city, load_city(city), cfg, seed)
    return build_world_from_city(str(getattr(city, "name", "city")), city, cfg, seed)
