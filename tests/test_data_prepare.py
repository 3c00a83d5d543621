"""Preparation: planned splits, resumable and bit-identical shards, config mismatch refused."""

import dataclasses
import json
import os
import re
import threading
import time

import numpy as np
import pytest

from data_synth import Factory, small_config
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data.simulated import prepare as pp
from seglocnet_jax.data.simulated import splits


def _shard_bytes(dataset_dir):
    out = {}
    for dirpath, _, files in os.walk(os.path.join(dataset_dir, "sensors")):
        for f in files:
            out[os.path.relpath(os.path.join(dirpath, f), dataset_dir)] = open(
                os.path.join(dirpath, f), "rb"
            ).read()
    return out


def test_prepare_writes_planned_disjoint_splits(tmp_path, capsys):
    cfg = small_config(tmp_path)
    factory = Factory()
    ddir = pp.prepare(cfg, factory, variants=())
    printed = capsys.readouterr().out  # the breakdown of where the preparation's time went
    assert re.search(
        r"data preparation of .*tiny: worlds and plans \d+ s, sensor shards \(rendered, "
        r"encoded, written\) \d+ s, map variants \d+ s",
        printed,
    ), printed
    man = mf.read_manifest(ddir)
    assert man["complete"] and man["config"] == cfg.identity()
    counts = {k: v["count"] for k, v in man["splits"].items()}
    assert counts == {"train": 24, "val": 8, "test": 8, "kouvola": 6}
    assert man["splits"]["kouvola"]["cities"] == {"kouvola": 6}
    xy, ids = {}, set()
    for split in counts:
        recs = []
        for path, n in mf.split_files(man, ddir, split):
            recs += [records.decode_sample(r) for r in records.read_shard(path, n)]
        assert len(recs) == counts[split]
        ids |= {r["sample_id"] for r in recs}
        poses = np.stack([r["pose"] for r in recs])
        priors = np.stack([r["prior"] for r in recs])
        assert np.abs(priors - poses[:, :2]).max() <= 32.0
        xy[split] = poses[:, :2]
    assert len(ids) == sum(counts.values())  # sample ids unique within the dataset
    splits.check_disjoint({k: xy[k] for k in ("train", "val", "test")})
    # Prepared already: a second call checks and renders nothing.
    again = Factory()
    assert pp.prepare(cfg, again, variants=()) == ddir and again.calls == 0
    assert "data preparation of" not in capsys.readouterr().out  # nothing done, nothing timed


def test_interrupted_preparation_resumes_to_identical_shards(tmp_path):
    full = pp.prepare(small_config(tmp_path / "a"), Factory(), variants=())
    cfg = small_config(tmp_path / "b")
    with pytest.raises(KeyboardInterrupt):
        pp.prepare(cfg, Factory(fail_after=5), variants=())  # 10-frame shards, 4-frame renders
    partial = _shard_bytes(os.path.join(cfg.root, cfg.name))
    assert 0 < len(partial) < len(_shard_bytes(full))
    assert not any(".tmp" in name for name in partial)  # no half-written shard left behind
    assert not mf.read_manifest(os.path.join(cfg.root, cfg.name))["complete"]
    resumed = Factory()
    pp.prepare(cfg, resumed, variants=())
    assert _shard_bytes(os.path.join(cfg.root, cfg.name)) == _shard_bytes(full)
    frames = 24 + 8 + 8 + 6
    assert 0 < resumed.calls < -(-frames // 4)  # finished shards were not rendered again
    for name, data in partial.items():  # and not touched
        assert open(os.path.join(cfg.root, cfg.name, name), "rb").read() == data


def test_config_mismatch_is_refused_and_nothing_is_touched(tmp_path):
    cfg = small_config(tmp_path)
    ddir = pp.prepare(cfg, Factory(), variants=())
    before = _shard_bytes(ddir)
    manifest_before = open(mf.manifest_path(ddir)).read()
    with pytest.raises(mf.ManifestError, match=r"config\.seed: manifest 5 != config 6"):
        pp.prepare(dataclasses.replace(cfg, seed=6), Factory(), variants=())
    with pytest.raises(mf.ManifestError, match=r"config\.split\.stripe_width"):
        pp.prepare(
            dataclasses.replace(cfg, split=splits.SplitConfig(stripe_width=30.0)),
            Factory(),
            variants=(),
        )
    assert _shard_bytes(ddir) == before and open(mf.manifest_path(ddir)).read() == manifest_before


def test_damaged_existing_shard_is_reported_not_overwritten(tmp_path):
    cfg = small_config(tmp_path)
    ddir = pp.prepare(cfg, Factory(), variants=())
    man = json.load(open(mf.manifest_path(ddir)))
    man["complete"] = False
    mf.write_json_atomic(mf.manifest_path(ddir), man)
    other = os.path.join(ddir, man["splits"]["train"]["shards"][0]["file"])
    records.write_shard(other, [b"x"])  # a shard with the wrong record count
    with pytest.raises(records.RecordError, match=os.path.basename(other)):
        pp.prepare(cfg, Factory(), variants=())
    assert records.count_records(other) == 1  # reported, left as it was


def test_bad_manifest_is_named(tmp_path):
    ddir = tmp_path / "d"
    ddir.mkdir()
    (ddir / "manifest.json").write_text("{not json")
    with pytest.raises(mf.ManifestError, match="manifest.json: unreadable"):
        mf.read_manifest(ddir)
    with pytest.raises(mf.ManifestError, match="no manifest"):
        mf.read_manifest(tmp_path)


def test_records_are_encoded_beside_the_renders_and_keep_their_order(tmp_path, monkeypatch):
    """Each batch is encoded in a thread while the next one renders; the shards are the same
    bytes however long each encoding takes, and an encoding error names its record."""
    reference = _shard_bytes(pp.prepare(small_config(tmp_path / "a"), Factory(), variants=()))
    encode, threads, delays = pp.encode_sample, set(), iter(np.tile([0.02, 0.0, 0.005], 100))

    def slow_encode(sample, **kw):
        threads.add(threading.current_thread().name)
        time.sleep(next(delays))  # later batches may be rendered before earlier ones are encoded
        return encode(sample, **kw)

    monkeypatch.setattr(pp, "encode_sample", slow_encode)
    ddir = pp.prepare(small_config(tmp_path / "b"), Factory(), variants=())
    assert _shard_bytes(ddir) == reference
    assert threading.main_thread().name not in threads  # encoded beside the renders

    def bad_encode(sample, **kw):
        return encode(dict(sample, lidar=sample["lidar"] * 1e3), **kw)  # beyond LIDAR_RANGE

    monkeypatch.setattr(pp, "encode_sample", bad_encode)
    with pytest.raises(records.SchemaError, match=r"train-00000-of-00003\.array_record record 0"):
        pp.prepare(small_config(tmp_path / "c"), Factory(), variants=())
