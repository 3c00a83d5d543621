"""``python -m seglocnet_jax.preview [map=sd] [source.city=PATH] [map.road_width=5]
[preview.tile=[x,y]] [preview.seed=0] [hydra.run.dir=OUT]``: PNGs of a city's binary map and of
one 256x256 tile. Logic: ``app.preview``."""

import hydra
from omegaconf import DictConfig

from seglocnet_jax.app import hydra_glue

hydra_glue.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_glue.conf_dir(), config_name="preview")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax.app.preview import run_preview

    tree = hydra_glue.to_tree(cfg)
    run_preview(tree, HydraConfig.get().runtime.output_dir)


if __name__ == "__main__":
    main()
