"""Records: round trips (bit-exact, or within the stated LiDAR / JPEG bounds), source JPEGs
passed through, old record versions refused with the remedy, atomic shards, and errors that name
the file and record."""

import importlib.util
import io
import json
import os
import pickle

import msgpack
import numpy as np
import pytest
from PIL import Image

from data_synth import random_sample
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data.schema import SchemaError

SEQUENCE_KEYS = ("sequence_id", "frame_index", "timestamp")
STEP = records.LIDAR_STEP


def _with_prior(sample):
    return dict(sample, prior=np.asarray(sample["pose"][:2] + 3.0, np.float64))


def _fields(record: bytes) -> dict:
    return msgpack.unpackb(record[len(records.MAGIC) :], raw=False)["f"]


def _smooth_images(rng, n=2, hw=(48, 80)):
    """Camera-like images (smooth gradients + a sharp-edged box + mild noise), not white noise."""
    y, x = np.mgrid[0 : hw[0], 0 : hw[1]]
    out = []
    for _ in range(n):
        a, b, c = rng.uniform(0.5, 2.0, 3)
        im = np.stack([60 + a * y, 90 + b * x, 120 + c * (x + y) / 2], axis=-1)
        r0, c0 = rng.integers(0, hw[0] // 2), rng.integers(0, hw[1] // 2)
        im[r0 : r0 + 15, c0 : c0 + 25] = rng.uniform(0, 255, 3)
        im += rng.normal(0, 1.0, im.shape)
        out.append(np.clip(im, 0, 255).astype(np.uint8))
    return np.stack(out)


def _jpeg_file(image, quality=90) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def test_round_trip_is_bit_exact_except_the_lidar_within_its_bound(tmp_path):
    rng = np.random.default_rng(0)
    samples = [_with_prior(random_sample(rng, f"s{i}", num_points=17 + i)) for i in range(5)]
    samples[0]["pose"][2] = -0.0  # signed zero must survive too
    path = tmp_path / "x.array_record"
    records.write_shard(path, [records.encode_sample(s) for s in samples])
    back = [records.decode_sample(r) for r in records.read_shard(path, expected=5)]
    for want, got in zip(samples, back, strict=True):
        assert set(got) == set(want)
        for key, value in want.items():
            if isinstance(value, str):
                assert got[key] == value
                continue
            assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
            if key == "lidar":
                assert np.abs(got[key][:, :3] - value[:, :3]).max() <= STEP / 2
                clipped = np.clip(value[:, 3], 0.0, 1.0)  # random_sample's are not in [0, 1]
                assert np.abs(got[key][:, 3] - clipped).max() <= 1 / 510 + 1e-7
            else:
                assert got[key].tobytes() == value.tobytes(), key
    assert np.signbit(back[0]["pose"][2])


def test_lidar_quantization_error_is_bounded_over_the_whole_range():
    rng = np.random.default_rng(1)
    n = 20000
    top = records.LIDAR_RANGE - STEP  # the largest value that is not rounded out of int16
    xyz = rng.uniform(-records.LIDAR_RANGE, top, (n, 3)).astype(np.float32)
    xyz[:3] = [[-records.LIDAR_RANGE, top, 0.0], [STEP / 2, -STEP / 2, 1e-6], [70.0, -0.3, 13.9]]
    inten = rng.uniform(0, 1, (n, 1)).astype(np.float32)
    inten[:2] = [[0.0], [1.0]]
    sample = _with_prior(random_sample(rng, num_points=n))
    sample["lidar"] = np.concatenate([xyz, inten], axis=1)
    got = records.decode_sample(records.encode_sample(sample))["lidar"]
    assert got.dtype == np.float32 and got.shape == (n, 4) and got.flags.c_contiguous
    err = np.abs(got[:, :3].astype(np.float64) - xyz)
    assert err.max() <= STEP / 2  # 1/256 m = 3.9 mm, exactly (no float32 slack needed)
    assert err.max() > 0.45 * STEP  # the bound is tight: the step is what the docstring says
    assert np.abs(got[:, 3] - inten[:, 0]).max() <= 1 / 510 + 1e-7
    assert got[0, 0] == -records.LIDAR_RANGE and got[0, 1] == top and got[1, 3] == 1.0
    # Decoded values are on the grid: encoding them again changes nothing (resumes, copies).
    again = dict(sample, lidar=got)
    assert records.decode_sample(records.encode_sample(again))["lidar"].tobytes() == got.tobytes()


def test_integer_intensities_and_grid_coordinates_come_back_bit_exactly():
    rng = np.random.default_rng(2)
    k = rng.integers(0, 256, 300)
    xyz = rng.integers(-20000, 20000, (300, 3)) * STEP
    lidar = np.concatenate([xyz, (k / 255.0)[:, None]], axis=1).astype(np.float32)
    sample = dict(_with_prior(random_sample(rng)), lidar=lidar)  # nuScenes / AV2: 0-255 / 255
    assert records.decode_sample(records.encode_sample(sample))["lidar"].tobytes() == (
        lidar.tobytes()
    )
    empty = dict(sample, lidar=np.zeros((0, 4), np.float32))
    assert records.decode_sample(records.encode_sample(empty))["lidar"].shape == (0, 4)


def test_lidar_beyond_the_stored_range_is_an_error_and_intensity_is_clipped():
    rng = np.random.default_rng(3)
    sample = _with_prior(random_sample(rng, num_points=10))
    for bad in (records.LIDAR_RANGE, -records.LIDAR_RANGE - STEP, 300.0, -1e4):
        lidar = sample["lidar"].copy()
        lidar[4, 1] = bad
        with pytest.raises(SchemaError, match=r"frame 9: key 'lidar': 1 of 10 points .*-256"):
            records.encode_sample(dict(sample, lidar=lidar), where="frame 9")
    lidar = sample["lidar"].copy()
    lidar[:, 3] = np.linspace(-1.0, 2.0, 10)
    got = records.decode_sample(records.encode_sample(dict(sample, lidar=lidar)))["lidar"][:, 3]
    np.testing.assert_allclose(got, np.clip(lidar[:, 3], 0, 1), atol=1 / 510)
    assert got.min() == 0.0 and got.max() == 1.0


def test_jpeg_images_are_close_and_small_and_png_stays_lossless():
    rng = np.random.default_rng(4)
    sample = _with_prior(random_sample(rng, hw=(48, 80)))
    sample["images"] = _smooth_images(rng)
    png = records.encode_sample(sample)
    q95 = records.encode_sample(sample, image_codec="jpeg")
    q75 = records.encode_sample(sample, image_codec="jpeg", jpeg_quality=75)
    assert records.decode_sample(png)["images"].tobytes() == sample["images"].tobytes()
    got = records.decode_sample(q95)["images"]
    assert got.dtype == np.uint8 and got.shape == sample["images"].shape
    err = got.astype(np.float64) - sample["images"]
    psnr = 10 * np.log10(255.0**2 / np.mean(err**2))
    assert psnr > 32 and np.abs(err).mean() < 2.0, psnr  # 4:2:0 chroma at the box edges
    f = _fields(q95)["images"]
    assert (
        f["t"] == "jpeg"
        and f["q"] == [95, 95]
        and len(f["b"][0]) < len(_fields(png)["images"]["b"][0])
    )
    assert len(q75) < len(q95)
    with pytest.raises(ValueError, match="image_codec"):
        records.encode_sample(sample, image_codec="webp")
    with pytest.raises(ValueError, match="jpeg_quality"):
        records.encode_sample(sample, image_codec="jpeg", jpeg_quality=0)


def test_source_jpegs_of_the_stored_size_are_passed_through_bit_for_bit():
    rng = np.random.default_rng(5)
    sample = _with_prior(random_sample(rng, hw=(48, 80)))
    src = _smooth_images(rng)
    files = [_jpeg_file(im) for im in src]
    decoded = np.stack([np.asarray(Image.open(io.BytesIO(b))) for b in files])  # the reader's
    other = _jpeg_file(src[1][:, :40])  # another size (a resized camera): re-encoded
    sample["images"] = records.with_source_jpegs(decoded, [files[0], other])
    rec = records.encode_sample(sample, image_codec="jpeg", jpeg_quality=96)
    f = _fields(rec)["images"]
    assert f["b"][0] == files[0] and f["q"] == [0, 96]  # camera 0 stored as it is
    got = records.decode_sample(rec)["images"]
    assert got[0].tobytes() == decoded[0].tobytes()
    # Bytes that do not decode to the sample's pixels are never stored in their place.
    edited = decoded.copy()
    edited[0, 0, 0] += 1
    sample["images"] = records.with_source_jpegs(edited, files)
    f = _fields(records.encode_sample(sample, image_codec="jpeg"))["images"]
    assert f["q"] == [95, 0] and f["b"][1] == files[1]
    # PNG ignores the sources; pickling keeps them; a slice or copy has none.
    sample["images"] = records.with_source_jpegs(decoded, files)
    png = records.decode_sample(records.encode_sample(sample))["images"]
    assert png.tobytes() == decoded.tobytes()
    assert pickle.loads(pickle.dumps(sample["images"])).source_jpegs == tuple(files)
    assert (
        sample["images"][:1].source_jpegs is None and sample["images"].copy().source_jpegs is None
    )
    with pytest.raises(ValueError, match="1 source JPEGs"):
        records.with_source_jpegs(decoded, files[:1])


@pytest.mark.parametrize("version", [1, 2, 3])
def test_old_records_and_datasets_are_refused_with_the_remedy(tmp_path, version):
    """Version 1 (float32 LiDAR), version 2 (no sequence metadata) and version 3 (no lighting)
    records and datasets."""
    rng = np.random.default_rng(6)
    rec = records.encode_sample(_with_prior(random_sample(rng)))
    payload = msgpack.unpackb(rec[len(records.MAGIC) :], raw=False)
    fields = {k: v for k, v in payload["f"].items() if k not in SEQUENCE_KEYS}
    old = records.MAGIC + msgpack.packb(dict(payload, v=version, f=fields), use_bin_type=True)
    with pytest.raises(
        records.RecordError, match=rf"shard-2 record 5: record version {version}.*re-run"
    ):
        records.decode_sample(old, "shard-2 record 5")
    ddir = tmp_path / "sim_quick_cpu"
    ddir.mkdir()
    man = dict(mf.new_manifest({"seed": 0}, {}), record_version=version, complete=True)
    (ddir / mf.MANIFEST_NAME).write_text(json.dumps(man))
    with pytest.raises(mf.ManifestError) as err:
        mf.read_manifest(ddir)
    msg = str(err.value)
    assert f"record_version {version}, this code reads 4" in msg
    assert "Re-run the data preparation" in msg and "lighting" in msg
    assert f"delete {ddir}" in msg and mf.manifest_path(ddir) in msg


def _bench():
    path = os.path.join(os.path.dirname(__file__), "..", "experiments", "bench_records.py")
    spec = importlib.util.spec_from_file_location("bench_records", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_paper_size_converted_record_fits_in_a_megabyte():
    """The issue's target: a 6 x 320 x 800 real-data record (JPEG q95 of natural-looking
    content, a 32-beam ~30k-point sweep) is <= 1 MB, ~4x less than record version 1."""
    bench = _bench()
    sample = bench.converted_sample(np.random.default_rng(0), 0, 6, (320, 800))
    assert 25_000 < len(sample["lidar"]) < 36_000
    rec = records.encode_sample(sample, image_codec="jpeg", jpeg_quality=95)
    assert len(rec) <= 1_000_000, len(rec)
    assert len(bench.v1_record(sample)) > 3 * len(rec)
    assert len(_fields(rec)["lidar"]["b"]) < 8 * len(sample["lidar"])  # < half of float32
    back = records.decode_sample(rec)
    assert back["images"].shape == (6, 320, 800, 3) and back["lidar"].shape == sample["lidar"].shape
    # Content at least as hard for JPEG as a real photograph (matplotlib's sample photo).
    ref = bench.reference_bpp(None, (320, 800), 95)  # raises if the photo is missing
    assert bench._jpeg_bpp(sample["images"][:1], 95) > ref


def test_invalid_sample_is_refused_with_its_key():
    sample = _with_prior(random_sample(np.random.default_rng(1)))
    sample["lidar"] = sample["lidar"].astype(np.float64)
    with pytest.raises(SchemaError, match="lidar"):
        records.encode_sample(sample, where="frame 7")
    sample = random_sample(np.random.default_rng(1))  # no prior
    with pytest.raises(SchemaError, match="prior"):
        records.encode_sample(sample)
    sample = _with_prior(random_sample(np.random.default_rng(1), lighting="twilight"))
    with pytest.raises(SchemaError, match=r"frame 8: key 'lighting' must be one of .*'twilight'"):
        records.encode_sample(sample, where="frame 8")


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


def test_simulator_stores_png_and_compact_lidar_converters_store_jpeg(tmp_path):
    import yaml

    from data_synth import Factory, small_config
    from seglocnet_jax.data.real import convert as rconv
    from seglocnet_jax.data.simulated import prepare as pp
    from seglocnet_jax.data.writer import DatasetWriter

    def first_fields(ddir, split):
        man = mf.read_manifest(ddir)
        path, n = mf.split_files(man, ddir, split)[0]
        return _fields(records.read_shard(path, n)[0])

    sim = pp.prepare(small_config(tmp_path / "sim"), Factory(), variants=())
    f = first_fields(sim, "val")
    assert f["images"]["t"] == "png" and f["lidar"]["t"] == "lidar16"
    rng = np.random.default_rng(7)
    samples = [random_sample(rng, f"c{i}", "boston-seaport", hw=(16, 24)) for i in range(3)]
    w = DatasetWriter(tmp_path / "real", {"source": "x"}, image_codec="jpeg", jpeg_quality=97)
    w.write_split("val", samples, 3)
    f = first_fields(w.close(), "val")
    assert f["images"]["t"] == "jpeg" and f["images"]["q"] == [97, 97]
    assert f["lidar"]["t"] == "lidar16"
    # The converters' config: JPEG q95 by default, in the dataset identity, checked.
    conf = os.path.join(os.path.dirname(__file__), "..", "conf", "dataset")
    for name in ("nuscenes", "argo_mia", "argo_pit"):
        with open(os.path.join(conf, f"{name}.yaml")) as fh:
            tree = yaml.safe_load(fh)
        keys = ("image_codec", "jpeg_quality", "png_level")
        cfg = rconv.ConvertConfig(**{k: tree["convert"][k] for k in keys})
        assert (cfg.image_codec, cfg.jpeg_quality) == ("jpeg", 95), name
    assert rconv.ConvertConfig().image_codec == "jpeg"

    class Reader:
        def identity(self):
            return {}

    identity = rconv.ConvertConfig(jpeg_quality=96).identity(Reader())
    assert (identity["image_codec"], identity["jpeg_quality"]) == ("jpeg", 96)
    with pytest.raises(ValueError, match="dataset.convert.image_codec"):
        rconv.ConvertConfig(image_codec="webp")
    with pytest.raises(ValueError, match="dataset.convert.jpeg_quality"):
        rconv.ConvertConfig(jpeg_quality=101)
