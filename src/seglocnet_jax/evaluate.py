"""``python -m seglocnet_jax.evaluate [+exp=NAME] checkpoint=PATH``: metrics JSON, the table and
figures of the evaluation splits. ``eval.bev_source=gt`` gives the GT-segmentation upper bound
and needs no checkpoint. The default directory names the checkpoint (run and step) and the
settings that change the numbers (conf/evaluate.yaml). Logic: ``app.eval_run``."""

import hydra
from omegaconf import DictConfig

from seglocnet_jax.app import allocator, hydra_glue

allocator.keep_freed_memory()  # before JAX starts: XLA reuses its buffers

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
    hc = HydraConfig.get()
    overrides = [str(o) for o in hc.overrides.task]
    run_evaluation(build_experiment(tree), checkpoint, hc.runtime.output_dir, overrides)


if __name__ == "__main__":
    main()
