"""Checkpoints (orbax seam): the last N steps and the best by a validation metric.

Each checkpoint holds the train state (params, optimizer, step, RNG) and the data iterator's
state (JSON), so a resume continues bit-identically.

Integrity (:mod:`.checksums`): once orbax has finished a step, ``<step>/checksums.json``
(``CHECKSUM_NAME``, written atomically) records the SHA-256 and size of every file of each item
(``state``, ``data`` and the ``metrics`` orbax keeps in ``best``) and the step's validation
metrics (also for ``last``, so a resume can offer the step to ``best`` if a kill came between
the two saves). Every restore verifies it first: a mismatch, or a step without the file (its
save was cut off, or it predates checksums), is corrupt. Then the checkpoint's tree (paths,
shapes, dtypes) is compared with the target's, because orbax itself restores a different shape
silently. :func:`resolve` names the step a path restores (and its checksum) without restoring.

A corrupt step is reported (``WARNING: ...`` naming the step directory and the reason) and the
previous good one is used; a step saved again replaces a corrupt one. When no step is usable
:class:`CheckpointError` names each step and the remedy (:func:`archive_checkpoints`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from seglocnet_jax import fileio
from seglocnet_jax.training.checksums import (
    CHECKSUM_NAME,
    plain,
    read_sidecar,
    verify_step,
    write_checksums,
)

__all__ = [
    "CHECKSUM_NAME",
    "CheckpointConfig",
    "CheckpointError",
    "CheckpointMismatchError",
    "CheckpointRef",
    "Checkpointer",
    "archive_checkpoints",
    "check_path",
    "resolve",
    "restore_params",
    "tree_differences",
    "verify_step",
]


class CheckpointError(RuntimeError):
    """No usable checkpoint where one was required; the message names the directory."""


class CheckpointMismatchError(CheckpointError):
    """A checkpoint's tree (paths, shapes, dtypes) differs from the model it is restored into;
    the message names the checkpoint and a few differing parameters."""


@dataclasses.dataclass(frozen=True)
class CheckpointConfig:
    keep_last: int = 2  # how many recent checkpoints to keep
    every_steps: int = 250  # save period (steps); the final step is always saved
    best_metric: str = "R@5m"  # validation metric that selects the best checkpoint
    best_mode: str = "max"

    def __post_init__(self):
        if self.keep_last < 1:
            raise ValueError(f"train.checkpoint.keep_last must be >= 1, got {self.keep_last}")
        if self.every_steps < 1:
            raise ValueError(f"train.checkpoint.every_steps must be >= 1, got {self.every_steps}")
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


# --------------------------------------------------------------------------- tree comparison


def _key_name(key) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)


def _leaves(tree) -> dict[str, tuple]:
    """``{"params.w1": (shape, dtype)}`` of a pytree of arrays or orbax array metadata."""
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if leaf is None:
            continue
        name = ".".join(_key_name(k) for k in path)
        shape = getattr(leaf, "shape", None)
        dtype = getattr(leaf, "dtype", None)
        if shape is None:
            shape, dtype = np.shape(leaf), np.asarray(leaf).dtype
        out[name] = (tuple(shape), str(np.dtype(dtype)) if dtype is not None else "?")
    return out


def tree_differences(saved: dict, wanted: dict, limit: int = 5) -> list[str]:
    """Human-readable differences between two ``_leaves`` maps (checkpoint vs target)."""
    diff = []
    # Parameters first: they name the model change; the optimizer mirrors them.
    for name in sorted(set(saved) | set(wanted), key=lambda n: (not n.startswith("params"), n)):
        if name not in saved:
            diff.append(f"{name}: not in the checkpoint (model {wanted[name][0]})")
        elif name not in wanted:
            diff.append(f"{name}: only in the checkpoint {saved[name][0]}")
        elif saved[name] != wanted[name]:
            (s_shape, s_dtype), (w_shape, w_dtype) = saved[name], wanted[name]
            diff.append(f"{name}: checkpoint {s_shape} {s_dtype}, model {w_shape} {w_dtype}")
    if len(diff) > limit:
        diff = diff[:limit] + [f"(+{len(diff) - limit} more)"]
    return diff


def _check_tree(step_dir: str, target_state) -> None:
    """Raises :class:`CheckpointMismatchError` when the saved state's tree differs from
    ``target_state`` (orbax would restore other shapes silently)."""
    if target_state is None:
        return
    meta = ocp.StandardCheckpointHandler().metadata(epath.Path(os.path.join(step_dir, "state")))
    tree = getattr(meta, "tree", meta)
    diff = tree_differences(_leaves(tree), _leaves(target_state))
    if diff:
        raise CheckpointMismatchError(
            f"checkpoint {step_dir} does not match the model it is restored into: "
            + "; ".join(diff)
            + ". Was it written with another model config (model.*, map.channels)?"
        )


# --------------------------------------------------------------------------- restore helpers


def _step_dir(manager_dir: str, step: int) -> str:
    return os.path.join(manager_dir, str(step))


def _restore_step(mngr, manager_dir: str, step: int, target_state):
    """``(out, sidecar, None)`` or ``(None, None, reason)``; a tree mismatch raises."""
    step_dir = _step_dir(manager_dir, step)
    side, reason = verify_step(step_dir)
    if reason is not None:
        return None, None, reason
    _check_tree(step_dir, target_state)
    try:
        out = mngr.restore(step, args=_args(target_state, restore=True))
    except Exception as err:  # noqa: BLE001 - any failure means this one is unusable
        return None, None, f"orbax could not restore it ({type(err).__name__}: {err})"
    return out, side, None


def _warn_corrupt(step_dir: str, reason: str) -> None:
    print(
        f"WARNING: checkpoint {step_dir} is corrupt or incomplete: {reason}; "
        "trying the previous one",
        flush=True,
    )


def _report_fallback(used_dir: str, step: int, failures: list[tuple[str, str]]) -> None:
    if failures:
        print(
            f"WARNING: using checkpoint {used_dir} (step {step}) instead of "
            f"{failures[0][0]}, which is corrupt",
            flush=True,
        )


def _failure_list(failures: list[tuple[str, str]]) -> str:
    return "; ".join(f"{d}: {r}" for d, r in failures)


class Checkpointer:
    """``<workdir>/checkpoints/last/<step>`` and ``<workdir>/checkpoints/best/<step>``."""

    def __init__(self, workdir: str, cfg: CheckpointConfig):
        self.cfg = cfg
        root = os.path.abspath(os.path.join(workdir, "checkpoints"))
        check_path(root)
        self.root = root
        self.last_dir = os.path.join(root, "last")
        self.best_dir = os.path.join(root, "best")
        if jax.process_index() == 0:
            fileio.clean_stale_tmp(root)  # checksum files of a killed save
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

    def _save_to(self, mngr, manager_dir, step, state, data_state, metrics, *, best: bool):
        """Saves one step into ``mngr``; a good existing step is kept (its stored metrics are
        filled in if they were missing), a corrupt one is replaced."""
        step_dir = _step_dir(manager_dir, step)
        if step in mngr.all_steps():
            side, reason = verify_step(step_dir)
            if reason is None:
                if metrics is not None and side.get("metrics") is None:
                    write_checksums(step_dir, step, metrics, side["items"])
                return
            print(
                f"WARNING: checkpoint {step_dir} is corrupt or incomplete: {reason}; replacing it",
                flush=True,
            )
            mngr.delete(step)
        mngr.save(
            step,
            args=_args(state, data_state),
            metrics=metrics if best else None,
            force=True,
        )
        mngr.wait_until_finished()
        if step in mngr.all_steps():  # best: a worse step is dropped at once
            write_checksums(step_dir, step, metrics)

    def _better_than_kept(self, metrics: dict) -> bool:
        """Whether ``metrics`` beat every good step kept in ``best`` (else orbax would write
        the step only to delete it again)."""
        value = metrics[self.cfg.best_metric]
        for step in self.best.all_steps():
            side, _ = read_sidecar(_step_dir(self.best_dir, step))
            kept = ((side or {}).get("metrics") or {}).get(self.cfg.best_metric)
            if not isinstance(kept, int | float) or kept != kept:  # unknown or NaN: no rival
                continue
            if not isinstance(value, int | float) or value != value:
                return False
            if not (value > kept if self.cfg.best_mode == "max" else value < kept):
                return False
        return True

    def _offer_best(self, step: int, state, data_state, metrics: dict | None):
        if metrics is None or self.cfg.best_metric not in metrics:
            return
        if step in self.best.all_steps() or self._better_than_kept(metrics):
            self._save_to(self.best, self.best_dir, step, state, data_state, metrics, best=True)

    def save(self, step: int, state, data_state: dict, metrics: dict | None = None):
        """Saves to ``last`` (with ``metrics`` when given); with validation ``metrics`` that
        hold ``best_metric`` also offers it to ``best``."""
        step = int(step)
        metrics = None if metrics is None else plain(metrics)
        self._save_to(self.last, self.last_dir, step, state, data_state, metrics, best=False)
        self._offer_best(step, state, data_state, metrics)

    def restore_latest(self, target_state):
        """Returns ``(state, data_state, step)`` from the newest good checkpoint of ``last``, or
        ``None`` when there is none. A corrupt step is reported and skipped; when steps exist but
        none is usable, :class:`CheckpointError` names each with its reason. The restored step
        is offered to ``best`` if its validation metrics are known and it is missing there."""
        failures: list[tuple[str, str]] = []
        for step in sorted(self.last.all_steps(), reverse=True):
            step_dir = _step_dir(self.last_dir, step)
            try:
                out, side, reason = _restore_step(self.last, self.last_dir, step, target_state)
            except CheckpointMismatchError as err:
                raise CheckpointMismatchError(
                    f"{err} To start this run afresh, delete {self.root} or rerun with "
                    "train.restart=true (moves the old checkpoints aside)"
                ) from None
            if reason is not None:
                _warn_corrupt(step_dir, reason)
                failures.append((step_dir, reason))
                continue
            _report_fallback(step_dir, step, failures)
            self._offer_best(step, out["state"], out["data"], side.get("metrics"))
            return out["state"], out["data"], step
        if failures:
            raise CheckpointError(
                f"no checkpoint under {self.last_dir} can be restored: {_failure_list(failures)}"
                f"; delete {self.root} or rerun with train.restart=true (moves the old "
                "checkpoints aside)"
            )
        return None

    def close(self):
        self.last.close()
        self.best.close()


def archive_checkpoints(workdir: str) -> str | None:
    """Moves ``<workdir>/checkpoints`` aside to ``<workdir>/checkpoints.discarded-<UTC time>``
    (nothing is deleted) and returns the new path; None when there is nothing to move. Call it
    before a :class:`Checkpointer` opens the directory (``train.restart=true``)."""
    root = os.path.abspath(os.path.join(workdir, "checkpoints"))
    if not os.path.exists(root):
        return None
    dest = fileio.discarded_path(root)
    os.rename(root, dest)
    return dest


def _manager_steps(manager_dir: str) -> list[int]:
    if not os.path.isdir(manager_dir):
        return []
    return sorted((int(d) for d in os.listdir(manager_dir) if d.isdigit()), reverse=True)


def _candidates(path: str) -> list[tuple[str, int]]:
    """``[(manager directory, step)]`` a checkpoint path may restore, in the order tried: a
    manager's steps newest first; a run directory's best, then its last; a step directory."""
    if not os.path.exists(path):
        raise CheckpointError(f"checkpoint={path!r} does not exist")
    candidates: list[tuple[str, int]] = []
    seen = set()
    for cand in (
        path,
        os.path.join(path, "best"),
        os.path.join(path, "checkpoints", "best"),
        os.path.join(path, "checkpoints", "last"),
    ):
        real = os.path.realpath(cand)
        if real in seen:
            continue
        seen.add(real)
        candidates += [(cand, s) for s in _manager_steps(cand)]
    parent, name = os.path.split(path)
    if not candidates and name.isdigit():
        candidates = [(parent, int(name))]
    if not candidates:
        raise CheckpointError(f"checkpoint={path!r} holds no orbax checkpoint steps")
    return candidates


@dataclasses.dataclass(frozen=True)
class CheckpointRef:
    """The one step a checkpoint path names, verified against its checksums.

    Attributes:
      step_dir: the step directory (``<run>/checkpoints/best/<step>``).
      step: its training step.
      run_dir: the run directory it belongs to (above ``checkpoints/``), else its manager's
        parent directory.
      checksum: ``sha256:<hex>`` of the step's recorded file checksums (every file of the
        state and data items): the same parameters give the same checksum wherever they lie.
      skipped: ``[(step directory, reason)]`` of newer steps that are corrupt.
    """

    step_dir: str
    step: int
    run_dir: str
    checksum: str
    skipped: tuple[tuple[str, str], ...] = ()

    @property
    def name(self) -> str:
        """``<run directory name>-step<step>`` (an evaluation's default directory names it)."""
        return f"{os.path.basename(self.run_dir)}-step{self.step}"

    def to_dict(self) -> dict:
        return {
            "run_dir": self.run_dir,
            "step": self.step,
            "step_dir": self.step_dir,
            "checksum": self.checksum,
        }


def resolve(path: str) -> CheckpointRef:
    """The step :func:`restore_params` restores from ``path`` (the first whose checksums
    verify), without restoring it; :class:`CheckpointError` when there is none."""
    path = os.path.abspath(path)
    failures: list[tuple[str, str]] = []
    for manager_dir, step in _candidates(path):
        step_dir = _step_dir(manager_dir, step)
        side, reason = verify_step(step_dir)
        if reason is not None:
            failures.append((step_dir, reason))
            continue
        items = json.dumps(side["items"], sort_keys=True).encode()
        run_dir = os.path.dirname(os.path.abspath(manager_dir))
        if os.path.basename(run_dir) == "checkpoints":
            run_dir = os.path.dirname(run_dir)
        return CheckpointRef(
            step_dir=step_dir,
            step=step,
            run_dir=run_dir,
            checksum="sha256:" + hashlib.sha256(items).hexdigest(),
            skipped=tuple(failures),
        )
    raise CheckpointError(
        f"checkpoint={path!r}: no usable checkpoint: {_failure_list(failures)}. Point "
        "checkpoint= at another run or step directory, or train again"
    )


def restore_params(path: str, target_state):
    """Restores a train state from a checkpoint path: a step directory (``.../last/1200``), a
    manager directory (``.../checkpoints/best``: its newest good step) or a run's workdir (its
    best, else its last checkpoints). Returns ``(state, step)``.

    Every step is verified against its checksums; a corrupt one is reported and the previous
    good one used. A tree that differs from ``target_state`` raises
    :class:`CheckpointMismatchError` naming the differing parameters."""
    path = os.path.abspath(path)
    candidates = _candidates(path)
    failures: list[tuple[str, str]] = []
    managers: dict[str, ocp.CheckpointManager] = {}
    try:
        for manager_dir, step in candidates:
            if manager_dir not in managers:
                managers[manager_dir] = ocp.CheckpointManager(
                    manager_dir, options=ocp.CheckpointManagerOptions(create=False)
                )
            step_dir = _step_dir(manager_dir, step)
            out, _, reason = _restore_step(managers[manager_dir], manager_dir, step, target_state)
            if reason is not None:
                _warn_corrupt(step_dir, reason)
                failures.append((step_dir, reason))
                continue
            _report_fallback(step_dir, step, failures)
            return out["state"], step
    finally:
        for mngr in managers.values():
            mngr.close()
    raise CheckpointError(
        f"checkpoint={path!r}: no usable checkpoint: {_failure_list(failures)}. Point "
        "checkpoint= at another run or step directory, or train again"
    )
