"""The odometry noise model: exact without noise, its statistics match its config, the filter
noise derived from it covers it, deterministic for a seed, bad configs rejected."""

import dataclasses
import math

import numpy as np
import pytest

from seglocnet_jax import geometry as g
from seglocnet_jax import tracking as tr

NONE = tr.OdometryConfig(**{f.name: 0.0 for f in dataclasses.fields(tr.OdometryConfig)})


def _drive(n=60, seed=0):
    """``(n, 3)`` GT poses (a wandering drive through every heading, 4-6 m steps) and
    ``(n,)`` timestamps (0.3-0.7 s apart)."""
    rng = np.random.default_rng(seed)
    yaw = 2.5 + np.cumsum(rng.uniform(-0.4, 0.4, n))
    step = rng.uniform(4.0, 6.0, n)
    xy = np.cumsum(np.stack([step * np.cos(yaw), step * np.sin(yaw)], 1), 0)
    poses = np.column_stack([xy + [300.0, -200.0], g.wrap_angle(yaw)])
    return poses, np.cumsum(rng.uniform(0.3, 0.7, n))


def test_relative_motion_is_the_ego_frame_step():
    poses, _ = _drive(12)
    rel = tr.relative_motion(poses)
    np.testing.assert_array_equal(rel[0], 0.0)
    for i in range(1, len(poses)):
        ego = g.world_to_ego(poses[i - 1], poses[i, :2])
        np.testing.assert_allclose(rel[i, :2], ego, atol=1e-9)
        assert abs(rel[i, 2] - g.wrap_angle(poses[i, 2] - poses[i - 1, 2])) < 1e-12
    # Driving forward while turning left: forward > 0, the turn is positive.
    assert (rel[1:, 0] > 0).all()
    wrap = tr.relative_motion([[0.0, 0.0, 3.1], [1.0, 0.0, -3.1]])[1, 2]
    assert abs(wrap - (2 * math.pi - 6.2)) < 1e-12  # across +-pi: the short way


