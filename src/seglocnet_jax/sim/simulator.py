"""``Simulator(world, sensor_cfg).render(poses, seed)``: sample dicts of the 6-camera rig and the
LiDAR at world poses (the producer samples of ``data.schema``, which ``data.simulated.source``
validates: ``sim`` does not import ``data``).

Per frame a square patch of the world raster around the pose is cut in NumPy (static size, so
one compiled function serves every frame, and every world of the same preset, resolution and
seed); ``cfg.chunk`` frames are rendered per call by a jitted, vmapped function, the chunks of a
call dispatched before any is fetched. Everything random (lighting, noise, dropout) derives
from ``seed`` and the frame's index in the call: the same poses and seed give the same samples.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.sim import camera as cam
from seglocnet_jax.sim import lidar as ld
from seglocnet_jax.sim import render as rn
from seglocnet_jax.sim import sensors as sn
from seglocnet_jax.sim.classes import thing_palette
from seglocnet_jax.sim.world import World

_LAYERS = ("surface", "thing", "colour", "top", "bottom")


@dataclasses.dataclass(frozen=True)
class _Rig:
    """What the compiled frame function reads: the sensors, the world's resolution, level
    height and palette seed. Equal rigs (every city of one preset) share one compiled renderer."""

    cfg: sn.SensorConfig
    resolution: float
    level_height: float
    palette_seed: int

    @functools.cached_property
    def arrays(self) -> dict:
        """The rig's device constants (camera and LiDAR columns, march samples, palette)."""
        cfg = self.cfg
        d, step = sn.march_distances(cfg)
        return {
            "cam": tuple(jnp.asarray(a) for a in sn.camera_columns(cfg)),
            "lidar": tuple(jnp.asarray(a) for a in sn.lidar_columns(cfg)),
            "dists": jnp.asarray(d),
            "steps": jnp.asarray(step),
            "palette": jnp.asarray(thing_palette(self.palette_seed)),
        }


@functools.lru_cache(maxsize=8)
def _renderer(rig: _Rig, diagnostics: bool):
    """The jitted, vmapped :func:`_frame` of ``rig`` (compiled once per rig and ``diagnostics``)."""
    return jax.jit(jax.vmap(functools.partial(_frame, rig, diagnostics=diagnostics)))


def _frame(rig: _Rig, patch, pose, cell0, light, key, *, diagnostics: bool):
    cfg, res, arr = rig.cfg, rig.resolution, rig.arrays
    patch = {
        k: v.astype(jnp.int32 if k in ("surface", "thing", "colour") else jnp.float32)
        for k, v in patch.items()
    }
    k_cam, k_lidar = jax.random.split(key)
    pos, az, slopes = arr["cam"]
    hits = rn.march(patch, pose, pos, az, slopes, arr["dists"], arr["steps"], cfg.max_range, res)
    rgb = cam.shade(
        hits,
        slopes,
        light,
        arr["palette"],
        cell0,
        res,
        k_cam,
        cfg.pixel_noise,
        rig.level_height,
    )  # (N*W, H, 3)
    n, h, w = len(geometry.CAMERA_NAMES), cfg.image_height, cfg.image_width
    images = cam.to_uint8(rgb).reshape(n, w, h, 3).transpose(0, 2, 1, 3)  # (N, H, W, 3)

    lpos, laz, lslopes = arr["lidar"]
    lhits = rn.march(
        patch, pose, lpos, laz, lslopes, arr["dists"], arr["steps"], cfg.max_range, res
    )
    lpts = rn.hit_points_ego(lhits, lpos, laz, lslopes)  # (A, beams, 3)
    lid = ld.returns(
        lhits,
        lpts,
        lpos[0],
        k_lidar,
        range_noise=cfg.range_noise,
        dropout=cfg.dropout,
        intensity_noise=cfg.intensity_noise,
        max_range=cfg.max_range,
    )
    out = {"images": images, "lidar": lid["points"], "lidar_valid": lid["valid"]}
    if diagnostics:  # ground truth for tests and benchmarks, never stored
        cam_points = rn.hit_points_ego(hits, pos, az, slopes)  # (N*W, H, 3) ego
        out["cam_points"] = cam_points.reshape(n, w, h, 3).transpose(0, 2, 1, 3)
        out["cam_kind"] = hits["kind"].reshape(n, w, h).transpose(0, 2, 1)
        out["lidar_thing"] = lid["thing"]
    return out


