"""Synthetic, learnable batches in the loader's schema (``data.schema.BATCH_KEYS``) for model
tests and benchmarks, independent of the simulator.

Each scene is a BEV label map (a road band, maybe a crossing, a few buildings beside the road).
The LiDAR sees it (bright flat returns on the road, tall returns on buildings) and the cameras
see it (a flat-world render: grey road, red building footprints, green elsewhere, blue sky), so
the labels are learnable from either modality. A map tile contains the labels at a known cell,
so ``pose_tile`` is exact (heading north: solver rotation 0); the NM model's ``nm_tile`` is that
tile in the OSM class raster's channels (road in ``road_minor``, building in ``building``).
"""

from __future__ import annotations

import math

import numpy as np

from seglocnet_jax import geometry

ROAD, BUILDING = 0, 1
CAMERA_HEIGHT = 1.5  # metres above the ego origin (on the ground)
# The OSM class raster's channel count and where road / building go in it: maps.OSM_CLASSES
# (the model floor does not import maps; tests/test_model.py pins these to it).
NUM_OSM_CLASSES = 9
OSM_ROAD, OSM_BUILDING = 2, 5  # road_minor, building


def scene_labels(rng: np.random.Generator, size: int = geometry.BEV_SIZE) -> np.ndarray:
    """``(2, size, size)`` float32 {0, 1}: road, building (disjoint), BEV orientation."""
    centers = geometry.bev_cell_centers_ego(size)  # (S, S, 2) forward, left
    road = np.zeros((size, size), bool)
    for _ in range(1 + int(rng.random() < 0.5)):
        angle = rng.uniform(0, math.pi)
        offset = rng.uniform(-4.0, 4.0)
        half_width = rng.uniform(3.0, 7.0)
        d = -math.sin(angle) * centers[..., 0] + math.cos(angle) * centers[..., 1] - offset
        road |= np.abs(d) < half_width
    building = np.zeros_like(road)
    for _ in range(int(rng.integers(3, 8))):
        h, w = rng.integers(8, 30, size=2)
        r, c = rng.integers(0, size - h), rng.integers(0, size - w)
        building[r : r + h, c : c + w] = True
    building &= ~road
    return np.stack([road, building]).astype(np.float32)


def lidar_points(rng: np.random.Generator, labels: np.ndarray, num_points: int) -> np.ndarray:
    """``(num_points, 4)`` ego x, y, z, intensity seeing ``labels`` (buildings 2-6 m tall)."""
    size = labels.shape[-1]
    cell = rng.integers(0, size, size=(num_points, 2))
    jitter = rng.uniform(-0.5, 0.5, size=(num_points, 2)) * geometry.RESOLUTION
    fl = geometry.bev_cell_centers_ego(size)[cell[:, 0], cell[:, 1]] + jitter
    road = labels[ROAD, cell[:, 0], cell[:, 1]] > 0
    bld = labels[BUILDING, cell[:, 0], cell[:, 1]] > 0
    z = np.where(bld, rng.uniform(0.0, 5.5, num_points), rng.normal(0.0, 0.05, num_points))
    intensity = np.where(road, 0.8, np.where(bld, 0.4, 0.15)) + rng.normal(0, 0.05, num_points)
    return np.stack([fl[:, 0], fl[:, 1], z, np.clip(intensity, 0, 1)], -1).astype(np.float32)


