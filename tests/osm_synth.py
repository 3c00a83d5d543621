"""Small real-OSM inputs for the data-pipeline tests: a street-grid town written as an OSM XML
file, and a frame source over any city (embedded or a file) whose ``drivable`` area is the city's
real OSM roads buffered to a width, so map variants are rasterized for real."""

from __future__ import annotations

import numpy as np
import shapely

from data_synth import Factory, GridSource
from fixtures_real import OsmXml
from seglocnet_jax import maps

HD_HALF_WIDTH = 3.0  # m: the fake world's carriageway (6 m) is narrower than SD's 10 m buffer


def write_grid_osm(
    path, size: float = 1200.0, spacing: float = 100.0, lat0: float = 60.2, lon0: float = 24.9
) -> str:
    """An OSM XML town of ``size`` metres: residential streets every ``spacing`` metres (each
    street one way through all its crossings) and a 40 m square building in every block."""
    proj = maps.Projection.tmerc(lat0, lon0)
    osm = OsmXml("test")

    def add_nodes(points) -> list[int]:
        xy = np.asarray(points, np.float64) - size / 2
        return osm.nodes(*proj.to_lonlat(xy[:, 0], xy[:, 1]))

    ticks = np.arange(0.0, size + 1e-6, spacing)
    for t in ticks:
        osm.way(add_nodes([(0.0, t), (size, t)]), highway="residential")
        osm.way(add_nodes([(t, 0.0), (t, size)]), highway="residential")
    for x in ticks[:-1] + spacing / 2:
        for y in ticks[:-1] + spacing / 2:
            ids = add_nodes(
                [(x - 20, y - 20), (x + 20, y - 20), (x + 20, y + 20), (x - 20, y + 20)]
            )
            osm.way(ids + ids[:1], building="yes")
    return osm.write(path)


def drivable_of(city) -> shapely.Geometry:
    """A stand-in for the simulator world's drivable area: the OSM roads of ``city`` (embedded
    name or OSM path) buffered by :data:`HD_HALF_WIDTH` metres."""
    return shapely.union_all(list(maps.buffer_roads(maps.load_city(city), 2 * HD_HALF_WIDTH)))


class OsmSource(GridSource):
    """A :class:`GridSource` centred on the world origin (where ``load_city`` puts the data)
    with the city's real drivable area."""

    def __init__(self, city, size: float = 1000.0, fail_after=None):
        super().__init__(city, size=size, fail_after=fail_after)
        self.drivable = drivable_of(city)

    def drive(self, rng, num_frames):
        poses = super().drive(rng, num_frames)
        poses[:, :2] -= self.size / 2
        return poses


class OsmFactory(Factory):
    """source_factory building :class:`OsmSource` s; remembers the cities it was called with."""

    def __init__(self, fail_after=None):
        super().__init__(fail_after)
        self.called = []

    def __call__(self, city):
        self.called.append(city)
        self.sources[city] = OsmSource(city, fail_after=self.fail_after)
        return self.sources[city]
