"""``manifest.json``: what a prepared dataset directory holds and how it was made.

Layout of a dataset directory (all paths in the manifest are relative to it)::

    manifest.json
    sensors/<split>/<split>-00000-of-00008.array_record   # records, see data.records
    maps/<variant>/<city>.npz                              # cached city rasters per map variant

Manifest keys: ``format`` (``FORMAT``), ``manifest_version``, ``record_version``,
``code_version`` (package version), ``config`` (the preparation config as a plain dict; a resume
or a loader with another config is refused), ``splits`` (split -> ``{"shards": [{"file",
"count"}], "count", "cities": {city: count}}``), ``map_variants`` (variant -> ``{"config",
"files": {city: path}}``) and ``complete`` (all shards written).
"""

from __future__ import annotations

import json
import os
from importlib import metadata

from seglocnet_jax.data.records import RECORD_VERSION

FORMAT = "seglocnet_jax.dataset"
MANIFEST_VERSION = 1
MANIFEST_NAME = "manifest.json"


class ManifestError(ValueError):
    """A manifest is missing, unreadable, or does not match the config; names the file/key."""


def code_version() -> str:
    """The installed package version (recorded, not checked: records carry their own version)."""
    try:
        return metadata.version("seglocnet_jax")
    except metadata.PackageNotFoundError:
        return "unknown"


def new_manifest(config: dict, splits: dict) -> dict:
    """A manifest for ``config`` (plain JSON-able dict) with planned ``splits``."""
    return {
        "format": FORMAT,
        "manifest_version": MANIFEST_VERSION,
        "record_version": RECORD_VERSION,
        "code_version": code_version(),
        "config": config,
        "splits": splits,
        "map_variants": {},
        "complete": False,
    }


def write_json_atomic(path: str | os.PathLike, obj) -> None:
    """Writes ``obj`` as JSON to ``path`` via a temporary file and ``os.replace``."""
    path = os.fspath(path)
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "w") as f:
            json.dump(obj, f, indent=1, sort_keys=True)
            f.write("\n")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def manifest_path(dataset_dir: str | os.PathLike) -> str:
    return os.path.join(os.fspath(dataset_dir), MANIFEST_NAME)


def read_manifest(dataset_dir: str | os.PathLike) -> dict:
    """Reads and sanity-checks ``<dataset_dir>/manifest.json``."""
    path = manifest_path(dataset_dir)
    if not os.path.isfile(path):
        raise ManifestError(f"{path}: no manifest; prepare the dataset first")
    try:
        with open(path) as f:
            man = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ManifestError(f"{path}: unreadable manifest ({err})") from err
    if not isinstance(man, dict) or man.get("format") != FORMAT:
        raise ManifestError(f"{path}: not a {FORMAT} manifest")
    if man.get("manifest_version") != MANIFEST_VERSION:
        raise ManifestError(
            f"{path}: manifest_version {man.get('manifest_version')}, expected {MANIFEST_VERSION}"
        )
    if man.get("record_version") != RECORD_VERSION:
        raise ManifestError(
            f"{path}: record_version {man.get('record_version')}, this code reads "
            f"{RECORD_VERSION}; prepare the dataset again in a new directory"
        )
    for key in ("config", "splits", "map_variants", "complete"):
        if key not in man:
            raise ManifestError(f"{path}: manifest lacks key {key!r}")
    return man


def config_diff(stored, wanted, prefix: str = "config") -> list[str]:
    """Human-readable differences between two plain config trees (``a.b: x != y``)."""
    if isinstance(stored, dict) and isinstance(wanted, dict):
        out = []
        for key in sorted(set(stored) | set(wanted)):
            if key not in stored:
                out.append(f"{prefix}.{key}: missing in manifest (config has {wanted[key]!r})")
            elif key not in wanted:
                out.append(f"{prefix}.{key}: in manifest ({stored[key]!r}) but not in config")
            else:
                out.extend(config_diff(stored[key], wanted[key], f"{prefix}.{key}"))
        return out
    if isinstance(stored, list | tuple) and isinstance(wanted, list | tuple):
        stored, wanted = list(stored), list(wanted)
    return [] if stored == wanted else [f"{prefix}: manifest {stored!r} != config {wanted!r}"]


def check_config(man: dict, config: dict, dataset_dir: str | os.PathLike) -> None:
    """Raises :class:`ManifestError` listing every key where ``config`` differs from the
    manifest's (JSON round trip first, so tuples and lists compare equal)."""
    wanted = json.loads(json.dumps(config))
    diff = config_diff(man["config"], wanted)
    if diff:
        raise ManifestError(
            f"{manifest_path(dataset_dir)} was prepared with another config: "
            + "; ".join(diff[:8])
            + (f" (+{len(diff) - 8} more)" if len(diff) > 8 else "")
            + ". Use a new dataset name/directory or the matching config."
        )


def split_files(man: dict, dataset_dir: str | os.PathLike, split: str) -> list[tuple[str, int]]:
    """``[(absolute shard path, expected record count)]`` of a split."""
    if split not in man["splits"]:
        raise ManifestError(
            f"{manifest_path(dataset_dir)}: no split {split!r}; has {sorted(man['splits'])}"
        )
    root = os.fspath(dataset_dir)
    shards = man["splits"][split]["shards"]
    return [(os.path.join(root, s["file"]), int(s["count"])) for s in shards]
