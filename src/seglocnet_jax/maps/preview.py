"""``python -m seglocnet_jax.maps.preview [map=sd] [map.city=PATH] [map.road_width=5]
[+preview.tile=[x,y]] [+preview.seed=0] [hydra.run.dir=OUT]``: writes PNGs of a city's binary
map and of one 256x256 tile (default: the city centre) into the Hydra run directory.

HD maps draw the simulator world's drivable area (seeded by ``preview.seed``), as the embedded
simulator's HD map does; SD maps need only OSM.
"""

import hydra
from omegaconf import DictConfig

from seglocnet_jax import hydra_app

hydra_app.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_app.conf_dir(), config_name="config")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax import maps
    from seglocnet_jax.maps.render import write_preview

    tree = hydra_app.to_tree(cfg)
    preview = tree.get("preview") or {}
    source, map_cfg = maps.configs_from_section(tree.get("map"))
    city = source.load()
    drivable = None
    if map_cfg.kind == "hd" and "road" in map_cfg.channels:
        from seglocnet_jax.sim.world import build_world  # the simulator's world is the HD map

        drivable = build_world(city, seed=int(preview.get("seed", 0))).drivable
    raster = maps.rasterize(city, map_cfg, drivable=drivable)
    out_dir = preview.get("out_dir") or HydraConfig.get().runtime.output_dir
    paths = write_preview(
        raster, out_dir, preview.get("tile"), prefix=f"{raster.name}_{map_cfg.kind}"
    )
    print(
        f"{city.name}: {len(city.roads)} roads, {len(city.buildings)} buildings, raster "
        f"{raster.mask.shape} -> {paths['city']}, {paths['tile']}"
    )


if __name__ == "__main__":
    main()
