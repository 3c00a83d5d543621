"""OSM alignment of a city whose frames lie in areas kilometres apart: fit windows on the
frames, one correction per city from all of them, quality per window, and refusals (empty
window, peak on the search bound, flat score, disagreeing windows) instead of a silent shift."""

import dataclasses
import math

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Polygon

import fixtures_real as fx
from seglocnet_jax import geometry, maps
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.real import align_fit as ra
from seglocnet_jax.data.real import align_windows as aw
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import convert as rconv
from seglocnet_jax.data.real import map_rasters as real_maps
from seglocnet_jax.data.real.alignment import AlignConfig, AlignmentError, Similarity
from seglocnet_jax.data.real.common import RealDataError

FAR = (3000.0, 2000.0)  # the second log's origin: 3.6 km from the first
# OSM = TRUTH^-1(city frame): a shift and a rotation about a point between the logs, so the
# two logs see different local shifts ((+3.7, -3.5) m and (+0.3, +1.7) m).
TRUTH = Similarity(shift=(2.0, -1.0), rotation=math.radians(0.1), centre=(1500.0, 1100.0))
FAST = AlignConfig(
    resolution=1.0,
    max_shift=8.0,
    max_rotation_deg=1.0,
    rotation_step_deg=0.5,
    scales=(1.0,),
    band=10.0,
    road_width=8.0,
    window=256.0,
)
LOGS = {"train": [("log-pit-a", "PIT", 40.0)], "val": [("log-pit-far", "PIT", 40.0)]}
PIT_FRAME = maps.Projection.utm(17, origin_latlon=av.CITY_FRAMES["PIT"][1])
# Points of each log's map (fixture frame, 0..400 x -20..300 m) where the fit is checked.
LOCAL_PROBES = np.array([[40.0, 100.0], [0.0, 0.0], [250.0, 250.0], [100.0, 200.0]])


def _inverse(sim: Similarity):
    return lambda xy: np.linalg.solve(sim.matrix(), np.c_[xy, np.ones(len(xy))].T).T[:, :2]


def _convert(tmp_path, osm_origins, warp, align=FAST, name="pit2"):
    root = str(tmp_path / "av2")
    fx.write_argoverse(root, logs=LOGS, origins={"log-pit-far": FAR})
    osm = str(tmp_path / "pit.osm")
    fx.write_osm(osm, PIT_FRAME.to_lonlat, warp=warp, origins=osm_origins)
    reader = av.ArgoverseReader(
        av.ArgoverseConfig(dataroot=root, cities=("PIT",), image_size=(12, 20), frame_stride=3)
    )
    cfg = rconv.ConvertConfig(
        name=name,
        root=str(tmp_path / "out"),
        shard_size=4,
        osm={"PIT": osm},
        map_variants=({"kind": "sd", "road_width": 8.0, "channels": ("road",)},),
        align=align,
    )
    return reader, cfg


def test_two_logs_kilometres_apart_recover_a_known_offset(tmp_path):
    reader, cfg = _convert(tmp_path, ((0.0, 0.0), FAR), _inverse(TRUTH))
    ddir = rconv.convert(reader, cfg)
    man = mf.read_manifest(ddir)
    entry = man["alignment"]["cities"]["PIT"]
    fit = Similarity.from_dict(entry)
    probes = np.concatenate([LOCAL_PROBES, LOCAL_PROBES + FAR])
    err = np.linalg.norm(fit.apply(probes) - TRUTH.apply(probes), axis=1)
    rot_err = math.degrees(fit.rotation - TRUTH.rotation)
    print(f"two logs 3.6 km apart: position error max {err.max():.3f} m (mean {err.mean():.3f}),")
    print(f"  rotation error {rot_err:+.4f} deg, fit {entry['shift_m']} about {entry['centre_m']}")
    assert err.max() < 0.5, (entry, err)
    assert abs(rot_err) < 0.02, entry
    # One window per log, each with its quality; both agree with the city fit.
    assert entry["method"] == "fit"
    q = entry["quality"]
    assert q["windows"] == 2 and q["sharp_windows"] == 2 and q["agreement"] == 1.0
    assert q["score"] > 0.3 and q["sharpness"] > 0.2
    for w in entry["windows"]:
        assert w["status"] == "ok" and w["residual_m"] < 0.5 and w["frames"] == 2, w
    # The corrected SD roads carry every pose of both logs; the log says how it was fitted.
    assert entry["poses_on_road"] == {"sd_w8_road": 1.0}
    text = rconv.summary(ddir)
    assert "OSM correction PIT: shift (" in text and "2 window(s), 2 sharp, agreement 100%" in text
    assert text.count("    window (") == 2


