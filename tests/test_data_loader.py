"""Loader: fixed-shape batches per the schema, determinism, per-epoch priors, resume, errors."""

import itertools
import json
import os
import shutil

import numpy as np
import pytest

from data_synth import Factory, random_raster, small_config
from seglocnet_jax import geometry
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data import records
from seglocnet_jax.data.schema import BATCH_KEYS, BATCH_METADATA_KEYS, OPTIONAL_BATCH_KEYS
from seglocnet_jax.data.simulated import prepare as pp
from seglocnet_jax.training import step as step_lib

B, P = 4, 48
CFG = ld.LoaderConfig(max_points=P, num_threads=0, prefetch=0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("loader")
    ddir = pp.prepare(small_config(root), Factory(), variants=())
    raster = random_raster(0, size_m=1300.0)
    return ddir, {"helsinki": raster, "kouvola": raster}


def _loader(dataset, split="train", seed=0, train=True, **kw):
    ddir, rasters = dataset
    cfg = ld.LoaderConfig(**{**CFG.__dict__, **kw})
    return ld.make_loader(ddir, split, None, B, seed, train, config=cfg, rasters=rasters)


def _take(it, n):
    return list(itertools.islice(it, n))


def _same(a, b):
    return all(np.array_equal(x[k], y[k]) for x, y in zip(a, b, strict=True) for k in x)


def test_batches_follow_the_schema(dataset):
    raster = dataset[1]["helsinki"]
    batch = next(iter(_loader(dataset)))
    dims = {"B": B, "P": P, "N": 2, "H": 8, "W": 12, "C": 2}
    assert set(batch) == set(BATCH_KEYS) - set(OPTIONAL_BATCH_KEYS)  # no nm_tile: not asked
    for key, (dtype, shape) in BATCH_KEYS.items():
        if key in OPTIONAL_BATCH_KEYS:
            continue
        want = tuple(dims.get(s, s) for s in shape)
        kind_ok = batch[key].dtype.kind == "U" if dtype == "str" else batch[key].dtype == dtype
        assert kind_ok and batch[key].shape == want, key
    on_devices = step_lib.device_batch(batch, step_lib.make_mesh(1))  # metadata stays on host
    assert set(on_devices) == set(BATCH_KEYS) - set(BATCH_METADATA_KEYS) - {"nm_tile"}
    for i in range(B):
        pose, centre = batch["pose"][i], batch["tile_center"][i]
        np.testing.assert_allclose(
            batch["pose_tile"][i], [*(pose[:2] - centre), pose[2]], atol=1e-4
        )
        assert np.abs(pose[:2] - centre).max() <= geometry.PRIOR_RANGE + 0.25
        tile, (cx, cy) = raster.tile(*centre)  # the centre is already on the grid
        assert (cx, cy) == tuple(centre)
        np.testing.assert_array_equal(batch["tile"][i], tile)
        np.testing.assert_array_equal(batch["bev_gt"][i], raster.cut_bev(pose))
        n = batch["points_mask"][i].sum()
        assert not batch["points"][i][n:].any()
    assert batch["valid"].all()


def test_nm_tiles_are_cut_around_the_same_prior_only_when_asked(dataset):
    ddir, rasters = dataset
    classes = random_raster(1, size_m=1300.0)  # a stand-in for the OSM class rasters
    classes.mask = np.concatenate([classes.mask] * 4 + [classes.mask[:1]])  # 9 channels
    nm = {"helsinki": classes, "kouvola": classes}
    for train in (True, False):
        plain = next(iter(_loader(dataset, train=train)))
        loader = ld.make_loader(
            ddir, "train", None, B, 0, train, config=CFG, rasters=rasters, nm_rasters=nm
        )
        batch = next(iter(loader))
        assert "nm_tile" not in plain
        assert batch["nm_tile"].shape == (B, 9, 256, 256) and batch["nm_tile"].dtype == np.uint8
        for key in ("tile", "pose", "tile_center", "bev_gt"):  # the same rows and priors
            np.testing.assert_array_equal(batch[key], plain[key])
        for i in range(B):
            np.testing.assert_array_equal(
                batch["nm_tile"][i], classes.tile(*batch["tile_center"][i])[0]
            )
    # Stored ones (nm_tiles=True) must have been prepared: the error names the remedy.
    with pytest.raises(ValueError, match="OSM class rasters are not prepared.*model.variant=nm"):
        ld.make_loader(ddir, "train", None, B, 0, True, config=CFG, rasters=rasters, nm_tiles=True)


def test_same_seed_same_batches_other_seed_other_priors(dataset):
    a = _take(iter(_loader(dataset, seed=1)), 3)
    b = _take(iter(_loader(dataset, seed=1)), 3)
    c = _take(iter(_loader(dataset, seed=2)), 3)
    assert _same(a, b)
    assert not np.array_equal(a[0]["sample_id"], c[0]["sample_id"])
    threaded = _take(iter(_loader(dataset, seed=1, num_threads=2, prefetch=2)), 3)
    assert _same(a, threaded)


def test_priors_change_every_epoch(dataset):
    loader = _loader(dataset, seed=0, num_epochs=2)
    assert loader.batches_per_epoch == 24 // B
    batches = list(loader)
    assert len(batches) == 2 * 24 // B
    centres = [{}, {}]
    for e, chunk in enumerate((batches[:6], batches[6:])):
        for b in chunk:
            centres[e].update(zip(b["sample_id"], map(tuple, b["tile_center"]), strict=True))
    assert set(centres[0]) == set(centres[1]) and len(centres[0]) == 24  # each record once
    assert sum(centres[0][k] != centres[1][k] for k in centres[0]) >= 20


def test_iterator_state_resumes_identically(dataset):
    it = iter(_loader(dataset, seed=3, num_epochs=2))
    _take(it, 4)
    state = it.get_state()
    assert state == json.loads(json.dumps(state))  # JSON-able
    rest = _take(it, 5)  # crosses the epoch boundary
    it2 = iter(_loader(dataset, seed=3, num_epochs=2))
    it2.set_state(state)
    assert _same(rest, _take(it2, 5))


def test_eval_uses_stored_priors_and_pads_the_last_batch(dataset):
    ddir, _ = dataset
    man = mf.read_manifest(ddir)
    stored = {}
    for path, n in mf.split_files(man, ddir, "kouvola"):
        for r in records.read_shard(path, n):
            s = records.decode_sample(r)
            stored[s["sample_id"]] = s["prior"]
    loader = _loader(dataset, "kouvola", train=False)
    batches = list(loader) + list(loader)  # two passes, same content
    assert len(batches) == 2 * loader.batches_per_epoch == 4  # 6 records, B = 4
    assert _same(batches[:2], batches[2:])
    valid = np.concatenate([b["valid"] for b in batches[:2]])
    np.testing.assert_array_equal(valid, [True] * 6 + [False] * 2)
    grid = dataset[1]["kouvola"].grid
    for b in batches[:2]:
        for sid, centre in zip(b["sample_id"], b["tile_center"], strict=True):
            _, _, cx, cy = geometry.tile_window(grid, *stored[sid])
            np.testing.assert_array_equal(centre, [cx, cy])


def test_fit_points_pads_and_subsamples_deterministically():
    lidar = np.arange(40, dtype=np.float32).reshape(10, 4)
    pts, mask = ld.fit_points(lidar, 16)
    np.testing.assert_array_equal(pts[:10], lidar)
    assert mask.sum() == 10 and not pts[10:].any()
    pts, mask = ld.fit_points(lidar, 4)
    assert mask.all()
    np.testing.assert_array_equal(pts[:, 0], lidar[[0, 2, 5, 7], 0])


def _copy(dataset, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(dataset[0], dst)
    man = mf.read_manifest(dst)
    return dst, mf.split_files(man, dst, "train")


def test_truncated_or_missing_shard_is_named(dataset, tmp_path):
    ddir, files = _copy(dataset, tmp_path)
    path, _ = files[1]
    data = open(path, "rb").read()
    open(path, "wb").write(data[: len(data) // 2])
    with pytest.raises(records.RecordError, match=os.path.basename(path)):
        ld.make_loader(ddir, "train", None, B, 0, True, config=CFG, rasters=dataset[1])
    os.remove(path)
    with pytest.raises(records.RecordError, match=f"{os.path.basename(path)}: shard file is miss"):
        ld.make_loader(ddir, "train", None, B, 0, True, config=CFG, rasters=dataset[1])
    with pytest.raises(mf.ManifestError, match="no split 'nope'"):
        ld.make_loader(ddir, "nope", None, B, 0, True, config=CFG, rasters=dataset[1])


def test_corrupt_record_is_named_with_file_and_index(dataset, tmp_path):
    ddir, files = _copy(dataset, tmp_path)
    path, _ = files[0]
    data = bytearray(open(path, "rb").read())
    at = [i for i in range(len(data) - 4) if data[i : i + 4] == records.MAGIC]
    assert len(at) == 10  # one record per chunk (group_size:1), stored as is
    data[at[3] + 200] ^= 0xFF  # inside record 3's payload: the chunk hash no longer matches
    open(path, "wb").write(bytes(data))
    source = ld.ShardSource(files)
    for i in range(3):
        source[i]  # the other records stay readable
    with pytest.raises(records.RecordError, match=rf"{os.path.basename(path)} record 3"):
        source[3]


def test_missing_city_raster_is_named(dataset):
    ddir, rasters = dataset
    it = iter(
        ld.make_loader(
            ddir, "val", None, B, 0, False, config=CFG, rasters={"kouvola": rasters["kouvola"]}
        )
    )
    with pytest.raises(records.RecordError, match="no map raster for city 'helsinki'"):
        next(it)


def _loader_sharded(dataset, split="train", seed=0, train=True, shard_options=None, b=B, **kw):
    ddir, rasters = dataset
    cfg = ld.LoaderConfig(**{**CFG.__dict__, **kw})
    return ld.make_loader(
        ddir, split, None, b, seed, train, config=cfg, rasters=rasters, shard_options=shard_options
    )


def _joined(parts):
    """Shard batches concatenated in shard order, as the global batch is laid out."""
    rows = zip(*parts, strict=True)
    return [{k: np.concatenate([p[k] for p in row]) for k in row[0]} for row in rows]


def test_process_shards_are_disjoint_halves_of_the_global_batch(dataset):
    whole = _loader_sharded(dataset, seed=5, num_epochs=2)
    shards = [
        _loader_sharded(dataset, seed=5, num_epochs=2, shard_options=ld.ShardOptions(i, 2))
        for i in range(2)
    ]
    assert [s.batch_size for s in shards] == [B // 2] * 2 and whole.batch_size == B
    assert all(s.batches_per_epoch == whole.batches_per_epoch for s in shards)
    want = list(whole)
    parts = [list(s) for s in shards]
    assert [len(p) for p in parts] == [len(want)] * 2 == [2 * 24 // B] * 2  # crosses epochs
    for a, b in zip(*parts, strict=True):
        assert a["images"].shape[0] == B // 2 and not set(a["sample_id"]) & set(b["sample_id"])
    assert _same(_joined(parts), want)  # bit for bit: same shuffle, same per-record priors
    # Deterministic for a seed; another seed shuffles otherwise.
    again = _loader_sharded(dataset, seed=5, num_epochs=2, shard_options=ld.ShardOptions(1, 2))
    assert _same(list(again), parts[1])
    other = _loader_sharded(dataset, seed=6, num_epochs=2, shard_options=ld.ShardOptions(1, 2))
    assert not np.array_equal(next(iter(other))["sample_id"], parts[1][0]["sample_id"])


def test_eval_shards_split_the_padded_batches(dataset):
    whole = list(_loader_sharded(dataset, "kouvola", train=False))  # 6 records, B = 4
    parts = [
        list(_loader_sharded(dataset, "kouvola", train=False, shard_options=ld.ShardOptions(i, 2)))
        for i in range(2)
    ]
    assert [len(p) for p in parts] == [2, 2]
    assert _same(_joined(parts), whole)
    np.testing.assert_array_equal(parts[1][1]["valid"], [False, False])  # the padding


def test_sharded_iterator_resumes_and_counts_global_batches(dataset):
    def shard(i):
        return _loader_sharded(dataset, seed=3, num_epochs=2, shard_options=ld.ShardOptions(i, 2))

    it = iter(shard(0))
    _take(it, 4)
    state = it.get_state()
    assert state == json.loads(json.dumps(state))
    rest = _take(it, 5)  # crosses the epoch boundary
    it2 = iter(shard(0))
    it2.set_state(state)
    assert _same(rest, _take(it2, 5))
    # The state of shard 0 (what process 0 checkpoints) resumes shard 1 and the unsharded
    # loader at the same global batch.
    it1 = iter(shard(1))
    it1.set_state(state)
    whole = iter(_loader_sharded(dataset, seed=3, num_epochs=2))
    whole.set_state(state)
    assert _same(_joined([rest, _take(it1, 5)]), _take(whole, 5))


def test_finite_epochs_give_every_shard_the_same_batch_count(dataset):
    # 24 records, B = 9 over 3 shards of 3 rows: 2 global batches; 8 whole local batches would
    # give shards 0 and 1 a third (partial) global batch and a multi-host run would hang.
    parts = [
        list(_loader_sharded(dataset, num_epochs=1, b=9, shard_options=ld.ShardOptions(i, 3)))
        for i in range(3)
    ]
    assert [len(p) for p in parts] == [2] * 3
    assert _same(_joined(parts), list(_loader_sharded(dataset, num_epochs=1, b=9)))


def test_batch_not_divisible_by_shards_is_an_error(dataset):
    with pytest.raises(ValueError, match="not divisible by the 3 loader shards"):
        _loader_sharded(dataset, shard_options=ld.ShardOptions(0, 3))
    with pytest.raises(ValueError, match="shard_index must be in"):  # grain checks it
        ld.ShardOptions(2, 2)
