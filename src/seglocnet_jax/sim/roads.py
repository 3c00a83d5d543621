"""The simulated world's roads: true widths, the world-versus-OSM centreline offset, markings.

All geometry is in the city's world frame (metres, x east, y north). A road of the world is an
OSM drivable way whose centreline is densified and displaced by a smooth random field of
magnitude 0.5-1.5 m (real OSM is traced from imagery whose registration error varies smoothly
over a city; one continuous field keeps junctions connected), then buffered to its width from
the ``lanes`` / ``width`` tags or per-class defaults. The union of the buffers is the world's
drivable area (the HD map).
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import shapely
from shapely.geometry import LineString
from shapely.ops import substring

# highway class -> (default total lanes, lane width m, default lanes when oneway)
ROAD_CLASSES: dict[str, tuple[int, float, int]] = {
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
# Classes without sidewalks or edge markings.
NO_SIDEWALK = {"motorway", "trunk", "motorway_link", "trunk_link"}
MARKED = {
    "motorway",
    "trunk",
    "primary",
    "secondary",
    "tertiary",
    "unclassified",
    "road",
    "motorway_link",
    "trunk_link",
    "primary_link",
    "secondary_link",
    "tertiary_link",
}


@dataclasses.dataclass(frozen=True)
class Road:
    """One drivable road of the world.

    Attributes:
      centerline: ``(M, 2)`` world metres, the *world's* centre (OSM centreline + offset),
        densified; traversal direction is the OSM way direction.
      width: carriageway width (m).
      lanes: total number of lanes.
      oneway: 0 both directions, 1 along the way, -1 against it.
      highway: OSM highway class.
      osm_index: index of the way in the city's road list.
      osm_centerline: ``(M, 2)`` the OSM centreline at the same vertices (before the offset).
    """

    centerline: np.ndarray
    width: float
    lanes: int
    oneway: int
    highway: str
    osm_index: int
    osm_centerline: np.ndarray

    @property
    def line(self) -> LineString:
        return LineString(self.centerline)


def tag(feature, key: str):
    """A tag of a maps feature: its ``tags`` mapping, else an attribute (``:`` -> ``_``)."""
    tags = getattr(feature, "tags", None)
    if isinstance(tags, dict) and key in tags:
        return tags[key]
    return getattr(feature, key.replace(":", "_"), None)


def parse_number(value) -> float | None:
    """First number in an OSM tag value (``"7"``, ``"7.5 m"``, ``"3;4"``); None if absent."""
    if value is None:
        return None
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value) if math.isfinite(value) else None
    m = re.search(r"\d+(?:\.\d+)?", str(value).replace(",", "."))
    return float(m.group()) if m else None


def parse_oneway(value, highway: str) -> int:
    """OSM ``oneway`` to 0 / 1 / -1; motorways are one-way unless tagged otherwise."""
    if value is None:
        return 1 if highway in ("motorway", "motorway_link") else 0
    v = str(value).strip().lower()
    if v in ("yes", "true", "1"):
        return 1
    if v in ("-1", "reverse"):
        return -1
    return 0


def road_profile(highway: str, lanes_tag, width_tag, oneway: int) -> tuple[float, int]:
    """``(width m, total lanes)`` from the tags, else the class defaults."""
    lanes_default, lane_w, oneway_lanes = ROAD_CLASSES[highway]
    lanes = parse_number(lanes_tag)
    lanes = int(lanes) if lanes and lanes >= 1 else (oneway_lanes if oneway else lanes_default)
    lanes = min(lanes, 8)
    width = parse_number(width_tag)
    if width is None or not 2.0 <= width <= 40.0:
        width = lanes * lane_w
    return float(width), lanes


class OffsetField:
    """A smooth random 2-D displacement of magnitude in ``[lo, hi]`` metres (world frame).

    Magnitude and direction each vary as a sum of two plane waves of wavelength ~``wavelength``,
    so neighbouring roads (and both sides of a junction) move together.
    """

    def __init__(self, rng: np.random.Generator, lo: float, hi: float, wavelength: float):
        self.lo, self.hi = lo, hi
        k = 2 * math.pi / (wavelength * rng.uniform(0.7, 1.4, size=4))
        ang = rng.uniform(0, 2 * math.pi, size=4)
        self.k = np.stack([k * np.cos(ang), k * np.sin(ang)], axis=-1)  # (4, 2) rad/m
        self.phase = rng.uniform(0, 2 * math.pi, size=4)
        self.theta0 = rng.uniform(0, 2 * math.pi)

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Displacements ``(..., 2)`` metres at world points ``(..., 2)``."""
        w = np.sin(xy @ self.k.T + self.phase)  # (..., 4)
        mag = self.lo + (self.hi - self.lo) * 0.5 * (1 + 0.5 * (w[..., 0] + w[..., 1]))
        theta = self.theta0 + math.pi * 0.5 * (w[..., 2] + w[..., 3])
        return np.stack([mag * np.cos(theta), mag * np.sin(theta)], axis=-1)


