"""The sequential filter: exact tracking with perfect inputs, dead reckoning with a flat
likelihood (also with the simulated odometry and the filter noise derived from it),
prediction signs in all four heading quadrants, the narrowed kernels, convergence from a 30 m
prior, a detected and recovered track loss, determinism, the credible-region test and the
lattice convention shared with the solver's tiles. Small K keeps
every test fast."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from seglocnet_jax import geometry as g
from seglocnet_jax import tracking as tr
from seglocnet_jax.tracking import motion, posterior

K = 16  # 22.5 degree bins; the window is the solver's 129 x 129 cells at 0.5 m
BIN = 2 * math.pi / K
CFG = tr.TrackerConfig(num_rotations=K)
EXACT = tr.TrackerConfig(
    num_rotations=K, sigma_xy=0.0, sigma_xy_per_m=0.0, sigma_yaw=0.0, sigma_yaw_per_rad=0.0
)


def _odometry(prev, cur):
    """``(forward, left, dyaw)`` of pose ``cur`` in the frame of pose ``prev``."""
    fwd, left = g.world_to_ego(prev, cur[:2])
    return np.array([fwd, left, g.wrap_angle(cur[2] - prev[2])])


def _drive(n, start=(200.0, 150.0, 0.4), speed=2.0, yaw_rate=0.03):
    """``(n, 3)`` world poses of a car driving a gentle left curve."""
    poses = [np.asarray(start, np.float64)]
    for _ in range(n - 1):
        x, y, yaw = poses[-1]
        yaw_mid = yaw + yaw_rate / 2
        poses.append(
            np.array(
                [
                    x + speed * math.cos(yaw_mid),
                    y + speed * math.sin(yaw_mid),
                    g.wrap_angle(yaw + yaw_rate),
                ]
            )
        )
    return np.stack(poses)


def _blob(cfg, cell, amplitude, sigma_cells=1.0, sigma_bins=1.0):
    """``(K, N, N)`` Gaussian bump at continuous cell ``(k, h, w)`` (wrapped in k)."""
    k0, h0, w0 = cell
    k = np.arange(cfg.num_rotations)[:, None, None]
    dk = np.abs(k - k0) % cfg.num_rotations
    dk = np.minimum(dk, cfg.num_rotations - dk)
    h = np.arange(cfg.size)[None, :, None]
    w = np.arange(cfg.size)[None, None, :]
    d2 = ((h - h0) ** 2 + (w - w0) ** 2) / sigma_cells**2 + dk**2 / sigma_bins**2
    return amplitude * np.exp(-0.5 * d2)


def _likelihood(cfg, belief, pose, rng, peak=16.0, distractors=3, ratio=0.6, noise=0.3):
    """A frame's log-likelihood: a blob of ``peak`` nats at ``pose``'s cell, distractor blobs
    of ``ratio * peak`` at random cells and Gaussian noise (what a network's score volume
    looks like to the filter)."""
    ll = rng.normal(0.0, noise, (cfg.num_rotations, cfg.size, cfg.size))
    if pose is not None:
        ll += _blob(cfg, np.asarray(tr.world_to_cell(belief, pose, cfg)), peak)
    for _ in range(distractors):
        cell = rng.uniform(0, [cfg.num_rotations, cfg.size, cfg.size])
        ll += _blob(cfg, cell, ratio * peak)
    return ll.astype(np.float32)


def _errors(est, pose):
    xy = float(np.hypot(*(np.asarray(est["map_pose"][:2], np.float64) - pose[:2])))
    return xy, float(g.angle_error(float(est["map_pose"][2]), pose[2]))


def _run(cfg, poses, prior_xy, rng, *, odo_noise=0.0, fake_offset=None, fake_frames=(), frame=None):
    """Tracks ``poses`` from ``prior_xy``; frames in ``fake_frames`` see a likelihood pointing
    at ``pose + fake_offset`` instead of the truth; ``frame``: :func:`_likelihood` options.
    Returns per-frame records (``single_error``: m, the frame's own argmax, no filter)."""
    belief = tr.init_belief(cfg, prior_xy)
    out = []
    for i, pose in enumerate(poses):
        if i:
            odo = _odometry(poses[i - 1], pose)
            odo[:2] += rng.normal(0.0, odo_noise * np.hypot(*odo[:2]), 2)
            belief, _ = tr.predict(belief, odo, cfg)
        target = pose if i not in fake_frames else pose + np.array([*fake_offset, 0.0])
        log_lik = _likelihood(cfg, belief, target, rng, **(frame or {}))
        single = tr.cell_to_world(belief, np.unravel_index(np.argmax(log_lik), log_lik.shape), cfg)
        belief, info = tr.update(belief, log_lik, cfg)
        gt = np.round(np.asarray(tr.world_to_cell(belief, pose, cfg))).astype(int)
        out.append(
            {
                "errors": _errors(info["estimate"], pose),
                "single_error": float(np.hypot(*(np.asarray(single[:2]) - pose[:2]))),
                "lost": bool(info["lost"]),
                "credible": bool(tr.in_credible_region(belief, gt, 0.9)),
                "map_pose": np.asarray(info["estimate"]["map_pose"]),
                "prob": np.asarray(belief.prob),
                "losses": int(belief.losses),
            }
        )
    return out


# --------------------------------------------------------------------------- conventions


def window_xy(belief):
    return tr.window_centre(belief, CFG)


def test_window_is_the_tile_of_a_raster_grid():
    grid = g.RasterGrid(x_min=-100.0, y_max=400.0, height=1000, width=1000)
    belief = tr.init_belief(CFG, (123.3, 77.9), origin=(grid.x_min, grid.y_max))
    row0, col0, cx, cy = g.tile_window(grid, *window_xy(belief))
    assert (row0, col0) == tr.tile_corner(belief, CFG)
    np.testing.assert_allclose(window_xy(belief), [cx, cy])
    np.testing.assert_allclose(window_xy(belief), [123.5, 78.0])  # nearest pixel corner
    cells = np.array([[0, 64, 64], [3, 10, 100], [15, 128, 0]], np.float32)
    tile_pose = g.cell_to_pose(cells, K)  # what the solver reports for these cells
    world = np.asarray(tr.cell_to_world(belief, cells, CFG))
    np.testing.assert_allclose(world[:, :2], tile_pose[:, :2] + [cx, cy], atol=1e-4)
    np.testing.assert_allclose(world[:, 2], tile_pose[:, 2], atol=1e-6)
    np.testing.assert_allclose(tr.world_to_cell(belief, world, CFG), cells, atol=1e-3)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="size"):
        tr.TrackerConfig(size=128)
    with pytest.raises(ValueError, match="floor"):
        tr.TrackerConfig(floor=1.0)
    for bad in (129, 131, 64, 1):  # not smaller than size, even, too small
        with pytest.raises(ValueError, match="track_size"):
            tr.TrackerConfig(track_size=bad)
    with pytest.raises(ValueError, match="reference_size"):
        tr.TrackerConfig(size=65, reference_size=33)
    assert tr.TrackerConfig().tracking_window() is None  # off in the filter's own default
    small = tr.TrackerConfig(track_size=65).tracking_window()
    assert (small.size, small.track_size, small.reference_size) == (65, 0, 129)
    for bad in (-1.0, math.inf):
        with pytest.raises(ValueError, match="off_road"):
            tr.TrackerConfig(off_road=bad)


