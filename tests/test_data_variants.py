"""Map variants: rasterized once per city (for real, from OSM), recorded in the manifest, never
re-simulated; one config class (maps.MapConfig) names and validates them."""

import os

import numpy as np
import pytest

from data_synth import small_config
from osm_synth import OsmFactory
from seglocnet_jax import fileio, maps, sequential
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import variants as vr
from seglocnet_jax.data.simulated import prepare as pp


@pytest.fixture
def rasterized(monkeypatch):
    """Records every rasterization (variant name, city) while doing it for real."""
    calls = []
    real = vr._rasterize

    def spy(cfg, city, drivable):
        calls.append((cfg.name, city, drivable is not None))
        return real(cfg, city, drivable)

    monkeypatch.setattr(vr, "_rasterize", spy)
    return calls


def test_variant_names_and_validation():
    assert maps.MapConfig().name == "hd_road-building"
    assert maps.MapConfig("sd", 5.0, ("road",)).name == "sd_w5_road"
    assert maps.MapConfig("sd", 2.5).name == "sd_w2.5_road-building"
    assert maps.MapConfig("hd", 5.0).name == "hd_road-building"  # HD ignores the width
    assert maps.MapConfig(channels=["road"]) == maps.MapConfig(channels=("road",))
    assert maps.MapConfig("sd", 5).to_dict() == {
        "kind": "sd",
        "road_width": 5.0,
        "channels": ["road", "building"],
    }
    for kwargs, match in [
        (dict(kind="xd"), "map.kind"),
        (dict(channels=("sky",)), r"map.channels.*'sky'.*allowed: road, building"),
        (dict(channels=()), "map.channels"),
        (dict(channels=("road", "road")), "map.channels repeats"),
        (dict(kind="sd", road_width=0), "map.road_width"),
    ]:
        with pytest.raises(maps.MapConfigError, match=match):
            maps.MapConfig(**kwargs)
    # A bad channel stops the data config at construction, before any simulation.
    with pytest.raises(ValueError, match=r"data.map_variants\[0\].*'sky'"):
        small_config("/nonexistent", map_variants=({"kind": "hd", "channels": ["sky"]},))


def test_variant_path_refuses_paths(tmp_path):
    assert vr.variant_path(tmp_path, "hd_road-building", "helsinki") == os.path.join(
        tmp_path, "maps", "hd_road-building", "helsinki.npz"
    )
    for bad in ("/data/town.osm.pbf", "sub/town", "..", "", "a\\b"):
        with pytest.raises(vr.VariantError, match="not a plain key"):
            vr.variant_path(tmp_path, "hd_road-building", bad)


def test_new_variant_only_rasterizes(tmp_path, rasterized):
    cfg = small_config(tmp_path)
    factory = OsmFactory()
    ddir = pp.prepare(cfg, factory, variants=[maps.MapConfig()])
    rendered = factory.calls
    assert rendered > 0
    hd = [c for c in rasterized if c[0] == "hd_road-building"]
    assert hd == [("hd_road-building", "helsinki", True), ("hd_road-building", "kouvola", True)]
    sd = maps.MapConfig("sd", 5.0)
    again = OsmFactory()
    ddir2, name = pp.prepare_for_training(cfg, sd, again)
    assert ddir2 == ddir and name == "sd_w5_road-building" and again.calls == 0
    assert again.called == []  # SD reads OSM only: no world is built
    assert [c[2] for c in rasterized if c[0] == name] == [False, False]
    man = mf.read_manifest(ddir)
    assert set(man["map_variants"]) == {"hd_road-building", name}
    assert man["map_variants"][name]["config"] == sd.to_dict()
    for city in ("helsinki", "kouvola"):
        assert os.path.exists(vr.variant_path(ddir, name, city))
    n = len(rasterized)
    pp.prepare_for_training(cfg, sd, OsmFactory())
    # HD with another (ignored) road width is the stored HD variant, not a conflict.
    pp.prepare_for_training(cfg, maps.MapConfig("hd", road_width=5.0), OsmFactory())
    assert len(rasterized) == n  # stored variants are not rasterized again

    # The stored rasters are the real ones: HD road = the world's drivable area, SD road = the
    # OSM centrelines buffered to 5 m; both with the OSM buildings.
    rasters = {v: vr.load_variant(ddir, v, ["helsinki"])["helsinki"] for v in man["map_variants"]}
    city = maps.load_city("helsinki")
    want_sd = maps.rasterize(city, sd)
    np.testing.assert_array_equal(rasters[name].mask, want_sd.mask)
    want_hd = maps.rasterize(city, maps.MapConfig(), drivable=factory.sources["helsinki"].drivable)
    np.testing.assert_array_equal(rasters["hd_road-building"].mask, want_hd.mask)
    assert rasters[name].mask[0].sum() != rasters["hd_road-building"].mask[0].sum()

    batch = next(
        iter(
            ld.make_loader(
                ddir, "val", name, 4, 0, False, config=ld.LoaderConfig(max_points=8, num_threads=0)
            )
        )
    )
    assert list(batch["city"]) == ["helsinki"] * 4
    np.testing.assert_array_equal(batch["bev_gt"][0], rasters[name].cut_bev(batch["pose"][0]))
    assert batch["bev_gt"].any()  # the centred drive is inside the city


