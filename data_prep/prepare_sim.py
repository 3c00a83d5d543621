"""Prepares the simulator dataset: sensors once, then the map variants.

    python data_prep/prepare_sim.py                       # data=quick, map=hd (conf/config.yaml)
    python data_prep/prepare_sim.py data=full
    python data_prep/prepare_sim.py map=sd map.road_width=5   # adds one SD variant, no re-render

The logic lives in ``seglocnet_jax.data.simulated.prepare``; an interrupted run resumes where it
stopped.
"""

import hydra
from omegaconf import DictConfig

from seglocnet_jax.app import allocator, hydra_glue

allocator.keep_freed_memory()  # before JAX starts: XLA reuses its buffers

hydra_glue.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_glue.conf_dir(), config_name="config")
def main(cfg: DictConfig) -> None:
    from seglocnet_jax.app.datasets import prepare_dataset
    from seglocnet_jax.app.schema import build_experiment

    exp = build_experiment(hydra_glue.to_tree(cfg))  # the same config and path as `train`
    dataset_dir = prepare_dataset(exp)
    print(f"dataset: {dataset_dir} (map variants: {exp.map.name} and data.map_variants)")


if __name__ == "__main__":
    main()