def test_zero_noise_is_exact_and_composes_back_to_the_drive():
    poses, stamps = _drive()
    odo = tr.odometry.simulate(poses, stamps, NONE, seed=3)
    np.testing.assert_array_equal(odo, tr.relative_motion(poses))
    back = tr.compose(poses[0], odo)
    np.testing.assert_allclose(back[:, :2], poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(g.angle_error(back[:, 2], poses[:, 2]), 0.0, atol=1e-12)


def test_a_seed_gives_one_odometry():
    poses, stamps = _drive(20)
    cfg = tr.OdometryConfig()
    a, b = (tr.odometry.simulate(poses, stamps, cfg, seed=5) for _ in range(2))
    np.testing.assert_array_equal(a, b)
    c = tr.odometry.simulate(poses, stamps, cfg, seed=6)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(a[0], 0.0)
    # Noisy dead reckoning drifts, but by about what the config says (not by metres per step).
    drift = np.hypot(*(tr.compose(poses[0], a)[-1, :2] - poses[-1, :2]))
    assert 0.0 < drift < 10.0


def test_noise_statistics_match_the_config():
    # Per-drive terms: one draw per drive, so many drives; per-step terms: residuals after
    # removing each drive's own systematic part.
    poses, stamps = _drive(30)
    rel = tr.relative_motion(poses)[1:]
    dt = np.diff(stamps)
    cfg = tr.OdometryConfig(
        scale_sigma=0.02,
        xy_sigma=0.03,
        xy_sigma_per_m=0.0,
        yaw_bias_sigma=math.radians(0.4),
        yaw_scale_sigma=0.0,
        yaw_sigma=math.radians(0.3),
    )
    scales, biases, res_xy, res_yaw = [], [], [], []
    for seed in range(400):
        odo = tr.odometry.simulate(poses, stamps, cfg, seed)[1:]
        # Least squares per drive: odo = (1 + s) rel + noise, dyaw = dyaw_true + b dt + noise.
        s = np.sum((odo[:, :2] - rel[:, :2]) * rel[:, :2]) / np.sum(rel[:, :2] ** 2)
        b = np.sum((odo[:, 2] - rel[:, 2]) * dt) / np.sum(dt**2)
        scales.append(s)
        biases.append(b)
        res_xy.append(odo[:, :2] - (1 + s) * rel[:, :2])
        res_yaw.append(odo[:, 2] - rel[:, 2] - b * dt)
    assert abs(np.std(scales) / cfg.scale_sigma - 1) < 0.2
    assert abs(np.std(biases) / cfg.yaw_bias_sigma - 1) < 0.2
    assert abs(np.mean(scales)) < 3 * cfg.scale_sigma / math.sqrt(len(scales))
    assert abs(np.std(res_xy) / cfg.xy_sigma - 1) < 0.2
    assert abs(np.std(res_yaw) / cfg.yaw_sigma - 1) < 0.2
    # Per-metre noise: the per-step spread grows with the distance travelled.
    per_m = tr.OdometryConfig(**{**dataclasses.asdict(NONE), "xy_sigma_per_m": 0.02})
    err = np.concatenate(
        [tr.odometry.simulate(poses, stamps, per_m, s)[1:, :2] - rel[:, :2] for s in range(200)]
    )
    dist = np.tile(np.hypot(rel[:, 0], rel[:, 1]), 200)
    assert abs(np.std(err / dist[:, None]) / 0.02 - 1) < 0.2


def test_tracker_noise_covers_the_odometry_error_per_step():
    # The filter's per-step noise (1 sigma, per axis) from tracker_noise() matches the spread
    # of the simulated odometry's error along the travel direction and in yaw.
    cfg = tr.OdometryConfig()
    n = 40
    poses = np.column_stack([np.arange(n) * 5.0, np.zeros(n), np.zeros(n)])  # 5 m east
    stamps = np.arange(n) * 0.5
    noise = tr.odometry.tracker_noise(cfg, frame_dt=0.5)
    assert set(noise) == {"sigma_xy", "sigma_xy_per_m", "sigma_yaw", "sigma_yaw_per_rad"}
    tr.TrackerConfig(**noise)  # valid filter settings
    err = np.stack([tr.odometry.simulate(poses, stamps, cfg, s)[1:] for s in range(300)])
    err -= tr.relative_motion(poses)[1:]
    expected_xy = math.hypot(noise["sigma_xy"], noise["sigma_xy_per_m"] * 5.0)
    assert abs(err[..., 0].std() / expected_xy - 1) < 0.15  # along the travel: covered
    assert err[..., 1].std() <= expected_xy  # sideways: no scale error, conservative
    assert abs(err[..., 2].std() / noise["sigma_yaw"] - 1) < 0.15
    # The defaults are those of wheel odometry + a MEMS gyro: cm-level and sub-degree.
    assert 0.01 < expected_xy < 0.2 and math.radians(0.05) < noise["sigma_yaw"] < math.radians(1)


def test_bad_config_and_inputs_are_rejected():
    with pytest.raises(ValueError, match="scale_sigma"):
        tr.OdometryConfig(scale_sigma=-0.01)
    with pytest.raises(ValueError, match="yaw_bias_sigma"):
        tr.OdometryConfig(yaw_bias_sigma=float("nan"))
    poses, stamps = _drive(5)
    with pytest.raises(ValueError, match="timestamps"):
        tr.odometry.simulate(poses, stamps[::-1], tr.OdometryConfig(), 0)
    with pytest.raises(ValueError, match="timestamps"):
        tr.odometry.simulate(poses, stamps[:3], tr.OdometryConfig(), 0)
    with pytest.raises(ValueError, match="poses"):
        tr.relative_motion(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="frame_dt"):
        tr.odometry.tracker_noise(tr.OdometryConfig(), frame_dt=-1.0)