def densify(coords: np.ndarray, step: float) -> np.ndarray:
    """Resamples a polyline ``(M, 2)`` to vertices at most ``step`` metres apart (keeps the
    original vertices so shared junction nodes stay shared)."""
    out = [coords[:1]]
    for a, b in zip(coords[:-1], coords[1:], strict=True):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def build_roads(city_roads, field: OffsetField, step: float = 2.0) -> list[Road]:
    """The world's roads from the city's OSM roads (non-drivable classes are skipped)."""
    roads = []
    for i, feat in enumerate(city_roads):
        highway = str(tag(feat, "highway") or "")
        geom = feat.geometry
        if highway not in ROAD_CLASSES or geom is None or geom.is_empty:
            continue
        lines = list(geom.geoms) if hasattr(geom, "geoms") else [geom]
        oneway = parse_oneway(tag(feat, "oneway"), highway)
        if str(tag(feat, "junction") or "") == "roundabout" and oneway == 0:
            oneway = 1
        width, lanes = road_profile(highway, tag(feat, "lanes"), tag(feat, "width"), oneway)
        for line in lines:
            coords = np.asarray(line.coords, np.float64)[:, :2]
            if len(coords) < 2 or line.length < 1.0:
                continue
            dense = densify(coords, step)
            roads.append(Road(dense + field(dense), width, lanes, oneway, highway, i, dense))
    return roads


def drivable_area(roads: list[Road]):
    """Union of the roads' carriageways (shapely, world metres): the HD drivable area."""
    polys = shapely.buffer(
        np.array([r.line for r in roads], dtype=object),
        np.array([r.width / 2 for r in roads]),
        cap_style="flat",
    )
    ends = [shapely.points(r.centerline[[0, -1]]).tolist() for r in roads]
    # Round discs at the ends close the wedge gaps where roads meet at an angle.
    discs = shapely.buffer(
        np.array([p for e in ends for p in e]), np.repeat([r.width / 2 for r in roads], 2)
    )
    return shapely.union_all(np.concatenate([polys, discs]))


def sidewalk_area(roads: list[Road], width: float):
    """Bands of ``width`` metres beside the carriageways (before removing roads/buildings)."""
    keep = [r for r in roads if r.highway not in NO_SIDEWALK]
    if not keep:
        return shapely.Polygon()
    lines = np.array([r.line for r in keep], dtype=object)
    return shapely.union_all(shapely.buffer(lines, [r.width / 2 + width for r in keep]))


def _dashes(line: LineString, on: float, off: float, start: float) -> list[LineString]:
    out = []
    pos = start
    while pos < line.length:
        seg = substring(line, pos, min(pos + on, line.length))
        if seg.length > 0.2:
            out.append(seg)
        pos += on + off
    return out


def marking_lines(road: Road, rng: np.random.Generator) -> list[LineString]:
    """Painted lines of one road (world metres, zero width): centre, lane dividers, edges."""
    if road.highway not in MARKED or road.lanes < 2 and road.width < 5.0:
        return []
    line = road.line
    lanes, half = road.lanes, road.width / 2
    lane_w = road.width / lanes
    out: list[LineString] = []
    start = rng.uniform(0, 9.0)
    for j in range(1, lanes):
        offset = -half + j * lane_w
        centre_div = road.oneway == 0 and j == lanes // 2 and lanes % 2 == 0
        src = line if abs(offset) < 1e-6 else line.offset_curve(offset)
        if src.is_empty or src.geom_type != "LineString":
            continue
        if centre_div and lanes >= 4:
            out.append(src)  # solid centre line on wide two-way roads
        else:
            out.extend(_dashes(src, 3.0, 6.0, start))
    if road.highway in NO_SIDEWALK or road.highway in ("primary", "secondary", "trunk"):
        for side in (-1, 1):
            edge = line.offset_curve(side * (half - 0.3))
            if not edge.is_empty and edge.geom_type == "LineString":
                out.append(edge)
    return out
