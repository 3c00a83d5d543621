"""Offline preparation: frames of a producer -> spatially split, seeded ArrayRecord shards.

``prepare(cfg)`` is what the training app calls ("prepare the data if the shards are missing").
Per city it builds a frame source (the simulator by default, :mod:`.source`), drives a pool of
poses, assigns spatially disjoint train / val / test frames in the main city (:mod:`.splits`)
and a generalization-only split named after the test city, plus whole continuous drives
(``drives`` in the test city, ``drives_val`` in the main city clear of train and, optionally,
``drives_val_unseen`` in the test city clear of its test frames: :mod:`.drives`),
draws seeded priors (these plans: :mod:`.planning`), renders the sensors in batches and writes
shards atomically. Sensors are prepared once; map variants (:mod:`..variants`) only rasterize.

Sequence metadata: a pool frame's sequence is its short route (``"{city}-p{round}-route{r:05d}"``,
``frame_index`` its index along the route, ``timestamp`` distance / ``sim.NOMINAL_SPEED_MPS``)
when the source reports routes (``drive_routes``), else the frame is a sequence of its own; a
drive split's sequence is the drive (:mod:`.drives`).

Resumable: everything is a pure function of the config, a shard path that exists is complete
(atomic rename), and each shard is rendered from its own seed, so an interrupted run resumed
writes exactly the shards a single run would have written.
"""

from __future__ import annotations

import collections
import concurrent.futures
import os
import time
from collections.abc import Callable

import numpy as np
from tqdm.auto import tqdm

from seglocnet_jax import fileio
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.records import (
    RecordError,
    count_records,
    encode_sample,
    file_checksum,
    shard_name,
    write_shard,
)
from seglocnet_jax.data.simulated import drives as dr
from seglocnet_jax.data.simulated.config import FrameSource, PrepareConfig
from seglocnet_jax.data.simulated.planning import (
    _seed,
    plan_main_city,
    plan_test_city,
)
from seglocnet_jax.data.simulated.splits import SplitPlan
from seglocnet_jax.data.variants import ensure_osm_classes, ensure_variant
from seglocnet_jax.maps import MapConfig, city_key


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
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="encode") as encoder:
        return _write_shards(
            dataset_dir, plan, split_entry, render, cfg, split_idx, progress, encoder
        )


def _encode_batch(plan: SplitPlan, samples: list, b0: int, start: int, path: str, cfg) -> list:
    """Record bytes of rendered ``samples`` (split frames ``b0, b0 + 1, ...``) with their split
    metadata; ``start``: the shard's first frame (names records in errors)."""
    records = []
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
            encode_sample(sample, compress_level=cfg.png_level, where=f"{path} record {i - start}")
        )
    return records


def _write_shards(dataset_dir, plan, split_entry, render, cfg, split_idx, progress, encoder):
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
        # A thread encodes each rendered batch while the simulator renders the next one (its
        # compiled code runs without the interpreter lock; zlib releases it too). Records keep
        # their order, so the shard's bytes do not depend on the overlap.
        records, pending = [], collections.deque()
        for b0 in range(start, stop, cfg.render_batch):
            b1 = min(b0 + cfg.render_batch, stop)
            seed = _seed(cfg.seed, split_idx, b0, 0x7E4)  # b0: frame index in the split
            samples = render(plan.poses[b0:b1], seed)
            if len(samples) != b1 - b0:
                raise ValueError(f"render returned {len(samples)} samples for {b1 - b0} poses")
            pending.append(encoder.submit(_encode_batch, plan, samples, b0, start, path, cfg))
            while len(pending) > 1:  # at most one batch waits: memory stays bounded
                records.extend(pending.popleft().result())
            if progress is not None:
                progress.update(b1 - b0)
        records.extend(r for job in pending for r in job.result())
        entry.update(write_shard(path, records))
        written += 1
    return written


def default_source_factory(cfg: PrepareConfig) -> Callable[[str], FrameSource]:
    """City name -> the simulator's frame source (imported lazily: sim is optional here)."""
    from seglocnet_jax.data.simulated.source import SimSource

    return lambda city: SimSource(city, cfg.sim, cfg.seed)


