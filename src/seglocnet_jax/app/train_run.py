"""The train run: prepare data, train with periodic validation and checkpoints, resume, and
evaluate the final splits with the best checkpoint into the paper's table (``eval.mode``:
single frames, whole drives through the sequential filter, or both). Every evaluation
(validation, best selection, tables, figures) goes through one cached localize step
(:func:`seglocnet_jax.evaluation.make_localize_step`)."""

from __future__ import annotations

import os
import time

import jax
import numpy as np
from tqdm import tqdm

from seglocnet_jax import evaluation, sequential
from seglocnet_jax.app import evalset, runs
from seglocnet_jax.app.datasets import prepare_dataset, reads_osm_classes
from seglocnet_jax.app.schema import ExperimentConfig
from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.data import manifest as manifest_lib
from seglocnet_jax.model import api as model_api
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import state as state_lib
from seglocnet_jax.training import step as step_lib
from seglocnet_jax.training.logger import MetricsLogger

progress = runs.progress

# An NM model's validation IoU (percent) of any segmentation class below this is reported as a
# collapsed segmentation term for that class (a warning line, not an error: its matching
# features may still localize, but its BEV no longer segments that class, unlike the paper's
# NM trained with both terms).
NM_MIN_IOU = 5.0


def warn_collapsed_segmentation(cfg: ExperimentConfig, val: dict, step: int) -> str | None:
    """Prints (and returns) the warning of an NM model whose validation ``IoU_<class>`` is below
    :data:`NM_MIN_IOU` for one class or more, naming each; None otherwise (a seg model, no IoU,
    every class healthy)."""
    collapsed = {
        key.removeprefix("IoU_"): iou
        for key, iou in val.items()
        if key.startswith("IoU_") and iou is not None and iou < NM_MIN_IOU
    }
    if cfg.model.variant != "nm" or not collapsed:
        return None
    listed = ", ".join(f"{name} {iou:.1f} %" for name, iou in collapsed.items())
    msg = (
        f"[seglocnet] warning: NM model at step {step}: validation IoU {listed} < "
        f"{NM_MIN_IOU:g} %: its segmentation term has collapsed for "
        f"{'this class' if len(collapsed) == 1 else 'these classes'} (the BEV no longer "
        "segments it; the pose loss alone drives it). Consider a larger model.seg_weight"
    )
    print(msg, flush=True)
    return msg


def init_state(cfg: ExperimentConfig, example_batch: dict):
    """The initial train state (same for any mesh: params come from the seed only)."""
    optimizer = state_lib.make_optimizer(cfg.train.optim_config())
    init_key, train_key = jax.random.split(jax.random.key(cfg.train.seed))
    params = model_api.init(init_key, example_batch, cfg.model)
    return state_lib.TrainState.create(params, optimizer, train_key), optimizer


