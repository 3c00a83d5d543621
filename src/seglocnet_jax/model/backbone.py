"""2D image backbones giving stride-8 and stride-16 feature maps: ResNet-style and VoVNet-style.

Both are initialized from scratch (no pretrained weights can be downloaded here). Input images
are uint8 RGB; they are scaled to [0, 1] and standardized with the usual ImageNet statistics.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from seglocnet_jax.model.layers import ConvNormAct, ResBlock

IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)
STRIDE = 16


def normalize_images(images: jax.Array) -> jax.Array:
    """uint8 ``(..., H, W, 3)`` RGB to standardized float32."""
    x = images.astype(jnp.float32) / 255.0
    return (x - jnp.asarray(IMAGE_MEAN)) / jnp.asarray(IMAGE_STD)


def check_image_size(height: int, width: int):
    if height % STRIDE or width % STRIDE:
        raise ValueError(
            f"camera images must have H and W divisible by {STRIDE} (the backbone "
            f"stride), got {height}x{width}: resize them in the data pipeline"
        )


class ResNet(nn.Module):
    """Stride-2 stem, then three stride-2 stages of basic residual blocks (stride 16 total).

    ``widths``: (stem, stage1, stage2, stage3) channels; ``blocks``: blocks per stage.
    ``(M, H, W, 3)`` standardized images -> the stage outputs ``[(M, H/4, W/4, widths[1]),
    (M, H/8, W/8, widths[2]), (M, H/16, W/16, widths[3])]``.
    """

    widths: Sequence[int]
    blocks: Sequence[int]

    @nn.compact
    def __call__(self, x):
        x = ConvNormAct(self.widths[0], (3, 3), 2)(x)
        stages = []
        for width, n in zip(self.widths[1:], self.blocks, strict=True):
            for i in range(n):
                x = ResBlock(width, strides=2 if i == 0 else 1)(x)
            stages.append(x)
        return stages


class OSAModule(nn.Module):
    """One-shot aggregation (VoVNet): a chain of 3x3 convs whose outputs are all concatenated
    once, fused by a 1x1 conv, gated by effective squeeze-excitation (VoVNetV2), plus an
    identity shortcut when the width is unchanged."""

    stage_width: int
    out_width: int
    num_layers: int

    @nn.compact
    def __call__(self, x):
        outputs = [x]
        y = x
        for _ in range(self.num_layers):
            y = ConvNormAct(self.stage_width)(y)
            outputs.append(y)
        y = ConvNormAct(self.out_width, (1, 1))(jnp.concatenate(outputs, axis=-1))
        gate = nn.Dense(self.out_width)(y.mean(axis=(1, 2), keepdims=True))  # eSE
        y = y * nn.hard_sigmoid(gate)
        return y + x if x.shape[-1] == self.out_width else y


class VoVNet(nn.Module):
    """VoVNet-style backbone: stride-2 stem, then three stages of (3x3/2 max-pool, OSA
    modules). Same widths/blocks convention and outputs as :class:`ResNet`."""

    widths: Sequence[int]
    blocks: Sequence[int]
    num_layers: int = 5

    @nn.compact
    def __call__(self, x):
        x = ConvNormAct(self.widths[0], (3, 3), 2)(x)
        stages = []
        for width, n in zip(self.widths[1:], self.blocks, strict=True):
            x = nn.max_pool(x, (3, 3), strides=(2, 2), padding="SAME")
            for _ in range(n):
                x = OSAModule(max(width // 4, 8), width, self.num_layers)(x)
            stages.append(x)
        return stages


def make_backbone(
    kind: str, widths: Sequence[int], blocks: Sequence[int], vovnet_layers: int
) -> nn.Module:
    if kind == "resnet":
        return ResNet(tuple(widths), tuple(blocks))
    if kind == "vovnet":
        return VoVNet(tuple(widths), tuple(blocks), vovnet_layers)
    raise ValueError(f"model.backbone must be 'resnet' or 'vovnet', got {kind!r}")