class Simulator:
    """Renders the sensors of ``cfg`` (:class:`sensors.SensorConfig`) in ``world``."""

    def __init__(self, world: World, cfg: sn.SensorConfig | None = None):
        self.world = world
        self.cfg = cfg = cfg or sn.SensorConfig()
        res = world.grid.resolution
        reach = cfg.max_range + 2.5  # sensors sit up to ~2 m from the ego origin
        self.patch_size = 2 * int(math.ceil(reach / res))
        self.intrinsics = sn.intrinsics(cfg)  # (N, 3, 3)
        self.cam_to_ego = sn.cam_to_ego(cfg)  # (N, 4, 4)
        self._rig = _Rig(cfg, float(res), float(world.cfg.level_height), int(world.seed))
        self._rig.arrays  # noqa: B018  (made here, outside any trace: the jit closes over them)

    def _renderer(self, diagnostics: bool):
        return _renderer(self._rig, diagnostics)

    # ------------------------------------------------------------------ host side

    def _patch(self, pose) -> tuple[dict, np.ndarray, np.ndarray]:
        """Crop around ``pose``: layers (P, P), patch-local pose (3,), cell offset (2,)."""
        grid, p = self.world.grid, self.patch_size
        row0, col0, _, _ = geometry.tile_window(grid, pose[0], pose[1], p)
        row0, col0 = int(row0), int(col0)
        if row0 >= grid.height or col0 >= grid.width or row0 + p <= 0 or col0 + p <= 0:
            raise ValueError(
                f"world {self.world.name!r}: pose {tuple(pose)} is outside the world "
                f"raster (bounds {grid.bounds})"
            )
        layers = {name: geometry.crop(getattr(self.world, name), row0, col0, p) for name in _LAYERS}
        x0, y0 = grid.pixel_to_world(row0, col0)  # patch north-west corner, world metres
        local = np.array([pose[0] - x0, pose[1] - y0, pose[2]], np.float32)
        return layers, local, np.array([row0, col0], np.int32)

    def render_arrays(self, poses, seed: int, *, diagnostics: bool = False) -> dict:
        """Batched NumPy outputs for ``poses`` (B, 3): ``images`` (B, N, H, W, 3) uint8,
        ``lidar`` (B, A*beams, 4), ``lidar_valid`` (B, A*beams) bool and ``lighting`` (B,) str
        (each frame's drawn condition: day, dusk or night).

        ``diagnostics`` also returns what only tests and benchmarks read (computed only then):
        ``cam_points`` (B, N, H, W, 3) ego-frame hit point per pixel, ``cam_kind`` (B, N, H, W)
        (render.SKY / GROUND / THING) and ``lidar_thing`` (B, A*beams) object class per return.
        The shared outputs are the same with or without it."""
        poses = np.asarray(poses, np.float64).reshape(-1, 3)
        b = len(poses)
        if b == 0:
            raise ValueError("render: no poses")
        if not np.all(np.isfinite(poses)):
            raise ValueError("render: poses must be finite (x m, y m, yaw rad)")
        chunk = self.cfg.chunk
        padded = np.concatenate([poses, np.repeat(poses[-1:], (-b) % chunk, axis=0)])
        outs, conditions = [], []
        for start in range(0, len(padded), chunk):
            frames = [self._patch(p) for p in padded[start : start + chunk]]
            lights = []
            for i in range(start, start + chunk):
                rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, i, 0x5E])
                lights.append(cam.draw_lighting(rng, self.cfg.night_prob, self.cfg.dusk_prob))
            base = jax.random.key(np.uint32(int(seed) & 0xFFFFFFFF))
            keys = jax.vmap(lambda i, base=base: jax.random.fold_in(base, i))(
                jnp.arange(start, start + chunk)
            )
            out = self._renderer(diagnostics)(
                {k: np.stack([f[0][k] for f in frames]) for k in _LAYERS},
                np.stack([f[1] for f in frames]),
                np.stack([f[2] for f in frames]),
                {k: np.stack([lt[k] for lt in lights]) for k in cam.LIGHT_KEYS},
                keys,
            )
            outs.append(out)  # not fetched yet: the next chunk's crops overlap this one
            conditions.extend(lt["condition"] for lt in lights)
        outs = jax.device_get(outs)
        arrays = {k: np.concatenate([o[k] for o in outs])[:b] for k in outs[0]}
        return {**arrays, "lighting": np.array(conditions[:b])}

    def render(self, poses, seed: int, sample_ids=None, sequences=None) -> list[dict]:
        """One sample dict (keys ``sample_id``, ``city``, ``sequence_id``, ``frame_index``,
        ``timestamp``, ``lighting``, ``pose``, ``images``, ``intrinsics``, ``cam_to_ego``,
        ``lidar``:
        ``data.schema.SAMPLE_KEYS``) per pose; ``sample_id`` defaults to
        ``"{city}-{seed}-{i:04d}"``. ``sequences``: one ``(sequence_id, frame_index, timestamp
        seconds)`` per pose; by default the poses are one sequence ``"{city}-{seed}"`` in their
        order, ``timestamp`` 0 (unknown)."""
        poses = np.asarray(poses, np.float64).reshape(-1, 3)
        arrays = self.render_arrays(poses, seed)
        samples = []
        for i, pose in enumerate(poses):
            sid = sample_ids[i] if sample_ids is not None else f"{self.world.name}-{seed}-{i:04d}"
            seq, index, stamp = (
                sequences[i] if sequences is not None else (f"{self.world.name}-{seed}", i, 0.0)
            )
            sample = {
                "sample_id": sid,
                "city": self.world.name,
                "sequence_id": str(seq),
                "frame_index": np.int64(index),
                "timestamp": np.float64(stamp),
                "lighting": str(arrays["lighting"][i]),
                "pose": pose.copy(),
                "images": arrays["images"][i],
                "intrinsics": self.intrinsics.copy(),
                "cam_to_ego": self.cam_to_ego.copy(),
                "lidar": np.ascontiguousarray(arrays["lidar"][i][arrays["lidar_valid"][i]]),
            }
            samples.append(sample)
        return samples