@pytest.mark.parametrize("bev_size", [8, 128])
def test_road_log_prior_is_zero_where_the_cells_ego_point_touches_the_road(bev_size):
    """Checked against the cell's tile-frame pose (geometry.cell_to_pose): its ego point is a
    pixel corner of the tile, on the road when one of the 4 pixels around it is."""
    n = 33
    tile = n - 1 + bev_size
    road = (np.random.default_rng(bev_size).random((2, tile, tile)) > 0.8).astype(np.float32)
    prior = np.asarray(tr.road_log_prior(road, 7.5, bev_size=bev_size))
    assert prior.shape == (2, n, n)
    h, w = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    cells = np.stack([np.zeros_like(h), h, w], -1)
    pose = g.cell_to_pose(cells, K, size=n, bev_size=bev_size)
    row = np.round(tile / 2 - pose[..., 1] / g.RESOLUTION).astype(int)
    col = np.round(tile / 2 + pose[..., 0] / g.RESOLUTION).astype(int)
    for b in range(2):
        px = road[b]
        on = (px[row - 1, col - 1] + px[row - 1, col] + px[row, col - 1] + px[row, col]) > 0
        np.testing.assert_array_equal(prior[b], np.where(on, 0.0, -7.5))
    assert 0.2 < (prior == 0).mean() < 0.9  # both kinds of cell are there


