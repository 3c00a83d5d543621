"""Map variants of a prepared dataset: cached city rasters, one npz per city and variant.

A variant (:class:`seglocnet_jax.maps.MapConfig`: HD; SD with road width w; a channel set) is a
rasterization of the cities' maps. It is stored once as ``maps/<variant name>/<city key>.npz``
(:func:`variant_path`; the city key is :func:`seglocnet_jax.maps.city_key`) and recorded in the
manifest; sensors are never re-simulated for a new variant. Tiles and GT BEVs are cut on the fly
from the cached raster by the loader instead of being stored per frame: cutting is a slice (tile)
plus a nearest-neighbour gather (BEV), well under a millisecond, and the evaluation priors are
stored, so the result is identical to stored tiles at a fraction of the disk (a 256x256x2 tile
per frame and variant).

The neural map's input, the multi-class OSM raster
(:func:`seglocnet_jax.maps.rasterize_osm_classes`), is stored the same way, once per city
whatever the map variant: ``maps/osm_classes/<city>.npz``
(:func:`osm_classes_path`), recorded under the manifest's ``osm_classes`` key with the class
table it was drawn with (:func:`seglocnet_jax.maps.osm_classes.spec`; a raster drawn with another
table is drawn again). It is made only for datasets an NM model reads (:func:`ensure_osm_classes`
for the simulator's, the conversion for real data, with its OSM alignment).
"""

from __future__ import annotations

import os
from collections.abc import Callable

from seglocnet_jax import fileio, maps
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.maps import MapConfig, osm_classes

OSM_CLASSES = "osm_classes"  # the directory under maps/ and the manifest key


class VariantError(ValueError):
    """A map variant is missing or inconsistent; the message names the variant and file."""


def _check_plain(what: str, value) -> None:
    if (
        not isinstance(value, str)
        or value in ("", ".", "..")
        or os.path.isabs(value)
        or any(sep in value for sep in ("/", "\\", os.sep, os.altsep) if sep)
    ):
        hint = (
            "; name a city by maps.city_key(city): 'helsinki', or '<file stem>-<hash>' for an "
            "OSM file"
            if what == "city"
            else ""
        )
        raise VariantError(
            f"{what} {value!r} is not a plain key (a name without path separators, not a "
            f"path){hint}"
        )


def variant_path(dataset_dir: str | os.PathLike, variant: str, city: str) -> str:
    """``<dataset_dir>/maps/<variant>/<city>.npz``; ``city`` must be a city key
    (:func:`seglocnet_jax.maps.city_key`), never a path: :class:`VariantError` otherwise."""
    _check_plain("map variant", variant)
    _check_plain("city", city)
    return os.path.join(os.fspath(dataset_dir), "maps", variant, f"{city}.npz")


def city_sources(man: dict) -> dict[str, str]:
    """``{city key: city as configured}`` (an embedded name or an OSM path) of a simulator
    dataset's manifest (``config.city`` / ``config.test_city``); a configured OSM file that is
    gone is left out (its key cannot be computed)."""
    config = man.get("config") or {}
    out = {}
    for spec in (config.get("city"), config.get("test_city")):
        if not spec:
            continue
        try:
            out[maps.city_key(spec)] = spec
        except maps.MapError:
            continue
    return out


def _rasterize(cfg: MapConfig, city: str, drivable):
    return maps.rasterize(maps.load_city(city), cfg, drivable=drivable)


def _same_config(stored: dict, cfg: MapConfig) -> bool:
    try:
        return MapConfig(**stored).same_map(cfg)
    except (TypeError, ValueError):
        return False