def camera_rig(num_cams: int, height: int, width: int, fov_deg: float = 70.0):
    """Intrinsics ``(N, 3, 3)`` and cam_to_ego ``(N, 4, 4)`` of cameras evenly spread in yaw
    (camera 0 looks forward), level, ``CAMERA_HEIGHT`` m above the ego origin."""
    f = width / 2 / math.tan(math.radians(fov_deg) / 2)
    k = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
    mats = []
    for i in range(num_cams):
        a = 2 * math.pi * i / num_cams
        fwd = np.array([math.cos(a), math.sin(a), 0.0])
        right = np.array([math.sin(a), -math.cos(a), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        m = np.eye(4)
        m[:3, :3] = np.stack([right, down, fwd], axis=1)  # columns: camera axes in ego
        m[:3, 3] = (0.0, 0.0, CAMERA_HEIGHT)
        mats.append(m)
    return np.tile(k, (num_cams, 1, 1)), np.asarray(mats, np.float32)


def render_cameras(
    labels: np.ndarray, intrinsics: np.ndarray, cam_to_ego: np.ndarray, height: int, width: int
) -> np.ndarray:
    """Flat-world render ``(N, H, W, 3)`` uint8 of the label map seen by the rig."""
    colours = np.array([[60, 140, 60], [110, 110, 110], [170, 50, 40]], np.float32)  # else,road,b
    sky = np.array([120, 170, 230], np.float32)
    v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    pix = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64)  # (H, W, 3)
    out = []
    for k, m in zip(intrinsics, cam_to_ego, strict=True):
        rays = pix @ np.linalg.inv(k).T @ m[:3, :3].T  # (H, W, 3) ego directions
        hits = rays[..., 2] < -1e-6  # rays that reach the ground
        t = np.where(hits, -m[2, 3] / np.minimum(rays[..., 2], -1e-6), 0.0)
        ground = m[:3, 3][:2] + t[..., None] * rays[..., :2]  # (H, W, 2) forward, left
        row, col = geometry.ego_to_bev_pixel(ground, labels.shape[-1])
        row, col = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
        n = labels.shape[-1]
        inside = hits & (row >= 0) & (row < n) & (col >= 0) & (col < n)
        r, c = np.clip(row, 0, n - 1), np.clip(col, 0, n - 1)
        cls = np.where(labels[BUILDING, r, c] > 0, 2, np.where(labels[ROAD, r, c] > 0, 1, 0))
        img = np.where(hits[..., None], colours[cls], sky)
        img = np.where((hits & ~inside)[..., None], colours[0], img)
        out.append(img)
    return np.clip(np.asarray(out), 0, 255).astype(np.uint8)


def make_batch(
    seed: int,
    batch_size: int,
    num_cams: int = 6,
    image_hw=(64, 160),
    num_points: int = 8192,
    num_rotations: int = geometry.NUM_ROTATIONS,
) -> dict:
    """A batch with the ``BATCH_KEYS`` the model and solver read (``nm_tile`` too), plus
    ``tile_center`` and ``pose`` (not the loader's ids, ``valid`` or sequence metadata); the GT
    cell is drawn uniformly in the volume."""
    rng = np.random.default_rng(seed)
    h, w = image_hw
    intr, cam = camera_rig(num_cams, h, w)
    keys = ("images", "points", "bev_gt", "tile", "pose_tile")
    out = {k: [] for k in keys}
    for _ in range(batch_size):
        labels = scene_labels(rng)
        out["bev_gt"].append(labels)
        out["images"].append(render_cameras(labels, intr, cam, h, w))
        out["points"].append(lidar_points(rng, labels, num_points))
        ch, cw = rng.integers(0, geometry.SCORE_SIZE, size=2)
        tile = np.zeros((2, geometry.TILE_SIZE, geometry.TILE_SIZE), np.float32)
        tile[:, ch : ch + geometry.BEV_SIZE, cw : cw + geometry.BEV_SIZE] = labels
        out["tile"].append(tile)
        dx, dy = geometry.cell_to_tile_offset(ch, cw)
        yaw = geometry.yaw_from_rotation(0, num_rotations)
        out["pose_tile"].append(np.array([dx, dy, yaw], np.float32))
    batch = {k: np.stack(v) for k, v in out.items()}
    nm_tile = np.zeros((batch_size, NUM_OSM_CLASSES, *batch["tile"].shape[2:]), np.uint8)
    nm_tile[:, OSM_ROAD] = batch["tile"][:, ROAD]
    nm_tile[:, OSM_BUILDING] = batch["tile"][:, BUILDING]
    batch["nm_tile"] = nm_tile
    batch["intrinsics"] = np.tile(intr, (batch_size, 1, 1, 1))
    batch["cam_to_ego"] = np.tile(cam, (batch_size, 1, 1, 1))
    batch["points_mask"] = np.ones((batch_size, num_points), bool)
    batch["tile_center"] = np.zeros((batch_size, 2), np.float64)
    batch["pose"] = batch["pose_tile"].astype(np.float64)
    return batch
