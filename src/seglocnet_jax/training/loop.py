"""``train_and_evaluate``: prepare data, train with periodic validation and checkpoints, resume,
and evaluate the test split(s) into the paper's table."""

from __future__ import annotations

import dataclasses
import json
import os
import time

import jax
import numpy as np
from tqdm import tqdm

from seglocnet_jax import evaluation, metrics
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.experiment import ExperimentConfig, prepare_dataset
from seglocnet_jax.model import api as model_api
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import state as state_lib
from seglocnet_jax.training import step as step_lib
from seglocnet_jax.training.logger import MetricsLogger


def _progress(msg: str):
    print(f"[seglocnet] {msg}", flush=True)


def init_state(cfg: ExperimentConfig, example_batch: dict, mesh):
    """The initial train state (same for any mesh: params come from the seed only)."""
    optimizer = state_lib.make_optimizer(cfg.train.optim_config())
    key = jax.random.key(cfg.train.seed)
    init_key, train_key = jax.random.split(key)
    params = model_api.init(init_key, example_batch, cfg.model)
    return state_lib.TrainState.create(params, optimizer, train_key), optimizer


def make_bev_fn(cfg: ExperimentConfig, params, mesh):
    """``batch -> (logits, probs)`` for evaluation, from the network or the GT labels."""
    if cfg.eval.bev_source == "gt":
        return evaluation.gt_bev_fn

    @jax.jit
    def predict(params, batch):
        logits, _ = model_api.forward(params, batch, cfg.model)
        return logits, jax.nn.sigmoid(logits)

    def bev_fn(batch):
        logits, probs = predict(params, step_lib.device_batch(batch, mesh))
        return np.asarray(logits), np.asarray(probs)

    return bev_fn


def evaluate_splits(
    cfg: ExperimentConfig,
    dataset_dir: str,
    bev_fn,
    workdir: str,
    splits,
    *,
    max_batches=None,
    num_figures: int = 0,
    tag: str = "",
) -> dict:
    """Metrics per split (paper keys); figures under ``<workdir>/figures/<split>``."""
    results = {}
    for split in splits:
        ld = loader_lib.make_loader(
            dataset_dir,
            split,
            cfg.variant.name,
            cfg.eval.batch_size,
            cfg.train.seed,
            train=False,
            config=cfg.loader,
        )
        n = ld.batches_per_epoch if max_batches is None else min(max_batches, ld.batches_per_epoch)
        results[split] = evaluation.evaluate_loader(
            iter(ld),
            bev_fn,
            cfg.solver,
            num_batches=n,
            desc=f"eval {split}{tag}",
            figure_dir=os.path.join(workdir, "figures", split) if num_figures else None,
            num_figures=num_figures,
            channels=cfg.variant.channels,
        )
    return results


def write_results(workdir: str, cfg: ExperimentConfig, results: dict, extra: dict) -> str:
    """``<workdir>/results.json`` (atomic) and the printed paper-style table."""
    path = os.path.join(workdir, "results.json")
    payload = {
        "experiment": cfg.name,
        "variant": cfg.variant.name,
        "bev_source": cfg.eval.bev_source,
        "splits": results,
        **extra,
    }
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2)
    os.replace(tmp, path)
    return path


def format_table(cfg: ExperimentConfig, results: dict) -> str:
    rows = []
    for split, res in results.items():
        rows.append((f"{cfg.name} [{cfg.variant.name}, {cfg.eval.bev_source}] {split}", res))
        if "prior" in res:
            rows.append((f"prior alone (tile centre, no heading) {split}", res["prior"]))
    return metrics.markdown_table(rows)


