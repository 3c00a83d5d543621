"""GT-segmentation upper bound through the app's one localize step (``eval.bev_source=gt``) on a
synthetic raster: host batches as the loader yields them -> evaluation.evaluate_split."""

import math

import numpy as np
import pytest

from seglocnet_jax import evaluation, metrics, solver
from seglocnet_jax import geometry as g
from seglocnet_jax.model.config import ModelConfig
from test_solver import blob_raster

N = 6
LIGHTING = ("day", "night", "unknown", "dusk", "night", "day")  # the frames' records say


def _batches(raster, poses, priors, batch_size, lighting=LIGHTING):
    """Loader-shaped host batches; the last one padded (``valid`` False) like the loader's."""
    for start in range(0, len(poses), batch_size):
        idx = list(range(start, min(start + batch_size, len(poses))))
        valid = [True] * len(idx) + [False] * (batch_size - len(idx))
        idx = idx + [idx[-1]] * (batch_size - len(idx))
        tiles = [raster.tile(*priors[i]) for i in idx]
        centre = np.asarray([c for _, c in tiles], np.float64)
        pose_tile = poses[idx].copy()
        pose_tile[:, :2] -= centre
        yield {
            "bev_gt": np.stack([raster.cut_bev(poses[i]) for i in idx]).astype(np.uint8),
            "tile": np.stack([t for t, _ in tiles]).astype(np.uint8),
            "tile_center": centre,
            "pose": poses[idx],
            "pose_tile": pose_tile,
            "valid": np.asarray(valid),
            "sample_id": np.asarray([f"s{i}" for i in idx]),
            "lighting": np.asarray([lighting[i] for i in idx]),
        }


@pytest.fixture(scope="module")
def setup():
    raster = blob_raster(seed=5)
    rng = np.random.default_rng(7)
    poses = np.column_stack(
        [rng.uniform(110, 210, N), rng.uniform(110, 210, N), rng.uniform(-math.pi, math.pi, N)]
    )
    priors = poses[:, :2] + rng.uniform(-g.PRIOR_RANGE, g.PRIOR_RANGE, size=(N, 2))
    return raster, poses, priors


def _evaluate(setup, refine, batch_size, lighting=LIGHTING):
    raster, poses, priors = setup
    step = evaluation.make_localize_step(
        ModelConfig(), solver.SolverConfig(refine=refine), bev_source="gt"
    )
    errors = []

    def place(batch):  # the app puts the batch on the mesh; here: the default device
        keep = {k: v for k, v in batch.items() if k in ("bev_gt", "tile")}
        out = step(None, keep)
        pred = solver.tile_pose_to_world(np.asarray(out["pose_tile"]), batch["tile_center"])
        pos, yaw = metrics.pose_errors(pred[batch["valid"]], batch["pose"][batch["valid"]])
        errors.append((pos, yaw))
        return keep

    res = evaluation.evaluate_split(
        step,
        None,
        _batches(raster, poses, priors, batch_size, lighting),
        num_batches=math.ceil(N / batch_size),
        place=place,
        desc="gt",
        channels=("road", "building"),
    )
    pos = np.concatenate([e[0] for e in errors])
    yaw = np.concatenate([e[1] for e in errors])
    return res, pos, yaw


def test_gt_upper_bound_recovers_continuous_poses(setup):
    # 6 samples in batches of 4: the padded last batch must not leak into the results.
    res, pos, yaw = _evaluate(setup, refine=False, batch_size=4)
    assert res["count"] == N and len(pos) == N
    bin_deg = 360.0 / g.NUM_ROTATIONS
    # Argmax quantization: <= 0.25 m per axis and half a bin, plus sampling noise.
    assert pos.max() < 0.5 and yaw.max() < bin_deg
    assert res["R@1m"] == 100.0
    assert res["APE"] == pytest.approx(pos.mean(), abs=1e-9)
    assert "IoU_road" not in res  # GT labels: no network segmentation to score
    refined, pos_r, yaw_r = _evaluate(setup, refine=True, batch_size=8)
    assert pos_r.mean() < pos.mean() and yaw_r.mean() < yaw.mean()
    assert refined["prior"]["APE"] == pytest.approx(res["prior"]["APE"])


def test_frames_are_also_summarized_by_their_lighting(setup):
    """``lighting``: each known condition's frames alone, as the split's numbers are for all
    (the padded rows left out); the frames of unknown lighting count only in the split's."""
    res, pos, yaw = _evaluate(setup, refine=True, batch_size=4)
    assert sorted(res["lighting"]) == ["day", "dusk", "night"]
    for name, sub in res["lighting"].items():
        mine = np.asarray(LIGHTING) == name
        assert sub == metrics.summarize(pos[mine], yaw[mine])
        assert sub["count"] == mine.sum()
    assert res["count"] == N
    unknown, _, _ = _evaluate(setup, refine=True, batch_size=4, lighting=("unknown",) * N)
    assert "lighting" not in unknown
