"""Map variants: rasterized once per city, recorded in the manifest, never re-simulated."""

import os

import numpy as np
import pytest

from data_synth import ArrayRaster, Factory, small_config
from seglocnet_jax import geometry, maps
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import prepare as pp
from seglocnet_jax.data import variants as vr


class SavedRaster(ArrayRaster):
    """ArrayRaster with the maps npz save/load pair."""

    def save(self, path):
        g = self.grid
        np.savez(path, mask=self.mask, grid=[g.x_min, g.y_max, g.height, g.width, g.resolution])

    @classmethod
    def load(cls, path):
        with np.load(path) as z:
            x0, y1, h, w, r = z["grid"]
            return cls(z["mask"], geometry.RasterGrid(x0, y1, int(h), int(w), r))


@pytest.fixture
def fake_maps(monkeypatch):
    """Stands in for maps.rasterize / CityRaster.load when the maps package lacks them."""
    calls = []

    def rasterize(vcfg, city, drivable):
        calls.append((vcfg.name, city, drivable))
        grid = geometry.RasterGrid.covering((0.0, 0.0, 1300.0, 1300.0))
        seed = len(vcfg.name) + len(city)
        mask = np.random.default_rng(seed).random((len(vcfg.channels), grid.height, grid.width))
        return SavedRaster((mask < 0.3).astype(np.uint8), grid)

    monkeypatch.setattr(vr, "_rasterize", rasterize)
    monkeypatch.setattr(maps, "CityRaster", SavedRaster, raising=False)
    return calls


class DrivableFactory(Factory):
    def __call__(self, city):
        source = super().__call__(city)
        source.drivable = f"drivable-of-{city}"
        return source


def test_variant_names():
    assert vr.VariantConfig().name == "hd_road-building"
    assert vr.VariantConfig("sd", 5.0, ("road",)).name == "sd_w5_road"
    with pytest.raises(ValueError, match="kind"):
        vr.VariantConfig("xd")


def test_new_variant_only_rasterizes(tmp_path, fake_maps):
    cfg = small_config(tmp_path)
    factory = DrivableFactory()
    ddir = pp.prepare(cfg, factory, variants=[vr.VariantConfig()])
    rendered = factory.calls
    assert rendered > 0
    hd = [c for c in fake_maps if c[0] == "hd_road-building"]
    assert sorted(c[1] for c in hd) == ["helsinki", "kouvola"]
    assert all(c[2] == f"drivable-of-{c[1]}" for c in hd)  # HD uses the world's drivable area
    sd = vr.VariantConfig("sd", 5.0)
    again = DrivableFactory()
    ddir2, name = pp.prepare_for_training(cfg, sd, again)
    assert ddir2 == ddir and name == "sd_w5_road-building" and again.calls == 0
    assert [c[2] for c in fake_maps if c[0] == name] == [None, None]  # SD reads OSM only
    man = mf.read_manifest(ddir)
    assert set(man["map_variants"]) == {"hd_road-building", name}
    for city in ("helsinki", "kouvola"):
        assert os.path.exists(vr.variant_path(ddir, name, city))
    n = len(fake_maps)
    pp.prepare_for_training(cfg, sd, DrivableFactory())
    assert len(fake_maps) == n  # stored variants are not rasterized again
    batch = next(
        iter(
            ld.make_loader(
                ddir, "val", name, 4, 0, False, config=ld.LoaderConfig(max_points=8, num_threads=0)
            )
        )
    )
    raster = vr.load_variant(ddir, name, ["helsinki"])["helsinki"]
    np.testing.assert_array_equal(batch["bev_gt"][0], raster.cut_bev(batch["pose"][0]))


def test_missing_variant_or_city_raster_is_named(tmp_path, fake_maps):
    ddir = pp.prepare(small_config(tmp_path), DrivableFactory(), variants=[vr.VariantConfig()])
    with pytest.raises(vr.VariantError, match="'sd_w5_road' is not prepared"):
        ld.make_loader(ddir, "val", "sd_w5_road", 4, 0, False)
    os.remove(vr.variant_path(ddir, "hd_road-building", "kouvola"))
    with pytest.raises(vr.VariantError, match="kouvola.npz: raster of city 'kouvola'"):
        ld.make_loader(ddir, "kouvola", "hd_road-building", 4, 0, False)
