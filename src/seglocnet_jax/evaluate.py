"""``python -m seglocnet_jax.evaluate [+exp=NAME] checkpoint=PATH``: metrics JSON, the table and
figures of the evaluation splits. ``eval.bev_source=gt`` gives the GT-segmentation upper bound
and needs no checkpoint. Logic: ``evaluation`` and ``training.loop``."""

import hydra
from omegaconf import DictConfig

from seglocnet_jax import hydra_app

hydra_app.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_app.conf_dir(), config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax.experiment import build_experiment
    from seglocnet_jax.training.loop import run_evaluation

    hydra_app.quiet_library_logs()
    hydra_app.maybe_initialize_distributed()
    tree = hydra_app.to_tree(cfg)
    checkpoint = tree.pop("checkpoint", None)
    run_evaluation(build_experiment(tree), checkpoint, HydraConfig.get().runtime.output_dir)


if __name__ == "__main__":
    main()
