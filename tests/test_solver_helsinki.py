"""The issue's acceptance test on real OSM: GT segmentation of Helsinki's SD map (roads buffered
to 10 m + buildings) cut at 200 random poses on drivable road centrelines, any yaw, priors
uniform within +-32 m. The argmax must recover >= 95% within 0.5 m and one rotation bin, and
the sub-cell refinement must bring the recovered ones closer."""

import math

import numpy as np
import pytest

from seglocnet_jax import geometry as g
from seglocnet_jax import metrics, solver
from seglocnet_jax.maps import MapConfig, load_city, rasterize

NUM_POSES = 200
SEED = 0


def road_poses(roads, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` poses on road centrelines (length-weighted), yaw uniform in (-pi, pi]."""
    lines = [r.geometry for r in roads]
    lengths = np.array([line.length for line in lines])
    pick = rng.choice(len(lines), size=n, p=lengths / lengths.sum())
    xy = np.array([lines[i].interpolate(rng.uniform(0, lengths[i])).coords[0][:2] for i in pick])
    return np.column_stack([xy, rng.uniform(-math.pi, math.pi, n)])


@pytest.fixture(scope="module")
def helsinki_sd():
    city = load_city("helsinki")
    return city, rasterize(city, MapConfig(kind="sd"))


@pytest.mark.slow
def test_helsinki_gt_segmentation_is_recovered(helsinki_sd):
    city, raster = helsinki_sd
    assert raster.mask.shape[0] == 2  # road, building
    rng = np.random.default_rng(SEED)
    poses = road_poses(city.roads, NUM_POSES, rng)
    priors = poses[:, :2] + rng.uniform(-g.PRIOR_RANGE, g.PRIOR_RANGE, size=(NUM_POSES, 2))
    bev = np.stack([raster.cut_bev(p) for p in poses]).astype(np.float32)
    tiles = [raster.tile(float(x), float(y)) for x, y in priors]
    tile = np.stack([t for t, _ in tiles]).astype(np.float32)
    centre = np.asarray([c for _, c in tiles], np.float64)
    cfg = solver.SolverConfig(refine=True)
    argmax, refined = [], []
    for s in range(0, NUM_POSES, 8):  # 200 = 25 batches of 8: one compiled shape
        out = solver.localize(
            solver.labels_to_logits(bev[s : s + 8]), tile[s : s + 8], cfg, return_volume=True
        )
        coarse = solver.decode(out["volume"], refine=False)
        argmax.append(solver.tile_pose_to_world(coarse, centre[s : s + 8]))
        refined.append(solver.tile_pose_to_world(out["pose_tile"], centre[s : s + 8]))
    pos0, yaw0 = metrics.pose_errors(np.concatenate(argmax), poses)
    pos1, yaw1 = metrics.pose_errors(np.concatenate(refined), poses)

    bin_deg = 360.0 / g.NUM_ROTATIONS
    ok = (pos0 < 0.5) & (yaw0 < bin_deg)
    failures = [
        f"#{i} pose {np.round(poses[i], 2)}: {pos0[i]:.2f} m, {yaw0[i]:.2f} deg, "
        f"road {bev[i, 0].mean():.0%} building {bev[i, 1].mean():.0%} of the BEV"
        for i in np.flatnonzero(~ok)
    ]
    print(f"\n{ok.sum()}/{NUM_POSES} recovered; failures:\n" + "\n".join(failures))
    print(
        metrics.markdown_table(
            {"argmax": metrics.summarize(pos0, yaw0), "refined": metrics.summarize(pos1, yaw1)}
        )
    )
    assert ok.mean() >= 0.95, "\n".join(failures)
    # Refinement: closer on the recovered samples, in position and in yaw.
    assert pos1[ok].mean() < 0.8 * pos0[ok].mean()
    assert yaw1[ok].mean() < 0.8 * yaw0[ok].mean()