# --------------------------------------------------------------------------- prediction


def _delta(cfg, cell, xy=(300.0, 200.0)):
    belief = tr.init_belief(cfg, xy)
    prob = np.zeros((cfg.num_rotations, cfg.size, cfg.size), np.float32)
    prob[tuple(cell)] = 1.0
    return belief._replace(prob=np.asarray(prob))


@pytest.mark.parametrize("k0", [2, 6, 10, 14])  # headings 135, 225, 315, 45 degrees
def test_predict_moves_the_peak_by_the_motion(k0):
    belief = _delta(EXACT, (k0, 64, 64))
    start = np.asarray(tr.cell_to_world(belief, [k0, 64, 64], EXACT), np.float64)
    odo = np.array([3.3, -1.2, 2 * BIN])  # 3.3 m forward, 1.2 m to the right, 2 bins left
    yaw = start[2]
    expected = np.array(
        [
            start[0] + math.cos(yaw) * odo[0] - math.sin(yaw) * odo[1],
            start[1] + math.sin(yaw) * odo[0] + math.cos(yaw) * odo[1],
            g.wrap_angle(yaw + odo[2]),
        ]
    )
    moved, info = tr.predict(belief, odo, EXACT)
    est = tr.estimate(moved, EXACT)
    # Bilinear shifts keep the mean exact; the peak is the nearest cell to the moved pose.
    np.testing.assert_allclose(est["mean_pose"][:2], expected[:2], atol=1e-3)
    assert g.angle_error(float(est["mean_pose"][2]), expected[2]) < 1e-5
    nearest = np.round(np.asarray(tr.world_to_cell(moved, expected, EXACT))).astype(int)
    nearest[0] %= K
    np.testing.assert_array_equal(est["map_cell"], nearest)
    assert int(est["map_cell"][0]) == (k0 + 2) % K
    # The window followed the peak, and nothing left it.
    assert np.abs(np.asarray(est["map_cell"][1:]) - EXACT.centre).max() <= 1
    assert float(info["dropped"]) < 1e-6
    np.testing.assert_allclose(float(np.asarray(moved.prob).sum()), 1.0, atol=1e-5)


def test_narrow_kernels_equal_the_full_width_and_a_given_map_cell_changes_nothing(monkeypatch):
    # predict drops Gaussian taps below 1e-7 of the central weight (here 1-2 of the 3 each
    # side): the result equals the full-width kernels' to float32 rounding.
    cfg = tr.TrackerConfig(num_rotations=K, sigma_xy=0.12, sigma_yaw=0.02)
    rng = np.random.default_rng(4)
    prob = rng.random((K, cfg.size, cfg.size)).astype(np.float32) ** 8
    belief = tr.init_belief(cfg, (300.0, 200.0))._replace(prob=prob / prob.sum())
    odo = np.array([2.6, -0.4, 0.3 * BIN])
    assert motion._widths(odo, cfg) < (cfg.kernel_radius, cfg.kernel_radius)
    narrow, info = tr.predict(belief, odo, cfg)
    given, _ = tr.predict(belief, odo, cfg, map_cell=tr.estimate(belief, cfg)["map_cell"])
    np.testing.assert_array_equal(given.prob, narrow.prob)
    monkeypatch.setattr(motion, "_widths", lambda o, c: (c.kernel_radius, c.kernel_radius))
    full, full_info = tr.predict(belief, odo, cfg)
    np.testing.assert_array_equal(full.centre, narrow.centre)
    np.testing.assert_allclose(narrow.prob, full.prob, rtol=0, atol=1e-6 * float(full.prob.max()))
    assert abs(float(info["dropped"]) - float(full_info["dropped"])) < 1e-6


