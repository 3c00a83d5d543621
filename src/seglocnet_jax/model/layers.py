"""Small building blocks shared by the encoders and decoders (NHWC / NDHWC, float32).

Normalization is GroupNorm everywhere: the model has parameters only (no batch statistics), so
``init`` / ``apply`` stay pure functions of ``params`` and batches of any size behave the same.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax


def num_groups(channels: int, max_groups: int = 8) -> int:
    """The largest group count <= ``max_groups`` that divides ``channels``."""
    return math.gcd(channels, max_groups)


class ConvNormAct(nn.Module):
    """Conv (2D or 3D, from the kernel's length) + GroupNorm + ReLU (``act=False``: no ReLU)."""

    features: int
    kernel: Sequence[int] = (3, 3)
    strides: Sequence[int] | int = 1
    act: bool = True

    @nn.compact
    def __call__(self, x):
        x = nn.Conv(
            self.features, tuple(self.kernel), strides=self.strides, padding="SAME", use_bias=False
        )(x)
        x = nn.GroupNorm(num_groups=num_groups(self.features))(x)
        return nn.relu(x) if self.act else x


class ResBlock(nn.Module):
    """Basic residual block (two 3x3 convs); a strided 1x1 projection when the shape changes."""

    features: int
    strides: int = 1
    ndim: int = 2

    @nn.compact
    def __call__(self, x):
        k3, k1 = (3,) * self.ndim, (1,) * self.ndim
        y = ConvNormAct(self.features, k3, self.strides)(x)
        y = ConvNormAct(self.features, k3, act=False)(y)
        if self.strides != 1 or x.shape[-1] != self.features:
            x = ConvNormAct(self.features, k1, self.strides, act=False)(x)
        return nn.relu(x + y)


class MLP(nn.Module):
    """Dense layers with ReLU between them (none after the last)."""

    features: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for i, f in enumerate(self.features):
            x = nn.Dense(f)(x)
            if i < len(self.features) - 1:
                x = nn.relu(x)
        return x


def upsample2x(x: jax.Array) -> jax.Array:
    """Bilinear x2 upsampling of ``(B, H, W, C)`` (pixel-centre aligned)."""
    b, h, w, c = x.shape
    return jax.image.resize(x, (b, 2 * h, 2 * w, c), method="bilinear")
