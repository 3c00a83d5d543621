"""Checkpoints (orbax seam): the last N steps and the best by a validation metric.

Each checkpoint holds the train state (params, optimizer, step, RNG) and the data iterator's
state (JSON), so a resume continues bit-identically. A latest checkpoint that fails to restore
(e.g. a write was cut off) is reported and the previous good one is used.
"""

from __future__ import annotations

import dataclasses
import logging
import os

import orbax.checkpoint as ocp

log = logging.getLogger(__name__)


class CheckpointError(RuntimeError):
    """No usable checkpoint where one was required; the message names the directory."""


@dataclasses.dataclass(frozen=True)
class CheckpointConfig:
    keep_last: int = 2  # how many recent checkpoints to keep
    every_steps: int = 200  # save period (steps); the final step is always saved
    best_metric: str = "R@5m"  # validation metric that selects the best checkpoint
    best_mode: str = "max"

    def __post_init__(self):
        if self.keep_last < 1:
            raise ValueError(f"train.checkpoint.keep_last must be >= 1, got {self.keep_last}")
        if self.best_mode not in ("max", "min"):
            raise ValueError(f"train.checkpoint.best_mode must be max|min, got {self.best_mode!r}")


def _args(state=None, data_state=None, restore: bool = False):
    if restore:
        return ocp.args.Composite(
            state=ocp.args.StandardRestore(state), data=ocp.args.JsonRestore()
        )
    return ocp.args.Composite(
        state=ocp.args.StandardSave(state), data=ocp.args.JsonSave(data_state)
    )


def check_path(path: str) -> None:
    """orbax (tensorstore) writes checkpoints under a path with ``[`` or ``]`` but cannot read
    them back; refuse such a path before any work is done."""
    if "[" in path or "]" in path:
        raise CheckpointError(
            f"checkpoint directory {path!r} contains '[' or ']', which orbax/tensorstore cannot "
            "restore from; choose a run directory without brackets (hydra.run.dir=...)"
        )


class Checkpointer:
    """``<workdir>/checkpoints/last/<step>`` and ``<workdir>/checkpoints/best/<step>``."""

    def __init__(self, workdir: str, cfg: CheckpointConfig):
        self.cfg = cfg
        root = os.path.abspath(os.path.join(workdir, "checkpoints"))
        check_path(root)
        self.last_dir = os.path.join(root, "last")
        self.best_dir = os.path.join(root, "best")
        common = dict(create=True, enable_async_checkpointing=False)
        self.last = ocp.CheckpointManager(
            self.last_dir, options=ocp.CheckpointManagerOptions(max_to_keep=cfg.keep_last, **common)
        )
        self.best = ocp.CheckpointManager(
            self.best_dir,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=1,
                best_fn=lambda m: m[cfg.best_metric],
                best_mode=cfg.best_mode,
                **common,
            ),
        )

    def save(self, step: int, state, data_state: dict, metrics: dict | None = None):
        """Saves to ``last``; with validation ``metrics`` also offers it to ``best``."""
        if step not in self.last.all_steps():
            self.last.save(step, args=_args(state, data_state), force=True)
        if (
            metrics is not None
            and self.cfg.best_metric in metrics
            and step not in self.best.all_steps()
        ):
            self.best.save(step, args=_args(state, data_state), metrics=metrics, force=True)
        self.last.wait_until_finished()
        self.best.wait_until_finished()

    def restore_latest(self, target_state):
        """Returns ``(state, data_state, step)`` from the newest good checkpoint, or ``None`` when
        there is none. A checkpoint that fails to restore is reported and skipped."""
        for step in sorted(self.last.all_steps(), reverse=True):
            try:
                out = self.last.restore(step, args=_args(target_state, restore=True))
            except Exception as err:  # noqa: BLE001 - any failure means this one is unusable
                log.warning(
                    "checkpoint %s is corrupt or incomplete (%s: %s); trying an older one",
                    os.path.join(self.last_dir, str(step)),
                    type(err).__name__,
                    err,
                )
                print(
                    f"WARNING: checkpoint {os.path.join(self.last_dir, str(step))} could not be "
                    f"restored ({type(err).__name__}); resuming from the previous good one",
                    flush=True,
                )
                continue
            return out["state"], out["data"], step
        return None

    def close(self):
        self.last.close()
        self.best.close()


def restore_params(path: str, target_state):
    """Restores a train state from a checkpoint path: a step directory (``.../last/1200``), a
    manager directory (``.../checkpoints/best``: its newest step) or a run's workdir."""
    path = os.path.abspath(path)
    if not os.path.exists(path):
        raise CheckpointError(f"checkpoint={path!r} does not exist")
    candidates = [
        path,
        os.path.join(path, "best"),
        os.path.join(path, "checkpoints", "best"),
        os.path.join(path, "checkpoints", "last"),
    ]
    for cand in candidates:
        if os.path.isdir(cand) and any(d.isdigit() for d in os.listdir(cand)):
            mngr = ocp.CheckpointManager(cand, options=ocp.CheckpointManagerOptions(create=False))
            step = mngr.latest_step()
            out = mngr.restore(step, args=_args(target_state, restore=True))
            mngr.close()
            return out["state"], step
    parent, name = os.path.split(path)
    if name.isdigit():
        mngr = ocp.CheckpointManager(parent, options=ocp.CheckpointManagerOptions(create=False))
        out = mngr.restore(int(name), args=_args(target_state, restore=True))
        mngr.close()
        return out["state"], int(name)
    raise CheckpointError(f"checkpoint={path!r} holds no orbax checkpoint steps")
