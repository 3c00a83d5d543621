"""``manifest.json``: what a prepared dataset directory holds and how it was made.

Layout of a dataset directory (all paths in the manifest are relative to it)::

    manifest.json
    sensors/<split>/<split>-00000-of-00008.array_record   # records, see data.records
    maps/<variant>/<city>.npz                              # cached city rasters per map variant
    maps/osm_classes/<city>.npz                            # the OSM class rasters (NM models)

Manifest keys: ``format`` (``FORMAT``), ``manifest_version``, ``record_version``,
``code_version`` (package version), ``config`` (the preparation config as a plain dict; a resume
or a loader with another config is refused), ``splits`` (split -> ``{"shards": [{"file",
"count", "sha256", "bytes"}], "count", "cities": {city: count}}``), ``map_variants`` (variant ->
``{"config", "files": {city: path}}``), ``complete`` (all shards written) and, once an NM
model's data was prepared, ``osm_classes`` (``{"config": the class table, "files": {city:
path}}``, :mod:`.variants`).

Integrity: a shard's SHA-256 and size are recorded when it is written; the loader checks them
before it reads a split (:func:`verify_split`). Shard ``i`` of ``n`` of split ``s`` is
``sensors/<s>/<s>-<i>-of-<n>.array_record`` (:func:`records.shard_name`): a manifest whose split
lists another file (another split's shard, or a file listed twice) is refused. Manifests of
version 1 (before shard checksums) are refused with the remedy: prepare again; so are datasets
whose ``record_version`` is not :data:`records.RECORD_VERSION` (version 1: float32 LiDAR, PNG
images only; version 2: compact LiDAR, JPEG images for real data; version 3: plus each frame's
sequence metadata; version 4: plus its lighting).
"""

from __future__ import annotations

import json
import os
from importlib import metadata

from seglocnet_jax import fileio
from seglocnet_jax.data.records import RECORD_CHANGES, RECORD_VERSION, shard_name, verify_shard
from seglocnet_jax.fileio import write_json_atomic  # noqa: F401 - the map writers import it here

FORMAT = "seglocnet_jax.dataset"
MANIFEST_VERSION = 2  # 2: shard checksums ("sha256", "bytes")
MANIFEST_NAME = "manifest.json"
CHECKSUM_KEYS = ("sha256", "bytes")


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


def manifest_path(dataset_dir: str | os.PathLike) -> str:
    return os.path.join(os.fspath(dataset_dir), MANIFEST_NAME)


def write_manifest(dataset_dir: str | os.PathLike, man: dict) -> None:
    """Writes ``<dataset_dir>/manifest.json`` atomically."""
    fileio.write_json_atomic(manifest_path(dataset_dir), man)


def strip_checksums(splits: dict) -> dict:
    """``splits`` without the shard checksums (to compare a plan with a stored manifest)."""
    return {
        name: dict(
            split,
            shards=[
                {k: v for k, v in s.items() if k not in CHECKSUM_KEYS} for s in split["shards"]
            ],
        )
        for name, split in splits.items()
    }


def check_splits(man: dict, path: str) -> None:
    """Every split lists its own shards (``sensors/<split>/<split>-i-of-n``), each once in the
    whole manifest, with a record count; a complete manifest records every shard's checksum."""
    splits = man["splits"]
    if not isinstance(splits, dict):
        raise ManifestError(f"{path}: 'splits' must be a mapping, got {type(splits).__name__}")
    owner: dict[str, str] = {}
    for name, split in splits.items():
        shards = split.get("shards") if isinstance(split, dict) else None
        if not isinstance(shards, list):
            raise ManifestError(f"{path}: split {name!r} lacks a 'shards' list")
        for i, entry in enumerate(shards):
            file = entry.get("file") if isinstance(entry, dict) else None
            if not isinstance(file, str) or not isinstance(entry.get("count"), int):
                raise ManifestError(
                    f"{path}: split {name!r} shard {i} must have 'file' (str) and 'count' "
                    f"(int), got {entry!r}"
                )
            norm = os.path.normpath(file)
            if norm in owner:
                raise ManifestError(
                    f"{path}: split {name!r} lists {file}, which split {owner[norm]!r} lists "
                    "too; a shard belongs to one split (was the manifest edited?)"
                )
            owner[norm] = name
            want = f"sensors/{name}/{shard_name(name, i, len(shards))}"
            if file != want:
                raise ManifestError(
                    f"{path}: split {name!r} lists {file} as its shard {i}, expected {want}; a "
                    "split reads only its own shards (was the manifest edited?)"
                )
            if man.get("complete") and not all(k in entry for k in CHECKSUM_KEYS):
                raise ManifestError(
                    f"{path}: split {name!r} shard {file} has no checksum although the dataset "
                    "is marked complete; prepare the dataset again into a new directory"
                )


def read_manifest(dataset_dir: str | os.PathLike) -> dict:
    """Reads and sanity-checks ``<dataset_dir>/manifest.json`` (version, keys, and that every
    split lists only its own shards)."""
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
    if man.get("manifest_version") == 1:
        raise ManifestError(
            f"{path}: this dataset was written before shards carried checksums "
            f"(manifest_version 1; this code reads version {MANIFEST_VERSION}). Prepare it again "
            f"into a new directory (another data.name or data.root) or delete "
            f"{os.path.dirname(path)}"
        )
    if man.get("manifest_version") != MANIFEST_VERSION:
        raise ManifestError(
            f"{path}: manifest_version {man.get('manifest_version')}, this code reads "
            f"{MANIFEST_VERSION}; prepare the dataset again into a new directory or delete "
            f"{os.path.dirname(path)}"
        )
    if man.get("record_version") != RECORD_VERSION:
        raise ManifestError(
            f"{path}: record_version {man.get('record_version')}, this code reads "
            f"{RECORD_VERSION} ({RECORD_CHANGES}). Re-run the data preparation (simulator) or "
            f"the conversion (real data) into a new directory (another data.name / "
            f"dataset.convert.name or root), or delete {os.path.dirname(path)} to have it "
            "prepared again"
        )
    for key in ("config", "splits", "map_variants", "complete"):
        if key not in man:
            raise ManifestError(f"{path}: manifest lacks key {key!r}")
    check_splits(man, path)
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


def verify_split(man: dict, dataset_dir: str | os.PathLike, split: str) -> list[tuple[str, int]]:
    """The one check before a split is read (single frames and drives alike): the split's record
    count is the sum of its shards' and of its cities', and every shard has the size and SHA-256
    the manifest records (:func:`records.verify_shard`: hashed once per process and file
    version). Returns :func:`split_files`; a difference raises :class:`records.RecordError` (a
    shard) or :class:`ManifestError` (the counts), naming the split and the manifest."""
    files = split_files(man, dataset_dir, split)  # names a missing split
    entry = man["splits"][split]
    shards = sum(c for _, c in files)
    cities = entry.get("cities")
    counts = {"its shards": shards}
    if isinstance(cities, dict):
        counts["its cities"] = sum(int(c) for c in cities.values())
    for what, n in counts.items():
        if entry.get("count") != n:
            raise ManifestError(
                f"{manifest_path(dataset_dir)}: split {split!r} records count "
                f"{entry.get('count')!r}, but {what} hold {n} records (was the manifest "
                "edited?); prepare the dataset again into a new directory"
            )
    root = os.fspath(dataset_dir)
    for shard in entry["shards"]:
        verify_shard(os.path.join(root, shard["file"]), shard, manifest_path(dataset_dir))
    return files
