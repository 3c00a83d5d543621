"""AV2 logs in the real on-disk format for camera-model and ego-frame tests.

``write_av2_log`` writes one log (poses, calibration, LiDAR sweeps, camera JPEGs, log map) under
``root/<split>/<log_id>``. Two image modes:

* ``dots=True``: full-resolution ring-camera images (2048 x 1550 portrait front centre,
  1550 x 2048 landscape others) with the calibration of a real AV2 log, radial distortion
  included, showing Gaussian dots at the *distorted* projections of known 3D points, i.e. the
  image a lens with that calibration would take (OpenCV radial model, the AV2
  ``intrinsics.feather`` columns ``k1, k2, k3``).
* ``dots=False``: small flat-colour images with a pinhole calibration (fast; for sync, split
  and ground-height tests).

The ego is parked (one pose for every timestamp), so sensor geometry is exact at any time
offset. LiDAR holds a ring of ground points at ``GROUND_Z`` (the ground in AV2's ego frame) and
a few points above it.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from PIL import Image

from fixtures_real import CAM_FORWARD, ROAD_Y, quat_wxyz, rot_z, write_av2_sweep
from seglocnet_jax.data.real.common import radial_distort
from seglocnet_jax.data.schema import EGO_HEIGHT_M

GROUND_Z = -EGO_HEIGHT_M["av2"]  # the road under the vehicle, in AV2's ego frame (m)
T0 = 315_969_000_000_000_000
SWEEP_NS = 100_000_000
# Calibration of two ring cameras of a published AV2 log (val/7606de8d-486c-4916-9cbb-002ee966f834,
# intrinsics.feather, as printed in argoverse/av2-api issue #274): fx = fy, cx, cy (px), k1, k2,
# k3, (height, width) px.
AV2_INTRINSICS = {
    "ring_front_center": (
        1782.709437,
        776.779882,
        1023.874790,
        (-0.242379, -0.210214, 0.323869),
        (2048, 1550),
    ),
    "ring_front_left": (
        1685.602179,
        1025.811119,
        779.617812,
        (-0.257576, -0.126533, 0.201116),
        (1550, 2048),
    ),
}
# Mounts (ego frame): position (m) and yaw (rad) of the optical axis, as in a real log.
AV2_MOUNTS = {
    "ring_front_center": ((1.63, 0.0, 1.43), 0.0),
    "ring_front_left": ((1.55, 0.20, 1.43), math.pi / 4),
    "ring_side_left": ((1.31, 0.27, 1.43), math.pi / 2),
}
DOT_CAMERAS = tuple(AV2_INTRINSICS)  # the cameras that write_av2_log writes by default
DOT_SIGMA = 8.0  # px of the raw image
DOT_DEPTH = 10.0  # m along the optical axis
DOT_GRID = {"landscape": (7, 5), "portrait": (5, 7)}  # dots across, down
FLAT_HW = (24, 40)
FLAT_FX = 20.0


def dot_rays(cam: str) -> np.ndarray:
    """``(n, 2)`` normalized pinhole coordinates ``(X/Z, Y/Z)`` of the dots of ``cam``: a grid
    filling the pinhole field of view of the stored intrinsics, with margins."""
    f, cx, cy, _, (h, w) = AV2_INTRINSICS[cam]
    nx, ny = DOT_GRID["portrait" if h > w else "landscape"]
    xs = np.linspace(-0.9, 0.9, nx) * (w / 2) / f
    ys = np.linspace(-0.85, 0.85, ny) * (h / 2) / f
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def ego_from_cam(cam: str) -> np.ndarray:
    """``(4, 4)`` AV2 camera-to-ego transform of the fixture's mount of ``cam``."""
    (x, y, z), yaw = AV2_MOUNTS[cam]
    t = np.eye(4)
    t[:3, :3] = rot_z(yaw) @ CAM_FORWARD
    t[:3, 3] = (x, y, z)
    return t


def _dots_image(cam: str) -> tuple[np.ndarray, np.ndarray]:
    """Raw (distorted) uint8 image of ``cam``'s dots and their ``(n, 2)`` raw pixel centres."""
    f, cx, cy, dist, (h, w) = AV2_INTRINSICS[cam]
    uv = radial_distort(dot_rays(cam), dist) * f + [cx, cy]  # (n, 2) distorted pixels
    img = np.zeros((h, w), np.float64)
    r = int(math.ceil(4 * DOT_SIGMA))
    for u, v in uv:
        c0, r0 = int(round(u)) - r, int(round(v)) - r
        rows = np.arange(r0, r0 + 2 * r + 1)[:, None]
        cols = np.arange(c0, c0 + 2 * r + 1)[None, :]
        img[r0 : r0 + 2 * r + 1, c0 : c0 + 2 * r + 1] += 250.0 * np.exp(
            -((cols - u) ** 2 + (rows - v) ** 2) / (2 * DOT_SIGMA**2)
        )
    grey = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2), uv


