"""The evaluate run: restore a checkpoint (none for the GT upper bound), evaluate
``eval.splits`` with figures and/or track the drives of ``eval.sequential_splits``
(``eval.mode``) through the same localize step as training, write ``results.json`` and print
the tables.

An evaluation directory has an identity, like a training run's: ``config.json`` beside
``results.json`` records the whole config and the checkpoint evaluated (its run directory,
step and checksum, :class:`training.checkpoint.CheckpointRef`). Every split is verified (record
counts, each shard's SHA-256) before any work. The set (config, results, per-frame arrays,
figures) is written whole (:class:`evalset.OutputSet`): a previous evaluation in the directory
is moved aside when the new one is complete, and the keys in which they differ are printed; a
training run's directory is refused.
"""

from __future__ import annotations

import json
import os
import time

import jax

from seglocnet_jax import fileio
from seglocnet_jax.app import evalset, runs
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.schema import ExperimentConfig
from seglocnet_jax.app.train_run import Evaluator, init_state
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import step as step_lib

# What does not change an evaluation's numbers: the training schedule (the checkpoint's
# identity stands for the model), devices, threads, where the data lives.
NOT_DEFINING = (
    "train",
    "loader.num_threads",
    "loader.prefetch",
    "loader.worker_count",
    "data.root",
    "dataset.convert.root",
    "dataset.reader.dataroot",
)


def checkpoint_ref(cfg: ExperimentConfig, checkpoint: str | None) -> ckpt_lib.CheckpointRef | None:
    """The checkpoint step an evaluation restores (None for the GT upper bound); the errors
    name ``checkpoint=`` before any work."""
    if cfg.eval.bev_source == "model" and not checkpoint:
        raise ckpt_lib.CheckpointError(
            "checkpoint=PATH is required with eval.bev_source=model (a run directory, its "
            "checkpoints/best, or one step directory); eval.bev_source=gt needs none"
        )
    if checkpoint and not os.path.exists(checkpoint):
        raise ckpt_lib.CheckpointError(f"checkpoint={os.path.abspath(checkpoint)!r} does not exist")
    return ckpt_lib.resolve(checkpoint) if cfg.eval.bev_source == "model" else None


def run_evaluation(
    cfg: ExperimentConfig,
    checkpoint: str | None,
    workdir: str,
    overrides: list[str] | None = None,
) -> dict:
    """The ``evaluate`` app; returns ``{split: metrics}``. ``overrides``: the command line's
    (recorded in ``config.json``)."""
    ref = checkpoint_ref(cfg, checkpoint)
    if checkpoint:
        runs.check_checkpoint_compatible(checkpoint, cfg)  # before any data work
    identity = {
        "evaluation": {
            "checkpoint": None if ref is None else ref.to_dict(),
            "overrides": None if overrides is None else list(overrides),
        },
        "config": runs.config_dict(cfg),
        "written": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    with runs.RunDir(workdir, cfg, "evaluation") as run:
        _refuse_training_run(run.workdir)
        out = evalset.OutputSet(run.workdir, evalset.EVAL_ITEMS)
        staging = out.open()
        try:
            _announce_previous(run.workdir, identity)
            fileio.write_json_atomic(os.path.join(staging, evalset.RUN_CONFIG), identity)
            results, seq = _evaluate(cfg, ref, staging)
        except BaseException:
            out.abandon()
            raise
        out.commit()
    print(runs.format_table(cfg, results, seq), flush=True)
    runs.progress(
        f"wrote {os.path.join(run.workdir, evalset.RESULTS)} and figures under "
        f"{os.path.join(run.workdir, evalset.FIGURES)}"
    )
    return results


def _refuse_training_run(workdir: str) -> None:
    stored = _read_config(workdir)
    if os.path.isdir(os.path.join(workdir, "checkpoints")) or (
        stored is not None and "evaluation" not in stored
    ):
        raise ConfigError(
            f"{workdir} is a training run's directory (checkpoints/ or its {evalset.RUN_CONFIG});"
            " an evaluation writes its own config.json, results.json and figures: evaluate into "
            "another directory (the default one, or hydra.run.dir=PATH)"
        )


def _read_config(workdir: str) -> dict | None:
    path = os.path.join(workdir, evalset.RUN_CONFIG)
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as err:
        raise ConfigError(
            f"{path}: unreadable ({err}); move it away if you know what it is"
        ) from err


def identity_diff(stored: dict, current: dict) -> list[str]:
    """``key: stored -> now`` lines of two evaluations' ``config.json`` (config and checkpoint)."""
    diff = runs.config_diff(stored["config"], current["config"], skip=NOT_DEFINING)
    a = stored["evaluation"].get("checkpoint") or {}
    b = current["evaluation"].get("checkpoint") or {}
    for key in ("run_dir", "step", "checksum"):
        if a.get(key) != b.get(key):
            diff.append(f"checkpoint.{key}: {a.get(key)!r} -> {b.get(key)!r}")
    return diff


def _announce_previous(workdir: str, identity: dict) -> None:
    """Says what the directory holds and that it will be moved aside, with the differing keys."""
    present = evalset.OutputSet(workdir, evalset.EVAL_ITEMS).present()
    if not present:
        return
    stored = _read_config(workdir)
    if stored is None:
        what = "an evaluation without config.json (written before evaluations recorded one)"
    else:
        diff = identity_diff(stored, identity)
        what = (
            "an evaluation of another config or checkpoint (stored -> now):\n  " + "\n  ".join(diff)
            if diff
            else "an evaluation of the same config and checkpoint"
        )
    runs.progress(
        f"{workdir} holds {what}\nit is moved aside to {evalset.DISCARDED}.discarded-<time> "
        "when this evaluation is complete (choose another directory with hydra.run.dir=PATH)"
    )


def _evaluate(cfg: ExperimentConfig, ref, out_dir: str) -> tuple[dict, dict | None]:
    dataset_dir = prepare_dataset(cfg)
    mesh = step_lib.make_mesh(cfg.train.num_devices)
    evaluate = Evaluator(cfg, dataset_dir, mesh, out_dir)
    evaluate.verify()  # every split it reads, before any work
    params, step = None, None
    if ref is not None:
        for step_dir, reason in ref.skipped:
            print(f"WARNING: checkpoint {step_dir} is corrupt or incomplete: {reason}", flush=True)
        example = evaluate.place(next(iter(evaluate.loader(cfg.eval.splits[0]))))
        target, _ = init_state(cfg, example)
        state, step = ckpt_lib.restore_params(ref.step_dir, jax.device_get(target))
        params = evaluate.replicate(state.params)
        runs.progress(f"restored {ref.step_dir} (step {step}, {ref.checksum[:19]}...)")
    results, seq = evaluate.final(params, out_dir)
    extra = {"checkpoint": None if ref is None else ref.step_dir, "step": step}
    if seq is not None:
        extra["sequential"] = seq
    runs.write_results(out_dir, cfg, results, extra)
    return results, seq
