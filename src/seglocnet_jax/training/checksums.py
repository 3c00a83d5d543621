"""Checkpoint integrity: ``<step>/checksums.json`` (:data:`CHECKSUM_NAME`) records the SHA-256
and size of every file of each item of a step, and the step's validation metrics;
:func:`verify_step` checks a step directory against it (see :mod:`.checkpoint`)."""

from __future__ import annotations

import hashlib
import json
import os

import jax
import numpy as np

from seglocnet_jax import fileio

CHECKSUM_NAME = "checksums.json"
CHECKSUM_FORMAT = "seglocnet_jax.checkpoint_checksums"
CHECKSUM_VERSION = 1
REQUIRED_ITEMS = ("state", "data")
_HASH_CHUNK = 1 << 20


def plain(obj):
    """JSON-able copy of a metrics tree (NumPy scalars and arrays become Python values)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
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


def write_checksums(
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


def read_sidecar(step_dir: str) -> tuple[dict | None, str | None]:
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
    side, reason = read_sidecar(step_dir)
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
