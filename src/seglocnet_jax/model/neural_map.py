"""SegLocNet-NM: a small U-Net turns the tile of the multi-class OSM raster (the paper's
rasterized SD map: road classes, paths, buildings, parking, green, water; ``maps.OSM_CLASSES``)
into matching features, matched against BEV matching features by the exhaustive solver's score
volume.

Both feature maps are L2-normalized per pixel, so the score volume sums cosine similarities; a
learned positive factor (initial ``nm_init_scale``) sets the sharpness of the log-softmax over
all ``K x 129 x 129`` cells. The tile keeps its north-up orientation; the BEV features keep the
ego orientation (forward = up), exactly like the segmentation path.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.model.layers import ConvNormAct, upsample2x


def l2_normalize(x: jax.Array, axis: int = -1, eps: float = 1e-6) -> jax.Array:
    return x * jax.lax.rsqrt(jnp.sum(x * x, axis=axis, keepdims=True) + eps)


class NeuralMapEncoder(nn.Module):
    """U-Net over the OSM class tile: ``(B, C_osm, 256, 256)`` {0, 1} (any dtype) ->
    ``(B, 256, 256, D')`` (unit norm)."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, tile):
        widths = self.cfg.nm_widths
        x = jnp.moveaxis(tile.astype(jnp.float32), 1, -1)  # (B, 256, 256, C)
        x = ConvNormAct(widths[0])(x)
        skips = []
        for width in widths[1:]:
            skips.append(x)
            x = ConvNormAct(width, strides=2)(x)
        for skip in reversed(skips):
            x = upsample2x(x)
            x = ConvNormAct(skip.shape[-1])(jnp.concatenate([x, skip], axis=-1))
        return l2_normalize(nn.Conv(self.cfg.nm_dim, (1, 1), name="match_proj")(x))


class BevMatchingHead(nn.Module):
    """Decoder features ``(B, 128, 128, F)`` -> BEV matching features ``(B, 128, 128, D')``."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, feats):
        x = ConvNormAct(feats.shape[-1])(feats)
        return l2_normalize(nn.Conv(self.cfg.nm_dim, (1, 1), name="match_proj")(x))


class MatchScale(nn.Module):
    """The learned positive factor on the cosine score volume (stored as its log)."""

    init_scale: float

    @nn.compact
    def __call__(self):
        log_scale = self.param("log_scale", nn.initializers.constant(jnp.log(self.init_scale)), ())
        return jnp.exp(log_scale)
