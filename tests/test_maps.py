"""Maps from real OSM: reading (pbf and XML alike), projections, the binary raster, tiles, GT
BEV labels, caching, and a clear error for each bad input."""

import math
import os

import numpy as np
import osmium
import pytest
import shapely
from shapely.geometry import LineString, Point, Polygon

from seglocnet_jax import maps
from seglocnet_jax.maps import osm

# A tiny hand-made OSM file: a residential street, a footway (not drivable), a building with a
# hole (multipolygon relation) and a plain building (closed way). Around lat 60.17, lon 24.94.
OSM_XML = """<?xml version='1.0' encoding='UTF-8'?>
<osm version="0.6" generator="test">
{nodes}
  <way id="100" version="1"><nd ref="1"/><nd ref="2"/><nd ref="3"/>
    <tag k="highway" v="residential"/><tag k="lanes" v="2"/><tag k="width" v="7 m"/>
    <tag k="oneway" v="-1"/><tag k="name" v="Testikatu"/></way>
  <way id="101" version="1"><nd ref="1"/><nd ref="3"/><tag k="highway" v="footway"/></way>
  <way id="200" version="1"><nd ref="10"/><nd ref="11"/><nd ref="12"/><nd ref="13"/>
    <nd ref="10"/><tag k="building" v="yes"/><tag k="height" v="12.5"/></way>
  <way id="201" version="1"><nd ref="20"/><nd ref="21"/><nd ref="22"/><nd ref="23"/>
    <nd ref="20"/></way>
  <way id="202" version="1"><nd ref="24"/><nd ref="25"/><nd ref="26"/><nd ref="27"/>
    <nd ref="24"/></way>
  <relation id="300" version="1"><member type="way" ref="201" role="outer"/>
    <member type="way" ref="202" role="inner"/><tag k="type" v="multipolygon"/>
    <tag k="building" v="yes"/><tag k="building:levels" v="4"/></relation>
</osm>
"""
NODES = {
    1: (24.9400, 60.1700),
    2: (24.9420, 60.1700),
    3: (24.9440, 60.1702),
    10: (24.9400, 60.1705),
    11: (24.9404, 60.1705),
    12: (24.9404, 60.1707),
    13: (24.9400, 60.1707),
    20: (24.9420, 60.1705),
    21: (24.9430, 60.1705),
    22: (24.9430, 60.1710),
    23: (24.9420, 60.1710),
    24: (24.9423, 60.1706),
    25: (24.9427, 60.1706),
    26: (24.9427, 60.1709),
    27: (24.9423, 60.1709),
}


def write_osm_xml(path, nodes=NODES, body=None):
    text = "\n".join(
        f'  <node id="{i}" version="1" lat="{lat}" lon="{lon}"/>' for i, (lon, lat) in nodes.items()
    )
    xml = OSM_XML.format(nodes=text)
    if body is not None:
        xml = xml[: xml.index("  <way")] + body + "</osm>\n"
    with open(path, "w") as f:
        f.write(xml)
    return str(path)


@pytest.fixture(scope="module")
def helsinki():
    return maps.load_city("helsinki")


@pytest.fixture(scope="module")
def helsinki_sd(helsinki):
    return maps.rasterize(helsinki, maps.MapConfig(kind="sd", road_width=10.0))


def synthetic_city(roads, buildings=()):
    return maps.CityGeometry(
        name="synthetic",
        projection=maps.Projection.tmerc(60.0, 25.0),
        roads=tuple(
            maps.Road(line, "residential", None, None, False, None, i)
            for i, line in enumerate(roads)
        ),
        buildings=tuple(maps.Building(p, None, None, i, "way") for i, p in enumerate(buildings)),
        bounds=(0.0, 0.0, 200.0, 200.0),
        source="<test>",
    )


# --------------------------------------------------------------------------- reading OSM


def test_helsinki_has_drivable_roads_and_buildings_only(helsinki):
    assert len(helsinki.roads) > 500 and len(helsinki.buildings) > 400
    assert {r.highway for r in helsinki.roads} <= maps.DRIVABLE_HIGHWAYS
    assert any(r.highway == "residential" for r in helsinki.roads)
    # Multipolygon relations are assembled with their holes.
    assert any(b.osm_type == "relation" for b in helsinki.buildings)
    assert any(
        len(getattr(p, "interiors", ()))
        for b in helsinki.buildings
        for p in getattr(b.geometry, "geoms", [b.geometry])
    )
    # Default frame: a transverse Mercator centred on the data -> bounds roughly symmetric.
    x0, y0, x1, y1 = helsinki.bounds
    assert abs(x0 + x1) < 1.0 and abs(y0 + y1) < 1.0 and 800 < x1 - x0 < 1300


