"""A user's OSM file is a first-class city: ``data.city=/path/file.osm`` (and ``data.test_city``)
are named by a stable key (file stem + content hash) in every file name and manifest entry, and
their HD and SD rasters land in the dataset directory, one file per variant."""

import hashlib
import os
import shutil

import numpy as np
import pytest

from data_synth import small_config
from osm_synth import OsmFactory, write_grid_osm
from seglocnet_jax import maps
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data import variants as vr
from seglocnet_jax.data.simulated import prepare as pp


def expected_key(path) -> str:
    with open(path, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()
    stem = os.path.basename(path).split(".osm")[0]
    return f"{stem}-{digest[:10]}"


@pytest.fixture
def user_osm(tmp_path):
    """Two user towns in a directory of their own (nothing may be written there)."""
    src = tmp_path / "user osm"  # a space: keys and paths must not care
    src.mkdir()
    main = write_grid_osm(src / "mytown.osm", size=1200.0, spacing=100.0)
    other = write_grid_osm(src / "othertown.osm", size=1100.0, spacing=110.0, lat0=61.0)
    return src, main, other


def test_city_key():
    assert maps.city_key("helsinki") == "helsinki"
    assert maps.city_key("Kouvola") == "kouvola"
    with pytest.raises(maps.MapError, match="atlantis"):
        maps.city_key("atlantis")


def test_city_key_of_a_file_follows_content_not_location(tmp_path):
    a = write_grid_osm(tmp_path / "town.osm", size=300.0)
    key = maps.city_key(a)
    assert key == expected_key(a) and key.startswith("town-") and len(key) == len("town-") + 10
    (tmp_path / "elsewhere").mkdir()
    b = shutil.copy(a, tmp_path / "elsewhere" / "town.osm")
    assert maps.city_key(b) == key  # moved / copied: same key
    write_grid_osm(b, size=400.0)
    assert maps.city_key(b) != key  # edited: another key
    # A user file named like an embedded city is not that city.
    h = shutil.copy(a, tmp_path / "helsinki.osm")
    assert maps.city_key(h).startswith("helsinki-")
    with pytest.raises(maps.MapError, match="does not exist"):
        maps.city_key(tmp_path / "nowhere.osm.pbf")


def test_user_osm_files_prepare_as_cities(tmp_path, user_osm):
    src, main, other = user_osm
    before = sorted(os.listdir(src))
    key, other_key = maps.city_key(main), maps.city_key(other)
    assert (key, other_key) == (expected_key(main), expected_key(other))
    hd, sd = maps.MapConfig("hd"), maps.MapConfig("sd", 10.0)
    root = tmp_path / "data_root"
    cfg = small_config(root, city=main, test_city=other)
    factory = OsmFactory()
    ddir = pp.prepare(cfg, factory, variants=[hd, sd])
    assert ddir == os.path.join(root, "tiny")
    assert sorted(factory.called) == sorted([main, other])  # sources get the file paths
    assert sorted(os.listdir(src)) == before  # nothing lands next to the user's files

    man = mf.read_manifest(ddir)
    assert set(man["splits"]) == {"train", "val", "test", other_key}  # test split: the key
    assert {c for s in man["splits"].values() for c in s["cities"]} == {key, other_key}
    for split in man["splits"].values():
        for shard in split["shards"]:
            assert os.path.isfile(os.path.join(ddir, shard["file"]))
    for variant in (hd, sd):
        files = man["map_variants"][variant.name]["files"]
        assert files == {
            c: os.path.join("maps", variant.name, f"{c}.npz") for c in (key, other_key)
        }
        for rel in files.values():
            assert os.path.isfile(os.path.join(ddir, rel))
    hd_path, sd_path = (vr.variant_path(ddir, v.name, key) for v in (hd, sd))
    assert hd_path != sd_path
    assert hd_path == os.path.join(ddir, "maps", "hd_road-building", f"{key}.npz")

    # HD and SD hold different rasters: SD's road is the 10 m OSM buffer, HD's the (6 m) world.
    hd_r, sd_r = (vr.load_variant(ddir, v.name, [key])[key] for v in (hd, sd))
    assert sd_r.mask[0].sum() != hd_r.mask[0].sum()
    assert sd_r.mask[0].sum() > 1.3 * hd_r.mask[0].sum()
    city = maps.load_city(main)
    np.testing.assert_array_equal(sd_r.mask, maps.rasterize(city, sd).mask)
    assert hd_r.mask[1].sum() == sd_r.mask[1].sum() > 0  # the same OSM buildings

    # Records carry the key; the loader finds the rasters of both cities.
    path, count = mf.split_files(man, ddir, other_key)[0]
    assert path.startswith(os.path.join(ddir, "sensors", other_key) + os.sep)
    assert records.decode_sample(records.read_shard(path, count)[0])["city"] == other_key
    lcfg = ld.LoaderConfig(max_points=8, num_threads=0)
    for split, want in (("val", key), (other_key, other_key)):
        batch = next(iter(ld.make_loader(ddir, split, sd.name, 2, 0, False, config=lcfg)))
        assert list(batch["city"]) == [want, want]
        assert all(sid.startswith(f"{want}-") for sid in batch["sample_id"])
        assert batch["bev_gt"].any()

    # Resuming with the same config touches nothing; a new variant only rasterizes.
    again = OsmFactory()
    pp.prepare_for_training(cfg, maps.MapConfig("sd", 5.0, ("road",)), again)
    assert again.called == [] and again.calls == 0
    assert os.path.isfile(vr.variant_path(ddir, "sd_w5_road", other_key))


def test_edited_user_file_is_not_silently_reused(tmp_path, user_osm):
    _, main, other = user_osm
    cfg = small_config(tmp_path / "root", city=main, test_city=other)
    ddir = pp.prepare(cfg, OsmFactory(), variants=[maps.MapConfig("sd")])
    write_grid_osm(main, size=1000.0)  # the user edits the file after preparation
    with pytest.raises(vr.VariantError, match="moved or edited"):
        pp.prepare(cfg, OsmFactory(), variants=[maps.MapConfig("sd", 5.0)])
    assert not os.path.exists(vr.variant_path(ddir, "sd_w5_road-building", maps.city_key(main)))


def test_sim_source_names_the_world_by_key(tmp_path):
    from seglocnet_jax.data.simulated.source import SimSource

    path = write_grid_osm(tmp_path / "tinytown.osm", size=300.0)
    assert SimSource(path, {}, 0).world.name == maps.city_key(path)