def test_dead_reckoning_with_simulated_odometry_keeps_the_truth_credible():
    # A flat likelihood: the belief is the prediction alone. With the filter noise derived
    # from the odometry model (tracker_noise), the truth stays inside the belief's 99 %
    # credible region while the simulated odometry drifts, and the mean follows the
    # dead-reckoned track. The drive starts on a cell and a yaw bin, as the belief does; 64 yaw
    # bins (16 would bend the mean's path by their width).
    k_dim = 64
    start = (250.0, 180.0, float(g.yaw_from_rotation(12, k_dim)))
    poses = _drive(12, start=start, speed=5.0, yaw_rate=0.02)
    odo_cfg = tr.OdometryConfig()
    cfg = tr.TrackerConfig(
        num_rotations=k_dim, lost_peak_mass=0.0, lost_entropy=1.0, **tr.tracker_noise(odo_cfg)
    )
    odo = tr.simulate(poses, np.arange(len(poses)) * 0.5, odo_cfg, seed=11)
    dead = tr.compose(poses[0], odo)
    belief = _delta(cfg, (12, cfg.centre, cfg.centre), xy=start[:2])
    flat = np.zeros((k_dim, cfg.size, cfg.size), np.float32)
    for i in range(1, len(poses)):
        belief, _ = tr.predict(belief, odo[i], cfg)
        belief, info = tr.update(belief, flat, cfg)
        assert not bool(info["lost"])
        gt = np.round(np.asarray(tr.world_to_cell(belief, poses[i], cfg))).astype(int)
        gt[0] %= k_dim
        assert bool(tr.in_credible_region(belief, gt, 0.99)), i
        mean = np.asarray(info["estimate"]["mean_pose"], np.float64)
        assert np.hypot(*(mean[:2] - dead[i, :2])) < 0.25, i  # half a cell


def test_recentre_drops_and_reports_the_mass_that_leaves():
    belief = tr.init_belief(CFG, (300.0, 200.0))  # uniform over the window
    moved, dropped = tr.recentre(belief, (10, -3), CFG)
    n = CFG.size
    np.testing.assert_allclose(float(dropped), 1 - (n - 10) * (n - 3) / n**2, atol=1e-5)
    np.testing.assert_array_equal(moved.centre, np.asarray(belief.centre) + [10, -3])
    prob = np.asarray(moved.prob)
    np.testing.assert_allclose(prob.sum(), 1.0, atol=1e-5)
    assert (prob[:, -10:, :] == 0).all() and (prob[:, :, :3] == 0).all()  # cells that entered


def test_narrowing_to_the_tracking_window_keeps_the_world_poses():
    small = tr.TrackerConfig(num_rotations=K, track_size=65).tracking_window()
    assert (small.size, small.tile_size, small.reference_size) == (65, 192, 129)
    box = tr.init_belief(CFG, (300.0, 200.0))
    # 0.9 at a peak, 0.1 at the full window's corner (cut away); the peak 15 m south and 10 m
    # east of the centre (the box centred on it), or near the full window's edge (the box
    # clipped inside the window: the peak is then off the new window's centre).
    for cell, at_centre in (((5, 64 + 30, 64 + 20), True), ((9, 3, 125), False)):
        prob = np.zeros((K, 129, 129), np.float32)
        prob[cell] = 0.9
        prob[(cell[0], 0, 0)] = 0.1
        belief = box._replace(prob=np.asarray(prob))
        before = np.asarray(tr.cell_to_world(belief, np.array(cell), CFG))
        narrowed, kept = tr.narrow(belief, CFG, small)
        given, kept_given = tr.narrow(belief, CFG, small, map_cell=np.array(cell))  # the loop's
        np.testing.assert_array_equal(given.prob, narrowed.prob)
        np.testing.assert_array_equal(given.centre, narrowed.centre)
        assert float(kept_given) == float(kept)
        new = np.asarray(narrowed.prob)
        assert new.shape == (K, 65, 65) and abs(new.sum() - 1.0) < 1e-5
        assert float(kept) == pytest.approx(0.9, abs=1e-6)
        at = np.unravel_index(np.argmax(new), new.shape)
        assert (at[1:] == (32, 32)) == at_centre, at
        np.testing.assert_allclose(tr.cell_to_world(narrowed, np.array(at), small), before)
    with pytest.raises(ValueError, match="narrow"):
        tr.narrow(narrowed, small, CFG)