def test_osm_xml_reads_like_pbf(tmp_path):
    xml = write_osm_xml(tmp_path / "tiny.osm")
    pbf = str(tmp_path / "tiny.osm.pbf")
    with osmium.SimpleWriter(pbf) as writer:
        for obj in osmium.FileProcessor(xml):
            writer.add(obj)
    a, b = maps.load_city(xml), maps.load_city(pbf)
    assert a.name == b.name == "tiny"
    assert a.projection == b.projection and a.bounds == pytest.approx(b.bounds)
    assert len(a.roads) == 1 and len(a.buildings) == 2
    for ra, rb in zip(a.roads, b.roads, strict=True):
        assert ra.geometry.equals_exact(rb.geometry, 1e-6)
        assert (ra.highway, ra.lanes, ra.width, ra.oneway, ra.name, ra.osm_id) == (
            rb.highway,
            rb.lanes,
            rb.width,
            rb.oneway,
            rb.name,
            rb.osm_id,
        )
    road = a.roads[0]
    assert (road.highway, road.lanes, road.width, road.oneway, road.name, road.osm_id) == (
        "residential",
        2,
        7.0,
        True,
        "Testikatu",
        100,
    )
    # oneway=-1: the centreline is drawn in the direction of travel (node 3 -> node 1: west).
    assert road.geometry.coords[0][0] > road.geometry.coords[-1][0]
    # ~222 m of street (0.004 deg lon at 60.17 N) -> metres, not degrees.
    assert road.geometry.length == pytest.approx(224.0, rel=0.02)
    by_id = {bd.osm_id: bd for bd in a.buildings}
    assert by_id[200].height == 12.5 and by_id[200].osm_type == "way"
    rel = by_id[300]
    assert rel.osm_type == "relation" and rel.levels == 4.0
    assert len(rel.geometry.interiors) == 1  # the hole is kept
    for ba in a.buildings:
        other = next(x for x in b.buildings if x.osm_id == ba.osm_id)
        assert ba.geometry.symmetric_difference(other.geometry).area < 1e-6


def test_bbox_clips_and_centres_projection(tmp_path):
    xml = write_osm_xml(tmp_path / "tiny.osm")
    bbox = (24.9410, 60.1695, 24.9435, 60.1712)
    city = maps.load_city(xml, bbox=bbox)
    assert city.projection.origin_latlon == pytest.approx(((60.1695 + 60.1712) / 2, 24.94225))
    box = shapely.box(*city.bounds).buffer(1e-6)
    assert all(box.contains(r.geometry) for r in city.roads)
    assert [b.osm_id for b in city.buildings] == [300]  # building 200 lies west of the box


# --------------------------------------------------------------------------- projections


@pytest.mark.parametrize(
    "proj",
    [
        maps.Projection.tmerc(60.17, 24.94),
        maps.Projection.utm(17, origin_latlon=(40.44177902989321, -80.01294377242584)),
        maps.Projection.topocentric(42.336849169438615, -71.05785369873047),
    ],
)
def test_projection_round_trip_below_one_millimetre(proj):
    lat0, lon0 = proj.origin_latlon
    rng = np.random.default_rng(0)
    lon = lon0 + rng.uniform(-0.03, 0.03, 200)  # a few km around the origin
    lat = lat0 + rng.uniform(-0.03, 0.03, 200)
    x, y = proj.to_metric(lon, lat)
    lon2, lat2 = proj.to_lonlat(x, y)
    # 1 mm is ~9e-9 deg of latitude; compare in metres through the local scale.
    err_n = np.abs(lat2 - lat) * 111_000
    err_e = np.abs(lon2 - lon) * 111_000 * math.cos(math.radians(lat0))
    assert err_n.max() < 1e-3 and err_e.max() < 1e-3
    x0, y0 = proj.to_metric(lon0, lat0)
    assert abs(x0) < 1e-6 and abs(y0) < 1e-6  # the origin is the world origin


def test_utm_matches_argoverse_published_origin():
    # Argoverse 1.1: the PIT origin is 583710.0070 E / 4477259.9999 N in UTM zone 17.
    en = (583710.0070, 4477259.9999)
    proj = maps.Projection.utm(17, origin_en=en)
    x, y = proj.to_metric(-80.01294377242584, 40.44177902989321)
    assert abs(x) < 0.05 and abs(y) < 0.05


