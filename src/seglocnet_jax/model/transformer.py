"""DETR-style transformer decoder: BEV queries attend to each other and to the camera tokens.

Pre-norm layers (LayerNorm before each sub-block, residual after), which train stably from
scratch without warm-up tricks. Positional embeddings are added to queries and keys, not to
values (DETR / PETR).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax


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
