"""Tiny synthetic producers for the data-pipeline tests: random valid samples, a frame source
driving on a square street grid, and a city raster with the maps API (tile / cut_bev)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.data.simulated import splits
from seglocnet_jax.data.simulated.config import PrepareConfig
from seglocnet_jax.sim import trajectory


def random_sample(
    rng: np.random.Generator,
    sample_id: str = "s0",
    city: str = "helsinki",
    num_cams: int = 2,
    hw=(8, 12),
    num_points: int | None = None,
    pose=None,
    sequence: tuple[str, int, float] | None = None,
    lighting: str = "day",
) -> dict:
    """A valid ``SAMPLE_KEYS`` dict with random content (images, intrinsics, LiDAR);
    ``sequence`` = ``(sequence_id, frame_index, timestamp)`` (default: its own sequence)."""
    n_pts = int(rng.integers(20, 60)) if num_points is None else num_points
    intr = np.tile(np.array([[10, 0, 6], [0, 10, 4], [0, 0, 1]], np.float32), (num_cams, 1, 1))
    cam = np.tile(np.eye(4, dtype=np.float32), (num_cams, 1, 1))
    cam[:, 0, 3] = rng.normal(size=num_cams).astype(np.float32)
    if pose is None:
        pose = np.array([*rng.uniform(0, 500, 2), rng.uniform(-np.pi, np.pi)], np.float64)
    seq_id, index, stamp = sequence or (f"seq-{sample_id}", 0, 0.0)
    return {
        "sample_id": sample_id,
        "city": city,
        "sequence_id": seq_id,
        "frame_index": np.int64(index),
        "timestamp": np.float64(stamp),
        "lighting": lighting,
        "pose": np.asarray(pose, np.float64),
        "images": rng.integers(0, 256, (num_cams, *hw, 3), dtype=np.uint8),
        "intrinsics": intr,
        "cam_to_ego": cam,
        "lidar": rng.normal(size=(n_pts, 4)).astype(np.float32),
    }


class GridSource:
    """A frame source on a square street grid (streets every 100 m over ``size`` metres).

    ``calls`` counts render() calls so tests can tell whether shards were re-rendered.
    """

    def __init__(self, city: str, size: float = 1200.0, fail_after: int | None = None):
        self.city = city
        self.size = size
        self.calls = 0
        self.fail_after = fail_after
        self._world = None

    def drive(self, rng: np.random.Generator, num_frames: int) -> np.ndarray:
        street = rng.integers(0, int(self.size // 100) + 1, num_frames) * 100.0
        along = rng.uniform(0, self.size, num_frames)
        east = rng.random(num_frames) < 0.5
        x = np.where(east, along, street)
        y = np.where(east, street, along)
        yaw = np.where(east, 0.0, np.pi / 2) + np.where(rng.random(num_frames) < 0.5, 0, np.pi)
        return np.stack([x, y, geometry.wrap_angle(yaw)], axis=1)

    def route(self, rng: np.random.Generator, length_m: float, spacing_m: float):
        """A continuous drive on the grid's two-way streets (``sim.trajectory.route``)."""
        if self._world is None:
            ticks = np.arange(0.0, self.size + 1e-6, 100.0)
            lines = [np.column_stack([ticks, np.full_like(ticks, t)]) for t in ticks]
            lines += [line[:, ::-1] for line in lines]  # north-south streets
            roads = [SimpleNamespace(centerline=c, width=8.0, lanes=2, oneway=False) for c in lines]
            self._world = SimpleNamespace(name=self.city, roads=roads, graph=None)
        return trajectory.route(self._world, rng, length_m, spacing_m)

    def render(self, poses: np.ndarray, seed: int) -> list[dict]:
        if self.fail_after is not None and self.calls >= self.fail_after:
            raise KeyboardInterrupt("simulated interruption")
        self.calls += 1
        rng = np.random.default_rng(seed)
        return [random_sample(rng, f"r{i}", self.city, pose=p) for i, p in enumerate(poses)]


class ArrayRaster:
    """A (C, H, W) uint8 city raster on a :class:`geometry.RasterGrid` with the maps API."""

    def __init__(self, mask: np.ndarray, grid: geometry.RasterGrid):
        self.mask = mask
        self.grid = grid

    def tile(self, x: float, y: float):
        row0, col0, cx, cy = geometry.tile_window(self.grid, x, y)
        tile = geometry.crop(self.mask, row0, col0, geometry.TILE_SIZE)
        return tile, (float(cx), float(cy))

    def cut_bev(self, pose):
        world = geometry.ego_to_world(pose, geometry.bev_cell_centers_ego())  # (128, 128, 2)
        row, col = self.grid.world_to_pixel(world[..., 0], world[..., 1])
        r, c = np.floor(row).astype(int), np.floor(col).astype(int)
        inside = (r >= 0) & (r < self.grid.height) & (c >= 0) & (c < self.grid.width)
        out = np.zeros((self.mask.shape[0], *r.shape), np.uint8)
        out[:, inside] = self.mask[:, r[inside], c[inside]]
        return out


def random_raster(seed: int = 0, size_m: float = 600.0) -> ArrayRaster:
    grid = geometry.RasterGrid.covering((0.0, 0.0, size_m, size_m))
    mask = np.random.default_rng(seed).random((2, grid.height, grid.width)) < 0.3
    return ArrayRaster(mask.astype(np.uint8), grid)


def small_config(root, **kw) -> PrepareConfig:
    base = dict(
        name="tiny",
        root=str(root),
        seed=5,
        num_train=24,
        num_val=8,
        num_test=8,
        num_test_city=6,
        shard_size=10,
        render_batch=4,
        pool_factor=2.0,
        max_rounds=10,
        split=splits.SplitConfig(stripe_width=25.0),
        num_drives=0,  # drive splits are opt-in here (tests of drives turn them on, tiny)
        num_val_drives=0,
        num_unseen_val_drives=0,
    )
    return PrepareConfig(**(base | kw))


class Factory:
    """source_factory that remembers its sources (render-call counts) and can interrupt."""

    def __init__(self, fail_after=None):
        self.fail_after = fail_after
        self.sources = {}

    def __call__(self, city):
        self.sources[city] = GridSource(city, size=1200.0, fail_after=self.fail_after)
        return self.sources[city]

    @property
    def calls(self):
        return sum(s.calls for s in self.sources.values())