def test_flat_likelihood_follows_the_odometry():
    cfg = tr.TrackerConfig(
        num_rotations=K, sigma_xy=0.05, sigma_xy_per_m=0.02, sigma_yaw=0.0, sigma_yaw_per_rad=0.0
    )
    belief = _delta(cfg, (5, 64, 64))
    pose = np.asarray(tr.cell_to_world(belief, [5, 64, 64], cfg), np.float64)
    flat = np.zeros((K, cfg.size, cfg.size), np.float32)
    rng = np.random.default_rng(0)
    spread = []
    for _ in range(10):
        odo = np.array([rng.uniform(0.5, 3.0), rng.uniform(-0.5, 0.5), BIN * rng.integers(-1, 2)])
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + [c * odo[0] - s * odo[1], s * odo[0] + c * odo[1], odo[2]]
        belief, _ = tr.predict(belief, odo, cfg)
        belief, info = tr.update(belief, flat, cfg)
        est = info["estimate"]
        np.testing.assert_allclose(est["mean_pose"][:2], pose[:2], atol=2e-3)
        assert g.angle_error(float(est["mean_pose"][2]), pose[2]) < 1e-4
        assert abs(float(info["agreement"])) < 1e-4  # a flat frame favours no hypothesis
        assert not bool(info["lost"])
        spread.append(float(np.trace(np.asarray(est["cov_xy"]))))
    assert all(b > a for a, b in zip(spread, spread[1:], strict=False))  # noise accumulates


def test_perfect_likelihood_and_odometry_track_exactly():
    # A lattice drive (every pose on a cell, headings on the bins, diagonal steps of 2.5 m per
    # axis): noise-free prediction keeps the belief a delta on the truth.
    poses = [np.array([250.0, 180.0, float(g.yaw_from_rotation(0, K))])]  # heading north
    for leg in range(8):
        for _ in range(3):
            x, y, yaw = poses[-1]
            step = 2.5 / max(abs(math.cos(yaw)), abs(math.sin(yaw)))  # 2.5 m per axis
            poses.append(np.array([x + step * math.cos(yaw), y + step * math.sin(yaw), yaw]))
        x, y, yaw = poses[-1]
        turn = math.pi / 2 if leg % 2 == 0 else -math.pi / 4  # 4 or -2 bins
        poses.append(np.array([x, y, float(g.wrap_angle(yaw + turn))]))
    belief = tr.init_belief(EXACT, poses[0][:2])
    for i, pose in enumerate(poses):
        if i:
            belief, info = tr.predict(belief, _odometry(poses[i - 1], pose), EXACT)
            gt = np.round(np.asarray(tr.world_to_cell(belief, pose, EXACT))).astype(int)
            gt[0] %= K
            assert float(belief.prob[tuple(gt)]) > 0.999, f"frame {i}: prediction left GT"
            assert float(info["dropped"]) < 1e-6
        gt = np.round(np.asarray(tr.world_to_cell(belief, pose, EXACT))).astype(int)
        gt[0] %= K
        log_lik = np.full((K, EXACT.size, EXACT.size), -1e4, np.float32)
        log_lik[tuple(gt)] = 0.0
        belief, info = tr.update(belief, log_lik, EXACT)
        est = info["estimate"]
        np.testing.assert_array_equal(est["map_cell"], gt)
        np.testing.assert_allclose(est["map_pose"][:2], pose[:2], atol=1e-3)
        assert g.angle_error(float(est["map_pose"][2]), pose[2]) < 1e-5
        np.testing.assert_array_equal(est["map_cell"][1:], [EXACT.centre] * 2)  # tile on it
        assert not bool(info["lost"]) and float(est["peak_mass"]) > 0.999
    assert int(belief.losses) == 0


# --------------------------------------------------------------------------- drives


def test_drive_converges_from_a_prior_30_m_off():
    # Four distractors as strong as the truth: one frame alone is usually wrong, the sequence
    # is not (the truth moves with the odometry, the distractors do not).
    poses = _drive(40)
    prior = poses[0, :2] + np.array([21.2, -21.2])  # 30 m off
    frame = {"peak": 8.0, "distractors": 4, "ratio": 1.0}
    rec = _run(CFG, poses, prior, np.random.default_rng(1), odo_noise=0.02, frame=frame)
    xy = np.array([r["errors"][0] for r in rec])
    yaw = np.array([r["errors"][1] for r in rec])
    assert np.mean([r["single_error"] > 1.0 for r in rec]) > 0.5  # single frames: mostly wrong
    assert (xy[5:] < 1.0).all(), xy
    assert (yaw[5:] < BIN).all(), yaw
    assert np.mean([r["credible"] for r in rec[5:]]) >= 0.8
    assert rec[-1]["losses"] == 0


