"""The grain input pipeline: ArrayRecord shards -> fixed-shape NumPy batches (``BATCH_KEYS``).

Training: globally shuffled (reshuffled every epoch), a fresh prior per epoch and record drawn
from ``np.random.Generator`` that grain seeds with ``(seed, global index)``, the map tile cut on
the fly around the snapped prior and the GT BEV cut at the GT pose from the cached city raster
(for an NM model also ``nm_tile``, the same tile of the city's OSM class raster).
Evaluation: file order, the stored seeded priors, the last batch padded by repeating the last
record (``valid`` marks real rows) so that every batch has the same shape.

Opening a split checks each shard's size and SHA-256 against the manifest (hashed once per
process and file version), so a shard that changed after it was written fails here, named.

Everything is NumPy and deterministic for a seed; ``iter(loader)`` returns grain's iterator whose
``get_state()`` (a small JSON-able dict) / ``set_state()`` resume bit-identically.

Many processes (``jax.distributed``): with ``shard_options = grain.sharding.ShardOptions(i, n)``
(``ShardOptions`` here) the loader of shard ``i`` reads and decodes only its ``batch_size / n``
rows of every global batch: rows ``[i * b, (i + 1) * b)`` with ``b = batch_size / n``, so the
``n`` shards' batches, concatenated in shard order, are the unsharded loader's batch bit for bit
(same shuffle, same per-record priors, same padding). Every shard yields the same number of
batches, and its iterator state counts global batches, so any shard's state resumes any other
shard (or the unsharded loader) at the same global batch. ``training.step.batch_shard(mesh)``
gives ``(i, n)`` of this process for a mesh.

No worker processes by default: on 2 cores grain workers were slower than decoding in threads
(DESIGN). If ``worker_count > 0`` under Hydra or pytest, call ``absl.flags.FLAGS.mark_as_parsed()``
first or the workers crash (grain 0.2.18).
"""

from __future__ import annotations

import dataclasses
import os

import grain
import numpy as np
from grain.sharding import ShardOptions

from seglocnet_jax import geometry
from seglocnet_jax.data.manifest import read_manifest, verify_split
from seglocnet_jax.data.records import RecordError, count_records, decode_sample


@dataclasses.dataclass(frozen=True)
class LoaderConfig:
    """Loader knobs (``data.loader``; the batch size comes from the train/eval config).

    Attributes:
      max_points: LiDAR points per sample (P): more are subsampled evenly, fewer zero-padded.
      num_threads: grain read threads (0 = decode in the calling thread).
      prefetch: batches buffered ahead by the read threads.
      worker_count: grain worker processes (0 = none; see the module docstring's absl trap).
      num_epochs: training epochs to iterate (None = forever); evaluation always runs once.
    """

    max_points: int = 32768
    num_threads: int = 2
    prefetch: int = 4
    worker_count: int = 0
    num_epochs: int | None = None

    def __post_init__(self):
        if self.max_points < 1 or self.num_threads < 0 or self.worker_count < 0:
            raise ValueError(
                f"data.loader: max_points must be >= 1 and num_threads, worker_count >= 0, got "
                f"{self.max_points}, {self.num_threads}, {self.worker_count}"
            )


