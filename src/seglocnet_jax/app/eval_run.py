"""The evaluate run: restore a checkpoint (none for the GT upper bound), evaluate
``eval.splits`` with figures and/or track the drives of ``eval.sequential_splits``
(``eval.mode``) through the same localize step as training, write ``results.json`` and print
the tables."""

from __future__ import annotations

import os

import jax

from seglocnet_jax.app import runs
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.schema import ExperimentConfig
from seglocnet_jax.app.train_run import Evaluator, init_state
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import step as step_lib


def run_evaluation(cfg: ExperimentConfig, checkpoint: str | None, workdir: str) -> dict:
    """The ``evaluate`` app; returns ``{split: metrics}``."""
    if cfg.eval.bev_source == "model" and not checkpoint:
        raise ckpt_lib.CheckpointError(
            "checkpoint=PATH is required with eval.bev_source=model (a run directory, its "
            "checkpoints/best, or one step directory); eval.bev_source=gt needs none"
        )
    if checkpoint:
        if not os.path.exists(checkpoint):
            raise ckpt_lib.CheckpointError(
                f"checkpoint={os.path.abspath(checkpoint)!r} does not exist"
            )
        runs.check_checkpoint_compatible(checkpoint, cfg)  # before any data work
    with runs.RunDir(workdir, cfg, "evaluation") as run:
        return _evaluate(cfg, checkpoint, run.workdir)


def _evaluate(cfg: ExperimentConfig, checkpoint: str | None, workdir: str) -> dict:
    dataset_dir = prepare_dataset(cfg)
    mesh = step_lib.make_mesh(cfg.train.num_devices)
    evaluate = Evaluator(cfg, dataset_dir, mesh, workdir)
    params, step = None, None
    if cfg.eval.bev_source == "model":
        example = evaluate.place(next(iter(evaluate.loader(cfg.eval.splits[0]))))
        target, _ = init_state(cfg, example)
        state, step = ckpt_lib.restore_params(checkpoint, jax.device_get(target))
        params = step_lib.replicate(state.params, mesh)
        runs.progress(f"restored {checkpoint} (step {step})")
    results, seq = evaluate.final(params)
    extra = {"checkpoint": os.path.abspath(checkpoint) if checkpoint else None, "step": step}
    if seq is not None:
        extra["sequential"] = seq
    path = runs.write_results(workdir, cfg, results, extra)
    print(runs.format_table(cfg, results, seq), flush=True)
    runs.progress(f"wrote {path} and figures under {os.path.join(workdir, 'figures')}")
    return results
