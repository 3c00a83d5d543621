"""DETR-style transformer decoder: BEV queries attend to each other and to the camera tokens.

Pre-norm layers (LayerNorm before each sub-block, residual after), which train stably from
scratch without warm-up tricks. Positional embeddings are added to queries and keys, not to
values (DETR / PETR).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp


class DecoderLayer(nn.Module):
    """Self-attention over queries, cross-attention to tokens, FFN."""

    num_heads: int
    ffn_dim: int
    dropout: float = 0.0

    @nn.compact
    def __call__(self, q, q_pos, tokens, t_pos, deterministic: bool = True, bias=None):
        # q, q_pos: (B, Q, D); tokens, t_pos: (B, T, D); bias: (B, Q, T) cross-attention logits
        attn = dict(
            num_heads=self.num_heads, dropout_rate=self.dropout, deterministic=deterministic
        )
        h = nn.LayerNorm()(q)
        q = q + nn.MultiHeadDotProductAttention(**attn, name="self_attn")(h + q_pos, h + q_pos, h)
        h = nn.LayerNorm()(q)
        if bias is not None:  # the same bias for every head
            attn["attention_fn"] = functools.partial(nn.dot_product_attention, bias=bias[:, None])
        q = q + nn.MultiHeadDotProductAttention(**attn, name="cross_attn")(
            h + q_pos, tokens + t_pos, tokens
        )
        h = nn.LayerNorm()(q)
        h = nn.Dense(self.ffn_dim)(h)
        h = nn.Dropout(self.dropout, deterministic=deterministic)(nn.gelu(h))
        return q + nn.Dense(q.shape[-1])(h)


class TransformerDecoder(nn.Module):
    """``num_layers`` :class:`DecoderLayer` then a final LayerNorm: ``(B, Q, D)`` out."""

    num_layers: int
    num_heads: int
    ffn_dim: int
    dropout: float = 0.0

    @nn.compact
    def __call__(self, q, q_pos, tokens, t_pos, deterministic: bool = True, bias=None) -> jax.Array:
        for _ in range(self.num_layers):
            q = DecoderLayer(self.num_heads, self.ffn_dim, self.dropout)(
                q, q_pos, tokens, t_pos, deterministic, bias
            )
        return nn.LayerNorm()(q)


class LocalCrossAttention(nn.Module):
    """Multi-head cross-attention of each query to its own ``k`` tokens only.

    ``q`` ``(B, Q, D)``; ``keys``, ``values`` ``(B, T, D)``; ``index`` ``(B, Q, k)`` int, the
    tokens each query reads; ``bias`` ``(B, Q, k)`` added to every head's logits. The
    projections are those of a dense attention; only the ``k`` gathered tokens enter the
    softmax, so the cost grows with ``Q * k``, not ``Q * T``."""

    num_heads: int

    @nn.compact
    def __call__(self, q, keys, values, index, bias):
        d = q.shape[-1]
        heads, dh = self.num_heads, q.shape[-1] // self.num_heads
        qp = nn.DenseGeneral((heads, dh), name="query")(q)  # (B, Q, h, dh)
        kp = nn.DenseGeneral((heads, dh), name="key")(keys)  # (B, T, h, dh)
        vp = nn.DenseGeneral((heads, dh), name="value")(values)
        gather = jax.vmap(lambda x, i: x[i])  # per sample: (T, h, dh), (Q, k) -> (Q, k, h, dh)
        kg, vg = gather(kp, index), gather(vp, index)
        logits = jnp.einsum("bqhd,bqkhd->bqhk", qp, kg) / jnp.sqrt(dh).astype(qp.dtype)
        weights = jax.nn.softmax(logits + bias[:, :, None, :], axis=-1)
        out = jnp.einsum("bqhk,bqkhd->bqhd", weights, vg)
        return nn.DenseGeneral(d, axis=(-2, -1), name="out")(out)


class LocalDecoderLayer(nn.Module):
    """Pre-norm cross-attention to each query's own tokens (:class:`LocalCrossAttention`),
    FFN, final LayerNorm: the fine query grid's refinement (no self-attention: the queries
    already carry their coarse query's context)."""

    num_heads: int
    ffn_dim: int

    @nn.compact
    def __call__(self, q, q_pos, tokens, t_pos, index, bias) -> jax.Array:
        h = nn.LayerNorm()(q)
        q = q + LocalCrossAttention(self.num_heads, name="cross_attn")(
            h + q_pos, tokens + t_pos, tokens, index, bias
        )
        h = nn.Dense(self.ffn_dim)(nn.LayerNorm()(q))
        q = q + nn.Dense(q.shape[-1])(nn.gelu(h))
        return nn.LayerNorm()(q)
