"""The multi-class OSM raster (SegLocNet-NM's map input): each OSM feature lands in its class's
channel and in no other, lines at their class's fixed width, from OSM alone; tiles line up with
the binary map variants'."""

import numpy as np
import pytest

from fixtures_real import OsmXml
from seglocnet_jax import maps
from seglocnet_jax.maps import osm_classes

PROJ = maps.Projection.tmerc(60.17, 24.94)


def _town(path) -> str:
    """A hand-made OSM town in metres around PROJ's origin: a primary street (y = 0), a
    residential one (x = 0), a service way, a footway and a cycleway (not drivable), a
    building, a parking lot, a park, a pond and a tagged-out building (``building=no``)."""
    osm = OsmXml("classes")

    def way(points, **tags):
        xy = np.asarray(points, np.float64)
        ids = osm.nodes(*PROJ.to_lonlat(xy[:, 0], xy[:, 1]))
        osm.way(ids, **tags)

    def area(x0, y0, x1, y1, **tags):
        way([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)], **tags)

    way([(-150, 0), (150, 0)], highway="primary")
    way([(0, -150), (0, 150)], highway="residential")
    way([(60, -150), (60, -40)], highway="service")
    way([(-150, 40), (-20, 40)], highway="footway")
    way([(-150, -40), (-20, -40)], highway="cycleway")
    way([(-150, 80), (-20, 80)], highway="construction")  # not drawn
    area(20, 20, 50, 50, building="yes")
    area(20, -80, 50, -50, amenity="parking")
    area(-100, 100, -40, 140, leisure="park")
    area(80, 80, 120, 120, natural="water")
    area(80, 20, 100, 40, building="no")
    return osm.write(path)


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    path = _town(tmp_path_factory.mktemp("osm") / "town.osm")
    city = maps.load_city(path, projection=PROJ)
    return city, maps.rasterize_osm_classes(city)


def _classes_at(raster, x, y) -> set[str]:
    row, col = raster.grid.world_to_pixel(x, y)
    values = raster.mask[:, int(row), int(col)]
    return {name for name, v in zip(raster.channels, values, strict=True) if v}


def test_each_feature_is_in_its_class_and_no_other(town):
    city, raster = town
    assert raster.channels == maps.OSM_CLASS_NAMES and raster.mask.dtype == np.uint8
    assert raster.mask.shape[0] == len(maps.OSM_CLASSES) <= 10
    assert {w.highway for w in city.ways} == {"footway", "cycleway"}  # not construction
    assert sorted(a.kind for a in city.areas) == ["green", "parking", "water"]
    expect = {
        (100.0, 0.0): {"road_major"},
        (0.0, 100.0): {"road_minor"},
        (60.0, -100.0): {"road_service"},
        (-100.0, 40.0): {"path"},  # a footway is not road
        (-100.0, -40.0): {"path"},
        (-100.0, 80.0): set(),  # highway=construction
        (35.0, 35.0): {"building"},
        (35.0, -65.0): {"parking"},
        (-70.0, 120.0): {"green"},
        (100.0, 100.0): {"water"},
        (90.0, 30.0): set(),  # building=no
        (0.0, 0.0): {"road_major", "road_minor"},  # channels are independent masks
    }
    for (x, y), classes in expect.items():
        assert _classes_at(raster, x + 0.1, y + 0.1) == classes, (x, y)


def test_lines_have_their_class_width(town):
    _, raster = town
    row, col = raster.grid.world_to_pixel(100.0, 0.0)
    across = raster.mask[raster.channels.index("road_major"), :, int(col)].sum()
    assert abs(across - osm_classes.ROAD_WIDTH_M / 0.5) <= 1
    _, col = raster.grid.world_to_pixel(-100.0, 40.0)
    path = raster.mask[raster.channels.index("path"), :, int(col)].sum()  # footway + cycleway
    assert abs(path - 2 * osm_classes.PATH_WIDTH_M / 0.5) <= 2


def test_every_drivable_highway_has_one_road_class():
    for highway in maps.DRIVABLE_HIGHWAYS:
        classes = [c.name for c in maps.OSM_CLASSES if c.matches("highway", highway)]
        assert len(classes) == 1 and classes[0].startswith("road_"), highway
    for highway in ("footway", "cycleway", "path", "pedestrian", "steps"):
        assert osm_classes.line_class(highway).name == "path"
    assert osm_classes.line_class("construction") is None
    spec = osm_classes.spec()
    assert spec["channels"] == list(maps.OSM_CLASS_NAMES)


def test_embedded_city_tiles_line_up_with_the_sd_map():
    """Helsinki's class raster: its buildings are the SD map's, and a tile around the same
    prior is centred on the same point (both grids' corners on the 0.5 m lattice)."""
    city = maps.load_city("helsinki")
    classes = maps.rasterize_osm_classes(city)
    sd = maps.rasterize(city, maps.MapConfig("sd"))
    assert all(classes.mask[i].any() for i in range(len(maps.OSM_CLASSES)))
    b = classes.channels.index("building")
    for x, y in [(12.3, -40.1), (-200.7, 300.2)]:
        a, ca = classes.tile(x, y)
        s, cs = sd.tile(x, y)
        assert ca == cs and a.shape == (9, 256, 256)
        np.testing.assert_array_equal(a[b], s[1])


def test_bbox_clips_ways_and_areas(town, tmp_path):
    city, _ = town
    lon, lat = PROJ.to_lonlat(np.array([-60.0, 60.0]), np.array([-60.0, 60.0]))
    clipped = maps.load_city(city.source, projection=PROJ, bbox=(lon[0], lat[0], lon[1], lat[1]))
    x0, y0, x1, y1 = clipped.bounds
    for feature in (*clipped.ways, *clipped.areas):
        fx0, fy0, fx1, fy1 = feature.geometry.bounds
        assert x0 - 0.01 <= fx0 and fx1 <= x1 + 0.01 and y0 - 0.01 <= fy0 and fy1 <= y1 + 0.01
    assert {w.highway for w in clipped.ways} == {"footway", "cycleway"}
    assert [a.kind for a in clipped.areas] == ["parking"]  # the park and the pond lie outside