def test_an_empty_map_window_is_refused_and_the_remedies_work(tmp_path):
    # OSM only around the first log: nothing near the second one.
    reader, cfg = _convert(tmp_path, ((0.0, 0.0),), _inverse(TRUTH))
    with pytest.raises(AlignmentError) as err:
        rconv.convert(reader, cfg)
    msg = str(err.value)
    assert "OSM alignment of 'PIT' refused: no OSM road matches the drivable area" in msg
    assert "in 1 of 2 window(s): (3042, 2100) m (2 frames, score 0.000)" in msg
    for remedy in (
        "dataset.convert.osm.PIT",
        "dataset.convert.align.max_shift=16",
        "'+dataset.convert.align.manual.PIT={shift: [dx, dy], rotation_deg: r, scale: s, "
        "centre: [x, y]}'",
        "dataset.convert.align.enabled=false",
    ):
        assert remedy in msg
    ddir = str(tmp_path / "out" / "pit2")
    assert "alignment" not in mf.read_manifest(ddir)  # nothing fitted was stored or drawn
    # A manual correction on the same directory: used as given, reported as such.
    manual = {"shift": [2.0, -1.0], "rotation_deg": 0.1, "centre": [1500.0, 1100.0]}
    by_hand = dataclasses.replace(cfg.align, manual={"PIT": manual})
    rconv.convert(reader, dataclasses.replace(cfg, align=by_hand))
    entry = mf.read_manifest(ddir)["alignment"]["cities"]["PIT"]
    assert entry["method"] == "manual" and entry["manual"] == dict(manual, scale=1.0)
    assert Similarity.from_dict(entry).matrix() == pytest.approx(TRUTH.matrix())
    assert "[manual]" in rconv.summary(ddir)
    # The first log's SD roads are right, the second has none (half the poses on a road).
    assert entry["poses_on_road"] == {"sd_w8_road": 0.5}


def _fixture_rasters(warp, extent=(-20.0, -40.0, 420.0, 320.0), roads=fx.ROADS, polygons=None):
    grid = geometry.RasterGrid.covering(extent)
    polygons = polygons or [Polygon(s, h) for s, h in fx.drivable_polygons()]
    target = maps.rasterize_geometries(polygons, grid)
    lines = [LineString(warp(np.array(r, np.float64))).buffer(4.0) for r in roads]
    return target, maps.rasterize_geometries(lines, grid), grid


def test_a_peak_beyond_max_shift_is_refused_as_on_the_search_bound():
    truth = Similarity(shift=(11.0, -10.0), centre=(200.0, 150.0))
    target, source, grid = _fixture_rasters(_inverse(truth))
    cfg = dataclasses.replace(FAST, window=512.0, max_rotation_deg=0.0)
    with pytest.raises(AlignmentError, match="peak on the search bound") as err:
        ra.fit_similarity(target, source, grid, cfg, progress=False)
    assert "dataset.convert.align.max_shift=16" in str(err.value)
    # With the larger search the remedy names, the same rasters give the truth.
    wide = dataclasses.replace(cfg, max_shift=16.0)
    fit = ra.fit_similarity(target, source, grid, wide, progress=False)
    probes = np.array([[0.0, 0.0], [400.0, 300.0]])
    assert np.abs(fit.apply(probes) - truth.apply(probes)).max() < 0.5, fit


def test_a_single_straight_road_is_refused_as_flat():
    road = [((0.0, 100.0), (400.0, 100.0))]
    drivable = [LineString(road[0]).buffer(fx.ROAD_HALF_WIDTH, cap_style="flat")]
    target, source, grid = _fixture_rasters(
        lambda xy: xy + [0.0, 2.0],
        extent=(-200.0, -40.0, 600.0, 240.0),
        roads=road,
        polygons=drivable,
    )
    cfg = dataclasses.replace(FAST, window=256.0, max_rotation_deg=0.0)
    al = ra.align_rasters(target, source, grid, cfg, progress=False, check=False)
    assert any(p.startswith("flat score") for p in al.problems), al.problems
    assert all(w["status"] == "flat" for w in al.windows)
    # Across the road the offset is still found (the fit is refused for the other axis).
    assert al.similarity.shift[1] == pytest.approx(-2.0, abs=0.3)


def _two_areas(warps, cfg):
    """The fixture map at the origin and at FAR with per-area OSM warps, fitted through
    ``real_maps.fit_alignment`` (windows rasterized from the geometries) on frames at both."""
    drivable = shapely.unary_union(
        [
            shapely.affinity.translate(Polygon(s, h), *o)
            for o in ((0.0, 0.0), FAR)
            for s, h in fx.drivable_polygons()
        ]
    )

    def warp(xy):
        near_far = (xy[:, :1] > FAR[0] / 2).astype(float)
        return (1 - near_far) * warps[0](xy) + near_far * warps[1](xy)

    return drivable, warp


