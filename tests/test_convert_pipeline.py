"""Real-data conversion end to end: fixtures -> shards + map rasters -> the grain loader; the
OSM similarity correction."""

import dataclasses
import math
import os

import numpy as np
import pytest
from shapely.geometry import LineString, Polygon

import fixtures_real as fx
from seglocnet_jax import geometry, maps
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.loader import LoaderConfig, make_loader
from seglocnet_jax.data.real import align_fit as ra
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import convert as rconv
from seglocnet_jax.data.real import map_rasters as real_maps
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.real.alignment import AlignConfig, AlignmentError, Similarity
from seglocnet_jax.data.real.common import RealDataError

OUT_HW = (12, 20)
SEQ_KEYS = ("sequence_id", "frame_index", "timestamp")
# A known OSM misalignment: OSM = TRUTH^-1(dataset), so the fit must return TRUTH.
TRUTH = Similarity(shift=(3.0, -2.0), rotation=math.radians(0.8), scale=1.0, centre=(200.0, 150.0))
FAST_ALIGN = AlignConfig(
    resolution=1.0,
    max_shift=8.0,
    max_rotation_deg=1.5,
    rotation_step_deg=0.5,
    scales=(1.0,),
    band=10.0,
    road_width=8.0,
)
PROBES = np.array([[0.0, 0.0], [400.0, 300.0], [200.0, 150.0], [0.0, 300.0]])


def _misaligned(xy):
    return np.linalg.solve(TRUTH.matrix(), np.c_[xy, np.ones(len(xy))].T).T[:, :2]


def _nus_setup(tmp_path):
    root = str(tmp_path / "nuscenes")
    fx.write_nuscenes(root)
    osm = str(tmp_path / "boston.osm")
    proj = maps.Projection.topocentric(*nu.MAP_ORIGINS["boston-seaport"])
    fx.write_osm(osm, proj.to_lonlat, warp=_misaligned)
    reader = nu.NuScenesReader(
        nu.NuScenesConfig(dataroot=root, version="v1.0-mini", image_size=OUT_HW)
    )
    cfg = rconv.ConvertConfig(
        name="nus_tiny",
        root=str(tmp_path / "out"),
        seed=3,
        shard_size=2,
        splits={"train": "mini_train", "val": "mini_val"},
        osm={"boston-seaport": osm},
        map_variants=({"kind": "hd"}, {"kind": "sd", "road_width": 8.0}),
        align=FAST_ALIGN,
    )
    return reader, cfg


def test_similarity_fit_recovers_a_known_shift_and_rotation():
    grid = geometry.RasterGrid.covering((-20.0, -40.0, 420.0, 320.0))
    target = maps.rasterize_geometries([Polygon(s, h) for s, h in fx.drivable_polygons()], grid)
    lines = [LineString(_misaligned(np.array(r))).buffer(4.0) for r in fx.ROADS]
    source = maps.rasterize_geometries(lines, grid)
    fit = ra.fit_similarity(target, source, grid, FAST_ALIGN, progress=False)
    err = np.abs(fit.apply(PROBES) - TRUTH.apply(PROBES)).max()
    assert err < 0.5, (fit.as_dict(), err)
    assert abs(math.degrees(fit.rotation - TRUTH.rotation)) < 0.1
    # Without the rotation in the search range, the fit is measurably worse.
    no_rot = dataclasses.replace(FAST_ALIGN, max_rotation_deg=0.0)
    worse = ra.fit_similarity(target, source, grid, no_rot, progress=False)
    assert np.abs(worse.apply(PROBES) - TRUTH.apply(PROBES)).max() > 1.5
    assert worse.score < fit.score


def test_similarity_fit_recovers_a_known_scale():
    grid = geometry.RasterGrid.covering((-20.0, -40.0, 420.0, 320.0))
    target = maps.rasterize_geometries([Polygon(s, h) for s, h in fx.drivable_polygons()], grid)
    truth = Similarity(scale=1.01, centre=(200.0, 150.0))
    inv = np.linalg.inv(truth.matrix())
    lines = [LineString(np.c_[r, np.ones(2)] @ inv[:2].T).buffer(4.0) for r in fx.ROADS]
    source = maps.rasterize_geometries(lines, grid)
    cfg = dataclasses.replace(FAST_ALIGN, max_rotation_deg=0.0, scales=(0.99, 1.0, 1.01, 1.02))
    fit = ra.fit_similarity(target, source, grid, cfg, progress=False)
    assert fit.scale == 1.01
    assert np.abs(fit.apply(PROBES) - truth.apply(PROBES)).max() < 0.5
    # The best scale at the end of the searched ones is refused: the truth may lie beyond.
    short = dataclasses.replace(cfg, scales=(0.99, 1.0, 1.01))
    with pytest.raises(AlignmentError, match=r"scale 1\.0100 on the search bound"):
        ra.fit_similarity(target, source, grid, short, progress=False)


