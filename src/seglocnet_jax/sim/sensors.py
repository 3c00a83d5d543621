"""Sensor configuration and rig geometry: a nuScenes-like 6-camera surround rig and a spinning
32-beam LiDAR.

Frames: ego = x forward, y left, z up (metres, origin on the ground at the vehicle reference
point); camera = OpenCV (x right, y down, z forward); intrinsics follow the OpenCV pixel
convention (integer coordinates are pixel centres). Cameras are level (no pitch or roll), so
every image column is a vertical plane through the camera centre: the renderer marches once per
column (see :mod:`.render`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

# (yaw deg CCW from forward, horizontal FOV deg, x m, y m) per camera of geometry.CAMERA_NAMES,
# nuScenes-like placement.
_RIG = (
    (0.0, 70.0, 1.70, 0.00),
    (-55.0, 70.0, 1.55, -0.50),
    (-110.0, 70.0, 1.05, -0.50),
    (180.0, 110.0, 0.05, 0.00),
    (110.0, 70.0, 1.05, 0.50),
    (55.0, 70.0, 1.55, 0.50),
)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """Sensor suite and rendering options (lengths in metres, angles in degrees).

    Attributes:
      image_height, image_width: stored image size (pixels); intrinsics are scaled to it.
      camera_height: camera mounting height above ground.
      max_range: rays stop here (cameras show haze / sky beyond, LiDAR returns nothing).
      near_range, near_step, far_step: ray-march sample spacing (horizontal metres) before and
        after ``near_range``.
      lidar_beams, lidar_azimuths: beams (elevation channels) and azimuth steps per sweep.
      lidar_elevation: (lowest, highest) beam elevation.
      lidar_height, lidar_x: LiDAR mounting height and forward offset.
      range_noise: LiDAR range noise std; dropout: probability a return is lost;
        intensity_noise: std of the intensity noise.
      night_prob, dusk_prob: fraction of night-like and dusk frames (rest: day).
      pixel_noise: image noise std (of [0, 1] intensities).
      chunk: frames rendered per compiled call (batches are padded to a multiple).
    """

    image_height: int = 64
    image_width: int = 160
    camera_height: float = 1.55
    max_range: float = 70.0
    near_range: float = 20.0
    near_step: float = 0.25
    far_step: float = 0.5
    lidar_beams: int = 32
    lidar_azimuths: int = 1024
    lidar_elevation: tuple[float, float] = (-30.0, 10.0)
    lidar_height: float = 1.8
    lidar_x: float = 0.9
    range_noise: float = 0.02
    dropout: float = 0.05
    intensity_noise: float = 0.05
    night_prob: float = 0.15
    dusk_prob: float = 0.15
    pixel_noise: float = 0.02
    chunk: int = 4

    def __post_init__(self):
        if self.image_height < 8 or self.image_width < 8:
            raise ValueError(
                f"SensorConfig image size {self.image_height}x{self.image_width}: "
                "expected at least 8x8"
            )
        if not 0 < self.near_step <= self.far_step:
            raise ValueError("SensorConfig.near_step/far_step: expected 0 < near <= far")
        if self.chunk < 1 or self.lidar_beams < 1 or self.lidar_azimuths < 1:
            raise ValueError("SensorConfig.chunk/lidar_beams/lidar_azimuths must be >= 1")

    @classmethod
    def preset(cls, name: str, **overrides) -> SensorConfig:
        """``"cpu"``: 6x64x160 images (fast); ``"paper"``: 6x320x800 (the paper's input)."""
        presets = {
            "cpu": {},
            "paper": {"image_height": 320, "image_width": 800, "chunk": 1},
        }
        if name not in presets:
            raise ValueError(f"unknown sensor preset {name!r}; known: {sorted(presets)}")
        return cls(**{**presets[name], **overrides})


def intrinsics(cfg: SensorConfig) -> np.ndarray:
    """``(N, 3, 3)`` float32 pinhole intrinsics of the rig at the stored image size."""
    out = []
    for _, fov, _, _ in _RIG:
        f = (cfg.image_width / 2) / math.tan(math.radians(fov) / 2)
        out.append(
            [[f, 0, (cfg.image_width - 1) / 2], [0, f, (cfg.image_height - 1) / 2], [0, 0, 1]]
        )
    return np.asarray(out, np.float32)


def cam_to_ego(cfg: SensorConfig) -> np.ndarray:
    """``(N, 4, 4)`` float32 camera (OpenCV) to ego transforms of the level rig."""
    out = []
    for yaw, _, x, y in _RIG:
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        # columns: camera x (right), y (down), z (forward) in the ego frame
        rot = np.array([[s, 0, c], [-c, 0, s], [0, -1, 0]])
        t = np.eye(4)
        t[:3, :3] = rot
        t[:3, 3] = [x, y, cfg.camera_height]
        out.append(t)
    return np.asarray(out, np.float32)


def camera_columns(cfg: SensorConfig):
    """Per image column of every camera (C = N*W columns): ego position ``(C, 3)``, ego azimuth
    ``(C,)`` radians, and the slope (metres up per horizontal metre) of each pixel row's ray
    ``(C, H)``."""
    k = intrinsics(cfg).astype(np.float64)
    t = cam_to_ego(cfg).astype(np.float64)
    u = np.arange(cfg.image_width, dtype=np.float64)
    v = np.arange(cfg.image_height, dtype=np.float64)
    pos, az, slope = [], [], []
    for i in range(len(_RIG)):
        a = (u - k[i, 0, 2]) / k[i, 0, 0]  # (W,) x/z of the column's rays
        b = (v - k[i, 1, 2]) / k[i, 1, 1]  # (H,) y/z of the row's rays
        d = t[i, :3, :3] @ np.stack([a, np.zeros_like(a), np.ones_like(a)])  # (3, W) ego
        az.append(np.arctan2(d[1], d[0]))
        norm = np.sqrt(1 + a**2)  # horizontal length per unit z
        slope.append(-b[None, :] / norm[:, None])  # (W, H)
        pos.append(np.broadcast_to(t[i, :3, 3], (cfg.image_width, 3)))
    return (
        np.concatenate(pos).astype(np.float32),
        np.concatenate(az).astype(np.float32),
        np.concatenate(slope).astype(np.float32),
    )


def lidar_columns(cfg: SensorConfig):
    """Per LiDAR azimuth (C = lidar_azimuths): ego position ``(C, 3)``, azimuth ``(C,)`` and
    beam slopes ``(C, beams)`` (tangent of the elevation)."""
    az = 2 * np.pi * np.arange(cfg.lidar_azimuths) / cfg.lidar_azimuths - np.pi
    elev = np.radians(np.linspace(*cfg.lidar_elevation, cfg.lidar_beams))
    pos = np.broadcast_to([cfg.lidar_x, 0.0, cfg.lidar_height], (cfg.lidar_azimuths, 3))
    slope = np.broadcast_to(np.tan(elev), (cfg.lidar_azimuths, cfg.lidar_beams))
    return pos.astype(np.float32), az.astype(np.float32), slope.astype(np.float32)


def march_distances(cfg: SensorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal sample distances ``(S,)`` of the ray march and each sample's step ``(S,)``."""
    near = np.arange(0.5, cfg.near_range, cfg.near_step)
    far = np.arange(near[-1] + cfg.far_step, cfg.max_range + 1e-6, cfg.far_step)
    d = np.concatenate([near, far])
    step = np.diff(d, prepend=d[0] - cfg.near_step)
    return d.astype(np.float32), step.astype(np.float32)
