"""``python -m seglocnet_jax.train [+exp=NAME] [overrides]``: train, validate, checkpoint,
resume, and print the paper-style table of the final splits. Logic: ``app.train_run``."""

import hydra
from omegaconf import DictConfig, OmegaConf

from seglocnet_jax.app import allocator, hydra_glue

allocator.keep_freed_memory()  # before JAX starts: XLA reuses its buffers

hydra_glue.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_glue.conf_dir(), config_name="config")
def main(cfg: DictConfig) -> None:
    # first: nothing may start JAX before (the config checks below do)
    hydra_glue.cpu_device_per_core(OmegaConf.select(cfg, "train.batch_size"))
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax.app.schema import build_experiment
    from seglocnet_jax.app.train_run import train_and_evaluate

    hydra_glue.quiet_library_logs()
    hydra_glue.maybe_initialize_distributed()
    exp = build_experiment(hydra_glue.to_tree(cfg))
    train_and_evaluate(exp, HydraConfig.get().runtime.output_dir)


if __name__ == "__main__":
    main()