class ShardSource:
    """Random access over a split's shards (grain ``ArrayRecordDataSource``), decoding records.

    Record counts are checked against the manifest when opened, so a truncated or missing shard
    fails here, naming the file. With ``pad_to``, indices past the end repeat the last record
    and carry ``valid = False``.
    """

    def __init__(self, files: list[tuple[str, int]], pad_to: int | None = None):
        if not files:
            raise RecordError("no shards to read")
        for path, expected in files:
            n = count_records(path)
            if n != expected:
                raise RecordError(
                    f"{path}: {n} records, manifest expects {expected} (truncated shard?)"
                )
        self._paths = [p for p, _ in files]
        self._starts = np.cumsum([0] + [c for _, c in files])  # (num_shards + 1,)
        self._n = int(self._starts[-1])
        self._len = max(self._n, pad_to or 0)
        self._src = grain.sources.ArrayRecordDataSource(self._paths)

    def __len__(self) -> int:
        return self._len

    def where(self, index: int) -> tuple[str, int]:
        """``(shard path, record index in that shard)`` of a global record index."""
        shard = int(np.searchsorted(self._starts, index, side="right") - 1)
        return self._paths[shard], int(index - self._starts[shard])

    def __getitem__(self, index: int) -> dict:
        real = min(int(index), self._n - 1)
        path, local = self.where(real)
        where = f"{path} record {local}"
        try:
            raw = self._src[real]
        except Exception as err:
            raise RecordError(f"{where}: unreadable ({err})") from err
        sample = decode_sample(raw, where)
        sample["valid"] = np.bool_(index < self._n)
        return sample

    def __repr__(self) -> str:  # grain prints sources in its dataset summaries
        return f"ShardSource({len(self._paths)} shards, {self._n} records)"