def test_windows_that_disagree_are_refused(tmp_path):
    # Area 1's OSM is 6 m east of the truth, area 2's 6 m west: no one similarity fits both.
    drivable, warp = _two_areas((lambda xy: xy + [6.0, 0.0], lambda xy: xy - [6.0, 0.0]), FAST)
    osm = str(tmp_path / "two.osm")
    fx.write_osm(osm, PIT_FRAME.to_lonlat, warp=warp, origins=((0.0, 0.0), FAR))
    city = dataclasses.replace(maps.load_city(osm, projection=PIT_FRAME), name="PIT")
    frames = np.array([[40.0, 100.0], [3040.0, 2100.0]])
    al = real_maps.fit_alignment(city, drivable, FAST, False, frames, check=False)
    assert [w["status"] for w in al.windows].count("disagrees") == 1, al.windows
    assert any(p.startswith("windows disagree: 1 of 2 sharp") for p in al.problems), al.problems
    with pytest.raises(AlignmentError, match="OSM alignment of 'PIT' refused: .*windows disagree"):
        al.check()
    # Shifts that one similarity explains (a rotation about the midpoint) are accepted.
    truth = Similarity(rotation=math.radians(0.15), centre=(1540.0, 1100.0))
    osm2 = str(tmp_path / "rot.osm")
    fx.write_osm(osm2, PIT_FRAME.to_lonlat, warp=_inverse(truth), origins=((0.0, 0.0), FAR))
    city2 = dataclasses.replace(maps.load_city(osm2, projection=PIT_FRAME), name="PIT")
    ok = real_maps.fit_alignment(city2, drivable, FAST, False, frames)
    assert np.abs(ok.similarity.apply(frames) - truth.apply(frames)).max() < 0.5, ok.report()


def test_manual_corrections_are_validated_and_parse_from_overrides():
    tree = {"source": "av2", "reader": {"dataroot": "x"}}
    for manual, match in (
        ({"PIT": {"shfit": [1, 2]}}, r"dataset\.convert\.align\.manual\.PIT\.shfit"),
        ({"PIT": {"shift": [1]}}, r"dataset\.convert\.align\.manual\.PIT\.shift must be \[x, y\]"),
        ({"PIT": {"scale": 3.0}}, r"manual\.PIT\.scale must be within \[0\.5, 2\]"),
        ({"PIT": [1, 2]}, r"dataset\.convert\.align\.manual\.PIT must be a mapping"),
    ):
        with pytest.raises(ConfigError, match=match):
            rconv.parse_tree(dict(tree, convert={"align": {"manual": manual}}))
    # The override the refusal suggests composes into a valid config.
    from hydra import compose, initialize_config_dir

    from seglocnet_jax.app import hydra_glue

    override = "+dataset.convert.align.manual.PIT={shift: [1.5, -2], rotation_deg: 0.1}"
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        cfg = compose(
            config_name="dataset/argo_pit", overrides=["dataset.reader.dataroot=x", override]
        )
    _, _, convert = rconv.parse_tree(hydra_glue.to_tree(cfg)["dataset"])
    assert convert.align.manual == {
        "PIT": {"shift": [1.5, -2.0], "rotation_deg": 0.1, "scale": 1.0, "centre": [0.0, 0.0]}
    }


def test_manual_entry_for_an_unknown_city_is_named(tmp_path):
    reader, cfg = _convert(tmp_path, ((0.0, 0.0), FAR), _inverse(TRUTH))
    bad = dataclasses.replace(cfg, align=dataclasses.replace(FAST, manual={"MIA": {}}))
    with pytest.raises(RealDataError, match=r"manual names \['MIA'\], not cities of this dataset"):
        rconv.convert(reader, bad)


def test_windows_lie_on_the_clusters_of_frames():
    cfg = dataclasses.replace(FAST, window=512.0, max_windows=3)
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 300, (50, 2))  # fits one window
    b = rng.uniform(0, 1000, (40, 2)) + [4000.0, 0.0]  # 1 km: 2 x 2 blocks
    c = np.array([[-3000.0, 50.0]])  # a lone frame
    placed, unchecked = aw.place_windows(np.concatenate([a, b, c]), cfg)
    assert placed[0][1] == 50 and len(placed) == 3
    assert unchecked == 91 - sum(n for _, n in placed) and unchecked >= 1
    centres = np.array([xy for xy, _ in placed])
    assert np.all(centres[1:, 0] > 3900)  # the 2 densest of b's blocks; c is left unchecked
