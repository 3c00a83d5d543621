"""LiDAR encoder: dense voxelization (a pure function) and a SECOND-style conv stack down to the
16x16 latent BEV grid.

The voxel grid has the BEV's orientation (``geometry.ego_to_bev_pixel``): row = -forward,
column = -left, so row 0 is the far front and columns run to the vehicle's right; z bins go up
from ``z_min``. Dense 3D convs run on the first (coarse-channel) stages; then z is folded into
channels and the rest are 2D convs (cheap on CPU, same receptive field as SECOND's BEV head).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from seglocnet_jax import geometry
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.model.layers import ConvNormAct, ResBlock

NUM_VOXEL_FEATURES = 3  # log(1 + count), mean intensity, mean height within the voxel


def voxel_indices(
    points: jax.Array, mask: jax.Array, grid: tuple[int, int, int], voxel_size: float, z_min: float
):
    """Integer voxel ``(row, col, z)`` of each point and whether it lies in the grid.

    Args:
      points: ``(P, >=3)`` ego ``(x forward, y left, z up, ...)`` metres.
      mask: ``(P,)`` bool, False for padding.
      grid: ``(rows, cols, nz)``; voxel_size: metres; z_min: metres at the bottom of z bin 0.

    Returns:
      ``(P, 3)`` int32 indices and ``(P,)`` bool validity (mask and inside the grid).
    """
    rows, cols, nz = grid
    row, col = geometry.ego_to_bev_pixel(points[:, :2], rows, voxel_size)
    row = jnp.floor(row).astype(jnp.int32)
    col = jnp.floor(col).astype(jnp.int32)
    zi = jnp.floor((points[:, 2] - z_min) / voxel_size).astype(jnp.int32)
    inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols) & (zi >= 0) & (zi < nz)
    return jnp.stack([row, col, zi], axis=-1), inside & mask


def voxelize(
    points: jax.Array, mask: jax.Array, grid: tuple[int, int, int], voxel_size: float, z_min: float
) -> jax.Array:
    """Scatters one sample's points into a dense voxel grid (static shapes, padding ignored).

    Args:
      points: ``(P, 4)`` ego ``x, y, z`` (m) and intensity in [0, 1]; mask: ``(P,)`` bool.

    Returns:
      ``(rows, cols, nz, 3)`` float32 features per voxel: ``log(1 + count)``, mean intensity,
      mean height of the points above the voxel's floor in voxel units ([0, 1)); zero where
      empty.
    """
    rows, cols, nz = grid
    idx, valid = voxel_indices(points, mask, grid, voxel_size, z_min)
    size = rows * cols * nz
    flat = (idx[:, 0] * cols + idx[:, 1]) * nz + idx[:, 2]
    flat = jnp.where(valid, flat, size)  # out of bounds: dropped by the scatter
    height = (points[:, 2] - z_min) / voxel_size - idx[:, 2]
    vals = jnp.stack([jnp.ones_like(height), points[:, 3], height], axis=-1)  # (P, 3)
    sums = jnp.zeros((size, 3), jnp.float32).at[flat].add(vals.astype(jnp.float32), mode="drop")
    count = sums[:, 0]
    mean = sums[:, 1:] / jnp.maximum(count, 1.0)[:, None]
    feats = jnp.concatenate([jnp.log1p(count)[:, None], mean], axis=-1)
    return feats.reshape(rows, cols, nz, NUM_VOXEL_FEATURES)


class LidarEncoder(nn.Module):
    """Points -> latent BEV ``(B, 16, 16, D)``, plus the stage features (z folded) for skips."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, points, points_mask):
        # points: (B, P, 4) ego frame; points_mask: (B, P) bool
        cfg = self.cfg
        grid = cfg.voxel_grid
        x = jax.vmap(lambda p, m: voxelize(p, m, grid, cfg.voxel_size, cfg.z_min))(
            points.astype(jnp.float32), points_mask.astype(bool)
        )  # (B, R, C, Z, 3)
        stages = []
        for i, width in enumerate(cfg.lidar_widths):
            if i < cfg.lidar_3d_stages:
                z_stride = 2 if x.shape[3] > 1 else 1
                x = ConvNormAct(width, (3, 3, 3), (2, 2, z_stride), name=f"conv3d_{i}")(x)
                folded = x.reshape(x.shape[:3] + (-1,))  # (B, R', C', Z' * width)
                stages.append(folded)
                if i == cfg.lidar_3d_stages - 1:
                    x = folded
            else:
                if x.ndim == 5:  # no 3D stage at all
                    x = x.reshape(x.shape[:3] + (-1,))
                x = ResBlock(width, strides=2, name=f"conv2d_{i}")(x)
                stages.append(x)
        x = ResBlock(cfg.lidar_widths[-1], name="head")(x)
        latent = nn.Dense(cfg.embed_dim, name="latent_proj")(x)  # (B, 16, 16, D)
        # Stage outputs above the latent resolution (64x64, 32x32 at 0.5 m voxels): skips.
        skips = {skip_key(f.shape[1]): f for f in stages[:-1]}
        return latent, skips


def skip_key(size: int) -> str:
    """Name of the LiDAR stage features at ``size x size`` in the encoder's outputs."""
    return f"lidar_stage{size}"