def prepare(
    cfg: PrepareConfig,
    source_factory: Callable[[str], FrameSource] | None = None,
    *,
    variants=None,
    osm_classes: bool = False,
) -> str:
    """Prepares (or resumes, or just checks) ``<cfg.root>/<cfg.name>``; returns that directory.

    ``source_factory(city) -> FrameSource`` defaults to the simulator. ``variants`` (a sequence
    of ``maps.MapConfig``; None: those of ``cfg.map_variants``) are rasterized afterwards
    unless already stored (:mod:`..variants`); with ``osm_classes`` also the OSM class raster
    of every city (the NM model's map input, :func:`..variants.ensure_osm_classes`).

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
        if not _nothing_to_write(cfg, dataset_dir, variants, osm_classes):
            raise
        print(f"note: {dataset_dir} is complete; checking it without the lock ({err})", flush=True)
        return _prepare(cfg, dataset_dir, source_factory, variants, osm_classes)
    try:
        if lock.previous:
            print(
                f"note: {dataset_dir}: took over the lock of a {lock.previous.get('what', 'run')}"
                f" that is gone (pid {lock.previous.get('pid')} on {lock.previous.get('host')})",
                flush=True,
            )
        fileio.clean_stale_tmp(dataset_dir)
        return _prepare(cfg, dataset_dir, source_factory, variants, osm_classes)
    finally:
        lock.release()


def _nothing_to_write(cfg: PrepareConfig, dataset_dir: str, variants, osm_classes) -> bool:
    """Whether :func:`_prepare` would only read and check (see :func:`dataset_ready`)."""
    if variants is None:
        variants = [MapConfig(**spec) for spec in cfg.map_variants]
    return dataset_ready(dataset_dir, variants, osm_classes=osm_classes)


def dataset_ready(dataset_dir: str, variants, *, osm_classes: bool = False) -> bool:
    """Whether ``dataset_dir`` holds complete sensor shards and every map variant of
    ``variants`` (``MapConfig``s) for every city (simulated or converted alike); with
    ``osm_classes`` also every city's current OSM class raster."""
    from seglocnet_jax.data.variants import osm_classes_ready, variant_path

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
            and (not osm_classes or osm_classes_ready(dataset_dir, man))
        )
    except (ValueError, OSError):  # ManifestError, VariantError, ...: not ready
        return False


def _prepare(cfg: PrepareConfig, dataset_dir: str, source_factory, variants, osm_classes) -> str:
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
    sources, times = {}, {}  # times: the printed breakdown, seconds
    if man is None or not man["complete"] or not all_shards_exist(man, dataset_dir):
        t0 = time.perf_counter()
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
        times["worlds and plans"] = time.perf_counter() - t0  # the worlds dominate
        t0 = time.perf_counter()
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
        times["sensor shards (rendered, encoded, written)"] = time.perf_counter() - t0
    if variants is None:
        variants = [MapConfig(**spec) for spec in cfg.map_variants]
    t0 = time.perf_counter()
    for vcfg in variants:
        ensure_variant(dataset_dir, vcfg, factory, sources)
    if osm_classes:
        ensure_osm_classes(dataset_dir)
    if times:
        times["map variants"] = time.perf_counter() - t0
        parts = ", ".join(f"{k} {v:.0f} s" for k, v in times.items())
        print(f"data preparation of {dataset_dir}: {parts}", flush=True)
    return dataset_dir


def prepare_for_training(
    cfg: PrepareConfig,
    variant: MapConfig,
    source_factory: Callable[[str], FrameSource] | None = None,
    *,
    osm_classes: bool = False,
):
    """What the training app calls: prepares what is missing (sensors, ``cfg.map_variants`` and
    ``variant``; with ``osm_classes``, for an NM model, the OSM class rasters) and returns
    ``(dataset_dir, variant name)`` for :func:`loader.make_loader`."""
    wanted = [MapConfig(**spec) for spec in cfg.map_variants]
    if variant not in wanted:
        wanted.append(variant)
    dataset_dir = prepare(cfg, source_factory, variants=wanted, osm_classes=osm_classes)
    return dataset_dir, variant.name


def all_shards_exist(man: dict, dataset_dir: str) -> bool:
    return all(
        os.path.exists(os.path.join(dataset_dir, s["file"]))
        for split in man["splits"].values()
        for s in split["shards"]
    )
