"""Writing a dataset directory from producer sample dicts (the dataset converters' entry).

    writer = DatasetWriter("data_cache/nuscenes", {"source": "nuscenes", ...}, seed=0)
    writer.write_split("train", samples, num_samples)   # any iterable of SAMPLE_KEYS dicts
    writer.write_split("val", val_samples, len(val_samples))
    writer.close()                                      # manifest "complete": True

Same records, shards and manifest as the simulator pipeline (:mod:`.prepare`), so the loader
reads both alike. Each sample gets a seeded prior (``splits.seeded_priors``) unless it carries
one. Re-running with the same config keeps finished shards (their samples are skipped, not
re-encoded); another config in an existing directory is refused. Each shard's SHA-256 and size
go into the manifest (a kept shard is hashed and compared with what the manifest recorded);
temporary files left by a killed earlier run are removed first.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterable

import numpy as np
from tqdm.auto import tqdm

from seglocnet_jax import fileio
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import splits as sp
from seglocnet_jax.data.records import (
    RecordError,
    count_records,
    encode_sample,
    file_checksum,
    shard_name,
    write_shard,
)


class DatasetWriter:
    """Writes splits of sample dicts as ArrayRecord shards plus ``manifest.json``.

    Args:
      dataset_dir: output directory (created).
      config: the JSON-able config that identifies the dataset (checked on re-runs).
      seed: prior seed; shard_size: records per shard; png_level: PNG compression level.
    """

    def __init__(
        self,
        dataset_dir: str | os.PathLike,
        config: dict,
        *,
        seed: int = 0,
        shard_size: int = 250,
        png_level: int = 1,
    ):
        self.dataset_dir = os.fspath(dataset_dir)
        self.seed, self.shard_size, self.png_level = seed, shard_size, png_level
        identity = json.loads(json.dumps(config))
        fileio.clean_stale_tmp(self.dataset_dir)  # half-written shards of a killed run
        if os.path.exists(mf.manifest_path(self.dataset_dir)):
            self.manifest = mf.read_manifest(self.dataset_dir)
            mf.check_config(self.manifest, identity, self.dataset_dir)
        else:
            os.makedirs(self.dataset_dir, exist_ok=True)
            self.manifest = mf.new_manifest(identity, {})
            mf.write_manifest(self.dataset_dir, self.manifest)

    def write_split(self, split: str, samples: Iterable[dict], num_samples: int) -> int:
        """Writes ``num_samples`` samples as ``split``; returns the number of shards written
        (finished shards of an earlier run are kept). Sample ids must be unique."""
        count = max(1, -(-num_samples // self.shard_size))
        old = self.manifest["splits"].get(split, {}).get("shards", [])
        recorded = {e["file"]: e for e in old if all(k in e for k in mf.CHECKSUM_KEYS)}
        entries, cities, ids = [], {}, set()
        stream = zlib.crc32(split.encode())  # a stable per-split prior stream
        buf, shard, written = [], 0, 0
        it = iter(samples)
        for i in tqdm(range(num_samples), desc=f"write {split}", unit="sample"):
            try:
                sample = next(it)
            except StopIteration:
                raise ValueError(
                    f"split {split!r}: got {i} samples, expected {num_samples}"
                ) from None
            sid = sample["sample_id"]
            if sid in ids:
                raise ValueError(f"split {split!r} sample {i}: duplicate sample_id {sid!r}")
            ids.add(sid)
            cities[sample["city"]] = cities.get(sample["city"], 0) + 1
            buf.append(sample)
            if len(buf) == self.shard_size or i == num_samples - 1:
                start = i + 1 - len(buf)
                entry = self._flush(split, shard, count, buf, start, stream, recorded)
                written += entry.pop("written")
                entries.append(entry)
                buf, shard = [], shard + 1
        self.manifest["splits"][split] = {"shards": entries, "count": num_samples, "cities": cities}
        mf.write_manifest(self.dataset_dir, self.manifest)
        return written

    def _flush(self, split, shard, count, buf, start, stream, recorded) -> dict:
        """Writes one shard unless it exists; returns its manifest entry (plus ``written``)."""
        rel = f"sensors/{split}/{shard_name(split, shard, count)}"
        path = os.path.join(self.dataset_dir, rel)
        if os.path.exists(path):
            n = count_records(path)
            if n != len(buf):
                raise RecordError(
                    f"{path}: existing shard has {n} records, "
                    f"expected {len(buf)}; delete it to have it written again"
                )
            checksum = file_checksum(path)
            if rel in recorded and {k: recorded[rel][k] for k in mf.CHECKSUM_KEYS} != checksum:
                raise RecordError(
                    f"{path}: existing shard differs from the checksum recorded in "
                    f"{mf.manifest_path(self.dataset_dir)} (it changed after it was written); "
                    "delete it to have it written again"
                )
            return {"file": rel, "count": len(buf), **checksum, "written": 0}
        xy = np.stack([np.asarray(s["pose"], np.float64)[:2] for s in buf])
        # Priors of the whole split drawn in one stream: index by the split position.
        priors = sp.seeded_priors(np.zeros((start + len(buf), 2)), self.seed, stream)[start:]
        recs = []
        for j, sample in enumerate(buf):
            if "prior" not in sample:
                sample = dict(sample, prior=xy[j] + priors[j])
            recs.append(
                encode_sample(sample, compress_level=self.png_level, where=f"{path} record {j}")
            )
        checksum = write_shard(path, recs)
        return {"file": rel, "count": len(buf), **checksum, "written": 1}

    def close(self) -> str:
        """Marks the dataset complete; returns its directory."""
        self.manifest["complete"] = True
        mf.write_manifest(self.dataset_dir, self.manifest)
        return self.dataset_dir
