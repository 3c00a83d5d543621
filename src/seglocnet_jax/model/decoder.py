"""Fusion (concatenation + 1x1 conv) and the fully convolutional semantic decoder.

16x16 latent -> residual block -> three (x2 bilinear upsampling, 3x3 conv) levels (32, 64, 128)
-> ``(B, 128, 128, C)`` logits in the BEV's
orientation (row 0 the far front, columns to the vehicle's right). Optional U-Net-style skips
take the LiDAR encoder's 32x32 and 64x64 stage features, which keep geometry (kerbs, walls) that
the 4 m latent cells blur.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from seglocnet_jax.model.camera import camera_skip_key, ground_skip_key
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.model.layers import ConvNormAct, ResBlock, upsample2x
from seglocnet_jax.model.lidar import skip_key


class Fusion(nn.Module):
    """Concatenates the available latents ``(B, 16, 16, D_i)`` and mixes them with a 1x1 conv."""

    features: int

    @nn.compact
    def __call__(self, latents: list[jax.Array]) -> jax.Array:
        if not latents:
            raise ValueError("fusion needs at least one modality latent")
        x = jnp.concatenate(latents, axis=-1)
        return ConvNormAct(self.features, (1, 1))(x)  # (B, 16, 16, D)


class SemanticDecoder(nn.Module):
    """Latent ``(B, 16, 16, D)`` -> logits ``(B, 128, 128, C)`` and the last features.

    ``skips``: features by name (``lidar.skip_key(size)``, ``camera.camera_skip_key(size)``),
    each concatenated at its size (the caller passes only those the config asks for)."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, x, skips: dict | None = None):
        cfg = self.cfg
        x = ResBlock(cfg.embed_dim)(x)  # (B, 16, 16, D)
        for width in cfg.decoder_widths:
            x = upsample2x(x)
            size = x.shape[1]
            skip = (skips or {}).get(skip_key(size))
            if skip is not None:
                # Squeeze the z-folded LiDAR features first: the 3x3 conv stays cheap.
                skip = ConvNormAct(width, (1, 1), name=f"skip{size}")(skip)
                x = jnp.concatenate([x, skip], axis=-1)
            for key, name in ((camera_skip_key, "camera_skip"), (ground_skip_key, "ground_skip")):
                skip = (skips or {}).get(key(size))
                if skip is not None:
                    skip = ConvNormAct(width, (1, 1), name=f"{name}{size}")(skip)
                    x = jnp.concatenate([x, skip], axis=-1)
            # One 3x3 conv per level: the 64 and 128 px levels dominate the model's FLOPs.
            x = ConvNormAct(width, name=f"up{size}")(x)  # (B, size, size, width)
        logits = nn.Conv(cfg.num_classes, (1, 1), name="classifier")(x)  # (B, 128, 128, C)
        return logits, x
