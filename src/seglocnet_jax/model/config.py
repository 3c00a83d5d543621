"""The network's configuration: one frozen dataclass, presets ``tiny`` and ``paper``.

Spatial constants are not configurable: the BEV (128x128 at 0.5 m/px, +-32 m) and the latent
grid (16x16, 4 m cells) come from :mod:`seglocnet_jax.geometry` and the three x2 decoder
upsamplings. All networks are initialized from scratch (no pretrained weights are downloaded).
"""

from __future__ import annotations

import dataclasses
import math

from seglocnet_jax import geometry

MODALITIES = ("fused", "camera", "lidar")
VARIANTS = ("seg", "nm")
BACKBONES = ("resnet", "vovnet")

LATENT_SIZE = geometry.BEV_SIZE // 8  # 16: three x2 upsamplings up to the BEV
PERCEPTION_RANGE = geometry.BEV_SIZE * geometry.RESOLUTION / 2  # 32 m each side of the ego


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """SegLocNet network + loss configuration (defaults: the network before each later option;
    the ``tiny`` preset is these defaults with ``geometric_attention`` and
    ``camera_ground_skip`` on and ``camera_aux_weight`` 1).

    Attributes:
      name: preset name (reporting only).
      modality: "fused" (camera + LiDAR), "camera" or "lidar"; the other branch is not built.
      variant: "seg" (segmentation, focal loss) or "nm" (SegLocNet-NM: neural-map matching
        features trained through the solver's score volume, plus the focal loss).
      num_classes: BEV channels C (order as the map variant's channels: road, building).
      embed_dim: latent width D of the 16x16 BEV map, the camera tokens and the queries.
      backbone: "resnet" (basic residual blocks) or "vovnet" (one-shot aggregation modules).
      backbone_widths: channels of the stride-2 stem and of the stride-4, -8, -16 stages.
      backbone_blocks: blocks per stage (3 entries; VoVNet: OSA modules per stage).
      vovnet_layers: 3x3 convs aggregated per OSA module.
      depth_bins: frustum depths per feature pixel for the 3D position embedding.
      depth_min, depth_max: metres along the camera z axis, linear-increasing bins (PETR's LID).
      pos_z_range: ego z (m) mapped to [-1, 1] for the position embedding (x, y use +-32 m).
      position_frequencies: 0: the position MLPs read the normalized coordinates; k > 0: their
        sinusoidal encoding at k octaves (``camera.fourier_features``).
      token_stride: 16: one camera token per stride-16 feature pixel; 8: per stride-8 pixel
        (the stride-16 features upsampled onto the stride-8 stage, FPN-style).
      geometric_attention: bias each BEV query's cross-attention towards the camera tokens its
        cell's pillar projects onto (``camera.geometric_attention_bias``).
      camera_queries: the BEV query grid is ``camera_queries x camera_queries`` over +-32 m:
        16 (the latent's 4 m cells) or 32 (2 m cells, averaged onto the latent for the fusion
        and fed to the decoder at 32x32 as a skip).
      camera_fine_grid: 0 (none), 32 or 64: a finer grid of camera cells, each starting from
        its coarse query's output and reading only the ``camera.FINE_TOKENS`` tokens its
        pillar projects nearest to (one cross-attention layer, ``transformer.LocalDecoderLayer``);
        fed to the decoder at its size as a skip. Needs ``camera_queries=16`` and
        ``geometric_attention``.
      camera_ground_skip: also sample the camera backbone's stride-4 features where each cell
        of a 64 x 64 (1 m) grid projects at ``camera.PILLAR_HEIGHTS`` (bilinear, in the camera
        that sees it most frontally; ``camera.ground_features``), fed to the decoder at 64 x 64 as
        a skip: the image's own resolution reaches the BEV without the 4 m latent.
      transformer_layers: DETR-style decoder layers (self-attn, cross-attn, FFN).
      num_heads: attention heads; ffn_dim: FFN hidden width; dropout: in attention and FFN.
      z_min, z_max: LiDAR voxel z range (m, ego frame); voxel_size: metres (x, y, z).
      lidar_widths: channels of the stride-2 LiDAR stages from the voxel grid to 16x16.
      lidar_3d_stages: how many of those stages are 3D convs (the rest run over z-folded
        channels in 2D).
      decoder_widths: channels at 32x32, 64x64 and 128x128.
      lidar_skips: also feed the LiDAR stage features at 32x32 and 64x64 to the decoder
        (concatenated, like U-Net skips; LiDAR modalities only).
      focal_alpha, focal_gamma: sigmoid focal loss (alpha < 0 disables class weighting).
      camera_aux_weight: weight of an auxiliary focal loss on the camera latent alone (a 1x1
        conv to the classes on its 16x16 cells, against the GT averaged over each cell), so
        that the camera branch learns the BEV where the LiDAR already explains it (fused
        modality only, as ``lidar_skips`` applies to LiDAR modalities only).
      nm_dim: D' matching channels (NM); nm_widths: neural-map U-Net channels per level.
      nm_num_rotations: K of the training score volume (NM; multiple of 4).
      nm_init_scale: initial value of the learned factor on the cosine score volume.
      nm_weight, seg_weight: NM loss = seg_weight * focal + nm_weight * pose NLL (seg_weight 10:
        at 1 the `tiny` NM's building channel collapsed, IoU 0.6 %; docs/results.md).
    """

    name: str = "tiny"
    modality: str = "fused"
    variant: str = "seg"
    num_classes: int = 2
    embed_dim: int = 64
    # camera
    backbone: str = "resnet"
    backbone_widths: tuple[int, ...] = (16, 24, 48, 64)
    backbone_blocks: tuple[int, ...] = (1, 1, 1)
    vovnet_layers: int = 3
    depth_bins: int = 16
    depth_min: float = 1.0
    depth_max: float = 45.0
    pos_z_range: tuple[float, float] = (-3.0, 5.0)
    position_frequencies: int = 0
    token_stride: int = 16
    geometric_attention: bool = False
    camera_queries: int = 16
    camera_fine_grid: int = 0
    camera_ground_skip: bool = False
    transformer_layers: int = 2
    num_heads: int = 4
    ffn_dim: int = 128
    dropout: float = 0.0
    # lidar
    z_min: float = -2.0
    z_max: float = 4.0
    voxel_size: float = geometry.RESOLUTION
    lidar_widths: tuple[int, ...] = (8, 32, 64)
    lidar_3d_stages: int = 1
    # decoder
    decoder_widths: tuple[int, ...] = (48, 32, 16)
    lidar_skips: bool = True
    # losses
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    camera_aux_weight: float = 0.0
    # neural map (variant "nm")
    nm_dim: int = 8
    nm_widths: tuple[int, ...] = (16, 32, 64)
    nm_num_rotations: int = 32
    nm_init_scale: float = 0.05
    nm_weight: float = 1.0
    seg_weight: float = 10.0

    def __post_init__(self):
        def bad(key, want):
            raise ValueError(f"model.{key} must be {want}, got {getattr(self, key)!r}")

        if self.modality not in MODALITIES:
            bad("modality", f"one of {MODALITIES}")
        if self.variant not in VARIANTS:
            bad("variant", f"one of {VARIANTS}")
        if self.backbone not in BACKBONES:
            bad("backbone", f"one of {BACKBONES}")
        for key in (
            "num_classes",
            "embed_dim",
            "depth_bins",
            "transformer_layers",
            "num_heads",
            "ffn_dim",
            "nm_dim",
            "nm_num_rotations",
            "vovnet_layers",
        ):
            if getattr(self, key) < 1:
                bad(key, ">= 1")
        if self.embed_dim % self.num_heads:
            bad("embed_dim", f"divisible by model.num_heads={self.num_heads}")
        if len(self.backbone_widths) != 4:
            bad("backbone_widths", "4 widths (stem, stride 4, 8, 16)")
        if len(self.backbone_blocks) != 3 or min(self.backbone_blocks) < 1:
            bad("backbone_blocks", "3 positive block counts (stride 4, 8, 16)")
        if not 0 < self.depth_min < self.depth_max:
            bad("depth_min", f"in (0, depth_max={self.depth_max})")
        if len(self.pos_z_range) != 2 or not self.pos_z_range[0] < self.pos_z_range[1]:
            bad("pos_z_range", "(low, high) with low < high")
        if self.token_stride not in (8, 16):
            bad("token_stride", "8 or 16")
        if self.camera_queries not in (LATENT_SIZE, 2 * LATENT_SIZE):
            bad("camera_queries", f"{LATENT_SIZE} or {2 * LATENT_SIZE}")
        if self.camera_fine_grid not in (0, 2 * LATENT_SIZE, 4 * LATENT_SIZE):
            bad("camera_fine_grid", f"0, {2 * LATENT_SIZE} or {4 * LATENT_SIZE}")
        if self.camera_fine_grid and (
            self.camera_queries != LATENT_SIZE or not self.geometric_attention
        ):
            bad(
                "camera_fine_grid",
                f"0 unless model.camera_queries={LATENT_SIZE} and model.geometric_attention "
                "(its cells read the tokens their pillars project nearest to)",
            )
        if self.position_frequencies < 0:
            bad("position_frequencies", ">= 0")
        if not 0.0 <= self.dropout < 1.0:
            bad("dropout", "in [0, 1)")
        if not self.z_min < self.z_max:
            bad("z_min", f"< model.z_max={self.z_max}")
        if len(self.lidar_widths) != self.num_lidar_stages:
            bad(
                "lidar_widths",
                f"{self.num_lidar_stages} widths: voxel grid "
                f"{self.voxel_grid[0]} down to {LATENT_SIZE} in x2 steps",
            )
        if not 0 <= self.lidar_3d_stages <= len(self.lidar_widths):
            bad("lidar_3d_stages", f"in [0, {len(self.lidar_widths)}]")
        if len(self.decoder_widths) != 3:
            bad("decoder_widths", "3 widths (32x32, 64x64, 128x128)")
        if self.nm_num_rotations % 4:
            bad("nm_num_rotations", "a multiple of 4")
        if len(self.nm_widths) < 1:
            bad("nm_widths", "at least one level")
        if self.nm_init_scale <= 0:
            bad("nm_init_scale", "> 0")
        if self.camera_aux_weight < 0:
            bad("camera_aux_weight", ">= 0")

    @property
    def camera_aux(self) -> bool:
        """Whether the fused model's camera latent has its own auxiliary loss."""
        return self.modality == "fused" and self.camera_aux_weight > 0

    @property
    def use_camera(self) -> bool:
        return self.modality in ("fused", "camera")

    @property
    def use_lidar(self) -> bool:
        return self.modality in ("fused", "lidar")

    @property
    def voxel_grid(self) -> tuple[int, int, int]:
        """``(rows, cols, z)`` voxels: rows = -forward, cols = -left (the BEV's orientation)."""
        n = 2 * PERCEPTION_RANGE / self.voxel_size
        nz = (self.z_max - self.z_min) / self.voxel_size
        if abs(n - round(n)) > 1e-6 or abs(nz - round(nz)) > 1e-6:
            raise ValueError(
                f"model.voxel_size={self.voxel_size} must divide the "
                f"{2 * PERCEPTION_RANGE} m range and model.z_max - model.z_min"
            )
        return int(round(n)), int(round(n)), int(round(nz))

    @property
    def num_lidar_stages(self) -> int:
        n = self.voxel_grid[0]
        steps = math.log2(n / LATENT_SIZE) if n >= LATENT_SIZE else -1
        if steps < 0 or steps != int(steps):
            raise ValueError(
                f"model.voxel_size={self.voxel_size}: a {n}-voxel grid does not "
                f"reach the {LATENT_SIZE}x{LATENT_SIZE} latent by x2 steps"
            )
        return int(steps)


