"""Prepares the simulator dataset: sensors once, then the map variants.

    python data_prep/prepare_sim.py                       # data=quick, map=hd (conf/config.yaml)
    python data_prep/prepare_sim.py data=full
    python data_prep/prepare_sim.py map=sd map.road_width=5   # adds one SD variant, no re-render

The logic lives in ``seglocnet_jax.data.prepare``; an interrupted run resumes where it stopped.
"""

import hydra
from omegaconf import DictConfig

from seglocnet_jax import hydra_app
from seglocnet_jax.config_util import from_dict
from seglocnet_jax.data.prepare import PrepareConfig, prepare_for_training
from seglocnet_jax.data.variants import VariantConfig

hydra_app.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_app.conf_dir(), config_name="config")
def main(cfg: DictConfig) -> None:
    tree = hydra_app.to_tree(cfg)
    prep = from_dict(PrepareConfig, tree["data"], "data")
    variant = from_dict(
        VariantConfig, {k: tree["map"][k] for k in ("kind", "road_width", "channels")}, "map"
    )
    dataset_dir, name = prepare_for_training(prep, variant)
    print(f"dataset: {dataset_dir} (map variant {name})")


if __name__ == "__main__":
    main()