def test_topocentric_is_metric_east_north():
    proj = maps.Projection.topocentric(42.336849169438615, -71.05785369873047)
    x, y = proj.to_metric(-71.05785369873047, 42.336849169438615 + 0.01)  # 0.01 deg north
    assert abs(x) < 1e-6 and y == pytest.approx(1111.0, rel=2e-3)  # not Web Mercator's x1.35


# --------------------------------------------------------------------------- rasters


def test_building_area_matches_shapely(helsinki, helsinki_sd):
    union = shapely.union_all([b.geometry for b in helsinki.buildings]).area
    raster_area = helsinki_sd.mask[helsinki_sd.channels.index("building")].sum() * 0.25
    assert raster_area == pytest.approx(union, rel=0.02)
    assert helsinki_sd.mask.dtype == np.uint8 and set(np.unique(helsinki_sd.mask)) == {0, 1}
    assert helsinki_sd.channels == ("road", "building")


def test_building_holes_are_empty(helsinki, helsinki_sd):
    holes = [
        Polygon(ring)
        for b in helsinki.buildings
        for p in getattr(b.geometry, "geoms", [b.geometry])
        for ring in p.interiors
    ]
    others = shapely.union_all([b.geometry for b in helsinki.buildings])
    big = [h for h in holes if h.area > 100 and not others.contains(h.representative_point())]
    assert big, "expected courtyards in central Helsinki"
    for hole in big:
        pt = hole.buffer(-1.0).representative_point()
        row, col = helsinki_sd.grid.world_to_pixel(pt.x, pt.y)
        assert helsinki_sd.mask[1, int(row), int(col)] == 0


@pytest.mark.parametrize("width", [2.5, 5.0, 10.0])
def test_sd_road_width_in_pixels(width):
    city = synthetic_city(
        [
            LineString([(20.3, 100.2), (180.7, 100.2)]),  # east-west
            LineString([(100.3, 20.1), (100.3, 180.9)]),
        ]
    )  # north-south
    r = maps.rasterize(city, maps.MapConfig(kind="sd", road_width=width, channels=("road",)))
    road = r.mask[0]
    expect = width / 0.5
    _, col = r.grid.world_to_pixel(60.0, 0.0)
    row, _ = r.grid.world_to_pixel(0.0, 60.0)
    across_ew = road[:, int(col)].sum()  # a column crossing the east-west road only
    across_ns = road[int(row), :].sum()
    assert abs(across_ew - expect) <= 1 and abs(across_ns - expect) <= 1
    assert r.mask.shape[0] == 1 and r.channels == ("road",)


def test_hd_uses_supplied_drivable_area_and_requires_it():
    area = Polygon([(10, 10), (60, 10), (60, 30), (10, 30)])
    city = synthetic_city([LineString([(0, 100), (200, 100)])], [Point(150, 150).buffer(10)])
    r = maps.rasterize(city, maps.MapConfig(kind="hd"), drivable=[area])
    assert r.mask[0].sum() * 0.25 == pytest.approx(area.area, rel=1e-6)  # grid-aligned box
    assert r.mask[1].sum() * 0.25 == pytest.approx(math.pi * 100, rel=0.03)
    with pytest.raises(maps.MapError, match="drivable"):
        maps.rasterize(city, maps.MapConfig(kind="hd"))


def test_tile_is_slice_of_city_raster(helsinki_sd):
    r = helsinki_sd
    x, y = 12.3, -40.1
    tile, (cx, cy) = r.tile(x, y)
    assert tile.shape == (2, 256, 256) and tile.dtype == np.uint8
    assert abs(cx - x) <= 0.25 and abs(cy - y) <= 0.25
    assert cx / 0.5 == round(cx / 0.5) and cy / 0.5 == round(cy / 0.5)  # a pixel corner
    row = round((r.grid.y_max - cy) / 0.5)
    col = round((cx - r.grid.x_min) / 0.5)
    np.testing.assert_array_equal(tile, r.mask[:, row - 128 : row + 128, col - 128 : col + 128])
    assert tile.any()