# geometric_attention: validation R@1m camera only 2.3 -> 13.3, fused 45.3 -> 52.0 (budget cpu,
# seed 0; docs/results.md). The field's default stays False: a run stored before the option existed
# had no bias (app.runs reads an absent network key as its default).
# camera_aux_weight 1.0: fused validation R@1m 55.8 -> 59.0, test 61.1 -> 65.8 (means of seeds
# 0-2, every seed above its seed without it; docs/results.md). Default 0.0 for the same reason.
# camera_ground_skip: validation R@1m camera only 15.0 / 20.3 -> 31.0 / 38.0 (seeds 1 / 2),
# fused 60.3 / 56.3 / 60.3 -> 61.7 / 58.3 / 60.3 (seeds 0-2; docs/results.md). Default False too.
TINY = ModelConfig(geometric_attention=True, camera_aux_weight=1.0, camera_ground_skip=True)

PAPER = ModelConfig(
    name="paper",
    embed_dim=256,
    backbone="vovnet",
    backbone_widths=(64, 256, 512, 768),
    backbone_blocks=(1, 2, 2),
    vovnet_layers=5,
    depth_bins=64,
    depth_min=1.0,
    depth_max=61.2,
    transformer_layers=6,
    num_heads=8,
    ffn_dim=1024,
    dropout=0.1,
    lidar_widths=(32, 64, 128),
    lidar_3d_stages=2,
    decoder_widths=(128, 64, 32),
    lidar_skips=False,
    nm_dim=16,
    nm_widths=(32, 64, 128),
    nm_num_rotations=64,
)

PRESETS = {"tiny": TINY, "paper": PAPER}


def preset(name: str, **overrides) -> ModelConfig:
    """A preset (``"tiny"`` or ``"paper"``) with some fields replaced."""
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; expected one of {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides)