class Evaluator:
    """Split evaluation of one run: loaders made once per split, one localize step."""

    def __init__(self, cfg: ExperimentConfig, dataset_dir: str, mesh, workdir: str):
        # the training mesh's devices, or on CPU its first device (step_lib.evaluation_mesh)
        self.mesh = step_lib.evaluation_mesh(mesh)
        self.cfg, self.dataset_dir, self.workdir = cfg, dataset_dir, workdir
        self.step = evaluation.make_localize_step(cfg.model, cfg.solver, cfg.eval.bev_source)
        self._loaders = {}
        self.seconds = 0.0
        self.rounds = 0
        self.final_seconds = {}  # the final evaluation's phases (:meth:`final`)

    def loader(self, split: str):
        if split not in self._loaders:
            self._loaders[split] = loader_lib.make_loader(
                self.dataset_dir,
                split,
                self.cfg.map.name,
                self.cfg.eval.batch_size,
                self.cfg.train.seed,
                train=False,
                config=self.cfg.loader,
                nm_tiles=self.step.reads_nm_tile,
            )
        return self._loaders[split]

    def final_splits(self) -> list[str]:
        """Every split the final evaluation (``eval.mode``) reads."""
        ev = self.cfg.eval
        names = list(ev.splits) if ev.single else []
        if ev.sequential:
            names += ev.tracked_splits()
            if ev.temperature is None:
                names.append(ev.temperature_split)
                names += [ev.temperature_drives] if ev.temperature_drives else []
        return list(dict.fromkeys(names))

    def verify(self) -> None:
        """Checks every split of the final evaluation (record counts, each shard's SHA-256)
        before any work: a damaged shard of the last split read stops the run at its start."""
        man = manifest_lib.read_manifest(self.dataset_dir)
        for split in self.final_splits():
            manifest_lib.verify_split(man, self.dataset_dir, split)

    def replicate(self, params):
        """``params`` replicated on the evaluation mesh (None stays None: the GT BEV)."""
        return None if params is None else step_lib.replicate(params, self.mesh)

    def place(self, batch: dict) -> dict:
        # Evaluation loaders are not sharded: every process reads the whole batch (the metrics
        # compare device outputs with the host rows of the whole batch).
        return step_lib.device_batch(batch, self.mesh, process_local=False)

    def __call__(
        self, params, splits, *, max_batches=None, num_figures=0, tag="", out_dir=None
    ) -> dict:
        t0 = time.time()
        params = self.replicate(params)  # e.g. a training state's, sharded on the train mesh
        out = {}
        for split in splits:
            ld = self.loader(split)
            n = ld.batches_per_epoch
            n = n if max_batches is None else min(max_batches, n)
            out[split] = evaluation.evaluate_split(
                self.step,
                params,
                iter(ld),
                num_batches=n,
                place=self.place,
                desc=f"eval {split}{tag}",
                channels=self.cfg.map.channels,
                figure_dir=os.path.join(out_dir or self.workdir, "figures", split)
                if num_figures
                else None,
                num_figures=num_figures,
            )
        self.seconds += time.time() - t0
        self.rounds += 1
        return out

    def sequential(self, params, out_dir: str) -> dict:
        """Tracks the drives of ``eval.sequential_splits`` (and the calibration split) through
        the same localize step; ``{split: summary}`` (:mod:`seglocnet_jax.sequential`); arrays
        and figures under ``out_dir``."""
        ev = self.cfg.eval

        def temperature_batches():
            ld = self.loader(ev.temperature_split)
            n = ld.batches_per_epoch
            return iter(ld), n if ev.max_batches is None else min(ev.max_batches, n)

        t0 = time.time()
        out = sequential.evaluate_sequential(
            self.step,
            params,
            dataset_dir=self.dataset_dir,
            map_variant=self.cfg.map.name,
            channels=self.cfg.map.channels,
            loader_cfg=self.cfg.loader,
            eval_cfg=ev,
            num_rotations=self.cfg.solver.num_rotations,
            place=self.place,
            temperature_batches=temperature_batches,
            output_dir=out_dir,
        )
        runs.progress(f"sequential evaluation: {time.time() - t0:.0f} s")
        return out

    def final(self, params, out_dir: str, logger=None, step: int = 0) -> tuple[dict, dict | None]:
        """The final evaluation of ``eval.mode``: ``(single-frame results by split, sequential
        results by split or None)``, logged to ``logger`` at ``step``; figures and arrays under
        ``out_dir`` (an :class:`evalset.OutputSet`'s staging directory)."""
        ev = self.cfg.eval
        self.verify()
        results = {}
        t0 = time.time()
        if ev.single:
            results = self(
                params,
                ev.splits,
                max_batches=ev.max_batches,
                num_figures=ev.num_figures,
                out_dir=out_dir,
            )
        self.final_seconds = {"single_frame_s": round(time.time() - t0, 1)}
        seq = None
        if ev.sequential:
            t0 = time.time()
            seq = self.sequential(params, out_dir)
            self.final_seconds["sequential_s"] = round(time.time() - t0, 1)
        if logger is not None:
            for split, res in results.items():
                logger.write(step, split, res)
            for split, res in (seq or {}).items():
                logger.write(step, f"{split}_sequential", sequential.scalars(res))
        return results, seq


def train_and_evaluate(cfg: ExperimentConfig, workdir: str) -> dict:
    """Runs the whole experiment in ``workdir``; resumes its latest checkpoint when the stored
    config defines the same run (else stops naming the keys; ``train.restart=true`` starts
    over, keeping the old checkpoints aside)."""
    ckpt_lib.check_path(os.path.abspath(os.path.join(workdir, "checkpoints")))
    with runs.RunDir(workdir, cfg, "training run") as run:
        run.check_identity(cfg.train.restart)
        return _train(cfg, run)


