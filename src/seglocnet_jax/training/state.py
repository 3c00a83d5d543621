"""Optimizer (optax seam) and the train state pytree."""

from __future__ import annotations

import dataclasses

import flax.struct
import jax
import optax


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """AdamW with linear warmup and cosine decay (paper: AdamW, lr 1e-4, cosine).

    Attributes:
      learning_rate: peak learning rate.
      weight_decay: decoupled weight decay.
      warmup_steps: linear warmup from 0 to the peak.
      total_steps: length of the schedule (warmup included); decays to ``final_lr_ratio``.
      grad_clip: global-norm clip (<= 0 disables).
    """

    learning_rate: float = 1e-4
    weight_decay: float = 1e-2
    warmup_steps: int = 100
    total_steps: int = 10_000
    final_lr_ratio: float = 0.01
    grad_clip: float = 1.0

    def __post_init__(self):
        if self.learning_rate <= 0:
            raise ValueError(f"train.optim.learning_rate must be > 0, got {self.learning_rate}")
        if self.total_steps <= 0:
            raise ValueError(f"train.optim.total_steps must be > 0, got {self.total_steps}")
        if not 0 <= self.warmup_steps < self.total_steps:
            raise ValueError(
                f"train.optim.warmup_steps must be in [0, total_steps={self.total_steps}), "
                f"got {self.warmup_steps}"
            )


def make_schedule(cfg: OptimConfig) -> optax.Schedule:
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0,
        peak_value=cfg.learning_rate,
        warmup_steps=cfg.warmup_steps,
        decay_steps=cfg.total_steps,
        end_value=cfg.learning_rate * cfg.final_lr_ratio,
    )


def make_optimizer(cfg: OptimConfig) -> optax.GradientTransformation:
    adamw = optax.adamw(make_schedule(cfg), weight_decay=cfg.weight_decay)
    if cfg.grad_clip > 0:
        return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), adamw)
    return adamw


class TrainState(flax.struct.PyTreeNode):
    """Everything a resume needs besides the data iterator: step, params, optimizer, RNG key."""

    step: jax.Array  # () int32
    params: dict
    opt_state: optax.OptState
    rng: jax.Array  # (2,) uint32 raw key data (checkpointable); wrapped and folded with the step

    @classmethod
    def create(cls, params, optimizer: optax.GradientTransformation, rng: jax.Array) -> TrainState:
        """``rng`` is a typed key (``jax.random.key``); its raw data is stored."""
        return cls(
            step=jax.numpy.zeros((), jax.numpy.int32),
            params=params,
            opt_state=optimizer.init(params),
            rng=jax.random.key_data(rng),
        )
