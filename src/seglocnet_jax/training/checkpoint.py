"""Checkpoints (orbax seam): the last N steps and the best by a validation metric.

Each checkpoint holds the train state (params, optimizer, step, RNG) and the data iterator's
state (JSON), so a resume continues bit-identically.

Integrity: once orbax has finished a step, ``<step>/checksums.json`` (``CHECKSUM_NAME``, written
atomically) records the SHA-256 and size of every file of each item (``state``, ``data`` and the
``metrics`` orbax keeps in ``best``) and the step's validation metrics (also for ``last``, so a
resume can offer the step to ``best`` if a kill came between the two saves). Every restore
verifies it first: a mismatch, or a step without the file (its save was cut off, or it predates
checksums), is corrupt. Then the checkpoint's tree (paths, shapes, dtypes) is compared with the
target's, because orbax itself restores a different shape silently.

A corrupt step is reported (``WARNING: ...`` naming the step directory and the reason) and the
previous good one is used; a step saved again replaces a corrupt one. When no step is usable
:class:`CheckpointError` names each step and the remedy (:func:`archive_checkpoints`).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from seglocnet_jax import fileio

CHECKSUM_NAME = "checksums.json"
CHECKSUM_FORMAT = "seglocnet_jax.checkpoint_checksums"
CHECKSUM_VERSION = 1
REQUIRED_ITEMS = ("state", "data")
_HASH_CHUNK = 1 << 20


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


# --------------------------------------------------------------------------- checksums


def _plain(obj):
    """JSON-able copy of a metrics tree (NumPy scalars and arrays become Python values)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
    if hasattr(obj, "__array__") and not isinstance(obj, str | bytes):  # jax arrays
        return np.asarray(obj).tolist()
    return obj


def _file_digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _item_files(item_dir: str) -> dict[str, int]:
    """``{path relative to the item directory: size}`` of every file under it."""
    out = {}
    for root, dirs, files in os.walk(item_dir):
        dirs.sort()
        for name in sorted(files):
            path = os.path.join(root, name)
            out[os.path.relpath(path, item_dir).replace(os.sep, "/")] = os.path.getsize(path)
    return out


def _checksums(step_dir: str) -> dict:
    """``{item: {relative file: {"sha256", "size"}}}`` of every item directory of a step."""
    items = {}
    for item in sorted(os.listdir(step_dir)):
        item_dir = os.path.join(step_dir, item)
        if not os.path.isdir(item_dir):
            continue
        items[item] = {
            rel: {"sha256": _file_digest(os.path.join(item_dir, rel)), "size": size}
            for rel, size in _item_files(item_dir).items()
        }
    return items


def _write_checksums(
    step_dir: str, step: int, metrics: dict | None, items: dict | None = None
) -> None:
    """``<step_dir>/checksums.json`` (process 0; ``items`` of a verified sidecar are reused)."""
    if jax.process_index() != 0:
        return
    fileio.write_json_atomic(
        os.path.join(step_dir, CHECKSUM_NAME),
        {
            "format": CHECKSUM_FORMAT,
            "version": CHECKSUM_VERSION,
            "step": int(step),
            "algorithm": "sha256",
            "items": _checksums(step_dir) if items is None else items,
            "metrics": metrics,
        },
    )


def _read_sidecar(step_dir: str) -> tuple[dict | None, str | None]:
    """``(sidecar, None)`` or ``(None, reason)``."""
    path = os.path.join(step_dir, CHECKSUM_NAME)
    if not os.path.isfile(path):
        return None, (
            f"no {CHECKSUM_NAME} (its save was cut off, or it was written before checkpoints "
            "carried checksums)"
        )
    try:
        with open(path) as f:
            side = json.load(f)
    except (OSError, ValueError) as err:
        return None, f"unreadable {CHECKSUM_NAME} ({err})"
    if (
        not isinstance(side, dict)
        or side.get("format") != CHECKSUM_FORMAT
        or side.get("version") != CHECKSUM_VERSION
        or not isinstance(side.get("items"), dict)
    ):
        return None, f"{CHECKSUM_NAME} is not a version-{CHECKSUM_VERSION} checksum file"
    return side, None


def verify_step(step_dir: str) -> tuple[dict | None, str | None]:
    """Checks a step directory against its ``checksums.json``: ``(sidecar, None)`` when every
    file of every recorded item is there with its size and SHA-256, else ``(None, reason)``."""
    side, reason = _read_sidecar(step_dir)
    if reason is not None:
        return None, reason
    items = side["items"]
    for item in REQUIRED_ITEMS:
        if item not in items:
            return None, f"{CHECKSUM_NAME} records no item {item!r}"
    for item, files in items.items():
        item_dir = os.path.join(step_dir, item)
        if not os.path.isdir(item_dir):
            return None, f"item directory {item}/ is missing"
        have = _item_files(item_dir)
        missing = sorted(set(files) - set(have))
        extra = sorted(set(have) - set(files))
        if missing:
            return None, f"file {item}/{missing[0]} is missing"
        if extra:
            return None, f"unexpected file {item}/{extra[0]} (not in {CHECKSUM_NAME})"
        for rel, want in files.items():
            if have[rel] != want["size"]:
                return None, (
                    f"file {item}/{rel} has {have[rel]} bytes, {CHECKSUM_NAME} records "
                    f"{want['size']} (truncated?)"
                )
        for rel, want in files.items():
            if _file_digest(os.path.join(item_dir, rel)) != want["sha256"]:
                return None, f"checksum mismatch in {item}/{rel} (the file changed after saving)"
    return side, None


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
                    _write_checksums(step_dir, step, metrics, side["items"])
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
            _write_checksums(step_dir, step, metrics)

    def _better_than_kept(self, metrics: dict) -> bool:
        """Whether ``metrics`` beat every good step kept in ``best`` (else orbax would write
        the step only to delete it again)."""
        value = metrics[self.cfg.best_metric]
        for step in self.best.all_steps():
            side, _ = _read_sidecar(_step_dir(self.best_dir, step))
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
        metrics = None if metrics is None else _plain(metrics)
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
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
    dest = f"{root}.discarded-{stamp}"
    n = 1
    while os.path.exists(dest):
        dest = f"{root}.discarded-{stamp}-{n}"
        n += 1
    os.rename(root, dest)
    return dest


def _manager_steps(manager_dir: str) -> list[int]:
    if not os.path.isdir(manager_dir):
        return []
    return sorted((int(d) for d in os.listdir(manager_dir) if d.isdigit()), reverse=True)


def restore_params(path: str, target_state):
    """Restores a train state from a checkpoint path: a step directory (``.../last/1200``), a
    manager directory (``.../checkpoints/best``: its newest good step) or a run's workdir (its
    best, else its last checkpoints). Returns ``(state, step)``.

    Every step is verified against its checksums; a corrupt one is reported and the previous
    good one used. A tree that differs from ``target_state`` raises
    :class:`CheckpointMismatchError` naming the differing parameters."""
    path = os.path.abspath(path)
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
