"""Data integrity: shard checksums recorded and verified, manifests that mix splits or predate
checksums refused, stale temporary files removed and the preparation lock."""

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from data_synth import Factory, random_raster, random_sample, small_config
from seglocnet_jax import fileio
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data.simulated import prepare as pp
from seglocnet_jax.data.writer import DatasetWriter
from seglocnet_jax.maps import MapConfig

CFG = ld.LoaderConfig(max_points=16, num_threads=0, prefetch=0)


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    return pp.prepare(small_config(tmp_path_factory.mktemp("integrity")), Factory(), variants=())


@pytest.fixture
def dataset(prepared, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(prepared, dst)
    raster = random_raster(0, size_m=1300.0)
    return str(dst), {"helsinki": raster, "kouvola": raster}


def _loader(dataset, split="train"):
    ddir, rasters = dataset
    return ld.make_loader(ddir, split, None, 2, 0, False, config=CFG, rasters=rasters)


def _edit_manifest(ddir, fn):
    path = mf.manifest_path(ddir)
    with open(path) as f:
        man = json.load(f)
    fn(man)
    with open(path, "w") as f:
        json.dump(man, f)


def _flip_inside_a_record(path):
    data = bytearray(open(path, "rb").read())
    at = data.index(records.MAGIC) + 300
    data[at] ^= 0x01
    open(path, "wb").write(bytes(data))


def _dead_pid():
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def _recorded(man, ddir):
    return {
        s["file"]: (s["sha256"], s["bytes"])
        for split in man["splits"].values()
        for s in split["shards"]
    }


def _actual(man, ddir):
    out = {}
    for split in man["splits"].values():
        for s in split["shards"]:
            c = records.file_checksum(os.path.join(ddir, s["file"]))
            out[s["file"]] = (c["sha256"], c["bytes"])
    return out


def test_prepare_and_writer_record_shard_checksums(prepared, tmp_path):
    man = mf.read_manifest(prepared)
    assert man["manifest_version"] == mf.MANIFEST_VERSION == 2
    assert _recorded(man, prepared) == _actual(man, prepared) and len(_recorded(man, prepared)) > 4
    rng = np.random.default_rng(0)
    w = DatasetWriter(tmp_path / "conv", {"source": "x"}, shard_size=3)
    w.write_split("val", [random_sample(rng, f"s{i}", "boston") for i in range(7)], 7)
    ddir = w.close()
    man = mf.read_manifest(ddir)
    assert _recorded(man, ddir) == _actual(man, ddir) and len(man["splits"]["val"]["shards"]) == 3


def test_changed_shard_is_refused_by_the_loader_naming_shard_and_manifest(dataset):
    ddir, _ = dataset
    man = mf.read_manifest(ddir)
    path, _ = mf.split_files(man, ddir, "train")[1]
    _flip_inside_a_record(path)  # same size, same record count
    with pytest.raises(records.RecordError) as err:
        _loader(dataset)
    msg = str(err.value)
    assert path in msg and mf.manifest_path(ddir) in msg and "SHA-256" in msg
    _loader(dataset, "val")  # the other splits are intact


def test_verified_shards_are_not_hashed_again(dataset, monkeypatch):
    calls = []
    real = records.file_checksum
    monkeypatch.setattr(records, "file_checksum", lambda p: calls.append(p) or real(p))
    _loader(dataset)
    man = mf.read_manifest(dataset[0])
    files = [p for p, _ in mf.split_files(man, dataset[0], "train")]
    assert sorted(calls) == sorted(files)
    calls.clear()
    _loader(dataset)
    _loader(dataset)
    assert calls == []
    st = os.stat(files[0])
    os.utime(files[0], ns=(st.st_atime_ns, st.st_mtime_ns + 1000))  # another file version
    _loader(dataset)
    assert calls == [files[0]]


def test_manifest_pointing_a_split_at_other_shards_is_refused(dataset):
    ddir, _ = dataset
    train0 = "sensors/train/train-00000-of-00003.array_record"

    def borrow(man):  # val reads train's first shard (a path that resolves to it)
        man["splits"]["val"]["shards"][0]["file"] = "sensors/val/../train/" + os.path.basename(
            train0
        )
        man["splits"]["val"]["shards"][0]["count"] = 10  # its record count too

    _edit_manifest(ddir, borrow)
    with pytest.raises(mf.ManifestError, match=r"split 'val' lists .*train-00000.*'train' lists"):
        _loader(dataset, "val")

    def foreign(man):  # kouvola's only shard renamed to a val shard name
        man["splits"]["val"]["shards"][0]["file"] = "sensors/val/val-00000-of-00001.array_record"
        man["splits"]["kouvola"]["shards"][0]["file"] = (
            "sensors/kouvola/val-00000-of-00001.array_record"
        )

    _edit_manifest(ddir, foreign)
    with pytest.raises(mf.ManifestError) as err:
        _loader(dataset, "kouvola")
    msg = str(err.value)
    assert "split 'kouvola'" in msg and "sensors/kouvola/val-00000-of-00001.array_record" in msg


def test_dataset_without_checksums_is_refused_with_the_remedy(dataset):
    ddir, _ = dataset

    def old(man):
        man["manifest_version"] = 1
        for split in man["splits"].values():
            for s in split["shards"]:
                s.pop("sha256", None), s.pop("bytes", None)

    _edit_manifest(ddir, old)
    with pytest.raises(mf.ManifestError) as err:
        _loader(dataset)
    msg = str(err.value)
    assert mf.manifest_path(ddir) in msg
    assert "prepare it again into a new directory" in msg.lower() and f"delete {ddir}" in msg


def test_resumed_prepare_checks_recorded_shards(tmp_path):
    cfg = small_config(tmp_path)
    ddir = pp.prepare(cfg, Factory(), variants=())
    _edit_manifest(ddir, lambda man: man.update(complete=False))
    path = os.path.join(ddir, "sensors/val/val-00000-of-00001.array_record")
    _flip_inside_a_record(path)
    with pytest.raises(records.RecordError, match="val-00000-of-00001.*differs from the checksum"):
        pp.prepare(cfg, Factory(), variants=())


def test_prepare_removes_stale_tmp_files_and_takes_the_lock(tmp_path, capsys):
    cfg = small_config(tmp_path)
    ddir = os.path.join(cfg.root, cfg.name)
    dead = _dead_pid()
    stale = os.path.join(ddir, "sensors", "train", f"train-00000-of-00003.tmp-{dead}.array_record")
    os.makedirs(os.path.dirname(stale))
    open(stale, "wb").write(b"half a shard")
    live = os.path.join(ddir, "maps", "x.tmp-1.npz")  # a live process's (pid 1): kept
    os.makedirs(os.path.dirname(live))
    open(live, "w").write("{")
    with open(os.path.join(ddir, ".lock"), "w") as f:  # left by a killed preparation
        json.dump({"pid": dead, "host": "elsewhere", "what": "data preparation"}, f)
    pp.prepare(cfg, Factory(), variants=())
    assert not os.path.exists(stale) and os.path.exists(live)
    assert f"took over the lock of a data preparation that is gone (pid {dead}" in (
        capsys.readouterr().out
    )
    with fileio.DirLock(ddir, what="data preparation"):  # held by another preparation
        assert pp.prepare(cfg, Factory(), variants=()) == ddir  # complete: only checked
        assert "is complete; checking it without the lock" in capsys.readouterr().out
        with pytest.raises(fileio.LockError, match=f"pid {os.getpid()}"):  # it would write
            pp.prepare(cfg, Factory(), variants=[MapConfig("sd", 10.0)])
        other = small_config(tmp_path / "b")
        with fileio.DirLock(os.path.join(other.root, other.name), what="data preparation"):
            with pytest.raises(fileio.LockError, match="in use by another data preparation"):
                pp.prepare(other, Factory(), variants=())
    assert "sd_w10_road-building" not in mf.read_manifest(ddir)["map_variants"]


def test_writer_removes_stale_tmp_files(tmp_path):
    ddir = tmp_path / "conv"
    stale = ddir / "sensors" / "val" / f"val-00000-of-00001.tmp-{_dead_pid()}.array_record"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"x")
    DatasetWriter(ddir, {"source": "x"})
    assert not stale.exists()