def test_nuscenes_converts_to_records_and_rasters_the_loader_reads(tmp_path):
    reader, cfg = _nus_setup(tmp_path)
    load, loads = reader.load, []

    def interrupted_load(frame):  # dies on val's 1st frame: both train shards are written
        loads.append(frame.key)
        if len(loads) == 4:
            raise KeyboardInterrupt
        return load(frame)

    reader.load = interrupted_load
    with pytest.raises(KeyboardInterrupt):
        rconv.convert(reader, cfg)
    loads.clear()
    reader.load = lambda frame: loads.append(frame.key) or load(frame)
    ddir = rconv.convert(reader, cfg)
    assert loads == [f.key for f in reader.frames("mini_val")]  # train is not read again
    man = mf.read_manifest(ddir)
    assert man["complete"] and {k: v["count"] for k, v in man["splits"].items()} == {
        "train": 3,
        "val": 3,
    }
    assert man["splits"]["val"]["cities"] == {"boston-seaport": 3}
    # The fitted correction is stored and recovers the synthetic misalignment.
    fit = Similarity.from_dict(man["alignment"]["cities"]["boston-seaport"])
    assert np.abs(fit.apply(PROBES) - TRUTH.apply(PROBES)).max() < 0.5
    hd, sd = "hd_road-building", "sd_w8_road-building"
    assert set(man["map_variants"]) == {hd, sd}
    rasters = {
        v: maps.CityRaster.load(
            os.path.join(ddir, man["map_variants"][v]["files"]["boston-seaport"])
        )
        for v in (hd, sd)
    }
    # Every pose lies on the HD drivable area and on the corrected SD (OSM) roads.
    poses = np.stack([f.pose for f in reader.frames("mini_train") + reader.frames("mini_val")])
    for v in (hd, sd):
        assert real_maps.drivable_fraction(rasters[v], poses) == 1.0, v
    # Corrected OSM buildings land where the fixture put them (centre of the first one).
    x0, y0, x1, y1 = fx.BUILDINGS[0]
    row, col = rasters[hd].grid.world_to_pixel((x0 + x1) / 2, (y0 + y1) / 2)
    assert rasters[hd].mask[1, int(row), int(col)] == 1
    # Read back through the loader: GT BEVs put the ego (central pixel corner) on the road.
    loader = make_loader(ddir, "val", hd, batch_size=2, seed=0, train=False)
    batches = list(iter(loader))
    assert len(batches) == 2 and batches[0]["images"].shape == (2, 6, *OUT_HW, 3)
    got = np.concatenate([b["pose"] for b in batches])[:3]  # file order; the 4th row is padding
    np.testing.assert_allclose(got, [f.pose for f in reader.frames("mini_val")], atol=1e-9)
    # The sequence metadata survives the records: the scene, keyframe index, time (s).
    val = reader.frames("mini_val")
    rows = {k: np.concatenate([b[k] for b in batches])[:3] for k in SEQ_KEYS}
    assert list(rows["sequence_id"]) == [f.sequence_id for f in val] == ["scene-0103"] * 3
    assert rows["frame_index"].tolist() == [0, 1, 2] and rows["frame_index"].dtype == np.int64
    assert rows["timestamp"].tolist() == [f.timestamp for f in val]
    for b in batches:
        assert np.all(b["bev_gt"][:, 0, 63:65, 63:65] == 1)
        assert np.abs(b["tile_center"] - b["pose"][:, :2]).max() <= 32.5
    # Converted again: everything is found complete, no sensor is read.
    again = nu.NuScenesReader(reader.cfg)
    again.load = lambda frame: (_ for _ in ()).throw(AssertionError("re-read " + frame.key))
    assert rconv.convert(again, cfg) == ddir