def train_and_evaluate(cfg: ExperimentConfig, workdir: str) -> dict:
    """Runs the whole experiment in ``workdir``; resumes from its latest checkpoint."""
    os.makedirs(workdir, exist_ok=True)
    t_start = time.time()
    dataset_dir = prepare_dataset(cfg)
    mesh = step_lib.make_mesh(cfg.train.num_devices)
    train_loader = loader_lib.make_loader(
        dataset_dir,
        "train",
        cfg.variant.name,
        cfg.train.batch_size,
        cfg.train.seed,
        train=True,
        config=cfg.loader,
    )
    example = next(iter(train_loader))
    state, optimizer = init_state(cfg, step_lib.device_batch(example, mesh), mesh)
    ckpt = ckpt_lib.Checkpointer(workdir, cfg.train.checkpoint)
    data_iter = iter(train_loader)
    restored = ckpt.restore_latest(jax.device_get(state))
    if restored is not None:
        state, data_state, step0 = restored
        data_iter.set_state(data_state)
        _progress(f"resumed from {ckpt.last_dir}/{step0}")
    elif cfg.train.init_from:  # fine-tuning: parameters only; fresh optimizer, step 0
        source, source_step = ckpt_lib.restore_params(cfg.train.init_from, jax.device_get(state))
        state = state.replace(params=source.params)
        _progress(f"initialized parameters from {cfg.train.init_from} (step {source_step})")
    state = step_lib.replicate(state, mesh)

    def loss_fn(params, batch, rng):
        return model_api.loss_fn(params, batch, cfg.model, rng)

    train_step = step_lib.make_train_step(loss_fn, optimizer, mesh)
    logger = MetricsLogger(workdir, enabled=jax.process_index() == 0)

    step = int(state.step)
    bar = tqdm(total=cfg.train.num_steps, initial=step, desc="train", unit="step")
    t_last, n_last = time.time(), step
    while step < cfg.train.num_steps:
        batch = next(data_iter)
        state, m = train_step(state, step_lib.device_batch(batch, mesh))
        step += 1
        bar.update(1)
        if step % cfg.train.log_every == 0 or step == cfg.train.num_steps:
            scalars = step_lib.to_host(m)
            if not np.isfinite(scalars["loss"]):
                raise FloatingPointError(f"loss is {scalars['loss']} at step {step}")
            rate = (step - n_last) * cfg.train.batch_size / max(time.time() - t_last, 1e-9)
            t_last, n_last = time.time(), step
            scalars["samples_per_s"] = rate
            bar.set_postfix(loss=f"{scalars['loss']:.4f}", sps=f"{rate:.1f}")
            logger.write(step, "train", scalars)
        val = None
        if cfg.train.eval_every and step % cfg.train.eval_every == 0 and step < cfg.train.num_steps:
            val = evaluate_splits(
                cfg,
                dataset_dir,
                make_bev_fn(cfg, state.params, mesh),
                workdir,
                ["val"],
                max_batches=cfg.train.val_batches,
                tag=f" @{step}",
            )
            logger.write(step, "val", val["val"])
            val = val["val"]
        if step % cfg.train.checkpoint.every_steps == 0 or val is not None:
            ckpt.save(step, jax.device_get(state), data_iter.get_state(), metrics=val)
    bar.close()
    val = evaluate_splits(
        cfg,
        dataset_dir,
        make_bev_fn(cfg, state.params, mesh),
        workdir,
        ["val"],
        max_batches=cfg.train.val_batches,
        tag=" final",
    )["val"]
    logger.write(step, "val", val)
    ckpt.save(step, jax.device_get(state), data_iter.get_state(), metrics=val)
    ckpt.close()
    train_time = time.time() - t_start
    # The test split is evaluated with the best checkpoint by validation (as `evaluate` does).
    best, best_step = ckpt_lib.restore_params(ckpt.best_dir, jax.device_get(state))
    _progress(
        f"evaluating the best checkpoint by validation {cfg.train.checkpoint.best_metric}: "
        f"step {best_step}"
    )
    params = step_lib.replicate(best.params, mesh)
    results = evaluate_splits(
        cfg,
        dataset_dir,
        make_bev_fn(cfg, params, mesh),
        workdir,
        cfg.eval.splits,
        max_batches=cfg.eval.max_batches,
        num_figures=cfg.eval.num_figures,
    )
    for split, res in results.items():
        logger.write(step, split, res)
    logger.close()
    write_results(
        workdir,
        cfg,
        results,
        {
            "steps": step,
            "best_step": best_step,
            "wall_time_s": time.time() - t_start,
            "train_time_s": train_time,
            "config": dataclasses.asdict(cfg),
        },
    )
    table = format_table(cfg, results)
    print(table, flush=True)
    return results


def run_evaluation(cfg: ExperimentConfig, checkpoint: str | None, workdir: str) -> dict:
    """The ``evaluate`` app: restores ``checkpoint`` (not needed for the GT upper bound),
    evaluates ``cfg.eval.splits`` with figures, writes ``results.json`` and prints the table."""
    os.makedirs(workdir, exist_ok=True)
    if cfg.eval.bev_source == "model" and not checkpoint:
        raise ckpt_lib.CheckpointError(
            "checkpoint=PATH is required with eval.bev_source=model (a run directory, its "
            "checkpoints/best, or one step directory); eval.bev_source=gt needs none"
        )
    dataset_dir = prepare_dataset(cfg)
    mesh = step_lib.make_mesh(cfg.train.num_devices)
    params, step = None, None
    if cfg.eval.bev_source == "model":
        ld = loader_lib.make_loader(
            dataset_dir,
            cfg.eval.splits[0],
            cfg.variant.name,
            cfg.eval.batch_size,
            cfg.train.seed,
            train=False,
            config=cfg.loader,
        )
        example = step_lib.device_batch(next(iter(ld)), mesh)
        target, _ = init_state(cfg, example, mesh)
        state, step = ckpt_lib.restore_params(checkpoint, jax.device_get(target))
        params = step_lib.replicate(state.params, mesh)
        _progress(f"restored {checkpoint} (step {step})")
    results = evaluate_splits(
        cfg,
        dataset_dir,
        make_bev_fn(cfg, params, mesh),
        workdir,
        cfg.eval.splits,
        max_batches=cfg.eval.max_batches,
        num_figures=cfg.eval.num_figures,
    )
    path = write_results(workdir, cfg, results, {"checkpoint": checkpoint, "step": step})
    print(format_table(cfg, results), flush=True)
    _progress(f"wrote {path} and figures under {os.path.join(workdir, 'figures')}")
    return results
