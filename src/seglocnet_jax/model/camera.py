"""Camera encoder: per-view stride-16 features + PETR-style 3D position embedding, read by BEV
queries through a DETR-style transformer decoder into a 16x16xD latent BEV map.

The position embedding lifts every feature pixel to ``depth_bins`` points along its camera ray
(:func:`frustum_points_ego`, a pure function tested against a NumPy projection), expresses them
in the ego frame (x forward, y left, z up, metres), normalizes them to the perception range and
maps them through an MLP. BEV queries come from the ego-frame centres of the 16x16 latent cells
(``geometry.bev_cell_centers_ego``: row 0 is the far front, columns run to the vehicle's right).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.model.backbone import check_image_size, make_backbone, normalize_images
from seglocnet_jax.model.config import LATENT_SIZE, PERCEPTION_RANGE, ModelConfig
from seglocnet_jax.model.layers import MLP, upsample2x
from seglocnet_jax.model.transformer import LocalDecoderLayer, TransformerDecoder


def depth_bins(num: int, depth_min: float, depth_max: float) -> np.ndarray:
    """Linear-increasing depths (PETR's LID): ``(num,)`` metres from near ``depth_min`` to
    exactly ``depth_max``, spacing growing linearly with the index."""
    i = np.arange(1, num + 1, dtype=np.float64)
    return (depth_min + (depth_max - depth_min) * i * (i + 1) / (num * (num + 1))).astype(
        np.float32
    )


def feature_pixel_centers(feat_h: int, feat_w: int, stride: int) -> np.ndarray:
    """Image ``(u, v)`` of each stride-``stride`` feature pixel's centre, ``(h, w, 2)``.

    OpenCV pixel convention (integer coordinates are pixel centres): feature pixel ``(i, j)``
    covers image pixels ``[s*j, s*j + s)``, so its centre is ``u = s*j + (s - 1) / 2``.
    """
    u = np.arange(feat_w, dtype=np.float32) * stride + (stride - 1) / 2
    v = np.arange(feat_h, dtype=np.float32) * stride + (stride - 1) / 2
    uu, vv = np.meshgrid(u, v, indexing="xy")
    return np.stack([uu, vv], axis=-1)


def frustum_points_ego(
    intrinsics: jax.Array, cam_to_ego: jax.Array, feat_hw: tuple[int, int], stride: int, depths
) -> jax.Array:
    """Ego-frame points of every feature pixel at every depth.

    Args:
      intrinsics: ``(..., 3, 3)`` pinhole matrices in pixels of the input image.
      cam_to_ego: ``(..., 4, 4)`` camera (OpenCV: x right, y down, z forward) to ego (x forward,
        y left, z up) transforms, metres.
      feat_hw: feature map ``(h, w)``; stride: image pixels per feature pixel.
      depths: ``(D,)`` metres along the camera z axis.

    Returns:
      ``(..., h, w, D, 3)`` ego ``(x, y, z)`` metres of ``z_cam * K^-1 [u, v, 1]``.
    """
    uv = jnp.asarray(feature_pixel_centers(*feat_hw, stride))  # (h, w, 2)
    pix = jnp.concatenate([uv, jnp.ones(uv.shape[:-1] + (1,), uv.dtype)], axis=-1)  # (h, w, 3)
    k_inv = jnp.linalg.inv(intrinsics)  # (..., 3, 3)
    rays = jnp.einsum("...ij,hwj->...hwi", k_inv, pix)  # (..., h, w, 3), z = 1 for pinhole K
    depths = jnp.asarray(depths, jnp.float32)
    pts_cam = rays[..., None, :] * depths[:, None]  # (..., h, w, D, 3)
    rot, trans = cam_to_ego[..., :3, :3], cam_to_ego[..., :3, 3]
    pts = jnp.einsum("...ij,...hwdj->...hwdi", rot, pts_cam)
    return pts + trans[..., None, None, None, :]


def normalize_ego_points(points: jax.Array, z_range: tuple[float, float]) -> jax.Array:
    """Ego ``(..., 3)`` metres to about [-1, 1]: x, y over +-``PERCEPTION_RANGE``, z over
    ``z_range``. Points outside the range keep growing linearly (no clipping)."""
    lo, hi = z_range
    scale = jnp.asarray([1 / PERCEPTION_RANGE, 1 / PERCEPTION_RANGE, 2 / (hi - lo)])
    shift = jnp.asarray([0.0, 0.0, -(hi + lo) / (hi - lo)])
    return points * scale + shift


PILLAR_HEIGHTS = (0.0, 1.0, 2.0, 3.0)  # ego z (m, ground = 0) of the points of a query's pillar
BIAS_FLOOR = -8.0  # attention logit bias of a token no pillar point projects near
FINE_TOKENS = 16  # tokens each cell of the fine query grid reads (model.camera_fine_grid)
GROUND_GRID = 64  # cells of model.camera_ground_skip's grid per side (1 m over +-32 m)


def pillar_points(size: int, heights) -> jax.Array:
    """Ego ``(x, y, z)`` metres of each ``size x size`` cell's centre (:func:`bev_reference_points`
    order) at each of ``heights``: ``(size * size, H, 3)``."""
    cells = jnp.asarray(bev_reference_points(size).reshape(-1, 2) * PERCEPTION_RANGE)
    z = jnp.broadcast_to(
        jnp.asarray(heights, jnp.float32)[None, :, None], (len(cells), len(heights), 1)
    )
    xy = jnp.broadcast_to(cells[:, None], (len(cells), len(heights), 2))
    return jnp.concatenate([xy, z], axis=-1)


def geometric_attention_bias(
    intrinsics: jax.Array,
    cam_to_ego: jax.Array,
    feat_hw: tuple[int, int],
    stride: int,
    size: int = LATENT_SIZE,
) -> jax.Array:
    """Cross-attention logit bias of each BEV query for each camera token: the pillar of the
    query's latent cell (its centre at :data:`PILLAR_HEIGHTS`) projected into every camera;
    ``-d^2 / 2`` for the distance ``d`` (in feature pixels) from the nearest projected point to
    the token's pixel centre, at least :data:`BIAS_FLOOR` (also behind the camera).

    Args:
      intrinsics: ``(B, N, 3, 3)``; cam_to_ego: ``(B, N, 4, 4)`` (OpenCV camera, ego frame).
      feat_hw: feature map ``(h, w)``; stride: image pixels per feature pixel.
      size: the query grid is ``size x size`` cells over +-32 m.

    Returns:
      ``(B, Q, N * h * w)`` float32, queries in :func:`bev_reference_points` order (row-major
      ``size x size``), tokens in ``(camera, row, column)`` order like the encoder's tokens.
    """
    pts = pillar_points(size, PILLAR_HEIGHTS)  # (Q, H, 3) ego metres
    ego_to_cam = jnp.linalg.inv(cam_to_ego)  # (B, N, 4, 4)
    cam = jnp.einsum("bnij,qhj->bnqhi", ego_to_cam[..., :3, :3], pts)
    cam = cam + ego_to_cam[..., None, None, :3, 3]  # (B, N, Q, H, 3)
    z = cam[..., 2]
    pix = jnp.einsum("bnij,bnqhj->bnqhi", intrinsics, cam)
    uv = pix[..., :2] / jnp.maximum(z, 1e-3)[..., None]  # (B, N, Q, H, 2) image pixels
    centres = feature_pixel_centers(*feat_hw, stride)  # (h, w, 2)
    du = (uv[..., :1] - jnp.asarray(centres[0, :, 0])) / stride  # (B, N, Q, H, w)
    dv = (uv[..., 1:] - jnp.asarray(centres[:, 0, 1])) / stride  # (B, N, Q, H, h)
    d2 = None
    for i in range(len(PILLAR_HEIGHTS)):  # one (B, N, Q, h, w) array per height, no reduction
        di = du[:, :, :, i, None, :] ** 2 + dv[:, :, :, i, :, None] ** 2
        di = jnp.where(z[:, :, :, i, None, None] > 0.1, di, jnp.inf)
        d2 = di if d2 is None else jnp.minimum(d2, di)
    bias = jnp.maximum(-0.5 * d2, BIAS_FLOOR)  # (B, N, Q, h, w)
    b, n, q = bias.shape[:3]
    return jnp.moveaxis(bias, 2, 1).reshape(b, q, n * feat_hw[0] * feat_hw[1])


def ground_features(
    stage: jax.Array,
    intrinsics: jax.Array,
    cam_to_ego: jax.Array,
    stride: int,
    size: int,
    heights=PILLAR_HEIGHTS,
) -> jax.Array:
    """Camera features sampled where each cell of a ``size x size`` BEV grid projects: every
    cell's centre at each of ``heights`` (ego z, m) is projected into the camera that sees it
    most frontally (the largest cosine between its optical axis and the point, among the
    cameras with the point in front and inside the feature map), and that camera's feature map
    is bilinearly interpolated there (feature pixel centres as in
    :func:`feature_pixel_centers`). One gather per corner and point: all cameras' samples
    averaged cost the training step twice its time (the scatter of the backward pass).

    Args:
      stage: ``(B, N, h, w, F)`` features of stride ``stride``.
      intrinsics: ``(B, N, 3, 3)``; cam_to_ego: ``(B, N, 4, 4)`` (OpenCV camera, ego frame).
      size: the grid is ``size x size`` cells over +-32 m, rows and columns as
        :func:`bev_reference_points`.

    Returns:
      ``(B, size, size, H * (F + 1))``: per height the sampled features (0 where no camera sees
      the point), then per height whether a camera sees it (1 or 0).
    """
    b, n, fh, fw, f = stage.shape
    pts = pillar_points(size, heights).reshape(-1, 3)  # (P * H, 3) ego metres
    ego_to_cam = jnp.linalg.inv(cam_to_ego)  # (B, N, 4, 4)
    cam = jnp.einsum("bnij,pj->bnpi", ego_to_cam[..., :3, :3], pts) + ego_to_cam[..., None, :3, 3]
    pix = jnp.einsum("bnij,bnpj->bnpi", intrinsics, cam)
    z = cam[..., 2]
    uv = pix[..., :2] / jnp.maximum(z, 1e-3)[..., None]
    fu = (uv[..., 0] - (stride - 1) / 2) / stride  # feature pixel coordinates, centres integer
    fv = (uv[..., 1] - (stride - 1) / 2) / stride
    seen = (z > 0.1) & (fu >= 0) & (fu <= fw - 1) & (fv >= 0) & (fv <= fh - 1)  # (B, N, PH)
    cosine = jnp.where(seen, z / jnp.maximum(jnp.linalg.norm(cam, axis=-1), 1e-6), -2.0)
    best = jnp.argmax(cosine, axis=1)[:, None]  # (B, 1, PH): the most frontal camera

    def pick(x):
        return jnp.take_along_axis(x, best, axis=1)[:, 0]  # (B, PH)

    fu, fv, seen = pick(fu), pick(fv), pick(seen)
    u0 = jnp.clip(jnp.floor(fu), 0, fw - 2)
    v0 = jnp.clip(jnp.floor(fv), 0, fh - 2)
    wu, wv = jnp.clip(fu - u0, 0, 1), jnp.clip(fv - v0, 0, 1)
    base = (best[:, 0] * (fh * fw) + v0 * fw + u0).astype(jnp.int32)  # (B, PH)
    flat = stage.reshape(b, n * fh * fw, f)

    def corner(offset, weight):
        vals = jnp.take_along_axis(flat, (base + offset)[..., None], axis=1)  # (B, PH, F)
        return vals * weight[..., None]

    sample = corner(0, (1 - wv) * (1 - wu)) + corner(1, (1 - wv) * wu)
    sample = sample + corner(fw, wv * (1 - wu)) + corner(fw + 1, wv * wu)
    seen = seen.astype(stage.dtype)
    nh = len(heights)
    feats = (sample * seen[..., None]).reshape(b, size, size, nh * f)
    return jnp.concatenate([feats, seen.reshape(b, size, size, nh)], axis=-1)


def fourier_features(x: jax.Array, num_frequencies: int) -> jax.Array:
    """Sinusoidal encoding of coordinates in about [-1, 1] (PETR / NeRF style): each of the
    ``(..., F)`` values becomes ``sin, cos`` of ``pi * 2**k * x`` for ``k < num_frequencies``,
    ``(..., F * 2 * num_frequencies)``."""
    freqs = jnp.pi * 2.0 ** jnp.arange(num_frequencies, dtype=jnp.float32)
    angles = (x[..., None] * freqs).reshape(x.shape[:-1] + (-1,))
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)


def bev_reference_points(size: int = LATENT_SIZE) -> np.ndarray:
    """Ego ``(forward, left)`` of the ``size x size`` query cell centres over +-32 m (the 16x16
    latent's by default), normalized to [-1, 1]: ``(size, size, 2)``; row 0 is the far front,
    columns run to the right."""
    cell = 2 * PERCEPTION_RANGE / size
    return (geometry.bev_cell_centers_ego(size, cell) / PERCEPTION_RANGE).astype(np.float32)


class CameraEncoder(nn.Module):
    """Surround images -> latent BEV ``(B, 16, 16, D)`` plus intermediates."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, images, intrinsics, cam_to_ego, deterministic: bool = True):
        # images: (B, N, H, W, 3) uint8; intrinsics (B, N, 3, 3); cam_to_ego (B, N, 4, 4)
        cfg = self.cfg
        b, n, h, w, _ = images.shape
        check_image_size(h, w)
        stride, d = cfg.token_stride, cfg.embed_dim
        fh, fw = h // stride, w // stride
        x = normalize_images(images).reshape(b * n, h, w, 3)
        stages = make_backbone(
            cfg.backbone, cfg.backbone_widths, cfg.backbone_blocks, cfg.vovnet_layers
        )(x)  # stride 4, 8, 16
        x = nn.Dense(d, name="token_proj")(stages[-1])  # (B*N, h/16, w/16, D)
        if stride == 8:  # FPN-style: the stride-16 tokens upsampled onto the stride-8 stage
            x = upsample2x(x) + nn.Dense(d, name="token_proj8")(stages[-2])
        feats = x.reshape(b, n * fh * fw, d)

        bins = depth_bins(cfg.depth_bins, cfg.depth_min, cfg.depth_max)
        pts = frustum_points_ego(
            intrinsics.astype(jnp.float32), cam_to_ego.astype(jnp.float32), (fh, fw), stride, bins
        )  # (B, N, fh, fw, Db, 3)
        pts = normalize_ego_points(pts, cfg.pos_z_range).reshape(b, n * fh * fw, -1)
        size = cfg.camera_queries
        ref = jnp.asarray(bev_reference_points(size)).reshape(-1, 2)  # (Q, 2)
        if cfg.position_frequencies:
            pts = fourier_features(pts, cfg.position_frequencies)
            ref = fourier_features(ref, cfg.position_frequencies)
        t_pos = MLP((4 * d, d), name="position_embedding")(pts)  # (B, T, D)

        q_pos = MLP((d, d), name="query_embedding")(ref)[None]  # (1, Q, D)
        content = self.param("query_content", nn.initializers.normal(0.02), (ref.shape[0], d))
        q = jnp.broadcast_to(content[None], (b,) + content.shape)
        q_pos = jnp.broadcast_to(q_pos, q.shape)
        bias = None
        if cfg.geometric_attention:
            bias = geometric_attention_bias(
                intrinsics.astype(jnp.float32),
                cam_to_ego.astype(jnp.float32),
                (fh, fw),
                stride,
                size,
            )  # (B, Q, T)
        q = TransformerDecoder(
            cfg.transformer_layers, cfg.num_heads, cfg.ffn_dim, cfg.dropout, name="decoder"
        )(q, q_pos, feats, t_pos, deterministic, bias)
        grid = q.reshape(b, size, size, d)  # (B, size, size, D)
        aux = {"camera_features": x.reshape(b, n, fh, fw, d)}
        if cfg.camera_ground_skip:  # the stride-4 stage sampled where each 1 m cell projects
            s4 = stages[0]
            aux["ground"] = ground_features(
                s4.reshape((b, n) + s4.shape[1:]),
                intrinsics.astype(jnp.float32),
                cam_to_ego.astype(jnp.float32),
                h // s4.shape[1],
                GROUND_GRID,
            )
        if cfg.camera_fine_grid:  # the decoder's camera skip (the latent stays the 16x16 grid)
            aux["skip"] = self._fine_grid(grid, feats, t_pos, intrinsics, cam_to_ego, (fh, fw))
        if size == LATENT_SIZE:
            return grid, aux
        # A finer query grid: its cells averaged onto the 16x16 latent for the fusion, the grid
        # itself a skip into the decoder at its size (like the LiDAR stages).
        f = size // LATENT_SIZE
        latent = grid.reshape(b, LATENT_SIZE, f, LATENT_SIZE, f, d).mean(axis=(2, 4))
        aux["skip"] = grid
        return latent, aux

    def _fine_grid(self, grid, feats, t_pos, intrinsics, cam_to_ego, feat_hw) -> jax.Array:
        """The ``camera_fine_grid`` refinement: each fine cell starts from its coarse query's
        output plus its own position embedding and reads the :data:`FINE_TOKENS` tokens its
        pillar projects nearest to (:func:`geometric_attention_bias`, top-k), biased the same
        way: ``(B, fine, fine, D)``."""
        cfg = self.cfg
        b, size, _, d = grid.shape
        fine = cfg.camera_fine_grid
        f = fine // size
        coarse = jnp.repeat(jnp.repeat(grid, f, axis=1), f, axis=2).reshape(b, fine * fine, d)
        ref = jnp.asarray(bev_reference_points(fine)).reshape(-1, 2)
        if cfg.position_frequencies:
            ref = fourier_features(ref, cfg.position_frequencies)
        q_pos = MLP((d, d), name="fine_query_embedding")(ref)[None]
        bias = geometric_attention_bias(
            intrinsics.astype(jnp.float32),
            cam_to_ego.astype(jnp.float32),
            feat_hw,
            cfg.token_stride,
            fine,
        )  # (B, fine^2, T)
        top, index = jax.lax.top_k(bias, min(FINE_TOKENS, bias.shape[-1]))
        refined = LocalDecoderLayer(cfg.num_heads, cfg.ffn_dim, name="fine_decoder")(
            coarse, jnp.broadcast_to(q_pos, coarse.shape), feats, t_pos, index, top
        )
        return refined.reshape(b, fine, fine, d)


def camera_skip_key(size: int) -> str:
    """Name of the camera's query grid at ``size x size`` among the decoder's skips."""
    return f"camera_grid{size}"


def ground_skip_key(size: int) -> str:
    """Name of the camera's ground-sampled features (``model.camera_ground_skip``) among the
    decoder's skips."""
    return f"camera_ground{size}"
