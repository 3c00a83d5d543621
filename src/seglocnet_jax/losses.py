"""Training losses: sigmoid focal loss on the BEV segmentation and the NM pose likelihood.

Both are pure ``jax.numpy`` functions, jit- and grad-friendly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from seglocnet_jax import geometry


def sigmoid_focal_loss(
    logits: jax.Array, labels: jax.Array, alpha: float = 0.25, gamma: float = 2.0
) -> jax.Array:
    """Per-class sigmoid focal loss (Lin et al. 2017), mean over batch and pixels.

    Args:
      logits: ``(B, C, H, W)``; labels: ``(B, C, H, W)`` in [0, 1].
      alpha: weight of positives (negatives get ``1 - alpha``); ``alpha < 0`` disables.
      gamma: focusing exponent (0: plain binary cross-entropy).

    Returns:
      ``(C,)`` mean loss per class.
    """
    if logits.shape != labels.shape or logits.ndim != 4:
        raise ValueError(
            f"focal loss expects logits and labels (B, C, H, W) of one shape, got "
            f"{logits.shape} and {labels.shape}"
        )
    logits = logits.astype(jnp.float32)
    labels = labels.astype(jnp.float32)
    p = jax.nn.sigmoid(logits)
    # Stable BCE with logits: max(x, 0) - x*y + log(1 + exp(-|x|)).
    ce = jnp.maximum(logits, 0) - logits * labels + jnp.log1p(jnp.exp(-jnp.abs(logits)))
    p_t = p * labels + (1 - p) * (1 - labels)
    loss = ce * (1 - p_t) ** gamma
    if alpha >= 0:
        loss = loss * (alpha * labels + (1 - alpha) * (1 - labels))
    return loss.mean(axis=(0, 2, 3))


def gt_cells(pose_tile: jax.Array, num_rotations: int, size: int) -> jax.Array:
    """Integer GT cells ``(B, 3)`` = ``(k, h, w)`` of tile-frame poses ``(B, 3)``:
    :func:`geometry.pose_to_cell` rounded, k wrapped into [0, K), h and w clipped to the
    volume."""
    cell = geometry.pose_to_cell(pose_tile.astype(jnp.float32), num_rotations, size=size)
    cell = jnp.round(cell).astype(jnp.int32)
    k = jnp.mod(cell[:, 0], num_rotations)
    hw = jnp.clip(cell[:, 1:], 0, size - 1)
    return jnp.concatenate([k[:, None], hw], axis=1)


def pose_nll(log_probs: jax.Array, cells: jax.Array) -> jax.Array:
    """Negative log-likelihood of the GT cells: ``(B, K, H, W)`` log-probabilities (normalized
    over all cells of each sample) and ``(B, 3)`` integer cells -> ``(B,)``."""
    b = jnp.arange(log_probs.shape[0])
    return -log_probs[b, cells[:, 0], cells[:, 1], cells[:, 2]]
