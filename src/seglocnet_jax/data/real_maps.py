"""Cached HD / SD map rasters of a converted real dataset, with the OSM similarity correction.

Per city: OSM comes from the user's extract (``ConvertConfig.osm[city]``), read through the
dataset's own map frame (``reader.projection(city)``: nuScenes topocentric about the map origin,
Argoverse UTM minus the city origin) and clipped to the drivable area's surroundings. A
similarity correction (:mod:`.real_align`) is fitted once per city by correlating the dataset's
drivable area with the OSM road raster, stored in the manifest (``alignment``) and applied to
every OSM geometry. HD = drivable area + corrected OSM buildings; SD = corrected OSM centrelines
buffered to ``road_width`` + buildings. Rasters land in ``maps/<variant>/<city>.npz``
(:func:`.variants.variant_path`: the dataset's city names are the keys) and
``manifest.map_variants`` exactly as :mod:`.variants` writes them, so the loader reads both the
same way.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
from shapely import affinity

from seglocnet_jax import fileio, geometry, maps
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import real_align as ra
from seglocnet_jax.data.real_common import RealDataError
from seglocnet_jax.data.variants import variant_path

# OSM is read this far (m) around the drivable area: a tile (64 m) around a prior (32 m) plus
# the largest alignment shift must stay inside the map.
CONTEXT_MARGIN = 128.0


def _bbox_lonlat(projection, bounds, margin: float) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = bounds
    xs = np.array([x0, x1, x0, x1]) + np.array([-1, 1, -1, 1]) * margin
    ys = np.array([y0, y0, y1, y1]) + np.array([-1, -1, 1, 1]) * margin
    lon, lat = projection.to_lonlat(xs, ys)
    return float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max())


def city_geometry(reader, city: str, cfg, drivable) -> maps.CityGeometry:
    """The city's OSM in the dataset frame, clipped around ``drivable``; without an extract in
    ``cfg.osm`` an empty geometry (HD road-only maps still work)."""
    projection = reader.projection(city)
    margin = CONTEXT_MARGIN + cfg.align.max_shift
    path = (cfg.osm or {}).get(city)
    if path is None:
        b = drivable.bounds
        bounds = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
        return maps.CityGeometry(city, projection, (), (), bounds, "")
    if not os.path.isfile(path):
        raise RealDataError(
            f"{path}: OSM extract of {city!r} (dataset.convert.osm.{city}) is missing"
        )
    bbox = _bbox_lonlat(projection, drivable.bounds, margin)
    geom = maps.load_city(path, projection=projection, bbox=bbox)
    return dataclasses.replace(geom, name=city)


def fit_alignment(
    city: maps.CityGeometry, drivable, cfg: ra.AlignConfig, progress: bool = True
) -> ra.Similarity:
    """Similarity moving ``city``'s OSM roads onto ``drivable`` (identity when disabled)."""
    if not cfg.enabled or not city.roads:
        c = drivable.centroid
        return ra.Similarity(centre=(float(c.x), float(c.y)))
    grid = geometry.RasterGrid.covering(drivable.bounds, margin=cfg.max_shift + 2 * cfg.band)
    target = maps.rasterize_geometries(drivable, grid)  # (H, W)
    source = maps.rasterize_geometries(list(maps.buffer_roads(city, cfg.road_width)), grid)
    return ra.fit_similarity(target, source, grid, cfg, progress=progress)


def apply_alignment(city: maps.CityGeometry, sim: ra.Similarity) -> maps.CityGeometry:
    """``city`` with every road and building moved by ``sim`` (bounds follow)."""
    params = sim.shapely_params()
    roads = tuple(
        dataclasses.replace(r, geometry=affinity.affine_transform(r.geometry, params))
        for r in city.roads
    )
    buildings = tuple(
        dataclasses.replace(b, geometry=affinity.affine_transform(b.geometry, params))
        for b in city.buildings
    )
    x0, y0, x1, y1 = city.bounds
    corners = sim.apply(np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]]))
    bounds = (*corners.min(0).tolist(), *corners.max(0).tolist())
    return dataclasses.replace(city, roads=roads, buildings=buildings, bounds=bounds)


