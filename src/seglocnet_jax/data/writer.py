"""Writing a dataset directory from producer sample dicts (the dataset converters' entry).

    writer = DatasetWriter("data_cache/nuscenes", {"source": "nuscenes", ...}, seed=0)
    writer.write_split("train", samples, num_samples)   # any iterable of SAMPLE_KEYS dicts
    writer.write_split("val", val_samples, len(val_samples))
    writer.close()                                      # manifest "complete": True

Same records, shards and manifest as the simulator pipeline (:mod:`.simulated.prepare`), so the
loader reads both alike. Each sample gets a seeded prior (``priors.seeded_priors``) unless it
carries one. Re-running with the same config keeps finished shards (their samples are skipped, not
re-encoded); another config in an existing directory is refused. Each shard's SHA-256 and size
go into the manifest (a kept shard is hashed and compared with what the manifest recorded);
temporary files left by a killed earlier run are removed first.

Worker processes: with ``load`` (``write_split(split, refs, n, load=fn)``), ``refs`` are light
stand-ins (``sample_id``, ``city``, ``pose``) and ``fn(ref)`` returns the full sample dict. With
``num_workers > 1`` the shards left to write are then loaded, encoded and written by that many
``spawn`` processes (fork is unsafe once JAX is imported), ``fn`` pickled once per worker and
each shard's ``refs`` per shard. A shard is a pure function of its samples, the seed and the
split position, and every worker writes its own shards atomically, so the output is
byte-identical for any number of workers and a killed run resumes shard by shard. Only this
process writes the manifest. A ``load`` that cannot be pickled (e.g. a reader patched in a
test) runs in this process, with a warning.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import multiprocessing
import os
import pickle
import warnings
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np
from tqdm.auto import tqdm

from seglocnet_jax import fileio
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.priors import seeded_priors
from seglocnet_jax.data.records import (
    RecordError,
    count_records,
    encode_sample,
    file_checksum,
    shard_name,
    write_shard,
)

# ref -> full sample dict (schema.SAMPLE_KEYS); must pickle to run in worker processes
LoadFn = Callable[[Mapping], Mapping]


@dataclasses.dataclass(frozen=True)
class ShardJob:
    """What writing one shard needs (picklable: it is sent to a worker process).

    Attributes:
      path: absolute shard path.
      samples: the shard's samples in split order (refs when a ``load`` function is used).
      start: split position of the first sample (indexes the split's prior stream).
      seed, stream: the prior stream (``priors.seeded_priors``).
      encode: keyword arguments of ``records.encode_sample`` (the record encoding options).
    """

    path: str
    samples: tuple
    start: int
    seed: int
    stream: int
    encode: dict


def run_shard_job(job: ShardJob, load: LoadFn | None = None) -> dict:
    """Loads (with ``load``), encodes and writes one shard atomically; returns its checksum.

    One sample is decoded at a time. The result depends only on ``job`` (and what ``load``
    returns), not on the process it runs in."""
    n = len(job.samples)
    # Priors of the whole split drawn in one stream: index by the split position.
    priors = seeded_priors(np.zeros((job.start + n, 2)), job.seed, job.stream)[job.start :]
    recs = []
    for j, ref in enumerate(job.samples):
        sample = ref if load is None else load(ref)
        if "prior" not in sample:
            xy = np.asarray(sample["pose"], np.float64)[:2]
            sample = dict(sample, prior=xy + priors[j])
        recs.append(encode_sample(sample, **job.encode, where=f"{job.path} record {j}"))
    return write_shard(job.path, recs)


_worker_load: LoadFn | None = None  # set in each worker process by _worker_init
# Thread pools of the native libraries a worker loads: one thread each (the workers already use
# the cores), unless the user set them. Spawned processes read them when numpy is imported.
_WORKER_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _single_threaded_children():
    added = [k for k in _WORKER_THREAD_VARS if k not in os.environ]
    os.environ.update(dict.fromkeys(added, "1"))
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _worker_init(blob: bytes) -> None:
    global _worker_load
    _worker_load = pickle.loads(blob)


def _worker_run(job: ShardJob) -> dict:
    return run_shard_job(job, _worker_load)


class DatasetWriter:
    """Writes splits of sample dicts as ArrayRecord shards plus ``manifest.json``.

    Args:
      dataset_dir: output directory (created).
      config: the JSON-able config that identifies the dataset (checked on re-runs).
      seed: prior seed; shard_size: records per shard; png_level: PNG compression level.
      num_workers: processes that write the shards of a split given with ``load`` (0 or 1: this
        process); the output does not depend on it.
      image_codec: "png" (lossless) or "jpeg" at ``jpeg_quality``, source JPEGs attached to the
        images passed through (``records.encode_sample``, ``records.with_source_jpegs``).
    """

    def __init__(
        self,
        dataset_dir: str | os.PathLike,
        config: dict,
        *,
        seed: int = 0,
        shard_size: int = 250,
        png_level: int = 1,
        num_workers: int = 0,
        image_codec: str = "png",
        jpeg_quality: int = 95,
    ):
        if num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {num_workers}")
        self.dataset_dir = os.fspath(dataset_dir)
        self.seed, self.shard_size, self.png_level = seed, shard_size, png_level
        self.num_workers = num_workers
        self.image_codec, self.jpeg_quality = image_codec, jpeg_quality
        identity = json.loads(json.dumps(config))
        fileio.clean_stale_tmp(self.dataset_dir)  # half-written shards of a killed run
        if os.path.exists(mf.manifest_path(self.dataset_dir)):
            self.manifest = mf.read_manifest(self.dataset_dir)
            mf.check_config(self.manifest, identity, self.dataset_dir)
        else:
            os.makedirs(self.dataset_dir, exist_ok=True)
            self.manifest = mf.new_manifest(identity, {})
            mf.write_manifest(self.dataset_dir, self.manifest)

    def encode_options(self) -> dict:
        """Keyword arguments of ``records.encode_sample`` for every record of this dataset."""
        return {
            "image_codec": self.image_codec,
            "compress_level": self.png_level,
            "jpeg_quality": self.jpeg_quality,
        }

    def write_split(
        self,
        split: str,
        samples: Iterable[Mapping],
        num_samples: int,
        *,
        load: LoadFn | None = None,
    ) -> int:
        """Writes ``num_samples`` samples as ``split``; returns the number of shards written
        (finished shards of an earlier run are kept). Sample ids must be unique.

        Without ``load``, ``samples`` are the sample dicts, encoded here one shard at a time.
        With ``load``, they are refs whose ``sample_id``, ``city`` and ``pose`` are cheap and
        ``load(ref)`` is the sample dict; only refs of shards still to write are loaded, in
        ``num_workers`` processes (see the module docstring)."""
        count = max(1, -(-num_samples // self.shard_size))
        old = self.manifest["splits"].get(split, {}).get("shards", [])
        recorded = {e["file"]: e for e in old if all(k in e for k in mf.CHECKSUM_KEYS)}
        entries, cities, ids, pending = [], {}, set(), []
        stream = zlib.crc32(split.encode())  # a stable per-split prior stream
        buf, shard, written = [], 0, 0
        it = iter(samples)
        with tqdm(total=num_samples, desc=f"write {split}", unit="sample") as bar:
            for i in range(num_samples):
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
                    rel = f"sensors/{split}/{shard_name(split, shard, count)}"
                    job = ShardJob(
                        path=os.path.abspath(os.path.join(self.dataset_dir, rel)),
                        samples=tuple(buf),
                        start=i + 1 - len(buf),
                        seed=self.seed,
                        stream=stream,
                        encode=self.encode_options(),
                    )
                    entry = self._existing(rel, job, recorded)
                    if entry is not None:
                        bar.update(len(buf))
                    elif load is None:
                        entry = {"file": rel, "count": len(buf), **run_shard_job(job)}
                        written += 1
                        bar.update(len(buf))
                    else:
                        pending.append((len(entries), rel, job))
                    entries.append(entry)
                    buf, shard = [], shard + 1
            for pos, checksum in self._write_pending(pending, load, bar):
                rel, job = pending[pos][1:]
                entries[pending[pos][0]] = {"file": rel, "count": len(job.samples), **checksum}
                written += 1
        self.manifest["splits"][split] = {"shards": entries, "count": num_samples, "cities": cities}
        mf.write_manifest(self.dataset_dir, self.manifest)
        return written

    def _existing(self, rel: str, job: ShardJob, recorded: dict) -> dict | None:
        """The manifest entry of a shard that is already on disk (checked), else None."""
        path = job.path
        if not os.path.exists(path):
            return None
        n = count_records(path)
        if n != len(job.samples):
            raise RecordError(
                f"{path}: existing shard has {n} records, "
                f"expected {len(job.samples)}; delete it to have it written again"
            )
        checksum = file_checksum(path)
        if rel in recorded and {k: recorded[rel][k] for k in mf.CHECKSUM_KEYS} != checksum:
            raise RecordError(
                f"{path}: existing shard differs from the checksum recorded in "
                f"{mf.manifest_path(self.dataset_dir)} (it changed after it was written); "
                "delete it to have it written again"
            )
        return {"file": rel, "count": len(job.samples), **checksum}

    def _write_pending(self, pending: list, load: LoadFn | None, bar) -> Iterator[tuple]:
        """Writes the pending shard jobs; yields ``(index in pending, checksum)`` as each one
        finishes (in any order)."""
        workers = min(self.num_workers, len(pending))
        blob = None
        if workers > 1:
            try:
                blob = pickle.dumps(load)
            except Exception as err:  # pickle raises several types (PicklingError, TypeError, ...)
                warnings.warn(
                    f"{self.dataset_dir}: the sample loader cannot be sent to worker processes "
                    f"({type(err).__name__}: {err}); writing the shards in this process",
                    RuntimeWarning,
                    stacklevel=3,
                )
                workers = 0
        if workers <= 1:
            for pos, (_, _, job) in enumerate(pending):
                yield pos, run_shard_job(job, load)
                bar.update(len(job.samples))
            return
        pool = ProcessPoolExecutor(
            workers,
            mp_context=multiprocessing.get_context("spawn"),  # JAX may be imported: no fork
            initializer=_worker_init,
            initargs=(blob,),
        )
        try:
            with _single_threaded_children():  # the pool spawns its processes in submit()
                futures = {pool.submit(_worker_run, p[2]): pos for pos, p in enumerate(pending)}
            for fut in as_completed(futures):
                pos = futures[fut]
                yield pos, fut.result()
                bar.update(len(pending[pos][2].samples))
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)  # running shards finish (atomically)
            raise
        pool.shutdown(wait=True)

    def close(self) -> str:
        """Marks the dataset complete; returns its directory."""
        self.manifest["complete"] = True
        mf.write_manifest(self.dataset_dir, self.manifest)
        return self.dataset_dir
