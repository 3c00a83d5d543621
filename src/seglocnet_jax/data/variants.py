"""Map variants of a prepared dataset: cached city rasters, one npz per city and variant.

A variant (HD; SD with road width w; a channel set) is a rasterization of the cities' maps. It is
stored once as ``maps/<variant>/<city>.npz`` and recorded in the manifest; sensors are never
re-simulated for a new variant. Tiles and GT BEVs are cut on the fly from the cached raster by
the loader instead of being stored per frame: cutting is a slice (tile) plus a nearest-neighbour
gather (BEV), well under a millisecond, and the evaluation priors are stored, so the result is
identical to stored tiles at a fraction of the disk (a 256x256x2 tile per frame and variant).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable

from seglocnet_jax.data import manifest as mf


class VariantError(ValueError):
    """A map variant is missing or inconsistent; the message names the variant and file."""


@dataclasses.dataclass(frozen=True)
class VariantConfig:
    """One map variant: ``kind`` "hd" (drivable area + buildings) or "sd" (OSM centrelines
    buffered to ``road_width`` metres + buildings), and the raster ``channels``."""

    kind: str = "hd"
    road_width: float = 10.0
    channels: tuple[str, ...] = ("road", "building")

    def __post_init__(self):
        if self.kind not in ("hd", "sd"):
            raise ValueError(f"map kind must be 'hd' or 'sd', got {self.kind!r}")
        if self.kind == "sd" and not self.road_width > 0:
            raise ValueError(f"road_width must be > 0 m for SD maps, got {self.road_width}")
        if not self.channels:
            raise ValueError("map channels must not be empty")

    @property
    def name(self) -> str:
        """Directory name, e.g. ``hd_road-building`` or ``sd_w5_road-building``."""
        width = f"_w{self.road_width:g}" if self.kind == "sd" else ""
        return f"{self.kind}{width}_{'-'.join(self.channels)}"


def variant_path(dataset_dir: str | os.PathLike, variant: str, city: str) -> str:
    return os.path.join(os.fspath(dataset_dir), "maps", variant, f"{city}.npz")


def _rasterize(vcfg: VariantConfig, city: str, drivable):
    from seglocnet_jax import maps  # the maps package is the one seam to OSM and rasterio

    map_cfg = maps.MapConfig(
        kind=vcfg.kind, road_width=vcfg.road_width, channels=tuple(vcfg.channels)
    )
    return maps.rasterize(maps.load_city(city), map_cfg, drivable=drivable)


def ensure_variant(
    dataset_dir: str | os.PathLike,
    vcfg: VariantConfig,
    source_factory: Callable | None = None,
    sources: dict | None = None,
) -> str:
    """Rasterizes and stores ``vcfg`` for every city of the dataset unless already there;
    returns the variant name.

    HD maps need the world's drivable area: ``sources[city]`` or ``source_factory(city)`` must
    offer ``.drivable`` (shapely geometry, world metres). SD maps only read OSM.
    """
    man = mf.read_manifest(dataset_dir)
    name = vcfg.name
    cities = sorted({c for s in man["splits"].values() for c in s["cities"]})
    entry = man["map_variants"].get(name)
    if entry is not None:
        if entry["config"] != _plain(vcfg):
            raise VariantError(
                f"{mf.manifest_path(dataset_dir)}: variant {name!r} was stored "
                f"with {entry['config']}, now {_plain(vcfg)}"
            )
        if all(os.path.exists(variant_path(dataset_dir, name, c)) for c in cities):
            return name
    sources = {} if sources is None else sources
    files = {}
    for city in cities:
        path = variant_path(dataset_dir, name, city)
        files[city] = os.path.relpath(path, dataset_dir)
        if os.path.exists(path):
            continue
        drivable = None
        if vcfg.kind == "hd":
            if city not in sources:
                if source_factory is None:
                    raise VariantError(
                        f"HD variant {name!r} of {city!r} needs the world's "
                        "drivable area: pass source_factory"
                    )
                sources[city] = source_factory(city)
            drivable = sources[city].drivable
        raster = _rasterize(vcfg, city, drivable)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path[:-4]}.tmp-{os.getpid()}.npz"  # np.savez keeps a .npz name as is
        try:
            raster.save(tmp)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
    man = mf.read_manifest(dataset_dir)  # re-read: only this entry changes
    man["map_variants"][name] = {"config": _plain(vcfg), "files": files}
    mf.write_json_atomic(mf.manifest_path(dataset_dir), man)
    return name


def load_variant(dataset_dir: str | os.PathLike, variant: str, cities) -> dict:
    """``{city: maps.CityRaster}`` of a stored variant; :class:`VariantError` names what is
    missing."""
    from seglocnet_jax import maps

    man = mf.read_manifest(dataset_dir)
    if variant not in man["map_variants"]:
        raise VariantError(
            f"{mf.manifest_path(dataset_dir)}: map variant {variant!r} is not prepared (have "
            f"{sorted(man['map_variants'])}); run data.prepare / ensure_variant for it"
        )
    out = {}
    for city in cities:
        path = variant_path(dataset_dir, variant, city)
        if not os.path.exists(path):
            raise VariantError(f"{path}: raster of city {city!r} for variant {variant!r} missing")
        out[city] = maps.CityRaster.load(path)
    return out


def _plain(vcfg: VariantConfig) -> dict:
    d = dataclasses.asdict(vcfg)
    d["channels"] = list(d["channels"])
    return d
