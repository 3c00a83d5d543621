"""Cached HD / SD map rasters of a converted real dataset, with the OSM similarity correction.

Per city: OSM comes from the user's extract (``ConvertConfig.osm[city]``), read through the
dataset's own map frame (``reader.projection(city)``: nuScenes topocentric about the map origin,
Argoverse UTM minus the city origin) and clipped to the drivable area's surroundings. A
similarity correction (:mod:`.align_fit`) is fitted once per city by correlating the dataset's
drivable area with the OSM road raster in windows on the city's frames (rasterized per window,
never for the whole city), checked (a degenerate fit is refused, naming the remedies), stored in
the manifest (``alignment``: the values, their quality per city and per window) and applied to
every OSM geometry; ``dataset.convert.align.manual`` gives a city's correction by hand.
HD = drivable area + corrected OSM buildings; SD = corrected OSM centrelines
buffered to ``road_width`` + buildings. Rasters land in ``maps/<variant>/<city>.npz``
(:func:`..variants.variant_path`: the dataset's city names are the keys) and
``manifest.map_variants`` exactly as :mod:`..variants` writes them, so the loader reads both the
same way. For an NM model, the multi-class OSM raster of the corrected OSM
(:func:`seglocnet_jax.maps.rasterize_osm_classes`) lands in ``maps/osm_classes/<city>.npz`` and
the manifest's ``osm_classes`` the same way.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import shapely
from shapely import affinity

from seglocnet_jax import fileio, geometry, maps
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import variants as variants_lib
from seglocnet_jax.data.real.align_fit import fit_windows
from seglocnet_jax.data.real.align_windows import (
    downsample,
    fine_factor,
    place_windows,
    window_grids,
)
from seglocnet_jax.data.real.alignment import (
    AlignConfig,
    Alignment,
    AlignmentError,
    Similarity,
    Window,
)
from seglocnet_jax.data.real.common import RealDataError
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


def _window(drivable, roads, tree, centre, frames, cfg: AlignConfig) -> Window:
    """The fit window around ``centre``: drivable area and OSM roads drawn at a fine resolution
    (<= 0.5 m) and block-averaged to ``cfg.resolution``."""
    t_grid, _, s_grid = window_grids(centre, cfg)
    f = fine_factor(cfg)

    def draw(geoms, grid):
        fine = geometry.RasterGrid(
            grid.x_min, grid.y_max, grid.height * f, grid.width * f, grid.resolution / f
        )
        return downsample(maps.rasterize_geometries(geoms, fine), fine, f)[0]

    target = draw(shapely.clip_by_rect(drivable, *t_grid.bounds), t_grid)
    near = roads[tree.query(shapely.box(*s_grid.bounds))] if len(roads) else []
    return Window(target, t_grid, draw(list(near), s_grid), s_grid, frames)


def fit_alignment(
    city: maps.CityGeometry,
    drivable,
    cfg: AlignConfig,
    progress: bool = True,
    points=None,
    check: bool = True,
) -> Alignment:
    """The correction moving ``city``'s OSM roads onto ``drivable``, with its quality.

    Identity when ``cfg.enabled`` is false or the city has no OSM extract; ``cfg.manual[name]``
    when given; else fitted in windows on ``points (N, 2)`` (the city's frame positions; None:
    the drivable area's outline) by :func:`.align_fit.fit_windows`, which refuses a degenerate
    fit (:class:`.alignment.AlignmentError`) unless ``check`` is false.
    """
    name = city.name
    c = drivable.centroid
    if not cfg.enabled:
        return Alignment.identity(name, "disabled", (c.x, c.y))
    if name in cfg.manual:
        return Alignment.manual(name, cfg.manual[name])
    if not city.source:
        return Alignment.identity(name, "no_osm", (c.x, c.y))
    if points is None:
        points = shapely.get_coordinates(drivable.boundary)
    placed, unchecked = place_windows(np.asarray(points, np.float64)[:, :2], cfg)
    roads = maps.buffer_roads(city, cfg.road_width) if city.roads else np.array([], object)
    tree = shapely.STRtree(roads)
    windows = [_window(drivable, roads, tree, xy, n, cfg) for xy, n in placed]
    return fit_windows(windows, cfg, name, progress, check, unchecked)


def apply_alignment(city: maps.CityGeometry, sim: Similarity) -> maps.CityGeometry:
    """``city`` with every road, building, other way and area moved by ``sim`` (bounds
    follow)."""
    params = sim.shapely_params()

    def moved(features):
        return tuple(
            dataclasses.replace(f, geometry=affinity.affine_transform(f.geometry, params))
            for f in features
        )

    x0, y0, x1, y1 = city.bounds
    corners = sim.apply(np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]]))
    bounds = (*corners.min(0).tolist(), *corners.max(0).tolist())
    return dataclasses.replace(
        city,
        roads=moved(city.roads),
        buildings=moved(city.buildings),
        ways=moved(city.ways),
        areas=moved(city.areas),
        bounds=bounds,
    )


def ensure_real_variants(
    dataset_dir: str,
    reader,
    cfg,
    poses: dict | None = None,
    progress: bool = True,
    *,
    osm_classes: bool = False,
) -> dict:
    """Fits (or reuses) each city's alignment and writes the missing variant rasters (with
    ``osm_classes``, also each city's OSM class raster, the NM model's map input; it needs the
    city's OSM extract).

    Returns ``{city: alignment report}`` (:meth:`.alignment.Alignment.report`: shift m,
    rotation deg, scale, score, method, quality, windows; plus the OSM path and the manual
    entry), also stored in ``manifest.alignment``. The fit windows lie on ``poses`` (city ->
    ``(N, 3)``; without, on the drivable area). Every city that needs a fit is fitted before
    anything is drawn or stored, and refused fits raise one :class:`.alignment.AlignmentError`
    naming each city, so a changed search config can be tried on the same directory. A stored
    alignment fitted with another ``dataset.convert.align`` config (:data:`.alignment.FIT_KEYS`)
    is refused, naming the keys; one fitted from another OSM extract (or none), or with another
    ``manual`` entry, is fitted again and the OSM-dependent rasters of the city are redrawn.
    With ``poses``, the report adds ``poses_on_road``: per variant, the fraction of poses on its
    road channel (HD: ~1 for real ego poses; SD: a check of the OSM correction).
    """
    man = mf.read_manifest(dataset_dir)
    cities = sorted({c for s in man["splits"].values() for c in s["cities"]})
    align_cfg = cfg.align.identity()
    unknown = sorted(set(cfg.align.manual) - set(cities))
    if unknown:
        raise RealDataError(
            f"dataset.convert.align.manual names {unknown}, not cities of this dataset ({cities})"
        )
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
    classes = variants_lib.OSM_CLASSES
    if osm_classes and not variants_lib.osm_classes_current(man):  # another class table
        for city in cities:
            if os.path.exists(variants_lib.osm_classes_path(dataset_dir, city)):
                os.remove(variants_lib.osm_classes_path(dataset_dir, city))
    todo = []  # (city, paths, drivable, OSM geometry, alignment report, refitted)
    errors = []
    for city in cities:
        paths = {v.name: variant_path(dataset_dir, v.name, city) for v in vcfgs}
        if osm_classes:
            paths[classes] = variants_lib.osm_classes_path(dataset_dir, city)
        osm_path = (cfg.osm or {}).get(city)
        manual = cfg.align.manual.get(city)
        # A stored fit is reused only for the same OSM extract (none: identity, refit later)
        # and the same manual entry.
        old = reports.get(city)
        reuse = old is not None and old.get("osm") == osm_path and old.get("manual") == manual
        if reuse and all(os.path.exists(p) for p in paths.values()):
            continue
        drivable = reader.drivable(city)
        osm = city_geometry(reader, city, cfg, drivable)
        if reuse:
            todo.append((city, paths, drivable, osm, dict(old), False))
            continue
        points = None if poses is None or city not in poses else np.asarray(poses[city])
        alignment = fit_alignment(osm, drivable, cfg.align, progress, points, check=False)
        if alignment.problems:
            errors.append(alignment.error())
            continue
        report = dict(alignment.report(), osm=osm_path, manual=manual)
        todo.append((city, paths, drivable, osm, report, True))
    if errors:
        raise errors[0] if len(errors) == 1 else AlignmentError("\n".join(map(str, errors)))
    for city, paths, drivable, osm, report, refitted in todo:
        if refitted:  # rasters drawn with another correction are stale
            for v in vcfgs:
                if os.path.exists(paths[v.name]) and (v.kind == "sd" or "building" in v.channels):
                    os.remove(paths[v.name])
            if classes in paths and os.path.exists(paths[classes]):
                os.remove(paths[classes])
        reports[city] = report
        osm = apply_alignment(osm, Similarity.from_dict(report))
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
        if classes in paths:
            _ensure_osm_classes(dataset_dir, city, paths[classes], osm, cfg)
        man = mf.read_manifest(dataset_dir)  # re-read: only our entries change
        man["alignment"] = {"config": align_cfg, "checks": cfg.align.checks(), "cities": reports}
        for v in vcfgs:
            entry = man["map_variants"].setdefault(v.name, {"config": v.to_dict(), "files": {}})
            entry["files"][city] = os.path.relpath(paths[v.name], dataset_dir)
        fileio.write_json_atomic(mf.manifest_path(dataset_dir), man)
    return reports


def _ensure_osm_classes(dataset_dir: str, city: str, path: str, osm, cfg) -> None:
    """Draws the city's OSM class raster (the NM model's map input) at ``path`` unless it is
    there, from the aligned ``osm``, and records it in the manifest."""
    if not os.path.exists(path):
        if not (cfg.osm or {}).get(city):
            raise RealDataError(
                f"the OSM class raster of {city!r} (the neural map's input, "
                f"model.variant=nm) needs OSM: set dataset.convert.osm.{city} to an "
                ".osm.pbf / .osm extract"
            )
        maps.rasterize_osm_classes(osm).save(path)  # atomic
    variants_lib.record_osm_classes(dataset_dir, {city: os.path.relpath(path, dataset_dir)})


def drivable_fraction(raster: maps.CityRaster, poses: np.ndarray) -> float:
    """Fraction of ``poses (N, 3)`` whose position falls on the raster's road channel."""
    road = raster.mask[raster.channels.index("road")]
    row, col = raster.grid.world_to_pixel(poses[:, 0], poses[:, 1])
    row, col = np.floor(row).astype(int), np.floor(col).astype(int)
    inside = (row >= 0) & (row < road.shape[0]) & (col >= 0) & (col < road.shape[1])
    hit = np.zeros(len(poses), bool)
    hit[inside] = road[row[inside], col[inside]] > 0
    return float(hit.mean()) if len(hit) else float("nan")
