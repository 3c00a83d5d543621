"""The preview app: PNGs of a city's binary map and of one 256x256 tile (default: the city
centre). HD maps draw the simulator world's drivable area (seeded by ``preview.seed``), as the
embedded simulator's HD map does; SD maps need only OSM. Config: ``conf/preview.yaml``
(``source``: :class:`maps.CitySource`, ``map``: :class:`maps.MapConfig`, ``preview``)."""

from __future__ import annotations

import dataclasses

from seglocnet_jax import maps
from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.maps.render import write_preview


@dataclasses.dataclass(frozen=True)
class PreviewConfig:
    """Attributes: tile: world ``[x, y]`` metres of the tile centre (None: the city centre);
    seed: the simulator world's seed (HD drivable area)."""

    tile: tuple[float, float] | None = None
    seed: int = 0


def run_preview(tree: dict, out_dir: str) -> dict:
    unknown = sorted(set(tree) - {"source", "map", "preview"})
    if unknown:
        raise ConfigError(
            f"unknown top-level config key(s) {unknown}; preview accepts source, map, preview"
        )
    source = from_dict(maps.CitySource, tree.get("source"), "source")
    map_cfg = from_dict(maps.MapConfig, tree.get("map"), "map")
    preview = from_dict(PreviewConfig, tree.get("preview"), "preview")
    city = source.load()
    drivable = None
    if map_cfg.kind == "hd" and "road" in map_cfg.channels:
        from seglocnet_jax.sim.world import build_world  # the simulator's world is the HD map

        drivable = build_world(city, seed=preview.seed).drivable
    raster = maps.rasterize(city, map_cfg, drivable=drivable)
    paths = write_preview(raster, out_dir, preview.tile, prefix=f"{raster.name}_{map_cfg.kind}")
    print(
        f"{city.name}: {len(city.roads)} roads, {len(city.buildings)} buildings, raster "
        f"{raster.mask.shape} -> {paths['city']}, {paths['tile']}"
    )
    return paths