def test_induced_track_loss_is_detected_and_recovered():
    # No floor: the filter cannot jump to the likelihood's peak by itself, so getting back on
    # track is the loss detector's doing (re-widen, reapply the frame).
    cfg = tr.TrackerConfig(num_rotations=K, floor=0.0, lost_log_odds=6.0)
    poses = _drive(40)
    rec = _run(
        cfg,
        poses,
        poses[0, :2],
        np.random.default_rng(2),
        odo_noise=0.02,
        fake_offset=(12.0, -8.0),  # the likelihood points 14 m away for 6 frames
        fake_frames=range(12, 18),
    )
    lost = [i for i, r in enumerate(rec) if r["lost"]]
    xy = np.array([r["errors"][0] for r in rec])
    assert (xy[:12] < 1.0).all() and not any(i < 12 for i in lost), (xy, lost)
    assert any(12 <= i < 18 for i in lost), lost  # detected while the likelihood is wrong
    assert any(18 <= i < 24 for i in lost), lost  # and when the truth comes back
    assert (xy[-10:] < 1.0).all(), xy  # recovered
    assert rec[-1]["losses"] == len(lost)


def test_a_drive_is_deterministic_for_a_seed():
    poses = _drive(6)
    runs = [_run(CFG, poses, poses[0, :2] + 10, np.random.default_rng(s)) for s in (7, 7, 8)]
    for a, b in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(a["prob"], b["prob"])
        np.testing.assert_array_equal(a["map_pose"], b["map_pose"])
    assert not np.array_equal(runs[0][-1]["prob"], runs[2][-1]["prob"])


def test_kernels_compile_once_per_config():
    kernels = (
        motion._plan_rows_kernel,
        motion._cols_kernel,
        motion._rotations_kernel,
        posterior._update_kernel,
        tr.estimate,
    )
    poses = _drive(3)
    _run(CFG, poses, poses[0, :2], np.random.default_rng(0))
    before = [k._cache_size() for k in kernels]
    _run(CFG, _drive(4, start=(400.0, 10.0, -2.0)), (401.0, 12.0), np.random.default_rng(3))
    assert [k._cache_size() for k in kernels] == before


# --------------------------------------------------------------------------- read-outs


def test_update_evidence_on_request_is_the_log_sum_of_prior_times_likelihood():
    rng = np.random.default_rng(3)
    prob = rng.random((K, CFG.size, CFG.size)) ** 4
    belief = tr.init_belief(CFG, (300.0, 200.0))._replace(
        prob=jnp.asarray(prob / prob.sum(), jnp.float32)
    )
    ll = rng.normal(40.0, 4.0, prob.shape).astype(np.float32)  # far from 0: the max matters
    post, info = tr.update(belief, ll, CFG, evidence=True)
    prior = (1 - CFG.floor) * np.asarray(belief.prob, np.float64) + CFG.floor / CFG.num_cells
    expected = np.log(np.sum(prior * np.exp(ll.astype(np.float64) - ll.max()))) + ll.max()
    assert abs(float(info["log_evidence"]) - expected) < 1e-4
    plain_post, plain = tr.update(belief, ll, CFG)
    assert "log_evidence" not in plain  # one pass less unless asked for
    np.testing.assert_array_equal(plain_post.prob, post.prob)


def test_credible_region_matches_sorting():
    cfg = tr.TrackerConfig(num_rotations=4, size=9)
    rng = np.random.default_rng(0)
    prob = rng.random((4, 9, 9)) ** 4
    prob[0, :2] = prob[0, 0, 0]  # ties
    prob = (prob / prob.sum()).astype(np.float32)
    belief = tr.init_belief(cfg, (0.0, 0.0))._replace(prob=prob)
    flat = np.sort(prob.ravel())[::-1]
    for mass in (0.5, 0.9):
        threshold = flat[np.searchsorted(np.cumsum(flat), mass)]
        for cell in np.ndindex(prob.shape):
            expected = prob[cell] >= threshold
            assert bool(tr.in_credible_region(belief, np.array(cell), mass)) == expected, cell
    assert not bool(tr.in_credible_region(belief, np.array([0, 9, 0]), 0.9))  # outside


# --------------------------------------------------------------------------- a bank of windows