def ensure_real_variants(
    dataset_dir: str, reader, cfg, poses: dict | None = None, progress: bool = True
) -> dict:
    """Fits (or reuses) each city's alignment and writes the missing variant rasters.

    Returns ``{city: alignment report}`` (shift m, rotation deg, scale, score, OSM path), also
    stored in ``manifest.alignment``. A stored alignment fitted with another
    ``dataset.convert.align`` config is refused, naming the keys; one fitted from another OSM
    extract (or none) is fitted again and the OSM-dependent rasters of the city are redrawn.
    With ``poses`` (city -> ``(N, 3)``), the report adds ``poses_on_road``: per variant, the
    fraction of poses on its road channel (HD: ~1 for real ego poses; SD: a check of the OSM
    correction).
    """
    man = mf.read_manifest(dataset_dir)
    cities = sorted({c for s in man["splits"].values() for c in s["cities"]})
    align_cfg = _plain_align(cfg.align)
    stored = man.get("alignment")
    if stored is not None:
        diff = mf.config_diff(stored["config"], align_cfg, "dataset.convert.align")
        if diff:
            raise mf.ManifestError(
                f"{mf.manifest_path(dataset_dir)}: maps were aligned with "
                f"another config: {'; '.join(diff)}; use a new directory"
            )
    reports = dict((stored or {}).get("cities", {}))
    vcfgs = [maps.MapConfig(**spec) for spec in cfg.map_variants]
    for city in cities:
        paths = {v.name: variant_path(dataset_dir, v.name, city) for v in vcfgs}
        osm_path = (cfg.osm or {}).get(city)
        # A stored fit is reused only for the same OSM extract (none: identity, refit later).
        reuse = city in reports and reports[city].get("osm") == osm_path
        if reuse and all(os.path.exists(p) for p in paths.values()):
            continue
        drivable = reader.drivable(city)
        osm = city_geometry(reader, city, cfg, drivable)
        sim = (
            ra.Similarity.from_dict(reports[city])
            if reuse
            else fit_alignment(osm, drivable, cfg.align, progress)
        )
        if not reuse:  # rasters drawn with another correction are stale
            for v in vcfgs:
                if os.path.exists(paths[v.name]) and (v.kind == "sd" or "building" in v.channels):
                    os.remove(paths[v.name])
        reports[city] = dict(sim.as_dict(), osm=osm_path)
        osm = apply_alignment(osm, sim)
        for v in vcfgs:
            if os.path.exists(paths[v.name]):
                continue
            needs_osm = v.kind == "sd" or "building" in v.channels
            if needs_osm and not (cfg.osm or {}).get(city):
                raise RealDataError(
                    f"map variant {v.name!r} of {city!r} needs OSM: set "
                    f"dataset.convert.osm.{city} to an .osm.pbf / .osm extract"
                )
            raster = maps.rasterize(osm, v, drivable=drivable if v.kind == "hd" else None)
            raster.save(paths[v.name])  # atomic
            if poses is not None and city in poses and "road" in v.channels:
                on_road = reports[city].setdefault("poses_on_road", {})
                on_road[v.name] = drivable_fraction(raster, np.asarray(poses[city]))
        man = mf.read_manifest(dataset_dir)  # re-read: only our entries change
        man["alignment"] = {"config": align_cfg, "cities": reports}
        for v in vcfgs:
            entry = man["map_variants"].setdefault(v.name, {"config": v.to_dict(), "files": {}})
            entry["files"][city] = os.path.relpath(paths[v.name], dataset_dir)
        fileio.write_json_atomic(mf.manifest_path(dataset_dir), man)
    return reports


def _plain_align(cfg: ra.AlignConfig) -> dict:
    d = dataclasses.asdict(cfg)
    d["scales"] = [float(s) for s in d["scales"]]
    return d


def drivable_fraction(raster: maps.CityRaster, poses: np.ndarray) -> float:
    """Fraction of ``poses (N, 3)`` whose position falls on the raster's road channel."""
    road = raster.mask[raster.channels.index("road")]
    row, col = raster.grid.world_to_pixel(poses[:, 0], poses[:, 1])
    row, col = np.floor(row).astype(int), np.floor(col).astype(int)
    inside = (row >= 0) & (row < road.shape[0]) & (col >= 0) & (col < road.shape[1])
    hit = np.zeros(len(poses), bool)
    hit[inside] = road[row[inside], col[inside]] > 0
    return float(hit.mean()) if len(hit) else float("nan")
