"""``python -m seglocnet_jax.evaluate [+exp=NAME] checkpoint=PATH``: metrics JSON, the table and
figures of the evaluation splits. ``eval.bev_source=gt`` gives the GT-segmentation upper bound
and needs no checkpoint. Logic: ``app.eval_run``."""

import hydra
from omegaconf import DictConfig

from seglocnet_jax.app import hydra_glue

hydra_glue.register_resolvers()


@hydra.main(version_base="1.3", config_path=hydra_glue.conf_dir(), config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from seglocnet_jax.app.eval_run import run_evaluation
    from seglocnet_jax.app.schema import build_experiment

    hydra_glue.quiet_library_logs()
    hydra_glue.maybe_initialize_distributed()
    tree = hydra_glue.to_tree(cfg)
    checkpoint = tree.pop("checkpoint", None)
    run_evaluation(build_experiment(tree), checkpoint, HydraConfig.get().runtime.output_dir)


if __name__ == "__main__":
    main()