def test_real_dataset_gets_osm_class_rasters_through_its_alignment(tmp_path):
    """An NM model's OSM class rasters are added to a converted dataset without reading a
    sensor, drawn from the OSM extract through the city's fitted correction."""
    reader, cfg = _nus_setup(tmp_path)
    cfg = dataclasses.replace(cfg, num_workers=1)  # no worker processes to start: faster here
    ddir = rconv.convert(reader, cfg)
    assert "osm_classes" not in mf.read_manifest(ddir)
    again = nu.NuScenesReader(reader.cfg)
    again.load = lambda frame: (_ for _ in ()).throw(AssertionError("re-read " + frame.key))
    ddir, _ = rconv.convert_for_training(again, cfg, maps.MapConfig(), osm_classes=True)
    man = mf.read_manifest(ddir)
    assert man["osm_classes"]["files"] == {
        "boston-seaport": os.path.join("maps", "osm_classes", "boston-seaport.npz")
    }
    classes = maps.CityRaster.load(
        os.path.join(ddir, man["osm_classes"]["files"]["boston-seaport"])
    )
    x0, y0, x1, y1 = fx.BUILDINGS[0]  # where the fixture put it: the correction was applied
    row, col = classes.grid.world_to_pixel((x0 + x1) / 2, (y0 + y1) / 2)
    assert classes.mask[:, int(row), int(col)].tolist() == [
        int(c == "building") for c in maps.OSM_CLASS_NAMES
    ]
    batch = next(iter(make_loader(ddir, "val", "hd_road-building", 2, 0, False, nm_tiles=True)))
    assert batch["nm_tile"].shape == (2, len(maps.OSM_CLASSES), 256, 256)
    assert batch["nm_tile"][:, maps.OSM_CLASS_NAMES.index("road_minor")].any()
    # Without an OSM extract there is no class raster: the error names the key to set.
    road_only = dataclasses.replace(
        cfg, name="no_osm", osm={}, map_variants=({"kind": "hd", "channels": ["road"]},)
    )
    with pytest.raises(RealDataError, match=r"neural map.*set dataset\.convert\.osm\.boston"):
        rconv.convert(reader, road_only, osm_classes=True)


def test_config_change_and_missing_osm_are_named(tmp_path):
    reader, cfg = _nus_setup(tmp_path)
    rconv.convert(reader, dataclasses.replace(cfg, map_variants=({"kind": "hd"},)), variants=False)
    with pytest.raises(mf.ManifestError, match=r"config\.seed: manifest 3 != config 4"):
        rconv.convert(reader, dataclasses.replace(cfg, seed=4))
    missing = dataclasses.replace(cfg, osm={"boston-seaport": str(tmp_path / "nope.osm")})
    with pytest.raises(
        RealDataError,
        match=r"nope\.osm: OSM extract of 'boston-seaport' "
        r"\(dataset\.convert\.osm\.boston-seaport\)",
    ):
        rconv.convert(reader, missing)
    no_osm = dataclasses.replace(cfg, osm={})
    with pytest.raises(RealDataError, match=r"set dataset\.convert\.osm\.boston-seaport"):
        rconv.convert(reader, no_osm)


def test_argoverse_miami_converts_and_loads(tmp_path):
    root = str(tmp_path / "av2")
    fx.write_argoverse(root)
    reader = av.ArgoverseReader(
        av.ArgoverseConfig(dataroot=root, cities=("MIA",), image_size=OUT_HW, frame_stride=3)
    )
    cfg = rconv.ConvertConfig(
        name="argo_mia_tiny",
        root=str(tmp_path / "out"),
        shard_size=4,
        map_variants=({"kind": "hd", "channels": ("road",)},),
        align=dataclasses.replace(FAST_ALIGN, enabled=False),
    )
    ddir = rconv.convert(reader, cfg)
    man = mf.read_manifest(ddir)
    assert {k: v["cities"] for k, v in man["splits"].items()} == {
        "train": {"MIA": 2},
        "val": {"MIA": 2},
    }
    assert man["alignment"]["cities"]["MIA"]["shift_m"] == [0.0, 0.0]
    one_epoch = LoaderConfig(num_epochs=1, num_threads=0)
    batches = list(
        iter(
            make_loader(
                ddir, "train", "hd_road", batch_size=2, seed=1, train=True, config=one_epoch
            )
        )
    )
    assert len(batches) == 1
    b = batches[0]
    assert b["images"].shape == (2, 7, *OUT_HW, 3) and b["bev_gt"].shape == (2, 1, 128, 128)
    assert np.all(b["bev_gt"][:, 0, 63:65, 63:65] == 1)
    ids = {str(s) for s in b["sample_id"]}
    assert all(i.startswith("log-mia-a/") for i in ids)