def test_missing_corrupt_variant_or_city_raster_is_named(tmp_path):
    cfg = small_config(tmp_path)
    ddir = pp.prepare(cfg, OsmFactory(), variants=[maps.MapConfig("sd", 10.0, ("road",))])
    with pytest.raises(vr.VariantError, match="'sd_w5_road' is not prepared"):
        ld.make_loader(ddir, "val", "sd_w5_road", 4, 0, False)
    path = vr.variant_path(ddir, "sd_w10_road", "kouvola")
    data = open(path, "rb").read()
    with open(path, "wb") as f:
        f.write(data[: len(data) // 3])  # truncated
    with pytest.raises(vr.VariantError, match=r"kouvola.npz: cached raster.*delete the file"):
        ld.make_loader(ddir, "kouvola", "sd_w10_road", 4, 0, False)
    os.remove(path)
    with pytest.raises(vr.VariantError, match="kouvola.npz: raster of city 'kouvola'"):
        ld.make_loader(ddir, "kouvola", "sd_w10_road", 4, 0, False)
    # The remedy works: preparing again rebuilds exactly the deleted raster.
    pp.prepare(cfg, OsmFactory(), variants=[maps.MapConfig("sd", 10.0, ("road",))])
    back = vr.load_variant(ddir, "sd_w10_road", ["kouvola"])["kouvola"]
    want = maps.rasterize(maps.load_city("kouvola"), maps.MapConfig("sd", 10.0, ("road",)))
    np.testing.assert_array_equal(back.mask, want.mask)


def test_stored_variant_with_another_config_is_refused(tmp_path):
    ddir = pp.prepare(small_config(tmp_path), OsmFactory(), variants=[maps.MapConfig("sd")])
    man = mf.read_manifest(ddir)
    man["map_variants"]["sd_w10_road-building"]["config"]["channels"] = ["road"]
    fileio.write_json_atomic(mf.manifest_path(ddir), man)
    with pytest.raises(vr.VariantError, match="was stored with"):
        vr.ensure_variant(ddir, maps.MapConfig("sd"))


def test_existing_dataset_gets_its_osm_class_rasters_without_rendering(tmp_path):
    """An NM model's map input is added to a prepared dataset (no sensor rendered), recorded in
    the manifest with its class table, cut by the loader beside the tile, and drawn again when
    the table changes."""
    cfg = small_config(tmp_path, test_city=None, map_variants=({"kind": "sd"},))
    ddir = pp.prepare(cfg, OsmFactory())
    assert vr.OSM_CLASSES not in mf.read_manifest(ddir)
    assert not pp.dataset_ready(ddir, [maps.MapConfig("sd")], osm_classes=True)
    again = OsmFactory()
    ddir2, name = pp.prepare_for_training(cfg, maps.MapConfig("sd"), again, osm_classes=True)
    assert ddir2 == ddir and again.calls == 0 and again.called == []  # OSM only: no world
    man = mf.read_manifest(ddir)
    assert man[vr.OSM_CLASSES]["config"] == maps.osm_classes.spec()
    assert man[vr.OSM_CLASSES]["files"] == {
        "helsinki": os.path.join("maps", "osm_classes", "helsinki.npz")
    }
    assert pp.dataset_ready(ddir, [maps.MapConfig("sd")], osm_classes=True)
    stored = vr.load_osm_classes(ddir, ["helsinki"])["helsinki"]
    want = maps.rasterize_osm_classes(maps.load_city("helsinki"))
    np.testing.assert_array_equal(stored.mask, want.mask)
    assert stored.channels == maps.OSM_CLASS_NAMES

    lcfg = ld.LoaderConfig(max_points=8, num_threads=0)
    batch = next(iter(ld.make_loader(ddir, "val", name, 2, 0, False, config=lcfg, nm_tiles=True)))
    for i in range(2):
        np.testing.assert_array_equal(batch["nm_tile"][i], stored.tile(*batch["tile_center"][i])[0])
    assert batch["nm_tile"].any()
    # The sequential filter's split reads them the same way (its rows, its window tiles).
    split = sequential.DriveSplit(ddir, "val", name, lcfg, nm_tiles=True)
    try:
        row = split.rows([0])[0]
        assert set(split.nm_rasters) == {"helsinki"}
        np.testing.assert_array_equal(row["nm_tile"], batch["nm_tile"][0])
    finally:
        split.close()

    # Another class table (a code change): the loader refuses the stale rasters, preparing
    # draws them again.
    man[vr.OSM_CLASSES]["config"]["channels"] = ["road", "building"]
    fileio.write_json_atomic(mf.manifest_path(ddir), man)
    with pytest.raises(vr.VariantError, match="another class table"):
        vr.load_osm_classes(ddir, ["helsinki"])
    os.remove(vr.osm_classes_path(ddir, "helsinki"))
    pp.prepare_for_training(cfg, maps.MapConfig("sd"), OsmFactory(), osm_classes=True)
    np.testing.assert_array_equal(
        vr.load_osm_classes(ddir, ["helsinki"])["helsinki"].mask, want.mask
    )
