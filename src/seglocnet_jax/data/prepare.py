"""Offline preparation: frames of a producer -> spatially split, seeded ArrayRecord shards.

``prepare(cfg)`` is what the training app calls ("prepare the data if the shards are missing").
Per city it builds a frame source (the simulator by default, :mod:`.sim_source`), drives a pool of
poses, assigns spatially disjoint train / val / test frames in the main city (:mod:`.splits`)
and a generalization-only split named after the test city, plus whole continuous drives
(``drives`` in the test city, ``drives_val`` in the main city clear of train and, optionally,
``drives_val_unseen`` in the test city clear of its test frames: :mod:`.drives`),
draws seeded priors (these plans: :mod:`.planning`), renders the sensors in batches and writes
shards atomically. Sensors are prepared once; map variants (:mod:`.variants`) only rasterize.

Sequence metadata: a pool frame's sequence is its short route (``"{city}-p{round}-route{r:05d}"``,
``frame_index`` its index along the route, ``timestamp`` distance / ``sim.NOMINAL_SPEED_MPS``)
when the source reports routes (``drive_routes``), else the frame is a sequence of its own; a
drive split's sequence is the drive (:mod:`.drives`).

Resumable: everything is a pure function of the config, a shard path that exists is complete
(atomic rename), and each shard is rendered from its own seed, so an interrupted run resumed
writes exactly the shards a single run would have written.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from typing import Protocol

import numpy as np
from tqdm.auto import tqdm

from seglocnet_jax import fileio
from seglocnet_jax.data import drives as dr
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import splits as sp
from seglocnet_jax.data.planning import (  # noqa: F401  (Pool, EMPTY_POOL: re-exported)
    EMPTY_POOL,
    Pool,
    _seed,
    plan_main_city,
    plan_test_city,
)
from seglocnet_jax.data.records import (
    RecordError,
    count_records,
    encode_sample,
    file_checksum,
    shard_name,
    write_shard,
)
from seglocnet_jax.data.splits import SplitPlan
from seglocnet_jax.data.variants import ensure_variant
from seglocnet_jax.maps import MapConfig, city_key


class FrameSource(Protocol):
    """What preparation needs from a producer of frames in one city (world frame metres).

    Optional: ``drive_routes(rng, num_frames)``, :meth:`drive`'s poses with each frame's route
    (an object with ``poses``, ``route`` and ``index`` ``(n,)`` int and ``timestamps`` ``(n,)``
    seconds: ``sim.Trajectory``), for the sequence metadata of the pool splits; and
    ``route(rng, length_m, spacing_m)``, one continuous drive (``poses``, ``timestamps``), which
    the drive splits need (:mod:`.drives`)."""

    def drive(self, rng: np.random.Generator, num_frames: int) -> np.ndarray:
        """Poses ``(num_frames, 3)`` along plausible trajectories."""

    def render(self, poses: np.ndarray, seed: int) -> list[dict]:
        """One sample dict (``schema.SAMPLE_KEYS``) per pose, deterministic for ``seed``."""


@dataclasses.dataclass(frozen=True)
class PrepareConfig:
    """The ``data`` config group (see ``conf/data/quick.yaml``).

    Attributes:
      name: dataset directory name under ``root``.
      root: output root (not part of the dataset identity).
      source: "sim" renders with the simulator; any other name (a converter's) means the
        directory was written by that converter and is only checked here.
      seed: master seed of worlds, trajectories, splits, priors and rendering.
      city: main city: train / val / test.
      test_city: generalization-only city (its split has the city's name); None to skip.
      num_train, num_val, num_test, num_test_city: frames per split.
      num_drives: continuous drives in the test city (split ``drives``; 0 or no test city:
        none).
      num_val_drives: continuous drives in the main city clear of every train frame (split
        ``drives_val``; 0: none).
      num_unseen_val_drives: continuous drives in the test city clear of every frame of
        ``drives`` and of the test city's split (split ``drives_val_unseen``: validation in a
        city the model never saw; 0 or no test city: none).
      drive_spacing_m: metres between consecutive frames of a drive.
      drive_length_m: length of a drive, metres (``drives``: exactly; ``drives_val``: at most).
      min_val_drive_m: shortest ``drives_val`` drive, metres.
      pool_factor: poses driven per requested frame per round (spares for the split clearance).
      max_rounds: driving rounds before giving up on filling the splits.
      shard_size: records per shard.
      render_batch: poses per simulator call (fixed: it defines the render seeds).
      png_level: PNG compression level of the stored images (lossless at any level).
      split: spatial split assignment (stripes + clearance).
      sim: simulator options, passed through to the frame source.
      map_variants: map variants rasterized after the sensors (``maps.MapConfig`` dicts).
    """

    name: str = "sim_quick"
    root: str = "data_cache"
    source: str = "sim"
    seed: int = 0
    city: str = "helsinki"
    test_city: str | None = "kouvola"
    num_train: int = 2000
    num_val: int = 300
    num_test: int = 300
    num_test_city: int = 300
    num_drives: int = 8
    num_val_drives: int = 4
    num_unseen_val_drives: int = 4
    drive_spacing_m: float = 5.0
    drive_length_m: float = 1000.0
    min_val_drive_m: float = 300.0
    pool_factor: float = 2.0
    max_rounds: int = 8
    shard_size: int = 250
    render_batch: int = 16
    png_level: int = 1
    split: sp.SplitConfig = sp.SplitConfig()
    sim: dict = dataclasses.field(default_factory=dict)
    map_variants: tuple[dict, ...] = ({"kind": "hd"},)

    def __post_init__(self):
        for i, spec in enumerate(self.map_variants):
            try:
                MapConfig(**spec)
            except (TypeError, ValueError) as err:
                raise ValueError(f"data.map_variants[{i}] = {spec!r}: {err}") from err
        counts = (self.num_train, self.num_val, self.num_test, self.num_test_city)
        if min(counts) < 1 or self.shard_size < 1 or self.render_batch < 1:
            raise ValueError(
                "data.num_train/num_val/num_test/num_test_city, shard_size and render_batch "
                f"must be >= 1, got {counts}, {self.shard_size}, {self.render_batch}"
            )
        if min(self.num_drives, self.num_val_drives, self.num_unseen_val_drives) < 0:
            raise ValueError(
                "data.num_drives, data.num_val_drives and data.num_unseen_val_drives must be "
                f">= 0 (0: no such split), got {self.num_drives}, {self.num_val_drives}, "
                f"{self.num_unseen_val_drives}"
            )
        if not self.drive_spacing_m > 0 or not self.drive_length_m >= self.drive_spacing_m:
            raise ValueError(
                "data.drive_spacing_m must be > 0 and data.drive_length_m >= it, got "
                f"{self.drive_spacing_m}, {self.drive_length_m}"
            )
        if not 0 < self.min_val_drive_m <= self.drive_length_m:
            raise ValueError(
                "data.min_val_drive_m must be in (0, data.drive_length_m], got "
                f"{self.min_val_drive_m} (drive_length_m {self.drive_length_m})"
            )

    def split_names(self) -> list[str]:
        """The splits a prepared dataset of this config holds, in preparation order."""
        names = ["train", "val", "test"]
        if self.test_city:
            names.append(city_key(self.test_city))  # the generalization split: the city's key
            if self.num_drives:
                names.append(dr.DRIVES)
        if self.num_val_drives:
            names.append(dr.VAL_DRIVES)
        if self.test_city and self.num_unseen_val_drives:
            names.append(dr.UNSEEN_VAL_DRIVES)
        return names

    def identity(self) -> dict:
        """The JSON-able config that defines the sensor shards (resume/loader check)."""
        d = dataclasses.asdict(self)
        for key in ("root", "map_variants"):
            d.pop(key)
        if not (d["test_city"] and d["num_unseen_val_drives"]):  # added later: when it makes
            d.pop("num_unseen_val_drives")  # no split, datasets prepared before it still match
        return json.loads(json.dumps(d))


def _planned_splits(plans: list[SplitPlan], shard_size: int) -> dict:
    out = {}
    for plan in plans:
        n = len(plan.poses)
        count = max(1, -(-n // shard_size))
        shards = [
            {
                "file": f"sensors/{plan.name}/{shard_name(plan.name, i, count)}",
                "count": min(shard_size, n - i * shard_size),
            }
            for i in range(count)
        ]
        out[plan.name] = {"shards": shards, "count": n, "cities": {plan.city: n}}
    return out


def write_plan(
    dataset_dir: str,
    plan: SplitPlan,
    split_entry: dict,
    render: Callable,
    cfg: PrepareConfig,
    split_idx: int,
    progress=None,
) -> int:
    """Renders and writes the missing shards of one split; returns how many were written.

    Each shard's checksum (``sha256``, ``bytes``) is recorded in its ``split_entry`` shard entry.
    Existing shards are kept after checking their record count and, where the entry records
    one, their checksum (a mismatch raises and leaves the file alone).
    """
    written = 0
    for shard_idx, entry in enumerate(split_entry["shards"]):
        path = os.path.join(dataset_dir, entry["file"])
        start = shard_idx * cfg.shard_size
        stop = start + entry["count"]
        if os.path.exists(path):
            n = count_records(path)
            if n != entry["count"]:
                raise RecordError(
                    f"{path}: existing shard has {n} records, expected {entry['count']}; "
                    "delete it to have it written again"
                )
            checksum = file_checksum(path)
            if "sha256" in entry and {k: entry.get(k) for k in mf.CHECKSUM_KEYS} != checksum:
                raise RecordError(
                    f"{path}: existing shard differs from the checksum recorded in "
                    f"{mf.manifest_path(dataset_dir)} (it changed after it was written); "
                    "delete it to have it written again"
                )
            entry.update(checksum)
            if progress is not None:
                progress.update(stop - start)
            continue
        records = []
        for b0 in range(start, stop, cfg.render_batch):
            b1 = min(b0 + cfg.render_batch, stop)
            seed = _seed(cfg.seed, split_idx, b0, 0x7E4)  # b0: frame index in the split
            samples = render(plan.poses[b0:b1], seed)
            if len(samples) != b1 - b0:
                raise ValueError(f"render returned {len(samples)} samples for {b1 - b0} poses")
            for i, sample in enumerate(samples, start=b0):
                sample = dict(
                    sample,
                    city=plan.city,  # the city key, whatever the source calls the city
                    sample_id=plan.sample_id(i),
                    sequence_id=str(plan.sequence_ids[i]),
                    frame_index=np.int64(plan.frame_index[i]),
                    timestamp=np.float64(plan.timestamps[i]),
                    prior=np.asarray(plan.priors[i], np.float64),
                )
                records.append(
                    encode_sample(
                        sample, compress_level=cfg.png_level, where=f"{path} record {i - start}"
                    )
                )
            if progress is not None:
                progress.update(b1 - b0)
        entry.update(write_shard(path, records))
        written += 1
    return written


def default_source_factory(cfg: PrepareConfig) -> Callable[[str], FrameSource]:
    """City name -> the simulator's frame source (imported lazily: sim is optional here)."""
    from seglocnet_jax.data.sim_source import SimSource

    return lambda city: SimSource(city, cfg.sim, cfg.seed)


def prepare(
    cfg: PrepareConfig, source_factory: Callable[[str], FrameSource] | None = None, *, variants=None
) -> str:
    """Prepares (or resumes, or just checks) ``<cfg.root>/<cfg.name>``; returns that directory.

    ``source_factory(city) -> FrameSource`` defaults to the simulator. ``variants`` (a sequence
    of ``maps.MapConfig``; None: those of ``cfg.map_variants``) are rasterized afterwards
    unless already stored (:mod:`.variants`).

    Holds ``fileio.DirLock(<dataset dir>)`` throughout (a second preparation of the same
    directory fails with :class:`fileio.LockError` naming the holder; a lock left by a killed
    process is taken over with a note) and first removes temporary files of killed runs. A
    dataset that needs no writing (complete, every variant stored) is checked without the lock
    when another process holds it or the directory cannot be locked (read-only).
    """
    dataset_dir = os.path.join(cfg.root, cfg.name)
    if cfg.source != "sim" and source_factory is None:
        mf.read_manifest(dataset_dir)  # a converter's: names a missing one before the lock
    lock = fileio.DirLock(dataset_dir, what="data preparation")
    try:
        lock.acquire()
    except (fileio.LockError, OSError) as err:  # another live preparation; a read-only dir
        if not _nothing_to_write(cfg, dataset_dir, variants):
            raise
        print(f"note: {dataset_dir} is complete; checking it without the lock ({err})", flush=True)
        return _prepare(cfg, dataset_dir, source_factory, variants)
    try:
        if lock.previous:
            print(
                f"note: {dataset_dir}: took over the lock of a {lock.previous.get('what', 'run')}"
                f" that is gone (pid {lock.previous.get('pid')} on {lock.previous.get('host')})",
                flush=True,
            )
        fileio.clean_stale_tmp(dataset_dir)
        return _prepare(cfg, dataset_dir, source_factory, variants)
    finally:
        lock.release()


def _nothing_to_write(cfg: PrepareConfig, dataset_dir: str, variants) -> bool:
    """Whether :func:`_prepare` would only read and check (see :func:`dataset_ready`)."""
    if variants is None:
        variants = [MapConfig(**spec) for spec in cfg.map_variants]
    return dataset_ready(dataset_dir, variants)


def dataset_ready(dataset_dir: str, variants) -> bool:
    """Whether ``dataset_dir`` holds complete sensor shards and every map variant of
    ``variants`` (``MapConfig``s) for every city (simulated or converted alike)."""
    from seglocnet_jax.data.variants import variant_path

    try:
        man = mf.read_manifest(dataset_dir)
        keys = {c for s in man["splits"].values() for c in s["cities"]}
        return (
            man["complete"]
            and all_shards_exist(man, dataset_dir)
            and all(
                v.name in man["map_variants"]
                and all(os.path.exists(variant_path(dataset_dir, v.name, c)) for c in keys)
                for v in variants
            )
        )
    except (ValueError, OSError):  # ManifestError, VariantError, ...: not ready
        return False


def _prepare(cfg: PrepareConfig, dataset_dir: str, source_factory, variants) -> str:
    identity = cfg.identity()
    man = None
    if cfg.source != "sim" and source_factory is None:
        man = mf.read_manifest(dataset_dir)  # a converter wrote it; names the missing file
        if not man["complete"] or not all_shards_exist(man, dataset_dir):
            raise mf.ManifestError(
                f"{mf.manifest_path(dataset_dir)}: conversion is incomplete "
                f"(source {cfg.source!r}); run the converter again"
            )
    elif os.path.exists(mf.manifest_path(dataset_dir)):
        man = mf.read_manifest(dataset_dir)
        mf.check_config(man, identity, dataset_dir)
    factory = source_factory
    if factory is None and cfg.source == "sim":
        factory = default_source_factory(cfg)
    sources = {}
    if man is None or not man["complete"] or not all_shards_exist(man, dataset_dir):
        main = city_key(cfg.city)
        sources[main] = factory(cfg.city)  # by city key, as the manifest
        plans = plan_main_city(sources[main], cfg)
        if cfg.test_city:
            other = city_key(cfg.test_city)
            sources[other] = factory(cfg.test_city)
            plans.append(plan_test_city(sources[other], cfg))
            if cfg.num_drives:
                plans.append(dr.plan_drives(sources[other], cfg, other))
        if cfg.num_val_drives:
            train = plans[0].poses[:, :2]
            plans.append(dr.plan_val_drives(sources[main], cfg, main, train))
        if cfg.test_city and cfg.num_unseen_val_drives:  # clear of every test-city test frame
            other = city_key(cfg.test_city)
            tested = np.concatenate([p.poses[:, :2] for p in plans if p.city == other])
            plans.append(
                dr.plan_val_drives(sources[other], cfg, other, tested, name=dr.UNSEEN_VAL_DRIVES)
            )
        planned = _planned_splits(plans, cfg.shard_size)
        if man is None:
            os.makedirs(dataset_dir, exist_ok=True)
            man = mf.new_manifest(identity, planned)
            mf.write_manifest(dataset_dir, man)
        elif mf.strip_checksums(man["splits"]) != planned:
            raise mf.ManifestError(
                f"{mf.manifest_path(dataset_dir)}: planned shards differ from the stored ones "
                "although the config matches (code changed?); prepare into a new directory"
            )
        else:
            planned = man["splits"]  # the plan, with the checksums of recorded shards
        total = sum(len(p.poses) for p in plans)
        with tqdm(total=total, desc=f"prepare {cfg.name}", unit="frame") as bar:
            for split_idx, plan in enumerate(plans):
                write_plan(
                    dataset_dir,
                    plan,
                    planned[plan.name],
                    sources[plan.city].render,
                    cfg,
                    dr.DRIVE_STREAMS.get(plan.name, split_idx),  # drives: whatever else exists
                    bar,
                )
                mf.write_manifest(dataset_dir, man)  # the split's shard checksums
        man = dict(man, complete=True)
        mf.write_manifest(dataset_dir, man)
    if variants is None:
        variants = [MapConfig(**spec) for spec in cfg.map_variants]
    for vcfg in variants:
        ensure_variant(dataset_dir, vcfg, factory, sources)
    return dataset_dir


def prepare_for_training(
    cfg: PrepareConfig,
    variant: MapConfig,
    source_factory: Callable[[str], FrameSource] | None = None,
):
    """What the training app calls: prepares what is missing (sensors, ``cfg.map_variants`` and
    ``variant``) and returns ``(dataset_dir, variant name)`` for :func:`loader.make_loader`."""
    wanted = [MapConfig(**spec) for spec in cfg.map_variants]
    if variant not in wanted:
        wanted.append(variant)
    return prepare(cfg, source_factory, variants=wanted), variant.name


def all_shards_exist(man: dict, dataset_dir: str) -> bool:
    return all(
        os.path.exists(os.path.join(dataset_dir, s["file"]))
        for split in man["splits"].values()
        for s in split["shards"]
    )
