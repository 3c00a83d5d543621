"""The SegLocNet network (flax.linen): camera and/or LiDAR encoders, fusion, semantic decoder,
and for the NM variant the neural-map encoder and matching heads.

A missing modality is configuration (``ModelConfig.modality``): its branch is neither built nor
read, so its batch keys may be absent. Outputs keep their intermediates (``aux``) so evaluation
and figures never need to re-run parts of the model.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from seglocnet_jax.model.camera import CameraEncoder, camera_skip_key, ground_skip_key
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.model.decoder import Fusion, SemanticDecoder
from seglocnet_jax.model.lidar import LidarEncoder
from seglocnet_jax.model.neural_map import BevMatchingHead, MatchScale, NeuralMapEncoder

CAMERA_KEYS = ("images", "intrinsics", "cam_to_ego")
LIDAR_KEYS = ("points", "points_mask")


# What the NM map side reads: the tile of the multi-class OSM raster (``maps.OSM_CLASSES``),
# ``(B, C_osm, 256, 256)`` {0, 1}, placed like ``tile`` (``make_loader(nm_tiles=True)``).
NM_MAP_KEY = "nm_tile"


def required_keys(cfg: ModelConfig, map_side: bool = True) -> tuple[str, ...]:
    """Batch keys the network reads for this configuration (``map_side=False``: without the
    NM map side, :data:`NM_MAP_KEY`)."""
    keys = ()
    if cfg.use_camera:
        keys += CAMERA_KEYS
    if cfg.use_lidar:
        keys += LIDAR_KEYS
    if cfg.variant == "nm" and map_side:
        keys += (NM_MAP_KEY,)
    return keys


def check_batch(batch: dict, cfg: ModelConfig, map_side: bool = True):
    """Raises a ``KeyError`` naming the missing batch keys for ``model.modality`` / variant."""
    missing = [k for k in required_keys(cfg, map_side) if k not in batch]
    if missing:
        hint = ""
        if NM_MAP_KEY in missing:
            hint = (
                f"; {NM_MAP_KEY!r} is the OSM class raster's tile: "
                "data.loader.make_loader(nm_tiles=True)"
            )
        raise KeyError(
            f"batch lacks key(s) {missing} needed by model.modality="
            f"{cfg.modality!r}, model.variant={cfg.variant!r}{hint}"
        )


class SegLocNet(nn.Module):
    """``batch -> (bev_logits (B, C, 128, 128), aux)``.

    ``aux`` holds: ``bev_latent`` (B, 16, 16, D) fused latent; ``camera_latent`` /
    ``lidar_latent`` (B, 16, 16, D) for the built branches; ``camera_aux_logits`` (B, C, 16, 16)
    the camera latent's own logits when ``cfg.camera_aux`` (read by the loss only);
    ``bev_features`` (B, 128, 128, F) the decoder's last features; for the NM variant
    ``bev_match`` (B, D', 128, 128), ``map_match`` (B, D', 256, 256) (the neural map of
    ``batch["nm_tile"]``; both unit-norm per pixel, channels first like the solver's inputs)
    and ``match_scale`` () the learned score factor. ``map_side=False`` leaves the map side out
    (no ``map_match``: the localize step computes the BEV once per frame and the neural map per
    tile, :func:`seglocnet_jax.model.api.encode_map`).
    """

    cfg: ModelConfig

    @nn.compact
    def __call__(self, batch: dict, deterministic: bool = True, map_side: bool = True):
        cfg = self.cfg
        check_batch(batch, cfg, map_side=map_side)
        aux, latents, skips = {}, [], {}
        if cfg.use_camera:
            cam, cam_aux = CameraEncoder(cfg, name="camera")(
                batch["images"], batch["intrinsics"], batch["cam_to_ego"], deterministic
            )
            aux["camera_latent"] = cam
            latents.append(cam)
            if cfg.camera_aux:
                cam_logits = nn.Conv(cfg.num_classes, (1, 1), name="camera_aux")(cam)
                aux["camera_aux_logits"] = jnp.moveaxis(cam_logits, -1, 1)  # (B, C, 16, 16)
        if cfg.use_lidar:
            lid, lidar_skips = LidarEncoder(cfg, name="lidar")(
                batch["points"], batch["points_mask"]
            )
            aux["lidar_latent"] = lid
            latents.append(lid)
            if cfg.lidar_skips:
                skips.update(lidar_skips)
        if cfg.use_camera and "skip" in cam_aux:
            skips[camera_skip_key(cam_aux["skip"].shape[1])] = cam_aux["skip"]
        if cfg.use_camera and "ground" in cam_aux:
            skips[ground_skip_key(cam_aux["ground"].shape[1])] = cam_aux["ground"]
        fused = Fusion(cfg.embed_dim, name="fusion")(latents)  # (B, 16, 16, D)
        logits, feats = SemanticDecoder(cfg, name="decoder")(fused, skips)
        aux["bev_latent"] = fused
        aux["bev_features"] = feats
        if cfg.variant == "nm":
            bev_match = BevMatchingHead(cfg, name="bev_match")(feats)  # (B, 128, 128, D')
            aux["bev_match"] = jnp.moveaxis(bev_match, -1, 1)  # (B, D', 128, 128)
            if map_side:
                map_match = NeuralMapEncoder(cfg, name="neural_map")(batch[NM_MAP_KEY])
                aux["map_match"] = jnp.moveaxis(map_match, -1, 1)  # (B, D', 256, 256)
            aux["match_scale"] = MatchScale(cfg.nm_init_scale, name="match_scale")()
        return jnp.moveaxis(logits, -1, 1), aux  # (B, C, 128, 128)
