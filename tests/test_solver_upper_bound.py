"""GT-segmentation upper bound on a synthetic raster: the library path the evaluation app calls
with ``eval.bev_source=gt``."""

import math

import numpy as np
import pytest

from seglocnet_jax import geometry as g
from seglocnet_jax import solver, upper_bound
from test_solver import blob_raster


@pytest.fixture(scope="module")
def setup():
    raster = blob_raster(seed=5)
    rng = np.random.default_rng(7)
    n = 6
    poses = np.column_stack(
        [rng.uniform(110, 210, n), rng.uniform(110, 210, n), rng.uniform(-math.pi, math.pi, n)]
    )
    priors = upper_bound.sample_priors(poses, rng)
    return raster, poses, priors


def test_priors_are_within_range_of_gt(setup):
    _, poses, priors = setup
    offset = priors - poses[:, :2]
    assert np.all(np.abs(offset) <= g.PRIOR_RANGE) and np.abs(offset).max() > 5.0


def test_gt_upper_bound_recovers_continuous_poses(setup):
    raster, poses, priors = setup
    # 6 samples in batches of 4: the padded last batch must not leak into the results.
    res = upper_bound.gt_upper_bound(
        raster, poses, priors, solver.SolverConfig(refine=False), batch_size=4, progress=False
    )
    assert res.pred.shape == (6, 3) and res.tile_center.shape == (6, 2)
    bin_deg = 360.0 / g.NUM_ROTATIONS
    # Argmax quantization: <= 0.25 m per axis and half a bin, plus sampling noise.
    assert res.pos_err.max() < 0.5 and res.yaw_err.max() < bin_deg
    assert res.metrics["R@1m"] == 100.0 and res.metrics["count"] == 6
    refined = upper_bound.gt_upper_bound(
        raster, poses, priors, solver.SolverConfig(refine=True), batch_size=8, progress=False
    )
    assert refined.pos_err.mean() < res.pos_err.mean()
    assert refined.yaw_err.mean() < res.yaw_err.mean()


def test_gt_inputs_checks_shapes(setup):
    raster, poses, _ = setup
    with pytest.raises(ValueError, match="priors"):
        upper_bound.gt_inputs(raster, poses, np.zeros((len(poses), 3)))