def ensure_variant(
    dataset_dir: str | os.PathLike,
    cfg: MapConfig,
    source_factory: Callable | None = None,
    sources: dict | None = None,
    cities: dict[str, str] | None = None,
) -> str:
    """Rasterizes and stores variant ``cfg`` for every city of the dataset unless already there;
    returns the variant name.

    Args:
      dataset_dir: the prepared dataset directory (its manifest lists the city keys).
      cfg: the map variant.
      source_factory: ``source_factory(city) -> FrameSource`` with ``.drivable`` (shapely
        geometry, world metres), called with the city as configured (name or OSM path); HD maps
        need it unless ``sources`` holds the city. SD maps only read OSM.
      sources: frame sources already built, by city key (reused; new ones are added).
      cities: ``{city key: city as configured}``; None: :func:`city_sources` of the manifest.
    """
    man = mf.read_manifest(dataset_dir)
    name = cfg.name
    keys = sorted({c for s in man["splits"].values() for c in s["cities"]})
    entry = man["map_variants"].get(name)
    if entry is not None:
        if not _same_config(entry["config"], cfg):
            raise VariantError(
                f"{mf.manifest_path(dataset_dir)}: variant {name!r} was stored "
                f"with {entry['config']}, now {cfg.to_dict()}"
            )
        if all(os.path.exists(variant_path(dataset_dir, name, c)) for c in keys):
            return name
    sources = {} if sources is None else sources
    specs = city_sources(man) if cities is None else dict(cities)
    files = {}
    for key in keys:
        path = variant_path(dataset_dir, name, key)
        files[key] = os.path.relpath(path, dataset_dir)
        if os.path.exists(path):
            continue
        spec = specs.get(key, key)
        if spec == key and key.lower() not in maps.EMBEDDED_CITIES:
            raise VariantError(
                f"{path}: cannot rasterize city {key!r} for variant {name!r}: it is neither an "
                f"embedded city nor the key of a configured OSM file (configured: "
                f"{specs or 'none'}); was the OSM file moved or edited after preparation?"
            )
        drivable = None
        if cfg.kind == "hd" and "road" in cfg.channels:
            if key not in sources:
                if source_factory is None:
                    raise VariantError(
                        f"HD variant {name!r} of {key!r} needs the world's "
                        "drivable area: pass source_factory"
                    )
                sources[key] = source_factory(spec)
            drivable = sources[key].drivable
        _rasterize(cfg, spec, drivable).save(path)
    man = mf.read_manifest(dataset_dir)  # re-read: only this entry changes
    old = man["map_variants"].get(name)
    man["map_variants"][name] = {"config": old["config"] if old else cfg.to_dict(), "files": files}
    fileio.write_json_atomic(mf.manifest_path(dataset_dir), man)
    return name


def load_variant(dataset_dir: str | os.PathLike, variant: str, cities) -> dict:
    """``{city key: maps.CityRaster}`` of a stored variant; :class:`VariantError` names what is
    missing or corrupt and the remedy."""
    man = mf.read_manifest(dataset_dir)
    if variant not in man["map_variants"]:
        raise VariantError(
            f"{mf.manifest_path(dataset_dir)}: map variant {variant!r} is not prepared (have "
            f"{sorted(man['map_variants'])}); run data.simulated.prepare / ensure_variant for it"
        )
    out = {}
    for city in cities:
        path = variant_path(dataset_dir, variant, city)
        if not os.path.exists(path):
            raise VariantError(f"{path}: raster of city {city!r} for variant {variant!r} missing")
        try:
            out[city] = maps.CityRaster.load(path)
        except maps.MapError as err:
            raise VariantError(
                f"{path}: cached raster of city {city!r} for variant {variant!r} is unreadable "
                f"({err}); delete the file: the next data preparation (training start or "
                "data_prep/) rasterizes it again"
            ) from err
    return out


def osm_classes_path(dataset_dir: str | os.PathLike, city: str) -> str:
    """``<dataset_dir>/maps/osm_classes/<city>.npz`` (``city``: a city key)."""
    return variant_path(dataset_dir, OSM_CLASSES, city)


def osm_classes_current(man: dict) -> bool:
    """Whether the manifest's OSM class rasters were drawn with this code's class table."""
    entry = man.get(OSM_CLASSES)
    return isinstance(entry, dict) and entry.get("config") == osm_classes.spec()


def osm_classes_ready(dataset_dir: str | os.PathLike, man: dict | None = None) -> bool:
    """Whether every city of the dataset has its OSM class raster, drawn with this code's
    class table."""
    man = mf.read_manifest(dataset_dir) if man is None else man
    keys = {c for s in man["splits"].values() for c in s["cities"]}
    return osm_classes_current(man) and all(
        os.path.exists(osm_classes_path(dataset_dir, c)) for c in keys
    )