def fit_points(lidar: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR ``(n, 4)`` to ``(max_points, 4)`` float32 plus a ``(max_points,)`` bool mask.

    More points than ``max_points`` are subsampled at evenly spaced indices (deterministic and
    spread over the whole sweep, unlike a plain truncation of an azimuth-ordered scan).
    """
    n = len(lidar)
    points = np.zeros((max_points, 4), np.float32)
    mask = np.zeros((max_points,), bool)
    if n > max_points:
        idx = (np.arange(max_points, dtype=np.int64) * n) // max_points
        points[:] = lidar[idx]
        mask[:] = True
    else:
        points[:n] = lidar
        mask[:n] = True
    return points, mask


class FrameTransform:
    """One decoded record -> one batch row (``BATCH_KEYS`` without B). The metadata
    (``schema.BATCH_METADATA_KEYS``: ``sample_id``, ``city``, ``sequence_id``, ``lighting`` str;
    ``frame_index`` int64; ``timestamp`` float64 seconds; ``valid``, ``pose``, ``tile_center``)
    stays NumPy on the host: a batch holds them as ``(B,)`` / ``(B, k)`` arrays (strings as
    unicode arrays).

    ``rasters`` maps city -> an object with ``tile(x, y) -> ((C, 256, 256), (cx, cy))`` and
    ``cut_bev(pose) -> (C, 128, 128)`` (``maps.CityRaster``). With ``train=True`` the prior is
    drawn from the generator grain passes; otherwise the record's stored prior is used.
    ``nm_rasters`` (city -> the OSM class raster, for an NM model; None: no ``nm_tile``) adds
    ``nm_tile``, the tile of that raster around the same prior (the same centre: both grids'
    corners lie on the resolution's lattice).
    """

    def __init__(self, rasters: dict, max_points: int, train: bool, nm_rasters=None):
        self.rasters = rasters
        self.max_points = max_points
        self.train = train
        self.nm_rasters = nm_rasters

    def __call__(self, sample: dict, rng: np.random.Generator | None = None) -> dict:
        city = sample["city"]
        if city not in self.rasters:
            raise RecordError(
                f"record {sample['sample_id']!r}: no map raster for city {city!r} "
                f"(have {sorted(self.rasters)})"
            )
        raster = self.rasters[city]
        pose = sample["pose"]  # (3,) world x, y (m), yaw (rad)
        if self.train:
            r = geometry.PRIOR_RANGE
            prior = pose[:2] + rng.uniform(-r, r, size=2)
        else:
            prior = sample["prior"]
        tile, (cx, cy) = raster.tile(float(prior[0]), float(prior[1]))
        bev = raster.cut_bev(pose)
        points, mask = fit_points(sample["lidar"], self.max_points)
        extra = {}
        if self.nm_rasters is not None:
            where = f"record {sample['sample_id']!r}"
            extra["nm_tile"] = nm_tile(self.nm_rasters, city, cx, cy, where)
        return {
            "images": sample["images"],  # (N, H, W, 3) uint8
            "intrinsics": sample["intrinsics"],  # (N, 3, 3)
            "cam_to_ego": sample["cam_to_ego"],  # (N, 4, 4)
            "points": points,  # (P, 4)
            "points_mask": mask,  # (P,)
            "bev_gt": np.asarray(bev, np.float32),  # (C, 128, 128)
            "tile": np.asarray(tile, np.float32),  # (C, 256, 256)
            "pose_tile": np.array([pose[0] - cx, pose[1] - cy, pose[2]], np.float32),
            "tile_center": np.array([cx, cy], np.float64),
            "pose": np.asarray(pose, np.float64),
            "valid": sample["valid"],
            "sample_id": sample["sample_id"],
            "city": city,
            "sequence_id": sample["sequence_id"],
            "frame_index": np.int64(sample["frame_index"]),
            "timestamp": np.float64(sample["timestamp"]),  # seconds
            "lighting": sample["lighting"],
            **extra,
        }


def nm_tile(nm_rasters: dict, city: str, cx: float, cy: float, where: str = "tile") -> np.ndarray:
    """The ``(C_osm, 256, 256)`` uint8 tile of ``city``'s OSM class raster centred on the map
    tile's centre ``(cx, cy)`` (world m, a pixel corner); an error names a missing city or a
    raster whose grid is off the lattice (the tiles would not be the same place)."""
    if city not in nm_rasters:
        raise RecordError(
            f"{where}: no OSM class raster for city {city!r} (have {sorted(nm_rasters)})"
        )
    tile, centre = nm_rasters[city].tile(cx, cy)
    if max(abs(centre[0] - cx), abs(centre[1] - cy)) > 1e-6:
        raise RecordError(
            f"{where}: the OSM class raster of {city!r} puts the tile at {centre}, the map at "
            f"({cx}, {cy}): its grid is not on the map's pixel lattice"
        )
    return tile


class Loader:
    """An iterable of batches; ``iter(loader)`` gives a checkpointable grain iterator.

    Attributes:
      dataset: the grain ``IterDataset``.
      num_records: records in the split (without eval padding).
      batches_per_epoch: full (global) batches per pass over the split (eval: including the
        padded one); the same for every shard.
      batch_size: rows of the batches this loader yields (the global batch size / shard count).
      shard_options: the ``ShardOptions`` it reads (``ShardOptions(0, 1)``: everything).
    """

    def __init__(
        self,
        dataset,
        num_records: int,
        batches_per_epoch: int,
        batch_size: int | None = None,
        shard_options: ShardOptions | None = None,
    ):
        self.dataset = dataset
        self.num_records = num_records
        self.batches_per_epoch = batches_per_epoch
        self.batch_size = batch_size
        self.shard_options = shard_options or ShardOptions(0, 1)

    def __iter__(self):
        return iter(self.dataset)


def load_rasters(dataset_dir: str | os.PathLike, map_variant: str, cities) -> dict:
    """City rasters of a prepared map variant (``maps/<variant>/<city>.npz``)."""
    from seglocnet_jax.data.variants import load_variant  # maps dependency stays lazy

    return load_variant(dataset_dir, map_variant, cities)


def load_osm_classes(dataset_dir: str | os.PathLike, cities) -> dict:
    """The cities' stored OSM class rasters (``maps/osm_classes/<city>.npz``)."""
    from seglocnet_jax.data import variants  # maps dependency stays lazy

    return variants.load_osm_classes(dataset_dir, cities)


def make_loader(
    dataset_dir: str | os.PathLike,
    split: str,
    map_variant: str | None,
    batch_size: int,
    seed: int,
    train: bool,
    *,
    config: LoaderConfig | None = None,
    rasters: dict | None = None,
    shard_options: ShardOptions | None = None,
    nm_tiles: bool = False,
    nm_rasters: dict | None = None,
) -> Loader:
    """The loader of one split of a prepared dataset.

    Args:
      dataset_dir: directory with ``manifest.json`` (see :func:`data.simulated.prepare.prepare`).
      split: ``train``, ``val``, ``test``, ``kouvola``, ... (manifest ``splits``).
      map_variant: prepared variant name (``data.variants.variant_name``); ignored if
        ``rasters`` is given.
      batch_size: samples per global batch (B); a shard's batches have ``B / shard_count``.
      seed: shuffling and training-prior seed (0 <= seed < 2**32).
      train: shuffle, repeat ``config.num_epochs`` times, random priors, drop the remainder;
        else file order, stored priors, one pass, last batch padded (``valid`` False).
      rasters: city -> raster, to bypass the stored map variants.
      shard_options: read only shard ``shard_index`` of ``shard_count`` of every global batch
        (one process of a multi-host run; ``grain.sharding.ShardByJaxProcess()`` or
        ``training.step.batch_shard``); None reads everything. ``drop_remainder`` is ignored:
        every shard gets the same number of rows.
      nm_tiles: also yield ``nm_tile`` (an NM model's map input: the same tile of each city's
        stored OSM class raster, ``data.variants.load_osm_classes``).
      nm_rasters: city -> OSM class raster, to bypass the stored ones (implies ``nm_tiles``).
    """
    cfg = config or LoaderConfig()
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    shard = shard_options or ShardOptions(0, 1)  # validates 0 <= index < count itself
    index, count = int(shard.shard_index), int(shard.shard_count)
    if batch_size % count:
        raise ValueError(
            f"batch_size {batch_size} is not divisible by the {count} loader shards (processes); "
            f"set the batch size to a multiple of {count}"
        )
    local = batch_size // count
    man = read_manifest(dataset_dir)
    files = verify_split(man, dataset_dir, split)  # counts; size + SHA-256 per shard
    n = sum(c for _, c in files)
    if n == 0:
        raise RecordError(f"{dataset_dir}: split {split!r} has no records")
    cities = sorted(man["splits"][split]["cities"])
    if rasters is None:
        rasters = load_rasters(dataset_dir, map_variant, cities)
    if nm_tiles and nm_rasters is None:
        nm_rasters = load_osm_classes(dataset_dir, cities)
    transform = FrameTransform(rasters, cfg.max_points, train, nm_rasters)
    if train:
        if n < batch_size:
            raise RecordError(f"split {split!r} has {n} records < batch_size {batch_size}")
        ds = grain.MapDataset.source(ShardSource(files)).seed(seed).shuffle()
        ds = ds.repeat(cfg.num_epochs).random_map(transform)
        if cfg.num_epochs is not None and count > 1:  # whole global batches: the same for all
            ds = ds[: len(ds) // batch_size * batch_size]
        batches = n // batch_size
    else:
        batches = -(-n // batch_size)
        ds = grain.MapDataset.source(ShardSource(files, pad_to=batches * batch_size))
        ds = ds.map(transform)
    # Rows [index * local, (index + 1) * local) of every global batch: local batches of
    # consecutive records, every count-th one. Records are mapped (priors drawn) before the
    # slicing, by their global index, so a shard's rows equal the unsharded loader's.
    ds = ds.batch(local, drop_remainder=True)
    if count > 1:
        ds = ds[index::count]
    it_ds = ds.to_iter_dataset(
        grain.ReadOptions(num_threads=cfg.num_threads, prefetch_buffer_size=cfg.prefetch)
    )
    if cfg.worker_count > 0:
        it_ds = it_ds.mp_prefetch(grain.MultiprocessingOptions(num_workers=cfg.worker_count))
    return Loader(
        it_ds,
        num_records=n,
        batches_per_epoch=batches,
        batch_size=local,
        shard_options=ShardOptions(index, count),
    )
