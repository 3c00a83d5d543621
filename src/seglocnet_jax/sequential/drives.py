"""The drives of a split: its sequences grouped and ordered by frame, random access to their
frames as the loader's rows, and each drive's odometry seed (see the package docstring)."""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import zlib

import numpy as np

from seglocnet_jax.data import loader as loader_lib
from seglocnet_jax.data.manifest import read_manifest, verify_split


def drive_seed(odometry_seed: int, sequence_id: str) -> int:
    """The odometry seed of one drive: independent of which other drives are tracked."""
    crc = zlib.crc32(sequence_id.encode())
    return int(np.random.SeedSequence([int(odometry_seed), crc]).generate_state(1)[0])


@dataclasses.dataclass
class Drive:
    """One sequence of a split, in ``frame_index`` order.

    Attributes:
      sequence_id, city: the sequence and its city key.
      records: ``(T,)`` record indices in the split (file order).
      frame_index: ``(T,)``; timestamps: ``(T,)`` seconds.
      poses: ``(T, 3)`` GT world poses (scoring and the odometry simulation only).
      priors: ``(T, 2)`` stored priors (frame 0's starts the filter; each one the single-frame
        protocol).
    """

    sequence_id: str
    city: str
    records: np.ndarray
    frame_index: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    priors: np.ndarray

    def __len__(self) -> int:
        return len(self.records)

    def distance(self) -> np.ndarray:
        """``(T,)`` metres driven (GT) up to each frame."""
        steps = np.hypot(*np.diff(self.poses[:, :2], axis=0).T)
        return np.concatenate([[0.0], np.cumsum(steps)])


class DriveSplit:
    """Random access to the frames of a split, grouped into :class:`Drive` s.

    ``rasters``: the map variant's city rasters; ``nm_rasters``: with ``nm_tiles`` (an NM
    model), the cities' OSM class rasters (the rows then carry ``nm_tile``), else None."""

    def __init__(
        self,
        dataset_dir: str,
        split: str,
        map_variant: str,
        loader_cfg,
        *,
        threads=1,
        nm_tiles: bool = False,
    ):
        man = read_manifest(dataset_dir)
        self.name = split
        # The loader's check (counts, SHA-256 of every shard) before any record is read.
        self.source = loader_lib.ShardSource(verify_split(man, dataset_dir, split))
        cities = sorted(man["splits"][split]["cities"])
        self.rasters = loader_lib.load_rasters(dataset_dir, map_variant, cities)
        self.nm_rasters = loader_lib.load_osm_classes(dataset_dir, cities) if nm_tiles else None
        self.transform = loader_lib.FrameTransform(
            self.rasters, loader_cfg.max_points, train=False, nm_rasters=self.nm_rasters
        )
        self.pool = concurrent.futures.ThreadPoolExecutor(max(1, threads))
        self.drives = self._index()

    def _index(self) -> list[Drive]:
        groups: dict[str, list] = collections.OrderedDict()
        n = len(self.source)
        for i, s in enumerate(self.pool.map(self.source.__getitem__, range(n))):
            row = (i, int(s["frame_index"]), float(s["timestamp"]), s["pose"], s["prior"])
            groups.setdefault((str(s["sequence_id"]), str(s["city"])), []).append(row)
        drives = []
        for (sid, city), rows in groups.items():
            rows.sort(key=lambda r: r[1])
            drives.append(
                Drive(
                    sequence_id=sid,
                    city=city,
                    records=np.array([r[0] for r in rows], np.int64),
                    frame_index=np.array([r[1] for r in rows], np.int64),
                    timestamps=np.array([r[2] for r in rows], np.float64),
                    poses=np.stack([np.asarray(r[3], np.float64) for r in rows]),
                    priors=np.stack([np.asarray(r[4], np.float64) for r in rows]),
                )
            )
        return drives

    def rows(self, indices) -> list[dict]:
        """Batch rows (the loader's, tile around the stored prior) of the given records."""
        return list(self.pool.map(lambda i: self.transform(self.source[int(i)]), indices))

    def close(self) -> None:
        self.pool.shutdown()
