"""Records: bit-exact round trips, atomic shards, and errors that name the file and record."""

import numpy as np
import pytest

from data_synth import random_sample
from seglocnet_jax.data import records
from seglocnet_jax.data.schema import SchemaError


def _with_prior(sample):
    return dict(sample, prior=np.asarray(sample["pose"][:2] + 3.0, np.float64))


def test_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    samples = [_with_prior(random_sample(rng, f"s{i}", num_points=17 + i)) for i in range(5)]
    samples[0]["lidar"][0, 0] = np.float32(-0.0)  # signed zero must survive too
    path = tmp_path / "x.array_record"
    records.write_shard(path, [records.encode_sample(s) for s in samples])
    back = [records.decode_sample(r) for r in records.read_shard(path, expected=5)]
    for want, got in zip(samples, back, strict=True):
        assert set(got) == set(want)
        for key, value in want.items():
            if isinstance(value, str):
                assert got[key] == value
            else:
                assert got[key].dtype == value.dtype and got[key].shape == value.shape
                assert got[key].tobytes() == value.tobytes(), key


def test_invalid_sample_is_refused_with_its_key():
    sample = _with_prior(random_sample(np.random.default_rng(1)))
    sample["lidar"] = sample["lidar"].astype(np.float64)
    with pytest.raises(SchemaError, match="lidar"):
        records.encode_sample(sample, where="frame 7")
    sample = random_sample(np.random.default_rng(1))  # no prior
    with pytest.raises(SchemaError, match="prior"):
        records.encode_sample(sample)


def test_corrupt_record_names_where():
    data = records.encode_sample(_with_prior(random_sample(np.random.default_rng(2))))
    with pytest.raises(records.RecordError, match="shard-3 record 9"):
        records.decode_sample(data[: len(data) // 2], "shard-3 record 9")
    with pytest.raises(records.RecordError, match="bad magic"):
        records.decode_sample(b"XXXX" + data[4:], "r")


def test_truncated_and_corrupt_shards_are_reported(tmp_path):
    rng = np.random.default_rng(3)
    recs = [records.encode_sample(_with_prior(random_sample(rng, hw=(40, 60)))) for _ in range(8)]
    path = tmp_path / "good.array_record"
    records.write_shard(path, recs)
    data = path.read_bytes()
    trunc = tmp_path / "trunc.array_record"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(records.RecordError, match="trunc.array_record"):
        records.read_shard(trunc, expected=8)
    bad = bytearray(data)
    bad[len(bad) // 3] ^= 0xFF
    corrupt = tmp_path / "corrupt.array_record"
    corrupt.write_bytes(bytes(bad))
    with pytest.raises(records.RecordError, match="corrupt.array_record"):
        records.read_shard(corrupt, expected=8)
    with pytest.raises(records.RecordError, match="missing"):
        records.count_records(tmp_path / "nope.array_record")


def test_failed_write_leaves_no_file(tmp_path):
    path = tmp_path / "s.array_record"
    with pytest.raises(TypeError):
        records.write_shard(path, [b"ok", None])
    assert list(tmp_path.iterdir()) == []