def test_split_modes_partitions_the_belief_first_window_the_single_ones():
    """Three blobs: A (strongest), B 10 m from A (inside A's window), C 50 m from A (outside
    it). The first window is the one a single-window filter moves to (centred on A, holding
    A and B); the second is centred on C and holds what the first left out; the parts'
    weights are their masses (a partition: they sum to 1). Every cell keeps its world pose."""
    cfg = tr.TrackerConfig(num_rotations=K, hypotheses=3)
    n, c = cfg.size, cfg.centre
    prob = np.full((K, n, n), 1e-12, np.float32)
    blobs = {"A": ((2, 70, 30), 0.5), "B": ((5, 70, 50), 0.3), "C": ((9, 20, 120), 0.2)}
    for (k, h, w), mass in blobs.values():
        prob[k, h, w] = mass
    prob /= prob.sum()
    belief = tr.init_belief(cfg, (300.0, 200.0))._replace(prob=jnp.asarray(prob))
    pieces = tr.hypotheses.split_modes(belief, cfg)
    weights = np.exp([lw for _, lw in pieces])
    assert weights.sum() == pytest.approx(1.0, abs=1e-5)
    first, second = pieces[0][0], pieces[1][0]
    single, _ = tr.recentre(belief, (70 - c, 30 - c), cfg)  # the single window on A
    np.testing.assert_array_equal(first.centre, single.centre)
    for name, piece in [("A", first), ("B", first), ("C", second)]:
        (k, h, w), mass = blobs[name]
        world = tr.cell_to_world(belief, jnp.array([k, h, w], jnp.float32), cfg)
        cell = np.round(np.asarray(tr.world_to_cell(piece, world, cfg))).astype(int)
        assert (0 <= cell[1:]).all() and (cell[1:] < n).all(), name
        p = float(piece.prob[cell[0] % K, cell[1], cell[2]])
        assert p * weights[0 if piece is first else 1] == pytest.approx(mass, rel=1e-3), name
    mode = np.asarray(tr.estimate(second, cfg)["map_cell"])
    np.testing.assert_array_equal(mode, [9, c, c])  # C is the second window's centre
    assert weights[1] == pytest.approx(0.2, rel=1e-3)


def test_prune_and_merge_keeps_the_heaviest_first():
    cfg = tr.TrackerConfig(num_rotations=K, hypotheses=4, hypothesis_prune=10.0)
    log_w = np.array([-3.0, 0.0, -12.0, -1.0])
    poses = np.array(
        [
            [0.0, 0.0, 0.1],
            [50.0, 0.0, 0.1],
            [90.0, 0.0, 0.1],  # 12 nats below the best: pruned
            [51.0, -1.0, 0.1 + BIN],  # the best one's place and heading: merged into it
        ]
    )
    kept, new = tr.hypotheses.prune_and_merge(log_w, poses, cfg)
    assert kept == [1, 0]
    w = np.exp([0.0, -1.0, -3.0])
    np.testing.assert_allclose(np.exp(new), [(w[0] + w[1]) / w.sum(), w[2] / w.sum()], rtol=1e-9)


def test_scale_estimate_learns_the_odometry_scale_from_corrections():
    """A straight drive whose odometry reads 3 % long; the filtered poses are the truth (the
    map corrected them): the estimate moves from 1 towards 1 / 1.03 as the distance grows,
    a jump is left out, and prior_m = 0 keeps the raw odometry."""
    est = tr.ScaleEstimate(prior_m=100.0)
    yaw = 0.7
    poses = [
        np.array([10.0 + 5.0 * i * math.cos(yaw), 5.0 * i * math.sin(yaw), yaw]) for i in range(80)
    ]
    odo = np.array([5.0 * 1.03, 0.0, 0.0])
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        est.observe(a, b, odo)
    assert est.scale == pytest.approx((79 * 5.0 + 100.0) / (79 * 5.15 + 100.0))
    assert abs(est.scale - 1 / 1.03) < 0.006
    np.testing.assert_allclose(est.apply(odo), [5.0 * 1.03 * est.scale, 0.0, 0.0])
    before = (est.along, est.distance)
    est.observe(poses[0], poses[0] + [30.0, 0.0, 0.0], odo)  # a 30 m jump: left out
    assert (est.along, est.distance) == before
    off = tr.ScaleEstimate(prior_m=0.0)
    off.observe(poses[0], poses[1], odo)
    assert off.scale == 1.0 and (off.apply(odo) == odo).all()