def _train(cfg: ExperimentConfig, run: runs.RunDir) -> dict:
    workdir = run.workdir
    t_start = time.time()
    dataset_dir = prepare_dataset(cfg)
    t_data = time.time() - t_start
    mesh = step_lib.make_mesh(cfg.train.num_devices)
    # Each process reads and decodes only its rows of every global batch (all in one process).
    train_loader = loader_lib.make_loader(
        dataset_dir,
        "train",
        cfg.map.name,
        cfg.train.batch_size,
        cfg.train.seed,
        train=True,
        config=cfg.loader,
        shard_options=loader_lib.ShardOptions(*step_lib.batch_shard(mesh)),
        nm_tiles=reads_osm_classes(cfg),
    )
    example = next(iter(train_loader))
    state, optimizer = init_state(cfg, step_lib.device_batch(example, mesh))
    data_iter = iter(train_loader)
    ckpt = ckpt_lib.Checkpointer(workdir, cfg.train.checkpoint)
    try:
        restored = ckpt.restore_latest(jax.device_get(state))
    except ckpt_lib.CheckpointError:
        if not cfg.train.restart:
            raise
        ckpt.close()
        run.archive("the unusable checkpoints")
        run.write_config()
        ckpt = ckpt_lib.Checkpointer(workdir, cfg.train.checkpoint)
        restored = None
    if restored is not None:
        state, data_state, step0 = restored
        data_iter.set_state(data_state)
        progress(f"resumed from {ckpt.last_dir}/{step0}")
    elif cfg.train.init_from:  # fine-tuning: parameters only; fresh optimizer, step 0
        source, source_step = ckpt_lib.restore_params(cfg.train.init_from, jax.device_get(state))
        state = state.replace(params=source.params)
        progress(f"initialized parameters from {cfg.train.init_from} (step {source_step})")
    state = step_lib.replicate(state, mesh)
    step = int(state.step)

    train_step = step_lib.make_train_step(model_api.make_loss_fn(cfg.model), optimizer, mesh)
    logger = MetricsLogger(workdir, enabled=jax.process_index() == 0, resume_step=step)
    evaluate = Evaluator(cfg, dataset_dir, mesh, workdir)
    evaluate.verify()  # the final evaluation's splits, before training
    t_train0 = time.time()
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
                raise FloatingPointError(
                    f"loss is {scalars['loss']} at step {step} (run {workdir}); lower "
                    "train.optim.learning_rate or check the data"
                )
            rate = (step - n_last) * cfg.train.batch_size / max(time.time() - t_last, 1e-9)
            t_last, n_last = time.time(), step
            scalars["samples_per_s"] = rate
            bar.set_postfix(loss=f"{scalars['loss']:.4f}", sps=f"{rate:.1f}")
            logger.write(step, "train", scalars)
        val = None
        periodic = cfg.train.eval_every and step % cfg.train.eval_every == 0
        if periodic or step == cfg.train.num_steps:
            tag = f" @{step}" if step < cfg.train.num_steps else " final"
            val = evaluate(state.params, ["val"], max_batches=cfg.train.val_batches, tag=tag)
            val = val["val"]
            logger.write(step, "val", val)
            warn_collapsed_segmentation(cfg, val, step)
        if (
            step % cfg.train.checkpoint.every_steps == 0
            or val is not None
            or step == cfg.train.num_steps
        ):
            ckpt.save(step, jax.device_get(state), data_iter.get_state(), metrics=val)
    bar.close()
    ckpt.close()
    t_loop = time.time() - t_train0
    times = {
        "data_preparation_s": t_data,
        "training_s": t_loop - evaluate.seconds,
        "validation_s": evaluate.seconds,
    }
    return _final_evaluation(
        cfg, evaluate, ckpt.best_dir, jax.device_get(state), logger, step, times, t_start
    )


def _final_evaluation(cfg, evaluate, best_dir, target, logger, step, times, t_start) -> dict:
    """The final splits, evaluated with the best checkpoint by validation (as ``evaluate``
    does), written as one set (:class:`evalset.OutputSet`) with the run's timing."""
    best, best_step = ckpt_lib.restore_params(best_dir, target)
    progress(
        f"evaluating the best checkpoint by validation {cfg.train.checkpoint.best_metric}: "
        f"step {best_step}"
    )
    t_final0 = time.time()
    out = evalset.OutputSet(evaluate.workdir, evalset.TRAIN_ITEMS)
    staging = out.open()
    try:
        params = evaluate.replicate(best.params)
        results, seq = evaluate.final(params, staging, logger, step)
        logger.close()
        timing = {k: round(v, 1) for k, v in times.items()}
        timing["final_evaluation_s"] = round(time.time() - t_final0, 1)
        timing.update(evaluate.final_seconds)
        timing["total_s"] = round(time.time() - t_start, 1)
        extra = {"steps": step, "best_step": best_step, "time": timing}
        if seq is not None:
            extra["sequential"] = seq
        runs.write_results(staging, cfg, results, extra)
    except BaseException:
        out.abandon()
        raise
    out.commit()
    print(runs.format_table(cfg, results, seq), flush=True)
    progress(
        "time: data preparation {data_preparation_s:.0f} s, training {training_s:.0f} s, "
        "validation {validation_s:.0f} s, final evaluation {final_evaluation_s:.0f} s{final}, "
        "total {total_s:.0f} s".format(final=_final_phases(timing, seq), **timing)
    )
    return results


def _final_phases(timing: dict, seq: dict | None) -> str:
    """`` (single-frame 55 s, sequential 730 s: temperature 388 s, drives 339 s)``: the final
    evaluation's phases for the printed time line (the sequential part split into the
    temperature's fit and choice and each tracked split's own pass)."""
    parts = [f"single-frame {timing['single_frame_s']:.0f} s"]
    if seq:
        fit = next(iter(seq.values())).get("temperature_fit_s")
        inner = [f"temperature {fit:.0f} s"] if fit else []
        inner += [f"{name} {res['seconds']:.0f} s" for name, res in seq.items()]
        parts.append(f"sequential {timing['sequential_s']:.0f} s: " + ", ".join(inner))
    return f" ({', '.join(parts)})"
