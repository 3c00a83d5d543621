"""Drive splits: whole drives in the test city (``drives``), main-city drives clear of the train
frames (``drives_val``) and test-city drives clear of every test frame there
(``drives_val_unseen``) with sequence metadata in every record; the default preset finds them in
the embedded cities; the other splits are unchanged by them."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from data_synth import Factory, random_raster, small_config
from seglocnet_jax import maps
from seglocnet_jax.data import loader as ld
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.simulated import drives as dr
from seglocnet_jax.data.simulated import planning
from seglocnet_jax.data.simulated import prepare as pp
from seglocnet_jax.data.simulated import splits as sp
from seglocnet_jax.data.simulated.config import PrepareConfig
from seglocnet_jax.sim import NOMINAL_SPEED_MPS, WorldConfig
from seglocnet_jax.sim import roads as rd
from seglocnet_jax.sim import trajectory as tr

TINY = dict(
    num_drives=2,
    num_val_drives=2,
    num_unseen_val_drives=2,
    drive_spacing_m=5.0,
    drive_length_m=40.0,  # 9 frames
    min_val_drive_m=20.0,  # >= 5 frames
)
SEQ = ("sample_id", "sequence_id", "frame_index", "timestamp", "pose", "valid")


def _rows(ddir, split):
    raster = random_raster(0, size_m=1300.0)
    cfg = ld.LoaderConfig(max_points=16, num_threads=0, prefetch=0)
    loader = ld.make_loader(
        ddir, split, None, 4, 0, False, config=cfg, rasters={"helsinki": raster, "kouvola": raster}
    )
    batches = list(iter(loader))
    rows = {k: np.concatenate([b[k] for b in batches]) for k in SEQ}
    return {k: v[rows["valid"]] for k, v in rows.items()}


@pytest.fixture(scope="module")
def with_drives(tmp_path_factory):
    root = tmp_path_factory.mktemp("drives")
    return pp.prepare(small_config(root, **TINY), Factory(), variants=())


def test_drive_splits_hold_whole_drives_in_order(with_drives):
    man = mf.read_manifest(with_drives)
    assert sorted(man["splits"]) == sorted(small_config("x", **TINY).split_names())
    assert sorted(man["splits"]) == [
        "drives", "drives_val", "drives_val_unseen", "kouvola", "test", "train", "val"
    ]  # fmt: skip
    assert man["splits"]["drives"]["cities"] == {"kouvola": 18}  # 2 drives x 9 frames
    assert set(man["splits"]["drives_val"]["cities"]) == {"helsinki"}
    assert set(man["splits"]["drives_val_unseen"]["cities"]) == {"kouvola"}
    rows = _rows(with_drives, "drives")
    want_seq = [f"kouvola-drives-d{d:03d}" for d in range(2) for _ in range(9)]
    assert rows["sequence_id"].tolist() == want_seq  # ordered by drive, then frame
    assert rows["frame_index"].tolist() == list(range(9)) * 2
    np.testing.assert_allclose(rows["timestamp"], rows["frame_index"] * 5.0 / NOMINAL_SPEED_MPS)
    assert rows["sample_id"][12] == "kouvola-drives-d001-000003"
    assert len(set(rows["sample_id"])) == 18
    for d in range(2):  # continuous: consecutive frames 5 m apart along the streets
        p = rows["pose"][9 * d : 9 * d + 9]
        step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
        assert step.max() < 5.0 + 4.0 + 1.0 and np.median(step) == pytest.approx(5.0, abs=0.5)


def test_drives_val_frames_are_clear_of_every_train_frame(with_drives):
    train, val = _rows(with_drives, "train"), _rows(with_drives, "drives_val")
    sp.check_disjoint(
        {"train": train["pose"][:, :2], "drives_val": val["pose"][:, :2]},
        min_distance=2 * sp.BEV_RADIUS + 1.0,  # + split.margin
    )
    for seq in np.unique(val["sequence_id"]):
        mine = val["sequence_id"] == seq
        assert 5 <= mine.sum() <= 9  # min_val_drive_m .. drive_length_m
        assert val["frame_index"][mine].tolist() == list(range(mine.sum()))
    # Non-drive splits carry sequence metadata too (GridSource reports no routes: one each).
    assert all(s.startswith("helsinki-p") for s in train["sequence_id"])


def test_drives_val_unseen_frames_are_clear_of_every_test_city_frame(with_drives):
    unseen = _rows(with_drives, "drives_val_unseen")
    tested = np.concatenate([_rows(with_drives, s)["pose"][:, :2] for s in ("drives", "kouvola")])
    sp.check_disjoint(
        {"tested": tested, "drives_val_unseen": unseen["pose"][:, :2]},
        min_distance=2 * sp.BEV_RADIUS + 1.0,  # + split.margin
    )
    seqs = np.unique(unseen["sequence_id"])
    assert seqs.tolist() == ["kouvola-drives_val_unseen-d000", "kouvola-drives_val_unseen-d001"]
    for seq in seqs:
        mine = unseen["sequence_id"] == seq
        assert 5 <= mine.sum() <= 9  # min_val_drive_m .. drive_length_m
        assert unseen["frame_index"][mine].tolist() == list(range(mine.sum()))


def test_other_splits_are_unchanged_by_the_drives(with_drives, tmp_path):
    plain = pp.prepare(small_config(tmp_path), Factory(), variants=())
    a, b = mf.read_manifest(with_drives)["splits"], mf.read_manifest(plain)["splits"]
    assert set(a) - set(b) == {"drives", "drives_val", "drives_val_unseen"}
    for split in b:  # same poses, priors, renders, metadata: the same bytes
        assert a[split] == b[split], split


def test_drive_plans_are_deterministic_and_seeded():
    cfg = small_config("x", **TINY)
    src = Factory()("kouvola")
    one, two = dr.plan_drives(src, cfg, "kouvola"), dr.plan_drives(src, cfg, "kouvola")
    np.testing.assert_array_equal(one.poses, two.poses)
    np.testing.assert_array_equal(one.priors, two.priors)
    other = dr.plan_drives(src, dataclasses.replace(cfg, seed=6), "kouvola")
    assert not np.array_equal(one.poses, other.poses)
    assert np.abs(one.priors - one.poses[:, :2]).max() <= 32.0  # seeded priors per frame


def test_drives_val_that_cannot_be_found_is_named():
    cfg = small_config("x", **TINY)
    src = Factory()("helsinki")
    everywhere = np.stack(np.meshgrid(np.arange(0, 1300, 50.0), np.arange(0, 1300, 50.0)), -1)
    with pytest.raises(sp.SplitError) as err:
        dr.plan_val_drives(src, cfg, "helsinki", everywhere.reshape(-1, 2))
    msg = str(err.value)
    assert msg.startswith("helsinki: found 0 of data.num_val_drives=2 drives_val")
    assert "data.min_val_drive_m" in msg and "data.num_val_drives=0" in msg
    with pytest.raises(sp.SplitError) as err:
        dr.plan_val_drives(
            Factory()("kouvola"), cfg, "kouvola", everywhere.reshape(-1, 2),
            name=dr.UNSEEN_VAL_DRIVES,
        )  # fmt: skip
    msg = str(err.value)
    assert msg.startswith("kouvola: found 0 of data.num_unseen_val_drives=2 drives_val_unseen")
    assert "from every test frame" in msg and "data.num_unseen_val_drives=0" in msg


def test_clear_runs_are_maximal():
    ok = np.array([1, 1, 0, 1, 1, 1, 0, 0, 1], bool)
    assert dr.clear_runs(ok) == [(0, 2), (3, 6), (8, 9)]
    assert dr.clear_runs(np.zeros(3, bool)) == []


@pytest.mark.parametrize(
    "kw, key",
    [
        (dict(num_drives=-1), "data.num_drives"),
        (dict(num_unseen_val_drives=-1), "data.num_unseen_val_drives"),
        (dict(drive_spacing_m=0.0), "data.drive_spacing_m"),
        (dict(drive_length_m=2.0), "data.drive_length_m"),
        (dict(min_val_drive_m=2000.0), "data.min_val_drive_m"),
    ],
)
def test_bad_drive_config_is_named(kw, key):
    with pytest.raises(ValueError, match=key):
        PrepareConfig(**kw)


def test_split_names_follow_the_config():
    assert PrepareConfig().split_names() == [
        "train", "val", "test", "kouvola", "drives", "drives_val", "drives_val_unseen"
    ]  # fmt: skip
    no_city = PrepareConfig(test_city=None)  # no test city: no drives there either
    assert no_city.split_names() == ["train", "val", "test", "drives_val"]
    none = PrepareConfig(num_drives=0, num_val_drives=0, num_unseen_val_drives=0)
    assert none.split_names() == ["train", "val", "test", "kouvola"]


def test_unseen_drives_enter_the_identity_only_when_on():
    # Off, the key is not in the identity, so a dataset prepared before it existed still matches.
    off = PrepareConfig(num_unseen_val_drives=0).identity()
    assert "num_unseen_val_drives" not in off
    on = PrepareConfig(num_unseen_val_drives=4).identity()
    assert on.pop("num_unseen_val_drives") == 4 and on == off
    no_city = PrepareConfig(test_city=None, num_unseen_val_drives=4).identity()
    assert "num_unseen_val_drives" not in no_city  # no test city: no such split


class RoadSource:
    """The simulator's trajectories on a city's world roads, without the world rasters (the
    roads and their offsets are those of ``sim.build_world(city, WorldConfig(), seed)``)."""

    def __init__(self, city: str, seed: int, spacing_m: float = 4.0):
        cfg = WorldConfig()
        rng = np.random.default_rng([seed, *city.encode()])  # as build_world_from_city
        field = rd.OffsetField(rng, cfg.offset_min, cfg.offset_max, cfg.offset_wavelength)
        roads = rd.build_roads(maps.load_city(city).roads, field)
        self.world = SimpleNamespace(name=city, roads=roads, graph=None)
        self.spacing_m = spacing_m

    def drive(self, rng, n):
        return tr.drive(self.world, rng, n, self.spacing_m)

    def drive_routes(self, rng, n):
        return tr.drive_routes(self.world, rng, n, self.spacing_m)

    def route(self, rng, length_m, spacing_m):
        return tr.route(self.world, rng, length_m, spacing_m)


def test_the_default_preset_finds_its_drives_in_the_embedded_cities():
    cfg = PrepareConfig()  # data=quick: 8 x 1 km in Kouvola, 4 clear of them, 4 in Helsinki
    helsinki, kouvola = RoadSource("helsinki", cfg.seed), RoadSource("kouvola", cfg.seed)
    train, val, test = planning.plan_main_city(helsinki, cfg)
    # The pool splits' sequences are the simulator's short routes.
    assert train.sequence_ids[0].startswith("helsinki-p0-route")
    same = train.sequence_ids[1:] == train.sequence_ids[:-1]
    assert np.all(np.diff(train.frame_index)[same] > 0)
    np.testing.assert_allclose(train.timestamps, train.frame_index * 4.0 / NOMINAL_SPEED_MPS)
    drives_val = dr.plan_val_drives(helsinki, cfg, "helsinki", train.poses[:, :2])
    sp.check_disjoint({"train": train.poses[:, :2], "drives_val": drives_val.poses[:, :2]})
    counts = [int((drives_val.sequence_ids == s).sum()) for s in np.unique(drives_val.sequence_ids)]
    assert len(counts) == 4 and min(counts) >= 61 and max(counts) <= 201  # 300 m .. 1 km
    drives = dr.plan_drives(kouvola, cfg, "kouvola")
    assert len(drives.poses) == 8 * 201 and drives.frame_index.max() == 200
    step = np.linalg.norm(np.diff(drives.poses[:, :2], axis=0), axis=1)
    within = np.diff(drives.frame_index) == 1
    assert step[within].max() < 5.0 + 6.0  # no jumps within a drive
    # drives_val_unseen: 4 Kouvola drives clear of the drives and of the Kouvola split.
    tested = np.concatenate(
        [drives.poses[:, :2], planning.plan_test_city(kouvola, cfg).poses[:, :2]]
    )
    unseen = dr.plan_val_drives(kouvola, cfg, "kouvola", tested, name=dr.UNSEEN_VAL_DRIVES)
    sp.check_disjoint({"tested": tested, "unseen": unseen.poses[:, :2]})
    counts = [int((unseen.sequence_ids == s).sum()) for s in np.unique(unseen.sequence_ids)]
    assert len(counts) == 4 and min(counts) >= 61 and max(counts) <= 201
