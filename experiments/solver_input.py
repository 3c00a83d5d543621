"""What the solver matches: a checkpoint's BEV logits as they are, or centred.

A diagnostic of the solver's input (the apps match the BEV logits as they are,
:mod:`seglocnet_jax.evaluation`): for every frame the network runs once and the solver localizes
each transform of its logits against the same tile, per channel over the 128 x 128 BEV:

- ``logits``: as the apps do;
- ``centred-probabilities``: ``sigmoid(logits)`` minus its mean over the BEV;
- ``centred-logits``: the logits minus their mean over the BEV.

Centred, a pose's score no longer grows with how much map lies under the BEV (the score of the
centred template is the raw score minus the mean times the map's mass under the turned BEV).
Choose on ``val``; look at the test splits once.

    python experiments/solver_input.py --checkpoint RUN_DIR --modality fused|camera|lidar \\
        [--splits val] [--transforms logits centred-probabilities centred-logits]
        [--overrides ...] [--max-batches N]

The checkpoint must match the network the default config builds with ``model.modality`` (plus
``--overrides``); the data are the default config's (under ``data_cache/``, prepared on first
use). Progress goes to stderr; the last stdout line is JSON: per split and transform, the
paper's recalls and APE / AOE.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
from late_fusion import KEYS, app_config, frames, restore

from seglocnet_jax import evaluation, metrics, solver
from seglocnet_jax.app.datasets import prepare_dataset
from seglocnet_jax.app.train_run import Evaluator
from seglocnet_jax.training import step as step_lib


def _centred(x):
    return x - jnp.mean(x, axis=(-2, -1), keepdims=True)


TRANSFORMS = {
    "logits": lambda x: x,
    "centred-probabilities": lambda x: _centred(jax.nn.sigmoid(x)),
    "centred-logits": _centred,
}


def solver_input(
    checkpoint, modality, transforms, splits, overrides=(), max_batches: int | None = None
) -> dict:
    """``{split: {transform: summary}}`` of localizing each transform of the BEV logits (the
    first ``max_batches`` batches of each split; None: all)."""
    base = app_config(overrides)
    cfg = app_config([*overrides, f"model.modality={modality}"])
    if cfg.model.variant != "seg":
        raise SystemExit(f"model.variant={cfg.model.variant}: only a seg model's BEV is logits")
    evaluator = Evaluator(base, prepare_dataset(base), step_lib.make_mesh(None), workdir="")
    example = evaluator.place(next(iter(evaluator.loader(splits[0]))))
    params, step = restore(cfg, checkpoint, evaluator, example)
    print(f"{checkpoint} step {step}", file=sys.stderr)
    net = evaluation.make_localize_step(cfg.model, base.solver)
    out = {}
    for split in splits:
        acc = {t: metrics.MetricAccumulator() for t in transforms}
        for batch, placed, valid, gt in frames(evaluator, split, max_batches):
            logits = net.network(params, placed)["template"]
            for t in transforms:
                res = jax.device_get(net.solve(params, {"template": TRANSFORMS[t](logits)}, placed))
                pose = solver.tile_pose_to_world(res["pose_tile"], batch["tile_center"])[valid]
                acc[t].update(pose, gt)
        out[split] = {t: {k: acc[t].result()[k] for k in KEYS} for t in transforms}
        for t in transforms:
            print(f"{split} {t}: " + json.dumps(out[split][t]), file=sys.stderr, flush=True)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="run directory or checkpoint")
    parser.add_argument("--modality", required=True, choices=("fused", "camera", "lidar"))
    parser.add_argument("--transforms", nargs="+", default=list(TRANSFORMS), choices=TRANSFORMS)
    parser.add_argument("--splits", nargs="+", default=["val"])
    parser.add_argument("--overrides", nargs="*", default=[], help="config overrides")
    parser.add_argument("--max-batches", type=int, default=None, help="per split (default all)")
    args = parser.parse_args(argv)
    if not os.path.exists(args.checkpoint):
        raise SystemExit(f"{args.checkpoint}: no such run or checkpoint")
    out = solver_input(
        args.checkpoint,
        args.modality,
        args.transforms,
        args.splits,
        args.overrides,
        args.max_batches,
    )
    print(json.dumps({"checkpoint": args.checkpoint, "modality": args.modality, "splits": out}))


if __name__ == "__main__":
    main()