def test_the_tracking_window_runs_the_full_windows_filter():
    """A belief inside the 65-cell box: updating the tracking window by the full window's
    log-likelihood (its centre, the loss test against its mean: update_tracking_window, the
    app's step) gives the full window's posterior on those cells, its loss-test agreement,
    entropy and lock state."""
    cfg = tr.TrackerConfig(num_rotations=K, track_size=65)
    narrow_cfg = cfg.tracking_window()
    assert narrow_cfg.reference_cells == cfg.num_cells
    rng = np.random.default_rng(7)
    full = tr.init_belief(cfg, (3.0, -2.0), sigma=4.0)
    box = np.zeros((K, 129, 129), np.float32)
    box[:, 32:97, 32:97] = 1.0
    prob = np.asarray(full.prob) * box
    full = full._replace(prob=jnp.asarray(prob / prob.sum()))
    narrow, kept = tr.narrow(full, cfg, narrow_cfg, map_cell=jnp.array([0, 64, 64]))
    assert float(kept) == pytest.approx(1.0)
    ll = rng.normal(0.0, 2.0, (K, 129, 129)).astype(np.float32)
    ll[3, 60:64, 66:70] += 6.0
    centre, log_mean = tr.crop_likelihood(jnp.asarray(ll), narrow_cfg)
    np.testing.assert_array_equal(centre, ll[:, 32:97, 32:97])
    assert float(log_mean) == pytest.approx(float(jax.nn.logsumexp(ll) - np.log(ll.size)))
    post_full, info_full = tr.update(full, ll, cfg)
    post_narrow, info_narrow, window = tr.update_tracking_window(narrow, ll, narrow_cfg, cfg)
    assert window is narrow_cfg  # no loss: still the tracking window
    want = np.asarray(post_full.prob)[:, 32:97, 32:97]
    np.testing.assert_allclose(post_narrow.prob, want / want.sum(), rtol=1e-4, atol=1e-9)
    assert float(info_narrow["agreement"]) == pytest.approx(float(info_full["agreement"]), abs=1e-3)
    for key in ("entropy", "peak_mass"):
        got, ref = info_narrow["estimate"][key], info_full["estimate"][key]
        assert float(got) == pytest.approx(float(ref), abs=1e-4), key
    assert bool(info_narrow["lost"]) == bool(info_full["lost"])
    assert bool(post_narrow.locked) == bool(post_full.locked)
    np.testing.assert_allclose(
        info_narrow["estimate"]["map_pose"], info_full["estimate"]["map_pose"], atol=1e-4
    )


def test_reset_is_the_updates_loss_path():
    cfg = tr.TrackerConfig(num_rotations=K, lost_log_odds=1.0)
    belief = tr.init_belief(cfg, (0.0, 0.0), sigma=1.0)
    ll = np.zeros((K, 129, 129), np.float32)
    ll[5, 10, 120] = 30.0  # far from the belief: the prior did not predict this frame
    lost, info = tr.update(belief, ll, cfg)
    assert bool(info["lost"]) and int(lost.losses) == 1
    kept, info_kept = tr.update(belief, ll, cfg, reset=False)
    assert bool(info_kept["lost"]) and int(kept.losses) == 0
    again, est = tr.reset(kept, ll, cfg)
    np.testing.assert_array_equal(again.prob, lost.prob)
    assert int(again.losses) == 1 and not bool(again.locked)
    np.testing.assert_array_equal(est["map_cell"], [5, 10, 120])


def test_a_loss_in_the_tracking_window_resets_the_full_window():
    """A frame whose peak the narrow belief did not predict: the loss is detected and the
    belief becomes the full window's around the same centre, reset with the whole volume (its
    mode on the peak, even one outside the tracking window), the loss counted."""
    cfg = tr.TrackerConfig(num_rotations=K, track_size=65, lost_log_odds=1.0)
    narrow_cfg = cfg.tracking_window()
    belief = tr.init_belief(narrow_cfg, (3.0, -2.0), sigma=1.0)._replace(losses=jnp.int32(2))
    ll = np.zeros((K, 129, 129), np.float32)
    ll[5, 10, 120] = 30.0  # 27 m from the centre: outside the tracking window
    new, info, window = tr.update_tracking_window(belief, ll, narrow_cfg, cfg)
    assert window is cfg and bool(info["lost"]) and int(new.losses) == 3
    assert new.prob.shape == (K, 129, 129)
    np.testing.assert_allclose(tr.window_centre(new, cfg), tr.window_centre(belief, narrow_cfg))
    np.testing.assert_array_equal(info["estimate"]["map_cell"], [5, 10, 120])