def test_tile_off_the_edge_is_zero_padded(helsinki_sd):
    r = helsinki_sd
    x0, _, _, y1 = r.grid.bounds
    tile, (cx, cy) = r.tile(x0, y1)  # centred on the north-west corner
    assert (cx, cy) == pytest.approx((x0, y1))
    assert not tile[:, :128, :].any() and not tile[:, :, :128].any()
    np.testing.assert_array_equal(tile[:, 128:, 128:], r.mask[:, :128, :128])
    far, _ = r.tile(x0 - 1000.0, y1 + 1000.0)
    assert far.shape == (2, 256, 256) and not far.any()


def test_cut_bev_north_heading_equals_raster_slice(helsinki_sd):
    r = helsinki_sd
    x, y = 20.0, 35.5  # a pixel corner of the grid (corners are multiples of 0.5 m)
    row, col = (int(v) for v in r.grid.snap_to_corner(x, y))
    expect = r.mask[:, row - 64 : row + 64, col - 64 : col + 64]
    north = r.cut_bev([x, y, math.pi / 2])
    assert north.shape == (2, 128, 128) and north.dtype == np.uint8 and north.any()
    np.testing.assert_array_equal(north, expect)
    # Facing east, forward (east) is up: the north-up slice turned a quarter counterclockwise.
    np.testing.assert_array_equal(r.cut_bev([x, y, 0.0]), np.rot90(expect, 1, axes=(1, 2)))
    np.testing.assert_array_equal(r.cut_bev([x, y, -math.pi / 2]), np.rot90(expect, 2, axes=(1, 2)))


def test_cut_bevs_batch_matches_single_and_zero_outside(helsinki_sd):
    r = helsinki_sd
    poses = np.array([[0.0, 0.0, 0.3], [100.2, -50.7, -2.0], [r.grid.x_min, 0.0, 1.0]])
    batch = r.cut_bevs(poses)
    assert batch.shape == (3, 2, 128, 128)
    for i, pose in enumerate(poses):
        np.testing.assert_array_equal(batch[i], r.cut_bev(pose))
    # The third pose sits on the west edge facing ~north-east: its left half sees outside.
    outside = r.cut_bev([r.grid.x_min - 100.0, 0.0, 0.0])
    assert not outside.any()


def test_save_load_round_trip(tmp_path, helsinki_sd):
    path = tmp_path / "helsinki.npz"
    helsinki_sd.save(path)
    assert os.listdir(tmp_path) == ["helsinki.npz"]  # no temporary left behind
    back = maps.CityRaster.load(path)
    assert back.grid == helsinki_sd.grid and back.channels == helsinki_sd.channels
    assert back.name == "helsinki"
    np.testing.assert_array_equal(back.mask, helsinki_sd.mask)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(maps.MapError, match="bad.npz"):
        maps.CityRaster.load(tmp_path / "bad.npz")
    data = (tmp_path / "helsinki.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])  # truncated: a kill mid-copy
    with pytest.raises(maps.MapError, match="cut.npz: corrupt"):
        maps.CityRaster.load(tmp_path / "cut.npz")
    with pytest.raises(maps.MapError, match="nowhere.npz: city raster file does not exist"):
        maps.CityRaster.load(tmp_path / "nowhere.npz")


# --------------------------------------------------------------------------- bad input


def test_missing_or_non_osm_file_names_the_file(tmp_path):
    with pytest.raises(maps.MapError, match="does not exist"):
        maps.load_city(tmp_path / "nowhere.osm.pbf")
    bad = tmp_path / "garbage.osm.pbf"
    bad.write_bytes(b"\x00\x01 this is not OSM")
    with pytest.raises(maps.MapError, match="garbage.osm.pbf.*not a readable OSM"):
        maps.load_city(bad)
    xml = tmp_path / "broken.osm"
    xml.write_text("<osm><node id=")
    with pytest.raises(maps.MapError, match="broken.osm"):
        maps.load_city(xml)
    with pytest.raises(maps.MapError, match="neither an embedded city"):
        maps.load_city("atlantis")


def test_no_roads_or_no_buildings_is_an_error(tmp_path):
    building_only = (
        '  <way id="200" version="1"><nd ref="10"/><nd ref="11"/><nd ref="12"/>'
        '<nd ref="13"/><nd ref="10"/><tag k="building" v="yes"/></way>\n'
    )
    path = write_osm_xml(tmp_path / "no_roads.osm", body=building_only)
    with pytest.raises(maps.MapError, match="no_roads.osm: no drivable roads"):
        maps.load_city(path)
    footway_only = (
        '  <way id="101" version="1"><nd ref="1"/><nd ref="3"/>'
        '<tag k="highway" v="footway"/></way>\n' + building_only
    )
    path = write_osm_xml(tmp_path / "footway.osm", body=footway_only)
    with pytest.raises(maps.MapError, match="no drivable roads"):
        maps.load_city(path)
    road_only = (
        '  <way id="100" version="1"><nd ref="1"/><nd ref="2"/>'
        '<tag k="highway" v="primary"/></way>\n'
    )
    path = write_osm_xml(tmp_path / "no_buildings.osm", body=road_only)
    with pytest.raises(maps.MapError, match="no_buildings.osm: no buildings"):
        maps.load_city(path)
    # An area with neither (requested bbox away from the data).
    full = write_osm_xml(tmp_path / "tiny.osm")
    with pytest.raises(maps.MapError, match="bbox"):
        maps.load_city(full, bbox=(25.5, 61.0, 25.6, 61.1))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(channels=("road", "sky")), "map.channels.*'sky'"),
        (dict(channels=()), "map.channels"),
        (dict(channels=("road", "road")), "repeats"),
        (dict(road_width=0.0), "map.road_width.*0.0"),
        (dict(road_width=-5), "map.road_width.*-5"),
        (dict(kind="xd"), "map.kind.*'xd'"),
        (dict(channels=("sky",)), "map.channels.*'sky'.*allowed: road, building"),
        (dict(channels=5), "map.channels"),
    ],
)
def test_map_config_validation_names_key_and_value(kwargs, match):
    with pytest.raises(maps.MapConfigError, match=match):
        maps.MapConfig(**kwargs)