def record_osm_classes(dataset_dir: str | os.PathLike, files: dict[str, str]) -> None:
    """Records ``{city key: path relative to the dataset}`` of OSM class rasters drawn with
    this code's class table in the manifest (re-read: only this entry changes; the other
    cities' files are kept when the table is the same)."""
    man = mf.read_manifest(dataset_dir)
    old = man.get(OSM_CLASSES) if osm_classes_current(man) else None
    man[OSM_CLASSES] = {
        "config": osm_classes.spec(),
        "files": {**((old or {}).get("files") or {}), **files},
    }
    fileio.write_json_atomic(mf.manifest_path(dataset_dir), man)


def ensure_osm_classes(dataset_dir: str | os.PathLike, cities: dict[str, str] | None = None):
    """Rasterizes and stores the OSM class raster of every city of a simulator dataset unless
    there (drawn with this code's class table); sensors are not touched.

    Args:
      dataset_dir: the prepared dataset directory.
      cities: ``{city key: city as configured}``; None: :func:`city_sources` of the manifest.

    A converted real dataset gets its class rasters from the conversion (through the city's
    OSM alignment): :class:`VariantError` names the remedy.
    """
    man = mf.read_manifest(dataset_dir)
    if osm_classes_ready(dataset_dir, man):
        return
    if "alignment" in man:
        raise VariantError(
            f"{mf.manifest_path(dataset_dir)}: a converted dataset's OSM class rasters (the "
            "neural map's input) are drawn by the conversion with its OSM alignment: run the "
            "training or conversion with dataset=..., not data.source"
        )
    current = osm_classes_current(man)
    keys = sorted({c for s in man["splits"].values() for c in s["cities"]})
    specs = city_sources(man) if cities is None else dict(cities)
    files = {}
    for key in keys:
        path = osm_classes_path(dataset_dir, key)
        files[key] = os.path.relpath(path, dataset_dir)
        if current and os.path.exists(path):
            continue
        spec = specs.get(key, key)
        if spec == key and key.lower() not in maps.EMBEDDED_CITIES:
            raise VariantError(
                f"{path}: cannot rasterize the OSM classes of city {key!r}: it is neither an "
                f"embedded city nor the key of a configured OSM file (configured: "
                f"{specs or 'none'}); was the OSM file moved or edited after preparation?"
            )
        maps.rasterize_osm_classes(maps.load_city(spec)).save(path)  # atomic
    record_osm_classes(dataset_dir, files)


def load_osm_classes(dataset_dir: str | os.PathLike, cities) -> dict:
    """``{city key: maps.CityRaster}`` of the stored OSM class rasters (the NM model's map
    input); :class:`VariantError` names what is missing, stale or corrupt and the remedy."""
    man = mf.read_manifest(dataset_dir)
    remedy = (
        "the training or evaluation of an NM model (model.variant=nm) prepares it; or "
        "data.variants.ensure_osm_classes"
    )
    if OSM_CLASSES not in man:
        raise VariantError(
            f"{mf.manifest_path(dataset_dir)}: the OSM class rasters are not prepared; {remedy}"
        )
    if not osm_classes_current(man):
        raise VariantError(
            f"{mf.manifest_path(dataset_dir)}: the OSM class rasters were drawn with another "
            f"class table ({man[OSM_CLASSES].get('config', {}).get('channels')}, now "
            f"{list(osm_classes.OSM_CLASS_NAMES)}); {remedy} draws them again"
        )
    out = {}
    for city in cities:
        path = osm_classes_path(dataset_dir, city)
        if not os.path.exists(path):
            raise VariantError(f"{path}: OSM class raster of city {city!r} missing; {remedy}")
        try:
            raster = maps.CityRaster.load(path)
        except maps.MapError as err:
            raise VariantError(
                f"{path}: cached OSM class raster of city {city!r} is unreadable ({err}); "
                f"delete the file: {remedy}"
            ) from err
        if raster.channels != osm_classes.OSM_CLASS_NAMES:
            raise VariantError(
                f"{path}: channels {raster.channels} are not the class table's "
                f"{osm_classes.OSM_CLASS_NAMES}; delete the file: {remedy}"
            )
        out[city] = raster
    return out
