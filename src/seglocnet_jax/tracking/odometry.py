"""Odometry as a vehicle measures it: the motion between consecutive frames from wheel
odometry (distance) and a MEMS gyro (yaw), with their errors, and the filter's process noise
that matches them (NumPy; deterministic for a seed).

Errors of one drive (:func:`simulate`), for the step from frame ``i - 1`` to frame ``i``
(``d`` metres travelled, ``dyaw`` radians turned, ``dt`` seconds between the timestamps)::

    forward, left = (1 + s) * (forward, left) + N(0, xy_sigma^2 + (xy_sigma_per_m * d)^2)
    dyaw          = (1 + g) * dyaw + b * dt + N(0, yaw_sigma^2)

with ``s ~ N(0, scale_sigma^2)`` (distance scale), ``g ~ N(0, yaw_scale_sigma^2)`` (gyro scale
factor) and ``b ~ N(0, yaw_bias_sigma^2)`` (gyro bias, rad/s) drawn once per drive, the rest
drawn per step. :func:`tracker_noise` gives the :class:`~seglocnet_jax.tracking.TrackerConfig`
motion noise that covers these errors step by step.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seglocnet_jax import geometry


@dataclasses.dataclass(frozen=True)
class OdometryConfig:
    """Noise of wheel odometry + a MEMS gyro (1 sigma; the defaults are typical values).

    Attributes:
      scale_sigma: per drive, relative error of the travelled distance (0.01: tyre radius
        changes with pressure, load and wear by ~0.5-2 %; calibration leaves ~1 %).
      xy_sigma: m per step and axis, independent of the distance (0.02: wheel-tick
        quantization of a few cm and the timestamp jitter between wheel and camera clocks).
      xy_sigma_per_m: m per step and axis per metre travelled (0.01: wheel slip and uneven
        road add ~1 % of the distance, varying from step to step).
      yaw_bias_sigma: rad/s, gyro bias drawn once per drive (0.2 deg/s: a MEMS gyro after
        turn-on calibration keeps ~0.1-0.5 deg/s; applied over the frames' timestamps).
      yaw_scale_sigma: per drive, relative error of the measured turn (0.005: MEMS gyro scale
        factor error ~0.2-1 %).
      yaw_sigma: rad per step, white yaw noise (0.2 deg: rate noise and quantization
        integrated over a frame, vibration on rough road; ~0.1-0.5 deg per step).
    """

    scale_sigma: float = 0.01
    xy_sigma: float = 0.02
    xy_sigma_per_m: float = 0.01
    yaw_bias_sigma: float = math.radians(0.2)
    yaw_scale_sigma: float = 0.005
    yaw_sigma: float = math.radians(0.2)

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(
                    f"odometry.{field.name} must be a finite number >= 0, got {value!r}"
                )


def _check_poses(poses) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must be (n, 3) world (x, y, yaw), got shape {poses.shape}")
    return poses


def relative_motion(poses) -> np.ndarray:
    """The exact motion between consecutive poses, in the frame of the earlier one.

    Args:
      poses: ``(n, 3)`` world ``(x, y, yaw)``, metres and radians.

    Returns:
      ``(n, 3)`` float64: row ``i`` is ``(forward m, left m, dyaw rad)`` of pose ``i`` seen from
      pose ``i - 1`` (``dyaw`` wrapped to ``(-pi, pi]``); row 0 is zeros. This is what
      :func:`seglocnet_jax.tracking.predict` takes as odometry.
    """
    poses = _check_poses(poses)
    out = np.zeros_like(poses)
    if len(poses) < 2:
        return out
    prev, cur = poses[:-1], poses[1:]
    dx, dy = cur[:, 0] - prev[:, 0], cur[:, 1] - prev[:, 1]
    c, s = np.cos(prev[:, 2]), np.sin(prev[:, 2])
    out[1:, 0] = c * dx + s * dy
    out[1:, 1] = -s * dx + c * dy
    out[1:, 2] = geometry.wrap_angle(cur[:, 2] - prev[:, 2])
    return out


def compose(start_pose, odometry) -> np.ndarray:
    """Dead reckoning: integrates odometry from ``start_pose``.

    Args:
      start_pose: ``(3,)`` world pose of frame 0.
      odometry: ``(n, 3)`` as :func:`relative_motion` returns (row 0 is ignored).

    Returns:
      ``(n, 3)`` float64 world poses (yaw wrapped); row 0 is ``start_pose``. The inverse of
      :func:`relative_motion`: ``compose(poses[0], relative_motion(poses))`` is ``poses``.
    """
    odometry = _check_poses(odometry)
    start = np.asarray(start_pose, np.float64).reshape(3)
    turns = odometry[:, 2].copy()
    turns[0] = 0.0
    yaw = start[2] + np.cumsum(turns)  # (n,) unwrapped; step i moves along yaw[i - 1]
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    steps = np.stack(
        [c * odometry[1:, 0] - s * odometry[1:, 1], s * odometry[1:, 0] + c * odometry[1:, 1]],
        axis=1,
    )  # (n - 1, 2) world
    out = np.empty_like(odometry)
    out[0] = start
    out[1:, :2] = start[:2] + np.cumsum(steps, axis=0)
    out[1:, 2] = geometry.wrap_angle(yaw[1:])
    out[0, 2] = start[2]
    return out


def simulate(poses, timestamps, cfg: OdometryConfig, seed: int) -> np.ndarray:
    """The odometry a vehicle would measure along GT ``poses`` (see the module docstring).

    Args:
      poses: ``(n, 3)`` GT world poses of one drive.
      timestamps: ``(n,)`` seconds of the frames (non-decreasing): the gyro bias acts over
        the time between frames.
      seed: the drive's seed; the same seed gives the same odometry.

    Returns:
      ``(n, 3)`` float64 noisy ``(forward, left, dyaw)`` per step, row 0 zeros. With every
      sigma 0 it equals :func:`relative_motion` exactly.
    """
    rel = relative_motion(poses)
    n = len(rel)
    t = np.asarray(timestamps, np.float64).reshape(-1)
    if t.shape != (n,):
        raise ValueError(f"timestamps must be ({n},) for {n} poses, got shape {t.shape}")
    dt = np.diff(t)
    if (dt < 0).any() or not np.isfinite(t).all():
        raise ValueError("timestamps must be finite and non-decreasing")
    rng = np.random.default_rng(seed)
    # Drawn in a fixed order whatever the config, so that one seed keeps its stream.
    scale, yaw_scale, bias = rng.normal(0.0, 1.0, 3) * [
        cfg.scale_sigma,
        cfg.yaw_scale_sigma,
        cfg.yaw_bias_sigma,
    ]
    unit_xy = rng.normal(0.0, 1.0, (max(n - 1, 0), 2))
    unit_yaw = rng.normal(0.0, 1.0, max(n - 1, 0))
    out = np.zeros_like(rel)
    if n < 2:
        return out
    step = rel[1:]
    dist = np.hypot(step[:, 0], step[:, 1])
    sigma_xy = np.sqrt(cfg.xy_sigma**2 + (cfg.xy_sigma_per_m * dist) ** 2)  # (n - 1,)
    out[1:, :2] = step[:, :2] + scale * step[:, :2] + unit_xy * sigma_xy[:, None]
    yaw = step[:, 2] + (yaw_scale * step[:, 2] + bias * dt + unit_yaw * cfg.yaw_sigma)
    # Wrap only what left (-pi, pi]: a wrap of an in-range angle is not exact in floats.
    out[1:, 2] = np.where(np.abs(yaw) > math.pi, geometry.wrap_angle(yaw), yaw)
    return out


def tracker_noise(cfg: OdometryConfig, *, frame_dt: float = 0.5) -> dict[str, float]:
    """The motion noise of :class:`~seglocnet_jax.tracking.TrackerConfig` that matches this
    odometry, step by step (1 sigma, per axis):

    * ``sigma_xy = xy_sigma``;
    * ``sigma_xy_per_m = sqrt(xy_sigma_per_m^2 + scale_sigma^2)``: the per-drive scale error
      moves each step by ``s * d`` along the travel direction, like ``d`` times a per-metre
      noise of ``scale_sigma`` (the filter spreads it over both axes: conservative sideways);
    * ``sigma_yaw = sqrt(yaw_sigma^2 + (yaw_bias_sigma * frame_dt)^2)``: the gyro bias turns
      each step by ``b * dt``; ``frame_dt`` is the frames' spacing in time (0.5 s: nuScenes
      keyframes at 2 Hz, the simulator's 5 m at 10 m/s);
    * ``sigma_yaw_per_rad = yaw_scale_sigma``.

    The per-drive terms are systematic (the same sign every step); the filter treats them as
    independent per step, which is what it needs between two frames' likelihoods.
    """
    if not frame_dt >= 0:
        raise ValueError(f"frame_dt must be >= 0, got {frame_dt}")
    return {
        "sigma_xy": float(cfg.xy_sigma),
        "sigma_xy_per_m": float(math.hypot(cfg.xy_sigma_per_m, cfg.scale_sigma)),
        "sigma_yaw": float(math.hypot(cfg.yaw_sigma, cfg.yaw_bias_sigma * frame_dt)),
        "sigma_yaw_per_rad": float(cfg.yaw_scale_sigma),
    }


@dataclasses.dataclass
class ScaleEstimate:
    """The filter's running estimate of one drive's odometry distance scale (the per-drive
    ``1 + s`` of :func:`simulate`), from one track: the along-track distance between
    consecutive filtered poses summed against the odometry's distance, with ``prior_m``
    metres of prior weight on a scale of 1::

        scale = (sum along-track filtered step + prior_m) / (sum odometry distance + prior_m)

    Where the map says little about the position along the road, the filter moves by the
    predicted ``scale * distance`` and the estimate stays put; where it does (a junction, a
    building corner), the filter's correction moves the estimate. A step whose filtered pose
    is more than ``gate`` metres (along or across) from its prediction is a jump (a new mode,
    a look-alike) and is left out. The estimate is clipped to ``1 +- max_error``. With a bank
    of windows each window keeps its own, fed its own mode track (the sequential app's
    lockstep loop): a window that wins late has learned from its own track, not from the
    look-alike that led before it.

    Attributes:
      prior_m: metres of prior weight on 1 (0 disables: the scale stays 1).
      gate: metres; a step off its prediction by more is left out.
      max_error: the estimate stays within ``1 +- max_error``.
    """

    prior_m: float
    gate: float = 2.0
    max_error: float = 0.05
    along: float = 0.0  # m, sum of the filtered steps' along-track components
    distance: float = 0.0  # m, sum of the odometry distances of the same steps

    @property
    def scale(self) -> float:
        if self.prior_m <= 0:
            return 1.0
        s = (self.along + self.prior_m) / (self.distance + self.prior_m)
        return float(np.clip(s, 1.0 - self.max_error, 1.0 + self.max_error))

    def apply(self, odometry) -> np.ndarray:
        """The odometry ``(forward, left, dyaw)`` with its distance scaled by the estimate."""
        out = np.array(odometry, np.float64)
        out[:2] *= self.scale
        return out

    def observe(self, previous_pose, pose, odometry) -> None:
        """One step: the filtered poses ``(x, y, yaw)`` before and after it (world) and its
        raw odometry ``(forward, left, dyaw)``."""
        if self.prior_m <= 0:
            return
        fwd, left = float(odometry[0]), float(odometry[1])
        dist = math.hypot(fwd, left)
        if dist < 1e-6:
            return
        x, y, yaw = (float(v) for v in previous_pose)
        c, s = math.cos(yaw), math.sin(yaw)
        u = np.array([c * fwd - s * left, s * fwd + c * left]) / dist  # along-track, world
        step = np.asarray(pose[:2], np.float64) - [x, y]
        along = float(step @ u)
        across = float(step @ [-u[1], u[0]])
        if abs(along - self.scale * dist) > self.gate or abs(across) > self.gate:
            return
        self.along += along
        self.distance += dist
