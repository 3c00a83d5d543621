"""Conversion in worker processes: byte-identical shards and manifest for any number of workers,
shard-by-shard resume after a worker fails, the ``dataset.convert.num_workers`` key."""

import dataclasses
import os
import warnings

import pytest

import fixtures_real as fx
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.real import convert as rconv
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.real.common import RealDataError

OUT_HW = (12, 20)


class LoggingReader(nu.NuScenesReader):
    """A nuScenes reader that leaves ``<log_dir>/<pid>__<frame key>`` for every frame it loads
    (worker processes included) and fails on the frame ``fail_key``. Picklable: module level."""

    def __init__(self, cfg, log_dir, fail_key=None):
        super().__init__(cfg)
        self.log_dir, self.fail_key = log_dir, fail_key

    def load(self, frame):
        with open(os.path.join(self.log_dir, f"{os.getpid()}__{frame.key}"), "w") as f:
            f.write(os.environ.get("OPENBLAS_NUM_THREADS", ""))
        if frame.key == self.fail_key:
            raise RealDataError(f"{frame.key}: unreadable (test)")
        return super().load(frame)


def _loads(log_dir, threads=None):
    """``{pid: {frame keys}}`` of the loads logged so far; clears the log. With ``threads``,
    collects each load's ``OPENBLAS_NUM_THREADS`` in it."""
    out = {}
    for name in os.listdir(log_dir):
        pid, key = name.split("__", 1)
        out.setdefault(int(pid), set()).add(key)
        with open(os.path.join(log_dir, name)) as f:
            if threads is not None:
                threads.add(f.read())
        os.remove(os.path.join(log_dir, name))
    return out


@pytest.fixture(scope="module")
def nus_root(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("nus") / "nuscenes")
    fx.write_nuscenes(root)
    return root


def _setup(nus_root, tmp_path, name, out="out", **kw):
    log = tmp_path / f"log-{name}-{out}"
    log.mkdir()
    cfg = nu.NuScenesConfig(dataroot=nus_root, version="v1.0-mini", image_size=OUT_HW)
    reader = LoggingReader(cfg, str(log), **kw)
    conv = rconv.ConvertConfig(
        name=name,
        root=str(tmp_path / out),
        seed=3,
        shard_size=1,  # 3 shards per split
        splits={"train": "mini_train", "val": "mini_val"},
    )
    return reader, conv, str(log)


def _files(ddir):
    """Every file of a converted dataset (relative path -> bytes)."""
    out = {}
    for root, _, names in os.walk(ddir):
        for n in names:
            path = os.path.join(root, n)
            with open(path, "rb") as f:
                out[os.path.relpath(path, ddir)] = f.read()
    return out


def test_one_and_two_workers_write_the_same_bytes_and_manifest(nus_root, tmp_path):
    dirs = {}
    for workers in (1, 2, 0):
        reader, cfg, log = _setup(nus_root, tmp_path, f"w{workers}")
        cfg = dataclasses.replace(cfg, num_workers=workers)
        dirs[workers] = rconv.convert(reader, cfg, variants=False)
        threads = set()
        pids = _loads(log, threads)
        keys = set().union(*pids.values())
        assert keys == {f.key for s in ("mini_train", "mini_val") for f in reader.frames(s)}
        if workers == 2:  # read in worker processes (a pool per split), not here
            assert len(pids) >= 2 and os.getpid() not in pids
            # one BLAS thread per worker (the workers use the cores) unless the user set one
            assert threads == {os.environ.get("OPENBLAS_NUM_THREADS", "1")}
        else:
            assert set(pids) == {os.getpid()}
    files = {w: _files(d) for w, d in dirs.items()}
    assert len([f for f in files[1] if f.endswith(".array_record")]) == 6
    assert "manifest.json" in files[1]
    assert files[1] == files[2] == files[0]  # shards and manifest, byte for byte


def test_a_failed_worker_leaves_finished_shards_and_the_rerun_completes(nus_root, tmp_path):
    ref_reader, ref_cfg, _ = _setup(nus_root, tmp_path, "ref")
    ref_cfg = dataclasses.replace(ref_cfg, num_workers=0)
    ref = _files(rconv.convert(ref_reader, ref_cfg, variants=False))
    train = [f.key for f in ref_reader.frames("mini_train")]
    reader, cfg, log = _setup(nus_root, tmp_path, "ref", out="out2", fail_key=train[1])
    cfg = dataclasses.replace(cfg, num_workers=2)
    with pytest.raises(RealDataError, match=rf"{train[1]}: unreadable \(test\)"):
        rconv.convert(reader, cfg, variants=False)
    ddir = os.path.join(cfg.root, cfg.name)
    shards = sorted(os.listdir(os.path.join(ddir, "sensors", "train")))
    assert "train-00000-of-00003.array_record" in shards  # finished before the failure
    assert "train-00001-of-00003.array_record" not in shards
    assert not any(".tmp-" in s for s in shards)
    assert "train" not in mf.read_manifest(ddir)["splits"]  # only the parent writes it
    _loads(log)
    # Rerun (another worker count: not part of the identity): only the missing shards are read.
    names = [f"train-{i:05d}-of-00003.array_record" for i in range(3)]
    missing = {k for k, n in zip(train, names, strict=True) if n not in shards}
    reader.fail_key = None
    rconv.convert(reader, dataclasses.replace(cfg, num_workers=3), variants=False)
    val = {f.key for f in reader.frames("mini_val")}
    assert set().union(*_loads(log).values()) == missing | val
    assert _files(ddir) == ref


def test_an_unpicklable_reader_converts_in_this_process_with_a_warning(nus_root, tmp_path):
    reader, cfg, log = _setup(nus_root, tmp_path, "patched")
    load = reader.load
    reader.load = lambda frame: load(frame)  # a local lambda: cannot be pickled
    with pytest.warns(RuntimeWarning, match="cannot be sent to worker processes"):
        rconv.convert(reader, dataclasses.replace(cfg, num_workers=2), variants=False)
    assert set(_loads(log)) == {os.getpid()}
    with warnings.catch_warnings():  # nothing left to write: no pool, no warning
        warnings.simplefilter("error")
        rconv.convert(reader, dataclasses.replace(cfg, num_workers=2), variants=False)


def test_num_workers_key():
    tree = {"source": "nuscenes", "reader": {"dataroot": "/x"}, "convert": {"num_workers": 3}}
    _, _, cfg = rconv.parse_tree(tree)
    assert cfg.num_workers == 3 and cfg.workers() == 3
    assert rconv.ConvertConfig().num_workers is None
    assert rconv.ConvertConfig().workers() == len(os.sched_getaffinity(0))
    assert rconv.ConvertConfig(num_workers=0).workers() == 0
    with pytest.raises(ValueError, match="dataset.convert.num_workers must be null"):
        rconv.ConvertConfig(num_workers=-1)
    reader = nu.NuScenesReader.__new__(nu.NuScenesReader)  # identity needs no tables
    reader.cfg = nu.NuScenesConfig(dataroot="/x")
    assert "num_workers" not in rconv.ConvertConfig(num_workers=4).identity(reader)
