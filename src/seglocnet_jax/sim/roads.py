"""The simulated world's roads: true widths, the world-versus-OSM centreline offset, markings.

All geometry is in the city's world frame (metres, x east, y north). A road of the world is an
OSM drivable way whose centreline is densified and displaced by a smooth random field of
magnitude 0.5-1.5 m (real OSM is traced from imagery whose registration error varies smoothly
over a city; one continuous field keeps junctions connected), then buffered to its width from
the ``lanes`` / ``width`` tags or per-class defaults (:func:`seglocnet_jax.maps.osm.road_profile`:
OSM tags are interpreted in ``maps`` only). The union of the buffers is the world's drivable area
(the HD map).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import shapely
from shapely.geometry import LineString
from shapely.ops import substring

from seglocnet_jax.maps import osm

# Classes without sidewalks; classes with painted lane and edge lines (all but residential
# streets, living streets and service roads).
NO_SIDEWALK = frozenset({"motorway", "trunk", "motorway_link", "trunk_link"})
MARKED = osm.DRIVABLE_HIGHWAYS - {"residential", "living_street", "service"}


@dataclasses.dataclass(frozen=True)
class Road:
    """One drivable road of the world.

    Attributes:
      centerline: ``(M, 2)`` world metres, the *world's* centre (OSM centreline + offset),
        densified; traversal direction is the OSM way direction.
      width: carriageway width (m).
      lanes: total number of lanes.
      oneway: one-way in the centreline's direction (``maps.Road`` draws one-way ways in their
        direction of travel).
      highway: OSM highway class.
      osm_index: index of the way in the city's road list.
      osm_centerline: ``(M, 2)`` the OSM centreline at the same vertices (before the offset).
    """

    centerline: np.ndarray
    width: float
    lanes: int
    oneway: bool
    highway: str
    osm_index: int
    osm_centerline: np.ndarray

    @property
    def line(self) -> LineString:
        return LineString(self.centerline)


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
    """The world's roads from the city's OSM roads (:class:`seglocnet_jax.maps.Road`: tags as
    :func:`seglocnet_jax.maps.load_city` parsed them); widths and lanes from
    :func:`seglocnet_jax.maps.osm.road_profile`."""
    roads = []
    for i, feat in enumerate(city_roads):
        geom = feat.geometry
        if feat.highway not in osm.DRIVABLE_HIGHWAYS or geom is None or geom.is_empty:
            continue
        width, lanes = osm.road_profile(feat)
        coords = np.asarray(geom.coords, np.float64)[:, :2]
        if len(coords) < 2 or geom.length < 1.0:
            continue
        dense = densify(coords, step)
        roads.append(
            Road(dense + field(dense), width, lanes, bool(feat.oneway), feat.highway, i, dense)
        )
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
        centre_div = not road.oneway and j == lanes // 2 and lanes % 2 == 0
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
