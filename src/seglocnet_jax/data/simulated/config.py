"""The simulator dataset's config (the ``data`` group, :class:`PrepareConfig`) and what its
preparation needs from a producer of frames (:class:`FrameSource`): shared by the plans
(:mod:`.planning`) and the writer of the plans (:mod:`.prepare`)."""

from __future__ import annotations

import dataclasses
import json
from typing import Protocol

import numpy as np

from seglocnet_jax.data.simulated import drives as dr
from seglocnet_jax.data.simulated import splits as sp
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
