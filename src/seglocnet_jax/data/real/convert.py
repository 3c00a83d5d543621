"""Real dataset -> the prepared-dataset layout the loader reads (same as the simulator's).

``convert(reader, cfg)`` writes ``<root>/<name>/`` with ``manifest.json``, ArrayRecord shards per
split and seeded evaluation priors (through the data pipeline's :class:`..writer.DatasetWriter`)
and the cached map rasters per city and map variant (:mod:`.map_rasters`). Resumable: a shard path
that exists is complete (atomic rename) and is only checked, its frames' sensors are not read
again; a config that differs from the manifest's is refused, naming the keys.

Shards are converted by ``num_workers`` worker processes (``spawn``; default: all cores), each
reading its frames with its own copy of the reader (pickled once per worker); the output is
byte-identical for any number of workers, and only this process writes the manifest.

Splits map output names to the reader's: nuScenes ``{"train": "train", "val": "val"}`` (scene
lists), AV2 ``{"train": "train", "val": "val"}`` (split directories, filtered by city).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping

import numpy as np

from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.real.alignment import AlignConfig, report_lines
from seglocnet_jax.data.real.common import (
    Frame,
    RealDataError,
    RealReader,
    check_disjoint_groups,
)
from seglocnet_jax.data.schema import SAMPLE_KEYS
from seglocnet_jax.data.writer import DatasetWriter
from seglocnet_jax.maps import MapConfig


@dataclasses.dataclass(frozen=True)
class ConvertConfig:
    """The ``dataset`` conversion options (reader options live in the reader's config).

    Attributes:
      name: dataset directory name under ``root``.
      root: output root (not part of the dataset identity).
      seed: seed of the stored evaluation priors.
      splits: output split name -> reader split name.
      shard_size: records per shard (the writer holds a shard's decoded samples in memory:
        ~5 MB each at 6 x 320 x 800, so 64 is ~300 MB).
      image_codec: stored camera images: "jpeg" (default; encoded at ``jpeg_quality``, except
        that a source JPEG the reader attached (``records.with_source_jpegs``) and that already
        has the stored size is kept as it is) or "png" (lossless, ~4x larger).
      jpeg_quality: JPEG quality (1-100) of re-encoded images.
      png_level: PNG compression level of the stored images (with ``image_codec: png``).
      osm: city -> user OSM extract (``.osm.pbf`` / ``.osm``): buildings and SD roads; a city
        without one gets HD variants from the drivable area alone only if ``channels`` has no
        building (else the error names ``dataset.convert.osm.<city>``).
      map_variants: ``maps.MapConfig`` dicts rasterized after the sensors.
      align: the OSM -> dataset similarity correction fitted per city.
      num_workers: worker processes that read and encode the shards (None: all cores of this
        process, ``os.sched_getaffinity``; 0 or 1: in this process). Not part of the dataset
        identity: the shards and the manifest are the same for any value, and a conversion may
        resume with another one. Each worker holds a copy of the reader and one shard's samples.
    """

    name: str = "nuscenes"
    root: str = "data_cache"
    seed: int = 0
    splits: dict = dataclasses.field(default_factory=lambda: {"train": "train", "val": "val"})
    shard_size: int = 64
    image_codec: str = "jpeg"
    jpeg_quality: int = 95
    png_level: int = 1
    osm: dict = dataclasses.field(default_factory=dict)
    map_variants: tuple[dict, ...] = ({"kind": "hd"}, {"kind": "sd", "road_width": 10.0})
    align: AlignConfig = AlignConfig()
    num_workers: int | None = None

    def __post_init__(self):
        if not self.splits:
            raise ValueError(
                "dataset.convert.splits must map at least one output split to a reader split"
            )
        if self.shard_size < 1:
            raise ValueError(f"dataset.convert.shard_size must be >= 1, got {self.shard_size}")
        if self.image_codec not in ("jpeg", "png"):
            raise ValueError(
                f"dataset.convert.image_codec must be jpeg or png, got {self.image_codec!r}"
            )
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(
                f"dataset.convert.jpeg_quality must be in [1, 100], got {self.jpeg_quality}"
            )
        if self.num_workers is not None and (
            isinstance(self.num_workers, bool)
            or not isinstance(self.num_workers, int)
            or self.num_workers < 0
        ):
            raise ValueError(
                "dataset.convert.num_workers must be null (all cores) or an integer >= 0, "
                f"got {self.num_workers!r}"
            )

    def workers(self) -> int:
        """The number of worker processes ``num_workers`` asks for (0/1: none)."""
        if self.num_workers is not None:
            return self.num_workers
        try:
            return len(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not on Linux
            return os.cpu_count() or 1

    def identity(self, reader: RealReader) -> dict:
        """What defines the sensor shards: the reader's config and these keys."""
        return json.loads(
            json.dumps(
                {
                    "reader": reader.identity(),
                    "seed": self.seed,
                    "splits": dict(self.splits),
                    "shard_size": self.shard_size,
                    "image_codec": self.image_codec,
                    "jpeg_quality": self.jpeg_quality,
                    "png_level": self.png_level,
                }
            )
        )


class FrameRef(Mapping):
    """What the dataset writer sees of a frame before its sensors are read: ``sample_id``,
    ``city`` and ``pose`` (a light, picklable stand-in; :class:`FrameLoader` loads it)."""

    def __init__(self, frame: Frame):
        self.frame = frame

    def __getitem__(self, key):
        f = self.frame
        if key == "sample_id":
            return f.sample_id
        if key == "city":
            return f.city
        if key == "pose":
            return np.asarray(f.pose, np.float64)
        raise KeyError(key)

    def __iter__(self):
        return iter(("sample_id", "city", "pose"))

    def __len__(self) -> int:
        return 3


class FrameLoader:
    """``loader(ref) -> sample dict`` (``schema.SAMPLE_KEYS``) of a :class:`FrameRef`, read
    with ``reader``. Picklable when the reader is: a conversion worker gets one copy.

    The sample's ``sample_id``, ``city`` and ``pose`` are the frame's (a reader that loads
    another sample or city than it listed is an error)."""

    def __init__(self, reader: RealReader):
        self.reader = reader

    def __call__(self, ref: FrameRef) -> dict:
        f = ref.frame
        data = self.reader.load(f)
        if data["sample_id"] != f.sample_id or data["city"] != f.city:
            raise RealDataError(
                f"{f.key}: loaded sample {data['sample_id']!r} in "
                f"{data['city']!r}, listed as {f.sample_id!r} in {f.city!r}"
            )
        sample = {k: data[k] for k in SAMPLE_KEYS}
        sample["pose"] = np.asarray(f.pose, np.float64)
        return sample


def convert(
    reader: RealReader, cfg: ConvertConfig, *, variants: bool = True, osm_classes: bool = False
) -> str:
    """Converts (or resumes, or checks) ``<cfg.root>/<cfg.name>``; returns that directory.

    Sensors go through :class:`data.writer.DatasetWriter` (the simulator pipeline's records,
    shards, manifest and seeded priors), in ``cfg.workers()`` processes; then the map variants
    (:mod:`.map_rasters`) and, with ``osm_classes`` (an NM model), the OSM class rasters.
    """
    dataset_dir = os.path.join(cfg.root, cfg.name)
    frames = {out: reader.frames(src) for out, src in cfg.splits.items()}
    check_disjoint_groups(  # a log / scene in two output splits leaks training frames
        {out: [f.group for f in fr] for out, fr in frames.items()},
        "scene / log",
        hint="dataset.convert.splits combines overlapping reader splits",
    )
    for out, fr in frames.items():
        if not fr:
            raise RealDataError(
                f"dataset.convert.splits.{out}: reader split {cfg.splits[out]!r} has no frames"
            )
    writer = DatasetWriter(
        dataset_dir,
        cfg.identity(reader),
        seed=cfg.seed,
        shard_size=cfg.shard_size,
        png_level=cfg.png_level,
        num_workers=cfg.workers(),
        image_codec=cfg.image_codec,
        jpeg_quality=cfg.jpeg_quality,
    )
    load = FrameLoader(reader)
    for out, fr in frames.items():
        writer.write_split(out, [FrameRef(f) for f in fr], len(fr), load=load)
    writer.close()
    if variants:
        from seglocnet_jax.data.real.map_rasters import ensure_real_variants

        poses = {}
        for f in (f for fr in frames.values() for f in fr):
            poses.setdefault(f.city, []).append(f.pose)
        ensure_real_variants(dataset_dir, reader, cfg, poses, osm_classes=osm_classes)
    return dataset_dir


def convert_for_training(
    reader: RealReader, cfg: ConvertConfig, variant: MapConfig, *, osm_classes: bool = False
):
    """What a training app calls for a real dataset (twin of ``prepare.prepare_for_training``):
    converts what is missing, adds ``variant`` to the map variants (and with ``osm_classes``
    the OSM class rasters of an NM model), and returns ``(dataset_dir, variant name)`` for
    :func:`loader.make_loader`."""
    specs = [dict(v) for v in cfg.map_variants]
    if variant not in [MapConfig(**v) for v in specs]:
        specs.append(variant.to_dict())
    cfg = dataclasses.replace(cfg, map_variants=tuple(specs))
    return convert(reader, cfg, osm_classes=osm_classes), variant.name


def parse_tree(tree: dict, prefix: str = "dataset"):
    """``(reader class, reader config, ConvertConfig)`` from a plain ``dataset`` config tree
    (``conf/dataset/*.yaml``: ``source`` (``nuscenes`` | ``av2``), ``reader`` and ``convert``
    sections), validated without touching the disk."""
    from seglocnet_jax.config_util import ConfigError, from_dict
    from seglocnet_jax.data.real import argoverse, nuscenes

    readers = {
        "nuscenes": (nuscenes.NuScenesConfig, nuscenes.NuScenesReader),
        "av2": (argoverse.ArgoverseConfig, argoverse.ArgoverseReader),
    }
    if not isinstance(tree, dict):
        raise ConfigError(f"{prefix} must be a mapping with source, reader, convert; got {tree!r}")
    unknown = sorted(set(tree) - {"source", "reader", "convert"})
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {[f'{prefix}.{k}' for k in unknown]}; "
            f"{prefix} accepts source, reader, convert"
        )
    source = tree.get("source")
    if source not in readers:
        raise ConfigError(f"{prefix}.source must be one of {sorted(readers)}, got {source!r}")
    cfg_cls, reader_cls = readers[source]
    reader_cfg = from_dict(cfg_cls, tree.get("reader"), f"{prefix}.reader")
    return (
        reader_cls,
        reader_cfg,
        from_dict(ConvertConfig, tree.get("convert"), f"{prefix}.convert"),
    )


def from_tree(tree: dict, prefix: str = "dataset"):
    """``(reader, ConvertConfig)`` from a plain ``dataset`` config tree (see :func:`parse_tree`);
    the reader opens ``dataset.reader.dataroot``."""
    reader_cls, reader_cfg, cfg = parse_tree(tree, prefix)
    return reader_cls(reader_cfg), cfg


def summary(dataset_dir: str) -> str:
    """A short report of a converted dataset: frames per split and city, map variants, and each
    city's OSM correction (shift m, rotation deg, scale, normalized score; for a fit its
    sharpness, windows and their agreement, and the worst windows)."""
    man = mf.read_manifest(dataset_dir)
    lines = [f"dataset {dataset_dir}"]
    for name, split in man["splits"].items():
        lines.append(f"  split {name}: {split['count']} frames {split['cities']}")
    lines.append(f"  map variants: {sorted(man['map_variants'])}")
    for city, a in sorted(man.get("alignment", {}).get("cities", {}).items()):
        lines.extend(report_lines(city, a))  # method, quality and the fit windows
        for variant, frac in sorted(a.get("poses_on_road", {}).items()):
            lines.append(f"    poses on the road of {variant}: {100 * frac:.1f}%")
    return "\n".join(lines)
