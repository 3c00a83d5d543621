"""Late fusion of a camera-only and a LiDAR-only checkpoint: how much does the camera-only
model's BEV add to the LiDAR-only model's, when both are trained on their own?

A diagnostic for the fused model (not a method of the paper, whose fusion is of BEV features):
for every frame, the BEV logits of the two single-modality networks are combined as
``lidar + w * camera`` (logits add: independent evidence multiplies the odds) and localized by
the same solver as every evaluation (:func:`seglocnet_jax.evaluation.make_localize_step`), for
each weight ``w`` (``w = 0`` is the LiDAR-only model alone). Choose ``w`` on ``val``; look at
the test splits once, with the weight chosen there.

    python experiments/late_fusion.py --camera CAMERA_RUN_DIR --lidar LIDAR_RUN_DIR \\
        --weights 0 0.25 0.5 1 --splits val [--overrides +budget=cpu ...]

Both checkpoints must match the network the overrides (plus ``model.modality``) build; the data
are the default config's (the simulator's dataset under ``data_cache/``, prepared on first use).
Progress goes to stderr; the last stdout line is JSON: per split and weight, the paper's
recalls, APE / AOE and R@1m on the night frames.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys

import jax
import numpy as np
from tqdm import tqdm

from seglocnet_jax import evaluation, metrics, solver
from seglocnet_jax.app import hydra_glue, runs
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.schema import ExperimentConfig, build_experiment
from seglocnet_jax.app.train_run import Evaluator, init_state
from seglocnet_jax.training import checkpoint as ckpt_lib
from seglocnet_jax.training import step as step_lib

KEYS = ("R@1m", "R@2m", "R@5m", "R@10m", "R@1deg", "R@5deg", "APE", "AOE", "count")


def app_config(overrides=()) -> ExperimentConfig:
    """The apps' config for ``overrides`` (Hydra's compose over ``conf/``)."""
    from hydra import compose, initialize_config_dir

    hydra_glue.register_resolvers()
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        return build_experiment(hydra_glue.to_tree(compose("config", overrides=list(overrides))))


def restore(cfg: ExperimentConfig, checkpoint: str, evaluator: Evaluator, example: dict):
    """The parameters of ``checkpoint``, checked against ``cfg``'s network, on the evaluation
    mesh; and the step restored."""
    runs.check_checkpoint_compatible(checkpoint, cfg)
    target, _ = init_state(cfg, example)
    state, step = ckpt_lib.restore_params(checkpoint, jax.device_get(target))
    return evaluator.replicate(state.params), step


def frames(evaluator: Evaluator, split: str, max_batches: int | None = None):
    """The first ``max_batches`` batches of ``split`` (None: all), with a progress bar:
    ``(batch, placed, valid, gt)``: the host batch, the batch on the evaluation mesh, the rows
    that are frames (not padding) and their GT poses ``(n, 3)``."""
    ld = evaluator.loader(split)
    total = ld.batches_per_epoch if max_batches is None else min(max_batches, ld.batches_per_epoch)
    batches = itertools.islice(iter(ld), total)
    for batch in tqdm(batches, total=total, desc=split, unit="batch"):
        valid = np.asarray(batch.get("valid", np.ones(len(batch["pose"]), bool)), bool)
        gt = np.asarray(batch["pose"], np.float64)[valid]
        yield batch, evaluator.place(batch), valid, gt


def late_fusion(
    camera: str, lidar: str, weights, splits, overrides=(), max_batches: int | None = None
) -> dict:
    """``{split: {str(w): summary}}`` of localizing ``lidar + w * camera`` BEV logits (the first
    ``max_batches`` batches of each split; None: all)."""
    base = app_config(overrides)  # fused: its loader yields both sensors' keys
    cfg_c = app_config([*overrides, "model.modality=camera"])
    cfg_l = app_config([*overrides, "model.modality=lidar"])
    evaluator = Evaluator(base, prepare_dataset(base), step_lib.make_mesh(None), workdir="")
    example = evaluator.place(next(iter(evaluator.loader(splits[0]))))
    params_c, step_c = restore(cfg_c, camera, evaluator, example)
    params_l, step_l = restore(cfg_l, lidar, evaluator, example)
    print(f"camera {camera} step {step_c}, LiDAR {lidar} step {step_l}", file=sys.stderr)
    net_c = evaluation.make_localize_step(cfg_c.model, base.solver)
    net_l = evaluation.make_localize_step(cfg_l.model, base.solver)
    out = {}
    for split in splits:
        acc = {w: metrics.MetricAccumulator() for w in weights}
        night = {w: metrics.MetricAccumulator() for w in weights}
        for batch, placed, valid, gt in frames(evaluator, split, max_batches):
            bev_c = net_c.network(params_c, placed)["template"]
            bev_l = net_l.network(params_l, placed)["template"]
            dark = np.asarray(batch["lighting"])[valid] == "night"
            for w in weights:
                comb = bev_l + w * bev_c
                res = jax.device_get(net_l.solve(params_l, {"template": comb}, placed))
                pose = solver.tile_pose_to_world(res["pose_tile"], batch["tile_center"])[valid]
                acc[w].update(pose, gt)
                if dark.any():
                    night[w].update(pose[dark], gt[dark])
        out[split] = {}
        for w in weights:
            summary = {k: acc[w].result()[k] for k in KEYS}
            summary["R@1m_night"] = night[w].result()["R@1m"] if len(night[w].errors()[0]) else None
            out[split][str(w)] = summary
            print(f"{split} w={w}: " + json.dumps(summary), file=sys.stderr, flush=True)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--camera", required=True, help="camera-only run or checkpoint")
    parser.add_argument("--lidar", required=True, help="LiDAR-only run or checkpoint")
    parser.add_argument("--weights", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0])
    parser.add_argument("--splits", nargs="+", default=["val"])
    parser.add_argument("--overrides", nargs="*", default=[], help="config overrides of both")
    parser.add_argument("--max-batches", type=int, default=None, help="per split (default all)")
    args = parser.parse_args(argv)
    for path in (args.camera, args.lidar):
        if not os.path.exists(path):
            raise SystemExit(f"{path}: no such run or checkpoint")
    out = late_fusion(
        args.camera, args.lidar, args.weights, args.splits, args.overrides, args.max_batches
    )
    print(json.dumps({"camera": args.camera, "lidar": args.lidar, "splits": out}))


if __name__ == "__main__":
    main()