def _feather(path: str, columns: dict) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    feather.write_feather(pa.table(columns), path)


def lidar_points() -> np.ndarray:
    """``(n, 4)`` AV2 ego-frame x, y, z, intensity: a ground ring at ``GROUND_Z`` (radius 4-12 m)
    and 8 points 1 m above the ground."""
    a = np.linspace(0, 2 * math.pi, 24, endpoint=False)
    rad = np.tile([4.0, 8.0, 12.0], 8)
    ground = np.stack([rad * np.cos(a), rad * np.sin(a), np.full_like(a, GROUND_Z)], 1)
    up = np.stack([np.full(8, 6.0), np.linspace(-3, 3, 8), np.full(8, GROUND_Z + 1.0)], 1)
    xyz = np.concatenate([ground, up])
    return np.concatenate([xyz, np.full((len(xyz), 1), 100.0)], axis=1).astype(np.float32)


def write_av2_log(
    root: str,
    split: str,
    log_id: str,
    *,
    city: str = "MIA",
    cameras=DOT_CAMERAS,
    dots: bool = False,
    sweeps: int = 1,
    cam_dt_ns: int = 10_000_000,
    x: float = 20.0,
) -> dict:
    """Writes one AV2 log at ``root/split/log_id``; returns facts for the tests.

    Cameras fire ``cam_dt_ns`` after each sweep. Facts: ``sweeps`` (LiDAR timestamps),
    ``lidar`` ``(n, 4)`` points of every sweep, ``dots`` camera -> ``(n, 3)`` dot centres in
    AV2's ego frame and ``dots_raw_px`` camera -> ``(n, 2)`` their pixels in the raw image.
    """
    d = os.path.join(root, split, log_id)
    sweep_t = [T0 + k * SWEEP_NS for k in range(sweeps)]
    times = sorted(set(sweep_t) | {t + cam_dt_ns for t in sweep_t})
    q = quat_wxyz(np.eye(3))
    _feather(
        os.path.join(d, "city_SE3_egovehicle.feather"),
        {
            "timestamp_ns": times,
            **{k: [v] * len(times) for k, v in zip(("qw", "qx", "qy", "qz"), q, strict=True)},
            "tx_m": [x] * len(times),
            "ty_m": [ROAD_Y] * len(times),
            "tz_m": [0.0] * len(times),
        },
    )
    ext = {c: [] for c in ("sensor_name", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
    intr_cols = ("sensor_name", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3")
    intr = {c: [] for c in (*intr_cols, "height_px", "width_px")}
    facts = {"sweeps": sweep_t, "lidar": lidar_points(), "dots": {}, "dots_raw_px": {}}
    for cam in cameras:
        t = ego_from_cam(cam)
        for key, v in zip(ext, [cam, *quat_wxyz(t[:3, :3]), *t[:3, 3]], strict=True):
            ext[key].append(v)
        if dots:
            f, cx, cy, dist, (h, w) = AV2_INTRINSICS[cam]
            image, facts["dots_raw_px"][cam] = _dots_image(cam)
            rays = np.c_[dot_rays(cam), np.ones(len(dot_rays(cam)))] * DOT_DEPTH  # (n, 3)
            facts["dots"][cam] = (np.c_[rays, np.ones(len(rays))] @ t.T)[:, :3]
        else:
            (h, w), f, dist = FLAT_HW, FLAT_FX, (0.0, 0.0, 0.0)
            cx, cy = w / 2, h / 2
            image = np.full((h, w, 3), 60 + 20 * len(intr["sensor_name"]), np.uint8)
        for key, v in zip(intr, [cam, f, f, cx, cy, *dist, h, w], strict=True):
            intr[key].append(v)
        for ts in sweep_t:
            path = os.path.join(d, "sensors", "cameras", cam, f"{ts + cam_dt_ns}.jpg")
            os.makedirs(os.path.dirname(path), exist_ok=True)
            Image.fromarray(image).save(path, quality=95)
    _feather(os.path.join(d, "calibration", "egovehicle_SE3_sensor.feather"), ext)
    _feather(os.path.join(d, "calibration", "intrinsics.feather"), intr)
    pts = facts["lidar"]
    for ts in sweep_t:
        write_av2_sweep(os.path.join(d, "sensors", "lidar", f"{ts}.feather"), pts)
    ring = [(x - 40, ROAD_Y - 4), (x + 40, ROAD_Y - 4), (x + 40, ROAD_Y + 4), (x - 40, ROAD_Y + 4)]
    area = {"id": 1, "area_boundary": [{"x": a, "y": b, "z": 0.0} for a, b in ring]}
    path = os.path.join(d, "map", f"log_map_archive_{log_id}____{city}_city_00000.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump({"drivable_areas": {"1": area}, "lane_segments": {}}, fh)
    return facts