def test_projection_validation():
    with pytest.raises(maps.ProjectionError, match="map.projection.*'mercator'"):
        maps.Projection("mercator", (60.0, 25.0))
    with pytest.raises(maps.ProjectionError, match="utm_zone"):
        maps.Projection.utm(0, origin_latlon=(60.0, 25.0))
    with pytest.raises(maps.ProjectionError, match="origin_latlon"):
        maps.Projection("topocentric")
    assert maps.make_projection("tmerc") is None  # centre on the data
    assert maps.make_projection("topocentric", [1.0, 103.0]).kind == "topocentric"


def test_embedded_city_paths_are_local():
    for name in maps.EMBEDDED_CITIES:
        assert os.path.isfile(osm.embedded_city_path(name))


# --------------------------------------------------------------------------- config, preview


def test_map_section_to_configs():
    source, cfg = maps.configs_from_section(
        {
            "kind": "sd",
            "city": "kouvola",
            "road_width": 5,
            "channels": ["building"],
            "projection": "utm",
            "utm_zone": 35,
            "origin_latlon": [60.53, 26.95],
            "utm_origin_en": None,
            "bbox": None,
        }
    )
    assert cfg == maps.MapConfig(kind="sd", road_width=5.0, channels=("building",))
    assert source.make_projection() == maps.Projection.utm(35, origin_latlon=(60.53, 26.95))
    with pytest.raises(ValueError, match="map.roadwidth"):
        maps.configs_from_section({"roadwidth": 5})
    with pytest.raises(ValueError, match="map.utm_zone"):
        maps.configs_from_section({"projection": "utm", "origin_latlon": [60.0, 25.0]})


def test_preview_command_writes_pngs(tmp_path):
    import subprocess
    import sys

    from PIL import Image

    osm_path = write_osm_xml(tmp_path / "tiny.osm")
    out = tmp_path / "out"
    proc = subprocess.run(  # the preview app with the repository's conf/preview.yaml
        [
            sys.executable,
            "-m",
            "seglocnet_jax.preview",
            "map=sd",
            f"source.city={osm_path}",
            f"hydra.run.dir={out}",
            "map.road_width=5",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    city = np.asarray(Image.open(out / "tiny_sd_city.png"))
    tile = np.asarray(Image.open(out / "tiny_sd_tile.png"))
    raster = maps.rasterize(maps.load_city(osm_path), maps.MapConfig(kind="sd", road_width=5))
    assert city.shape == (*raster.mask.shape[1:], 3) and tile.shape == (256, 256, 3)
    from seglocnet_jax.maps import render

    x0, y0, x1, y1 = raster.grid.bounds
    expect, _ = raster.tile((x0 + x1) / 2, (y0 + y1) / 2)  # default tile: the raster centre
    np.testing.assert_array_equal((tile == render.COLOURS["building"]).all(-1), expect[1] == 1)
    road_only = (expect[0] == 1) & (expect[1] == 0)
    np.testing.assert_array_equal((tile == render.COLOURS["road"]).all(-1), road_only)
