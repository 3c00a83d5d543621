"""``python -m seglocnet_jax.train [+exp=NAME] [overrides]``: train, validate, checkpoint,
resume, and print the paper-style table of the test split(s). Logic: ``training.loop``."""

import hydra
from omegaconf import DictConfig

from seglocnet_jax import hydra_app

hydra_app.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_app.conf_dir(), config_name="config")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax.experiment import build_experiment
    from seglocnet_jax.training.loop import train_and_evaluate

    hydra_app.quiet_library_logs()
    hydra_app.maybe_initialize_distributed()
    exp = build_experiment(hydra_app.to_tree(cfg))
    train_and_evaluate(exp, HydraConfig.get().runtime.output_dir)


if __name__ == "__main__":
    main()
