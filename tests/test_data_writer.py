"""DatasetWriter (converters): same shards and manifest as the simulator pipeline."""

import os

import numpy as np
import pytest

from data_synth import random_raster, random_sample
from seglocnet_jax import geometry
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data.writer import DatasetWriter


def _samples(n, city="boston-seaport", seed=0):
    rng = np.random.default_rng(seed)
    return [random_sample(rng, f"{city}-{i}", city) for i in range(n)]


def test_written_splits_load_with_seeded_priors(tmp_path):
    cfg = {"source": "nuscenes", "version": "v1.0-mini"}
    w = DatasetWriter(tmp_path / "ns", cfg, shard_size=4)
    assert w.write_split("val", _samples(10), 10) == 3
    ddir = w.close()
    man = mf.read_manifest(ddir)
    assert man["complete"] and man["splits"]["val"]["cities"] == {"boston-seaport": 10}
    recs = [
        records.decode_sample(r)
        for p, n in mf.split_files(man, ddir, "val")
        for r in records.read_shard(p, n)
    ]
    off = np.stack([r["prior"] - r["pose"][:2] for r in recs])
    assert np.abs(off).max() <= geometry.PRIOR_RANGE and len({tuple(o) for o in off}) == 10
    raster = random_raster(0)
    batches = list(
        ld.make_loader(
            ddir,
            "val",
            None,
            4,
            0,
            False,
            rasters={"boston-seaport": raster},
            config=ld.LoaderConfig(max_points=64, num_threads=0),
        )
    )
    assert len(batches) == 3 and sum(b["valid"].sum() for b in batches) == 10
    # A re-run keeps finished shards byte for byte; another config is refused.
    before = {p: open(p, "rb").read() for p, _ in mf.split_files(man, ddir, "val")}
    again = DatasetWriter(ddir, cfg, shard_size=4)
    assert again.write_split("val", _samples(10), 10) == 0
    assert all(open(p, "rb").read() == b for p, b in before.items())
    with pytest.raises(mf.ManifestError, match="config.version"):
        DatasetWriter(ddir, {"source": "nuscenes", "version": "v1.0-trainval"})


def test_bad_samples_are_named(tmp_path):
    w = DatasetWriter(tmp_path / "d", {"source": "x"}, shard_size=4)
    bad = _samples(3)
    bad[2]["pose"] = bad[2]["pose"].astype(np.float32)
    with pytest.raises(ValueError, match=r"train-00000-of-00001.array_record record 2.*pose"):
        w.write_split("train", bad, 3)
    with pytest.raises(ValueError, match="duplicate sample_id"):
        w.write_split("train", _samples(2) + _samples(1), 3)
    with pytest.raises(ValueError, match="got 2 samples, expected 3"):
        w.write_split("train", _samples(2), 3)
    assert not os.path.exists(tmp_path / "d" / "sensors")
