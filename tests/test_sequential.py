"""Sequential localization (seglocnet_jax.sequential): the tile is cut around the filter's
estimate (a flat likelihood follows dead reckoning, not the truth), the lattice is the raster's,
the streamed temperature fit, the credible-region read-out, the metric definitions, config
validation, and whole drives through the evaluate and train apps (GT BEV: near-perfect
tracking; results.json, the tables, the figures) and on converted nuScenes / AV2 fixtures."""

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fixtures_real as fx
from apphelpers import DRIVES_EVAL, TINY_DRIVES, app_tree
from seglocnet_jax import evaluation, geometry, maps, sequential, solver
from seglocnet_jax import tracking as tr
from seglocnet_jax.app import eval_run, train_run
from seglocnet_jax.app.schema import build_experiment
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.data.loader import LoaderConfig
from seglocnet_jax.data.real import alignment as ra
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import convert as rconv
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.schema import BATCH_METADATA_KEYS
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.sequential import config as seq_config
from seglocnet_jax.sequential import drive_filter, temperature, tracks
from seglocnet_jax.training import step as step_lib

K = 16


def _raster(seed=0, x_min=-123.5, y_max=456.0, h=700, w=600):
    mask = (np.random.default_rng(seed).random((2, h, w)) > 0.5).astype(np.uint8)
    grid = geometry.RasterGrid(x_min=x_min, y_max=y_max, height=h, width=w)
    return maps.CityRaster(mask, grid, ("road", "building"), "town")


# --------------------------------------------------------------------------- the tile


def test_the_compile_clock_counts_a_new_program_not_a_cached_one():
    """The lockstep loop times later compilations apart with it: the jax.monitoring event
    names it listens to must still be the ones this jax sends."""
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)
    with tracks.CompileClock() as clock:
        f(jnp.ones(7)).block_until_ready()
        first = clock.seconds
        f(jnp.ones(7)).block_until_ready()  # cached
        cached = clock.seconds - first
        f(jnp.ones(9)).block_until_ready()  # a new shape: compiled again
    assert first > 0 and cached == 0 and clock.seconds > first
    seen = clock.seconds
    f(jnp.ones(13)).block_until_ready()  # after exit: no longer listening
    assert clock.seconds == seen


def test_filter_tile_is_the_raster_tile_at_the_window_centre():
    raster = _raster()
    cfg = tr.TrackerConfig(num_rotations=K)
    belief = sequential.start_belief(raster, (-100.3, 130.7), cfg)  # the tile hangs over the edge
    np.testing.assert_array_equal(belief.origin, [raster.grid.x_min, raster.grid.y_max])
    odometry = np.array([7.3, -2.1, 0.4])
    for _ in range(3):  # at the start (zeros outside the raster) and after moves
        tile, centre = sequential.filter_tile(raster, belief, cfg)
        want, want_centre = raster.tile(*centre)
        np.testing.assert_array_equal(tile, want)
        np.testing.assert_allclose(centre, want_centre)
        np.testing.assert_allclose(centre, tr.window_centre(belief, cfg))
        belief, _ = tr.predict(belief, odometry * 6, cfg)
    assert np.hypot(*(centre - [-100.3, 130.7])) > 20.0  # the window moved with the belief


class _FakeSplit:
    """A drive split in memory: the rows a DriveSplit gives, over one raster."""

    name = "fake"
    nm_rasters = None  # a seg model's split: no OSM class rasters

    def __init__(self, raster, drive):
        self.rasters = {drive.city: raster}
        self.drive = drive

    def rows(self, indices):
        out = []
        for i in indices:
            pose = self.drive.poses[int(i)]
            tile, centre = self.rasters[self.drive.city].tile(*self.drive.priors[int(i)])
            out.append(
                {
                    "tile": tile.astype(np.float32),
                    "tile_center": np.asarray(centre),
                    "pose_tile": np.array([*(pose[:2] - centre), pose[2]], np.float32),
                    "pose": pose,
                    "frame_index": np.int64(i),
                }
            )
        return out


def _straight_drive(n=30, spacing=5.0):
    yaw = float(geometry.yaw_from_rotation(3, K))  # on a yaw bin of the filter
    s = np.arange(n) * spacing
    poses = np.stack([20.0 + s * math.cos(yaw), 30.0 + s * math.sin(yaw), np.full(n, yaw)], 1)
    return sequential.Drive(
        sequence_id="drive-0",
        city="town",
        records=np.arange(n),
        frame_index=np.arange(n),
        timestamps=s / 10.0,
        poses=poses,
        priors=poses[:, :2] + [17.0, -11.0],
    )


class _FakeStep:
    """A localize step whose outputs ``tiles(params, batch, figures, volume)`` makes from the
    batch of tiles alone (the network's side is nothing here)."""

    def __init__(self, tiles):
        self.tiles = tiles

    def network(self, params, batch):
        return None

    def solve(self, params, bev, batch, rows=None, *, figures=False, volume=False):
        return self.tiles(params, batch, figures, volume)

    def __call__(self, params, batch, figures=False, volume=False):
        return self.tiles(params, batch, figures, volume)


def _track_one(step, split, drive, cfg, odometry):
    """``drive`` through the lockstep loop the apps run (batch 1, T = 1, odometry seed 0)."""
    (track,), _ = sequential.track_split(
        _FakeStep(step),
        None,
        split,
        [drive],
        cfg=cfg,
        odometry_cfg=odometry,
        odometry_seed=0,
        temperature=1.0,
        batch_size=1,
        place=lambda b: b,
        desc=drive.sequence_id,
    )
    return track


def test_flat_likelihood_follows_dead_reckoning_not_the_truth():
    """Frame 0's likelihood is a peak at the truth, every later frame's is flat: the filter can
    only dead-reckon, and the tiles it asks for are centred on its estimate, which follows the
    (noisy) odometry away from the truth."""
    drive = _straight_drive()
    # A 9 % distance scale error (seed 0), exact yaw: dead reckoning runs 13 m ahead of the car.
    odometry = tr.OdometryConfig(
        scale_sigma=0.1, yaw_bias_sigma=0.0, yaw_scale_sigma=0.0, yaw_sigma=0.0
    )
    ev = sequential.EvalConfig(
        odometry=odometry,
        tracker=sequential.TrackerSettings(lost_peak_mass=0.0, lost_entropy=1.0, off_road=0.0),
    )
    cfg = sequential.tracker_config(ev, K)
    tile_centres = []

    def step(params, batch, figures=False, volume=False):
        b = len(batch["tile"])
        out = {"pose_tile": jnp.zeros((b, 3))}
        if volume:
            tile_centres.append(np.asarray(batch["tile_center"][0]))
            n = batch["tile"].shape[-1] - geometry.BEV_SIZE + 1  # 129
            vol = np.zeros((b, K, n, n), np.float32)
            if int(batch["frame_index"][0]) == 0:  # a perfect first frame
                pose_tile = batch["pose_tile"][0]
                cell = np.round(geometry.pose_to_cell(pose_tile, K, size=n)).astype(int)
                vol[0, cell[0] % K, cell[1], cell[2]] = 100.0
            out["volume"] = jnp.asarray(vol)
        return out

    split = _FakeSplit(_raster(1), drive)
    track = _track_one(step, split, drive, cfg, odometry)
    odo = tr.simulate(drive.poses, drive.timestamps, odometry, sequential.drive_seed(0, "drive-0"))
    dead = tr.compose(track.filtered[0], odo)
    truth_gap = np.hypot(*(dead[-1, :2] - drive.poses[-1, :2]))
    assert truth_gap > 8.0, truth_gap  # the odometry does drift away from the truth
    err_dead = np.hypot(*(track.filtered[:, :2] - dead[:, :2]).T)
    assert err_dead.max() < 1.5, err_dead
    centres = np.stack(tile_centres)  # frame 0: the prior; frame t: the predicted estimate
    np.testing.assert_allclose(centres[0], split.rasters["town"].tile(*drive.priors[0])[1])
    assert np.hypot(*(centres[1:] - dead[1:, :2]).T).max() < 1.5
    assert np.hypot(*(centres[-1] - drive.poses[-1, :2])) > truth_gap - 1.5
    assert not track.lost.any()
    assert tile_centres and len(tile_centres) == len(drive)


def _peaks_step(peaks_of, sizes=None):
    """A localize step whose score volume holds, per row, the peaks ``peaks_of(batch, i)``
    (``(tile pose, score)`` each; one outside the volume is left out), its size the tile's
    (``sizes``: the window sizes it was asked for)."""

    def step(params, batch, figures=False, volume=False):
        b = len(batch["tile"])
        out = {"pose_tile": jnp.zeros((b, 3))}
        if volume:
            n = batch["tile"].shape[-1] - geometry.BEV_SIZE + 1
            if sizes is not None:
                sizes.append(n)
            vol = np.zeros((b, K, n, n), np.float32)
            for i in range(b):
                for p, score in peaks_of(batch, i):
                    cell = np.round(geometry.pose_to_cell(p, K, size=n)).astype(int)
                    if (0 <= cell[1:]).all() and (cell[1:] < n).all():
                        vol[i, cell[0] % K, cell[1], cell[2]] = score
            out["volume"] = jnp.asarray(vol)
        return out

    return step


@pytest.mark.parametrize("hypotheses", [1, 3])
def test_a_far_first_peak_loses_the_truth_with_one_window_only(hypotheses):
    """Frame 0's likelihood peaks 55 m from the truth, at the far side of the prior box, and
    (more weakly, 5 nats) at the truth; every later frame peaks at the truth alone. The window
    follows the mode: the 129-cell window drops the truth's cells at frame 0 and never finds it
    again; a bank of windows gives the truth's mode a window of its own, whose evidence wins
    from frame 1, and the far window is pruned."""
    drive = _straight_drive(n=12)
    wrong = drive.priors[0] + [28.0, -20.0]  # inside the +-32 m box around the prior
    assert np.hypot(*(wrong - drive.poses[0, :2])) > 50.0
    odometry = tr.OdometryConfig(
        scale_sigma=0.0, yaw_bias_sigma=0.0, yaw_scale_sigma=0.0, yaw_sigma=0.0
    )
    ev = sequential.EvalConfig(
        odometry=odometry,
        tracker=sequential.TrackerSettings(
            lost_log_odds=0.0,
            lost_peak_mass=0.0,
            lost_entropy=1.0,
            hypotheses=hypotheses,
            off_road=0.0,
        ),
    )
    cfg = sequential.tracker_config(ev, K)

    def peaks(batch, i):
        pose_tile = np.asarray(batch["pose_tile"][i], np.float64)
        out = [(pose_tile, 20.0)]
        if int(batch["frame_index"][i]) == 0:
            off = wrong - np.asarray(batch["tile_center"][i])
            out.append((np.array([*off, pose_tile[2]]), 25.0))
        return out

    track = _track_one(_peaks_step(peaks), _FakeSplit(_raster(2), drive), drive, cfg, odometry)
    err = np.hypot(*(track.filtered[:, :2] - drive.poses[:, :2]).T)
    assert err[0] > 50.0  # the first frame's mode is the far peak either way
    if hypotheses > 1:
        assert err[1:].max() < 1.0, err
        assert track.hypotheses[0] >= 2 and track.hypotheses[-1] == 1  # the far one pruned
    else:
        assert err[1:].min() > 20.0, err
        assert (track.hypotheses == 1).all()


def test_temperature_candidates_in_one_pass_are_the_separate_runs():
    """The temperature choice tracks every candidate in one pass (a filter per candidate, one
    network pass per frame, their tiles in the same solver batches): each candidate's tracks
    are those of its own run, and the candidates differ. The fake volume is a function of the
    world cell (a noise floor per frame, the truth's peak), as the solver's is: the
    candidates' windows a few cells apart, solved as one union tile, give their own volumes."""
    drive = _straight_drive(n=8)
    ev = sequential.EvalConfig(
        odometry=_EXACT_ODOMETRY, tracker=sequential.TrackerSettings(hypotheses=3, off_road=2.0)
    )
    cfg = sequential.tracker_config(ev, K, ("road", "building"))
    raster = _raster(6)
    grid = raster.grid

    def peaks(params, batch, figures, volume):  # the truth's peak on a noise floor per frame
        b, size = len(batch["tile"]), batch["tile"].shape[-1]
        n = size - 127
        out = {"pose_tile": jnp.zeros((b, 3))}
        if volume:
            vol = np.empty((b, K, n, n), np.float32)
            for i in range(b):
                cx, cy = np.asarray(batch["tile_center"][i], np.float64)
                row = round((grid.y_max - cy) / grid.resolution) - size // 2 + 64
                col = round((cx - grid.x_min) / grid.resolution) - size // 2 + 64
                f = float(batch["frame_index"][i] % 8)
                k, r, c = np.meshgrid(
                    np.arange(K), row + np.arange(n), col + np.arange(n), indexing="ij"
                )
                noise = np.sin(12.9898 * f + 78.233 * k + 37.719 * r + 4.581 * c) * 43758.5453
                vol[i] = 6.0 * (noise - np.floor(noise))  # the world cell's, per frame
                cell = np.round(geometry.pose_to_cell(batch["pose_tile"][i], K, size=n))
                cell = cell.astype(int)
                if (0 <= cell[1:]).all() and (cell[1:] < n).all():
                    vol[i, cell[0] % K, cell[1], cell[2]] += 12.0
            out["volume"] = jnp.asarray(vol)
        return out

    split, temps = _FakeSplit(raster, drive), (0.5, 2.0, 8.0)
    common = dict(cfg=cfg, odometry_cfg=_EXACT_ODOMETRY, odometry_seed=0, batch_size=1,
                  place=lambda b: b, desc="t", single=False)  # fmt: skip
    solved, sizes = [], []

    def counted(params, batch, figures, volume):
        solved.append(len(batch["tile"]))
        sizes.append(batch["tile"].shape[-1])
        return peaks(params, batch, figures, volume)

    together, _ = sequential.track_candidates(
        _FakeStep(counted), None, split, [drive], temperatures=temps, **common
    )
    one_pass, unions = sum(solved), sizes.count(256 + tracks.UNION_SPAN)
    for t, (got,) in zip(temps, together, strict=True):
        (want,), _ = sequential.track_split(
            _FakeStep(counted), None, split, [drive], temperature=t, **common
        )
        for key in ("filtered", "mean", "cov_xy", "above", "log_p_gt", "hypotheses", "scale"):
            np.testing.assert_array_equal(getattr(got, key), getattr(want, key), err_msg=key)
    assert not np.array_equal(together[0][0].log_p_gt, together[2][0].log_p_gt)
    # the candidates' windows share volumes (coinciding, or a few cells apart: a union tile)
    assert unions > 0 and one_pass < sum(solved) - one_pass, (unions, one_pass, sum(solved))


def test_windows_a_few_cells_apart_are_solved_as_one_union_tile():
    """A frame's window tiles within tracks.UNION_SPAN pixels of each other are solved as one
    larger tile; each window's volume, a crop of the union's, is the solver's on its own tile
    (to float32 rounding: another FFT size). A far window is solved on its own."""
    split, _, _, _, preset = _network_drives(frames=1)
    step = evaluation.make_localize_step(preset("tiny"), solver.SolverConfig(num_rotations=K), "gt")
    raster = split.rasters["town"]
    frame_rows = split.rows([0, 1])
    frame = _place(_stack_rows(frame_rows))
    bev = step.network(None, frame)
    window_rows, owners = [], []
    for j in (0, 1):
        base = np.array([20.0 + 7.0 * j, 250.0])  # inside the raster
        for dx, dy in ((0.0, 0.0), (1.5, -1.0), (10.0, 6.0), (-40.0, 0.0)):  # metres
            tile, centre = raster.tile(*(base + [dx, dy]))
            window_rows.append(tracks._window_row(frame_rows[j], tile, np.asarray(centre)))
            owners.append(j)
    counting = _CountingStep(step)
    kw = dict(off_road=0.0, batch_size=8, devices=1)
    temps = [1.0] * len(owners)
    united = tracks._volumes(counting, None, _place, bev, window_rows, owners, None, temps,
                             rasters=[raster] * len(owners), **kw)  # fmt: skip
    alone = tracks._volumes(step, None, _place, bev, window_rows, owners, None, temps, **kw)
    assert counting.solved_rows == [2, 2]  # the far windows, then each frame's three as one
    for a, b in zip(united, alone, strict=True):
        assert a.shape == b.shape == (K, 129, 129)
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-2)
    assert not np.allclose(united[0], united[1], atol=1.0)  # the windows' own volumes


def test_a_drive_left_in_flight_alone_is_solved_alone():
    """Drives of different lengths in lockstep: once the short one is done, the long one's
    prior tile and window tiles are solved without rows padded up to the batch size (the
    network's pass keeps its static batch)."""
    long = _straight_drive(n=5)
    short = dataclasses.replace(
        long, sequence_id="drive-1", records=long.records[:2], frame_index=long.frame_index[:2],
        timestamps=long.timestamps[:2], poses=long.poses[:2], priors=long.priors[:2],
    )  # fmt: skip
    ev = sequential.EvalConfig(
        odometry=_EXACT_ODOMETRY, tracker=sequential.TrackerSettings(hypotheses=1, off_road=0.0)
    )
    cfg = sequential.tracker_config(ev, K)
    calls = []

    def counted(params, batch, figures, volume):
        calls.append(("volume" if volume else "pose", len(batch["tile"])))
        b = len(batch["tile"])
        out = {"pose_tile": jnp.zeros((b, 3))}
        if volume:
            out["volume"] = jnp.zeros((b, K, 129, 129))
        return out

    (a, b), _ = sequential.track_split(
        _FakeStep(counted), None, _FakeSplit(_raster(2), long), [long, short], cfg=cfg,
        odometry_cfg=_EXACT_ODOMETRY, odometry_seed=0, temperature=1.0, batch_size=2,
        place=lambda b: b, desc="t",
    )  # fmt: skip
    assert [len(a.filtered), len(b.filtered)] == [5, 2]
    # a prior tile and a window tile per drive in flight: 2 frames of both, then 3 of one
    assert calls == [("pose", 2), ("volume", 2)] * 2 + [("pose", 1), ("volume", 1)] * 3


def test_each_window_of_the_bank_learns_the_odometry_scale_of_its_own_track():
    """Frames 0-9 peak at the truth (20) and, more strongly (25), at a look-alike 48 m away
    that moves at 0.9 of the car's speed; from frame 10 only the truth peaks. The look-alike's
    window leads the bank first and learns a scale of about 0.98 from its own track; the
    truth's window, exact odometry along its track, learns about 1. Once the truth's window
    leads, the drive's scale is its window's: not the look-alike's carried over."""
    drive = _straight_drive(n=20)
    wrong0 = drive.priors[0] + [15.0, -25.0]  # inside the prior box
    assert np.hypot(*(wrong0 - drive.poses[0, :2])) > 45.0

    def peaks(batch, i):
        t = int(batch["frame_index"][i])
        truth = np.asarray(batch["pose_tile"][i], np.float64)
        out = [(truth, 20.0)]
        if t < 10:
            wrong = wrong0 + 0.9 * (drive.poses[t, :2] - drive.poses[0, :2])
            off = wrong - np.asarray(batch["tile_center"][i])
            out.append((np.array([*off, truth[2]]), 40.0))
        return out

    section = sequential.TrackerSettings(
        hypotheses=2, hypothesis_prune=1000.0, lost_log_odds=0.0, lost_peak_mass=0.0, off_road=0.0
    )
    ev = sequential.EvalConfig(odometry=_EXACT_ODOMETRY, tracker=section)
    cfg = sequential.tracker_config(ev, K)
    split = _FakeSplit(_raster(5), drive)
    track = _track_one(_peaks_step(peaks), split, drive, cfg, _EXACT_ODOMETRY)
    err = np.hypot(*(track.filtered[:, :2] - drive.poses[:, :2]).T)
    assert (err[:10] > 30.0).all(), err  # the look-alike's window leads ...
    assert (track.hypotheses == 2).all()  # (nothing pruned: both windows tracked throughout)
    # ... and learns its own track's scale, (9 * 4.5 + 200) / (9 * 5 + 200) ~ 0.98
    assert track.scale[9] == pytest.approx((9 * 4.5 + 200) / (9 * 5 + 200), abs=0.004)
    lead = int(np.argmax(err < 1.0))  # the truth's window leads from here on
    assert 10 <= lead <= 12 and err[lead:].max() < 1.0, err
    # its scale: its own exact steps (~1), not the 0.98 carried over (~0.985 here)
    assert np.abs(track.scale[lead:] - 1.0).max() < 0.004, track.scale


@pytest.mark.parametrize("off_road", [0.0, 10.0])
def test_the_on_road_prior_drops_a_look_alike_off_the_road(off_road):
    """Every frame peaks at the truth (20) and, more strongly (25), at a look-alike 48 m away
    (21 m to the side of the truth's line) that moves with the car; the map's road is an 8 m
    band along the truth's track. Without the on-road prior the look-alike's window leads the
    bank throughout; with it (10 nats a frame off the road) the truth's window leads from the
    first frame."""
    drive = _straight_drive(n=12)
    wrong0 = drive.priors[0] + [15.0, -25.0]  # inside the prior box
    heading = np.array([math.cos(drive.poses[0, 2]), math.sin(drive.poses[0, 2])])
    side = wrong0 - drive.poses[0, :2]
    assert abs(side[0] * heading[1] - side[1] * heading[0]) > 20.0  # far off the band

    grid = geometry.RasterGrid(x_min=-100.0, y_max=200.0, height=800, width=800)
    x = grid.x_min + (np.arange(grid.width) + 0.5) * grid.resolution
    y = grid.y_max - (np.arange(grid.height) + 0.5) * grid.resolution
    dx, dy = x[None, :] - drive.poses[0, 0], y[:, None] - drive.poses[0, 1]
    mask = np.zeros((2, grid.height, grid.width), np.uint8)
    mask[0] = np.abs(dx * heading[1] - dy * heading[0]) <= 4.0  # the road: the truth's line
    raster = maps.CityRaster(mask, grid, ("road", "building"), "town")

    def peaks(batch, i):
        t = int(batch["frame_index"][i])
        truth = np.asarray(batch["pose_tile"][i], np.float64)
        wrong = wrong0 + (drive.poses[t, :2] - drive.poses[0, :2])
        off = wrong - np.asarray(batch["tile_center"][i])
        return [(truth, 20.0), (np.array([*off, truth[2]]), 25.0)]

    section = sequential.TrackerSettings(
        hypotheses=2,
        hypothesis_prune=1000.0,
        lost_log_odds=0.0,
        lost_peak_mass=0.0,
        off_road=off_road,
    )
    ev = sequential.EvalConfig(odometry=_EXACT_ODOMETRY, tracker=section)
    cfg = sequential.tracker_config(ev, K)
    assert cfg.off_road == off_road
    split = _FakeSplit(raster, drive)
    track = _track_one(_peaks_step(peaks), split, drive, cfg, _EXACT_ODOMETRY)
    err = np.hypot(*(track.filtered[:, :2] - drive.poses[:, :2]).T)
    if off_road:
        assert err.max() < 1.0, err
    else:
        assert (err > 45.0).all(), err
    assert (track.hypotheses == 2).all()  # both windows tracked either way


def test_a_null_on_road_prior_is_derived_from_the_maps_channels():
    ev = sequential.EvalConfig()  # the app's default: null
    assert ev.tracker.off_road is None
    assert (
        sequential.tracker_config(ev, K, ("road", "building")).off_road == seq_config.OFF_ROAD_NATS
    )
    assert sequential.tracker_config(ev, K, ("building",)).off_road == 0.0  # no road to keep to
    with pytest.raises(ValueError, match="eval.tracker.off_road is null"):
        sequential.tracker_config(ev, K)
    given = sequential.EvalConfig(tracker=sequential.TrackerSettings(off_road=2.5))
    assert sequential.tracker_config(given, K, ("building",)).off_road == 2.5  # checked later


def test_the_on_road_prior_needs_a_road_channel():
    raster = _raster()
    raster = maps.CityRaster(raster.mask[1:], raster.grid, ("building",), "town")
    cfg = tr.TrackerConfig(num_rotations=K, off_road=3.0)
    with pytest.raises(ValueError, match="off_road = 3.0 needs a 'road' channel.*'town'"):
        seq_config.road_channels({"town": raster}, cfg)
    assert seq_config.road_channels({"town": raster}, tr.TrackerConfig(num_rotations=K)) is None


def _peak_step(peak_of, sizes=None):
    """:func:`_peaks_step` with one peak of score 20 per row, at ``peak_of(batch, i)``."""
    return _peaks_step(lambda batch, i: [(peak_of(batch, i), 20.0)], sizes)


_EXACT_ODOMETRY = tr.OdometryConfig(
    scale_sigma=0.0, yaw_bias_sigma=0.0, yaw_scale_sigma=0.0, yaw_sigma=0.0
)


@pytest.mark.parametrize("hypotheses", [1, 3])
def test_a_locked_drive_narrows_to_the_tracking_window(hypotheses):
    """Every frame peaks at the truth: the drive tracks it in the 129-cell window (the bank's
    windows first), narrows to the 65-cell tracking window once its box has held NARROW_MASS
    for NARROW_FRAMES frames with one window left (drive_filter), and tracks on in it (its
    tile 192 px)."""
    drive = _straight_drive(n=14)
    ev = sequential.EvalConfig(
        odometry=_EXACT_ODOMETRY,
        tracker=sequential.TrackerSettings(track_size=65, hypotheses=hypotheses, off_road=0.0),
    )
    cfg = sequential.tracker_config(ev, K)
    sizes = []
    step = _peak_step(lambda batch, i: np.asarray(batch["pose_tile"][i], np.float64), sizes)
    track = _track_one(step, _FakeSplit(_raster(3), drive), drive, cfg, _EXACT_ODOMETRY)
    err = np.hypot(*(track.filtered[:, :2] - drive.poses[:, :2]).T)
    assert err.max() < 1.0, err
    assert not track.lost[2:].any()
    first = int(np.argmax(track.narrowed))  # the first frame in the tracking window
    assert track.narrowed[first:].all() and first >= drive_filter.NARROW_FRAMES
    assert (track.hypotheses[first - drive_filter.NARROW_FRAMES : first] == 1).all()
    assert set(sizes) == {129}  # every frame localized on the full tile


def test_a_loss_in_the_tracking_window_widens_it_and_recovers():
    """From frame 12 on every frame peaks 12 m to the side of the truth (inside the 65-cell
    window, 24 cells off the filter's mode): the narrow filter detects the loss, resets the
    129-cell window around its estimate with the frame's whole volume (on the new peak at
    once), and narrows again."""
    drive = _straight_drive(n=30)
    side = 12.0 * np.array([-math.sin(drive.poses[0, 2]), math.cos(drive.poses[0, 2])])

    def peak(batch, i):
        p = np.asarray(batch["pose_tile"][i], np.float64)
        if int(batch["frame_index"][i]) >= 12:
            p[:2] += side
        return p

    # floor 0: no prior mass where the peak jumps to, so the belief cannot simply follow it.
    section = sequential.TrackerSettings(track_size=65, hypotheses=1, floor=0.0, off_road=0.0)
    ev = sequential.EvalConfig(odometry=_EXACT_ODOMETRY, tracker=section)
    cfg = sequential.tracker_config(ev, K)
    track = _track_one(_peak_step(peak), _FakeSplit(_raster(4), drive), drive, cfg, _EXACT_ODOMETRY)
    assert track.narrowed[8:12].all()  # locked and narrow before the jump
    lost = np.flatnonzero(track.lost)
    assert lost.size == 1 and 12 <= lost[0] <= 14, lost
    assert not track.narrowed[lost[0]]  # widened at once
    assert track.narrowed[-1]  # and narrow again
    moved = drive.poses[:, :2] + side
    assert np.hypot(*(track.filtered[lost[0] :, :2] - moved[lost[0] :]).T).max() < 1.0


def test_the_tracking_windows_likelihood_is_the_centre_of_its_tiles_volume():
    """A tracking-window frame is localized on the full tile around its window centre (the tile
    the network was trained on, every variant); the window's cell of a pose is that volume's
    cell of it, 32 cells in, so the window's likelihood is the volume's centre."""
    raster = _raster()
    cfg = tr.TrackerConfig(num_rotations=K, track_size=65)
    narrow_cfg = cfg.tracking_window()
    belief, _ = tr.narrow(sequential.start_belief(raster, (-20.3, 130.7), cfg), cfg, narrow_cfg)
    tile, centre = sequential.filter_tile(raster, belief, cfg)
    assert tile.shape[-1] == 256
    np.testing.assert_allclose(centre, tr.window_centre(belief, narrow_cfg))
    volume = np.random.default_rng(0).normal(size=(K, 129, 129)).astype(np.float32)
    window, log_mean = tr.crop_likelihood(jnp.asarray(volume), narrow_cfg)
    window = np.asarray(window)
    want = np.log(np.mean(np.exp(volume.astype(np.float64))))
    assert float(log_mean) == pytest.approx(want, abs=1e-4)  # the full window's
    rng = np.random.default_rng(1)
    for _ in range(20):
        pose = np.array([*(centre + rng.uniform(-15.0, 15.0, 2)), rng.uniform(-np.pi, np.pi)])
        in_tile = np.array([*(pose[:2] - centre), pose[2]])
        full = np.round(geometry.pose_to_cell(in_tile, K, size=129)).astype(int)
        cell = np.asarray(drive_filter._gt_cell(belief, pose, narrow_cfg))
        np.testing.assert_array_equal(cell[1:], full[1:] - 32)
        k = full[0] % K
        assert window[k, cell[1], cell[2]] == volume[k, full[1], full[2]]


# --------------------------------------------------------------------------- the network, once


class _SensorSplit:
    """Drives over one raster whose rows carry a network's inputs (synthetic sensors, cycled)
    and the stored prior's tile: what a DriveSplit gives the localize step."""

    name = "sensors"

    def __init__(self, raster, drives, sensors, nm_raster=None):
        self.rasters = {raster.name: raster}
        self.nm_rasters = None if nm_raster is None else {raster.name: nm_raster}
        self.frames = {int(r): (d, t) for d in drives for t, r in enumerate(d.records)}
        self.sensors = sensors

    def rows(self, indices):
        out = []
        for i in indices:
            drive, t = self.frames[int(i)]
            tile, centre = self.rasters[drive.city].tile(*drive.priors[t])
            pose = drive.poses[t]
            row = {k: v[int(i) % len(v)] for k, v in self.sensors.items()}
            row.update(
                tile=tile.astype(np.float32),
                tile_center=np.asarray(centre, np.float64),
                pose_tile=np.array([*(pose[:2] - centre), pose[2]], np.float32),
                pose=pose,
                frame_index=np.int64(t),
            )
            if self.nm_rasters is not None:
                row["nm_tile"] = self.nm_rasters[drive.city].tile(*centre)[0]
            out.append(row)
        return out


class _CountingStep:
    """The localize step, counting the rows each network pass and each solve got."""

    def __init__(self, step):
        self.step, self.network_rows, self.solved_rows = step, [], []

    def network(self, params, batch):
        self.network_rows.append(len(batch["tile"]))
        return self.step.network(params, batch)

    def solve(self, params, bev, batch, rows=None, **kw):
        self.solved_rows.append(len(batch["tile"]))
        return self.step.solve(params, bev, batch, rows, **kw)


class _PerTileStep:
    """The path before the network ran once per frame: the whole step (network and solver) for
    every tile, on the frame's row with that tile."""

    def __init__(self, step):
        self.step = step

    def network(self, params, batch):
        return batch  # nothing runs yet

    def solve(self, params, bev, batch, rows=None, *, figures=False, volume=False):
        frame = bev if rows is None else {k: v[np.asarray(rows)] for k, v in bev.items()}
        return self.step(params, {**frame, "tile": batch["tile"]}, figures=figures, volume=volume)


def _class_raster(seed=0):
    """A random 9-channel stand-in for the OSM class raster, on another grid than
    :func:`_raster`'s (larger; corners on the same 0.5 m lattice)."""
    mask = (np.random.default_rng(seed).random((9, 760, 640)) > 0.7).astype(np.uint8)
    grid = geometry.RasterGrid(x_min=-143.5, y_max=471.0, height=760, width=640)
    return maps.CityRaster(mask, grid, maps.OSM_CLASS_NAMES, "town")


def _network_drives(frames=4, nm=False):
    """Two drives over one raster with a tiny network's inputs: the split, its drives, the
    network's parameters and the preset; ``nm``: the rows also carry ``nm_tile``."""
    from seglocnet_jax.model import api, synthetic
    from seglocnet_jax.model.config import preset

    raster = _raster(5)
    drives = []
    for d in range(2):
        drive = _straight_drive(n=frames)
        drive.sequence_id, drive.records = f"drive-{d}", drive.records + frames * d
        drive.poses[:, :2] += [10.0 * d, -8.0 * d]
        drive.priors = drive.poses[:, :2] + [6.0, -4.0 + 3 * d]
        drives.append(drive)
    sensors = synthetic.make_batch(0, 4, num_cams=2, image_hw=(32, 64), num_points=2048)
    keys = ("images", "intrinsics", "cam_to_ego", "points", "points_mask", "bev_gt")
    split = _SensorSplit(
        raster, drives, {k: sensors[k] for k in keys}, _class_raster() if nm else None
    )
    example = {k: np.asarray(v)[:1] for k, v in _stack_rows(split.rows([0])).items()}
    return split, drives, example, api, preset


def _place(batch):
    return {k: jnp.asarray(v) for k, v in batch.items() if k not in BATCH_METADATA_KEYS}


def test_the_network_runs_once_per_frame_and_the_tracks_are_the_per_tile_ones():
    """Two drives in lockstep through the default filter (a bank of windows, the tracking
    window, the on-road prior) with a (random) tiny network: one network pass per lockstep
    step covers every drive's frame, and the solver matches that BEV against every window's
    tile and the prior tile; the tracks equal those of the network rerun for every tile."""
    split, drives, example, api, preset = _network_drives()
    params = api.init(jax.random.key(0), example, preset("tiny"))
    step = evaluation.make_localize_step(preset("tiny"), solver.SolverConfig(num_rotations=K))
    raster = split.rasters["town"]
    cfg = sequential.tracker_config(sequential.EvalConfig(), K, raster.channels)

    def run(s):
        out, _ = sequential.track_split(
            s, params, split, drives, cfg=cfg, odometry_cfg=tr.OdometryConfig(),
            odometry_seed=0, temperature=2.0, batch_size=2, place=_place, desc="net",
        )  # fmt: skip
        return out

    counting = _CountingStep(step)
    once = run(counting)
    assert counting.network_rows == [2] * 4  # a pass per lockstep step: both drives' frame
    windows = sum(counting.solved_rows) - 2 * 4  # beyond the prior tiles
    assert windows > 2 * 4 and [len(t.filtered) for t in once] == [4, 4]
    assert max(t.hypotheses.max() for t in once) > 1  # a bank: several tiles per frame
    per_tile = run(_PerTileStep(step))
    for a, b in zip(once, per_tile, strict=True):
        for key in ("filtered", "single", "mean", "cov_xy", "above", "log_p_gt", "scale"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
        for key in ("lost", "narrowed", "hypotheses"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


def test_nm_matches_the_frames_bev_features_against_each_tiles_neural_map():
    """SegLocNet-NM through the split step: the BEV matching features of a frame (network once)
    against the neural map of other tiles (the map side per tile) give the volumes of the whole
    network run on the frame's row with each tile."""
    split, drives, example, api, preset = _network_drives(frames=1, nm=True)
    model_cfg = dataclasses.replace(preset("tiny"), variant="nm")
    params = api.init(jax.random.key(0), example, model_cfg)
    # the initial projections are zero (all-zero features): bend every parameter
    params = jax.tree.map(
        lambda x: x + 0.05 * jnp.sin(1.7 * jnp.arange(x.size)).reshape(x.shape), params
    )
    step = evaluation.make_localize_step(model_cfg, solver.SolverConfig(num_rotations=K))
    frame = _place(_stack_rows(split.rows([0, 1])))  # drive 0's and drive 1's first frames
    tiles = {k: frame[k][::-1] for k in ("tile", "nm_tile")}  # against the other frame's tile
    assert step.reads_nm_tile
    rows = np.array([1, 0])
    got = step.solve(params, step.network(params, frame), tiles, rows, volume=True)
    want = step(params, {**{k: v[rows] for k, v in frame.items()}, **tiles}, volume=True)
    # Two XLA programs: equal up to float32 rounding (bit-equal on the Intel machine; on an AMD
    # EPYC 0.9 % of the cells differ, by at most 3e-7 relative)
    np.testing.assert_allclose(got["volume"], want["volume"], rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(got["pose_tile"], want["pose_tile"], rtol=0, atol=1e-3)
    assert not np.array_equal(got["volume"][0], got["volume"][1])


def test_nm_window_rows_carry_the_class_tile_at_the_window_centre():
    """The filter's window tiles for an NM model: beside the map tile, the OSM class raster's
    tile around the same centre (another grid, the same lattice); a seg model's rows have none."""
    raster, classes = _raster(2), _class_raster(3)
    cfg = sequential.tracker_config(sequential.EvalConfig(), K, raster.channels)
    belief = drive_filter.start_belief(raster, np.array([31.3, 52.8]), cfg)
    tile, centre = drive_filter.filter_tile(raster, belief, cfg)
    frame = {"pose": np.array([30.0, 50.0, 0.3]), "frame_index": np.int64(0), "city": "town"}
    row = tracks._window_row(frame, tile, centre, {"town": classes})
    want, at = classes.tile(*centre)
    assert at == tuple(centre) and row["nm_tile"].shape == (9, 256, 256)
    np.testing.assert_array_equal(row["nm_tile"], want)
    np.testing.assert_array_equal(row["tile"], raster.tile(*centre)[0])
    assert "nm_tile" not in tracks._window_row(frame, tile, centre)


def _stack_rows(rows):
    return {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


# --------------------------------------------------------------------------- read-outs


def test_streamed_temperature_fit_matches_the_in_memory_fit():
    rng = np.random.default_rng(0)
    volumes = rng.normal(0.0, 10.0, (400, 4, 9, 9)).astype(np.float32)
    logits = volumes.reshape(400, -1) / 4.0  # generated at T = 4
    p = np.exp(logits - logits.max(1, keepdims=True))
    p /= p.sum(1, keepdims=True)
    flat = np.array([rng.choice(p.shape[1], p=row) for row in p])
    cells = np.stack(np.unravel_index(flat, (4, 9, 9)), axis=1)
    fit = sequential.TemperatureFit()
    whole = sequential.TemperatureFit(window_points=len(temperature.TEMPERATURE_GRID))
    for i in range(0, 400, 64):  # batch by batch; padding rows weigh 0
        v, c = volumes[i : i + 64], cells[i : i + 64]
        for f in (fit, whole):
            f.add(np.concatenate([v, v[:3]]), np.concatenate([c, c[:3]]), [1] * len(c) + [0] * 3)
    assert fit.count == 400
    # after the first batch, 25 of the 57 grid points; the same fit as the whole grid's
    assert len(range(57)[fit.window]) == 2 * temperature.WINDOW_POINTS + 1 == 25
    assert fit.result() == whole.result() and not fit.at_edge
    # each batch's rows in parts side by side (a thread per core): one program's values
    log_t = np.log(temperature.TEMPERATURE_GRID[:9])
    one = temperature._objective(jnp.asarray(volumes[:5]), jnp.asarray(cells[:5]), log_t)
    parts = temperature._row_objectives(volumes[:5], cells[:5], log_t)
    np.testing.assert_array_equal(parts, np.asarray(one, np.float64))
    # the objective on a fine grid, all frames at once (float64)
    grid = np.geomspace(1.0, 16.0, 400)
    flat_v = volumes.reshape(400, -1).astype(np.float64)
    gt = flat_v[np.arange(400), flat]
    objective = [
        np.mean(
            gt / t
            - np.log(np.exp(flat_v / t - (flat_v / t).max(1, keepdims=True)).sum(1))
            - (flat_v / t).max(1)
        )
        for t in grid
    ]
    in_memory = grid[int(np.argmax(objective))]
    assert abs(fit.result() / in_memory - 1) < 0.03, (fit.result(), in_memory)
    assert abs(fit.result() / 4.0 - 1) < 0.15


def test_a_temperature_fit_beyond_the_first_batchs_window_is_flagged_at_its_edge():
    """The first batch peaks at T = 1, the rest (many more frames) at T = 1,000: the fit ends
    on the window's edge (+-1.5 decades around 1) and says so, as on the grid's edge."""
    rng = np.random.default_rng(1)

    def frames(n, t):  # volumes whose GT cell is drawn from softmax(volume / t)
        v = rng.normal(0.0, 10.0, (n, 4, 9, 9)).astype(np.float32)
        p = np.exp(v.reshape(n, -1) / t - (v.reshape(n, -1) / t).max(1, keepdims=True))
        flat = [rng.choice(p.shape[1], p=row / row.sum()) for row in p]
        return v, np.stack(np.unravel_index(flat, (4, 9, 9)), axis=1)

    fit = sequential.TemperatureFit()
    fit.add(*frames(64, 1.0))
    for _ in range(8):
        fit.add(*frames(64, 1000.0))
    t = fit.result()
    assert fit.at_edge and 20.0 < t < 40.0, t  # 10**1.5 = 31.6: the window's last point


def _readout(beliefs, log_w, pose, cfg):
    """The credible mass and log p of the GT pose, as the lockstep loop reads them out."""
    cells = [drive_filter._gt_cell(b, pose, cfg) for b in beliefs]
    return tr.hypotheses.mixture_readout(beliefs, log_w, cells, cfg, drive_filter.LOG_P_FLOOR_P)


def test_readout_credible_mass_is_the_credible_region_test():
    cfg = tr.TrackerConfig(num_rotations=4, size=9, bev_size=8)
    prob = np.random.default_rng(0).random((4, 9, 9)) ** 4
    prob = (prob / prob.sum()).astype(np.float32)
    belief = tr.init_belief(cfg, (0.0, 0.0))._replace(prob=jnp.asarray(prob))
    for cell in [(0, 4, 4), (1, 0, 8), (3, 7, 2), (2, 5, 5)]:
        pose = tr.cell_to_world(belief, np.array(cell, np.float32), cfg)
        above, log_p = _readout([belief], [0.0], pose, cfg)
        for mass in (0.5, 0.9, 0.99):
            assert bool(above < mass) == bool(tr.in_credible_region(belief, np.array(cell), mass))
        want = max(math.log(float(prob[cell])), drive_filter.LOG_P_FLOOR)
        assert float(log_p) == pytest.approx(want, abs=1e-5)
    outside = tr.cell_to_world(belief, np.array([0.0, 4.0, 20.0], np.float32), cfg)
    above, log_p = _readout([belief], [0.0], outside, cfg)
    assert math.isinf(float(above)) and float(log_p) == pytest.approx(drive_filter.LOG_P_FLOOR)


def test_readout_of_a_bank_is_the_mixtures():
    """Two windows 100 m apart with weights 0.3 / 0.7: the credible mass and log p of a GT in
    either are those of the mixture over the union of their cells."""
    cfg = tr.TrackerConfig(num_rotations=4, size=9, bev_size=8)
    rng = np.random.default_rng(3)
    probs = [rng.random((4, 9, 9)) ** 4 for _ in range(2)]
    probs = [(p / p.sum()).astype(np.float32) for p in probs]
    beliefs = [
        tr.init_belief(cfg, xy)._replace(prob=jnp.asarray(p))
        for xy, p in zip([(0.0, 0.0), (100.0, 0.0)], probs, strict=True)
    ]
    weights = np.array([0.3, 0.7])
    union = np.concatenate([w * p.ravel() for w, p in zip(weights, probs, strict=True)])
    for b, cell in [(0, (1, 2, 3)), (1, (3, 4, 4)), (1, (0, 8, 1))]:
        pose = tr.cell_to_world(beliefs[b], np.array(cell, np.float32), cfg)
        above, log_p = _readout(beliefs, np.log(weights) + 5.0, pose, cfg)  # unnormalized
        p = weights[b] * probs[b][cell]
        assert above == pytest.approx(union[union > p].sum(), abs=1e-6)
        assert log_p == pytest.approx(math.log(p), abs=1e-5)


def test_readout_mode_is_the_solvers_refined_peak():
    """The filtered pose: the posterior's mode refined like the solver refines a volume's peak
    (here a volume whose peak is off the window's border and on it)."""
    cfg = tr.TrackerConfig(num_rotations=8, size=9, bev_size=8)
    rng = np.random.default_rng(1)
    for peak in [(3, 4, 5), (0, 0, 6), (7, 8, 2)]:
        logp = rng.normal(0.0, 0.3, (8, 9, 9))
        logp[peak] = 3.0
        prob = np.exp(logp) / np.exp(logp).sum()
        belief = tr.init_belief(cfg, (10.0, 20.0))._replace(prob=jnp.asarray(prob, jnp.float32))
        mode = tr.estimate(belief, cfg)["map_cell"]
        np.testing.assert_array_equal(mode, peak)
        pose = drive_filter._readout(belief, mode, cfg)
        cell, _ = solver.decode_cell(jnp.log(jnp.asarray(prob, jnp.float32)))
        want = tr.cell_to_world(belief, cell, cfg)
        np.testing.assert_allclose(pose[:2], want[:2], atol=1e-4)
        assert abs(geometry.angle_error(float(pose[2]), float(want[2]))) < 1e-5


def test_summary_follows_the_documented_definitions():
    n = 30
    drive = _straight_drive(n)
    err = np.full(n, 0.5)
    err[:3] = 12.0  # converges at frame 3
    err[10:22] = 7.0  # a 12-frame lost run (> 10): the drive was lost
    filtered = drive.poses.copy()
    filtered[:, 0] += err  # off the truth by err
    lost = np.zeros(n, bool)
    lost[[11, 25]] = True  # a real loss (recovered at 22) and a false alarm (on track)
    track = sequential.Track(
        drive=drive,
        filtered=filtered,
        single=drive.poses,
        mean=filtered,
        cov_xy=np.tile(np.eye(2), (n, 1, 1)),
        above=np.where(err < 1.0, 0.3, np.inf),
        log_p_gt=np.where(err < 1.0, -2.0, -5.0),
        lost=lost,
        narrowed=np.arange(n) >= 21,
        hypotheses=np.where(np.arange(n) < 4, 3, 1),
        scale=np.full(n, 1.01),
    )
    s = sequential.summarize([track])
    d = s["per_drive"][0]
    assert d["frames_to_converge"] == 22 and d["metres_to_converge"] == pytest.approx(110.0)
    assert d["longest_lost_run"] == 12 and d["lost_episodes"] == 2
    assert d["lost_episodes_detected"] == 1  # frames 0-2 were never flagged
    assert d["losses_detected"] == 2 and d["losses_recovered"] == 1  # 11 within 10 frames: no
    assert s["tracked_pct"] == pytest.approx(100 * 15 / 30)
    assert s["drives_never_lost_pct"] == 0.0
    assert s["mean_log_p_gt"] == pytest.approx((-2.0 * 15 - 5.0 * 15) / 30)
    assert s["coverage"]["0.5"] == s["coverage_90"] == pytest.approx(100 * 15 / 30)
    assert s["filtered"]["count"] == s["single"]["count"] == n
    assert d["frames_narrowed"] == 9 and s["narrowed_pct"] == pytest.approx(30.0)
    assert d["frames_multi_hypothesis"] == 4 and d["odometry_scale"] == 1.01
    assert s["hypotheses_mean"] == pytest.approx((4 * 3 + 26) / 30)
    assert s["single"]["APE"] == 0.0 and s["filtered"]["APE"] == pytest.approx(err.mean())


# --------------------------------------------------------------------------- the apps


@pytest.fixture(scope="module")
def data_root(drives_data_root):
    return drives_data_root


def _tree(data_root, **eval_):
    return app_tree(
        data_root,
        "seq_test",
        TINY_DRIVES,
        eval_={
            "mode": "sequential",
            "splits": ["test"],
            **DRIVES_EVAL,
            "batch_size": 2,
            "num_figures": 1,
            "max_batches": 1,
            **eval_,
        },
    )


def test_gt_drives_are_tracked_through_the_evaluate_app(data_root, tmp_path, capsys):
    # With one window (not the default bank) and the tracking window (on by default): the
    # app's path through both windows (129 cells -> 65 cells) within the short drives.
    # With a given on-road prior (null by default: derived from the map).
    tracker = {"hypotheses": 1, "off_road": 5.0}
    cfg = build_experiment(_tree(data_root, bev_source="gt", tracker=tracker))
    assert cfg.eval.tracker.hypotheses == 1 and cfg.eval.tracker.track_size == 65
    assert cfg.eval.tracker.off_road == 5.0
    key = (cfg.model, cfg.solver, "gt", "volume", "rows")  # the solver of the windows' tiles
    before = evaluation.TRACE_COUNTS.get(key, 0)
    workdir = str(tmp_path / "gt")
    assert eval_run.run_evaluation(cfg, None, workdir) == {}  # no single-frame splits
    out = capsys.readouterr().out
    saved = json.load(open(os.path.join(workdir, "results.json")))
    assert saved["splits"] == {}
    s = saved["sequential"]["drives_val"]
    assert s["drives"] == 2 and s["frames"] == s["filtered"]["count"] == s["single"]["count"]
    assert s["off_road"] == 5.0  # the on-road prior it ran with
    # The GT BEV makes a near-perfect likelihood: the filter tracks every frame.
    assert s["tracked_pct"] == 100.0 and s["filtered"]["R@2m"] == 100.0
    assert s["filtered"]["APE"] < 1.0 and s["filtered"]["R@5deg"] == 100.0
    assert s["drives_not_converged"] == 0 and s["losses_detected"] == 0
    # Fitted on val single frames (eval.max_batches=1 batch of eval.batch_size=2), then chosen
    # on the drives_val drives among T_single x eval.temperature_scales.
    fit = s["temperature_fit"]
    assert {k: fit[k] for k in ("split", "frames", "at_grid_edge")} == {
        "split": "val",
        "frames": 2,
        "at_grid_edge": False,
    }
    table = fit["filter"]["candidates"]
    assert fit["filter"]["split"] == "drives_val" and len(table) == 4
    assert [row["scale"] for row in table] == [1.0, 4.0, 16.0, 64.0]
    for row in table:
        assert row["temperature"] == pytest.approx(fit["single_frame"] * row["scale"])
    best = max(table, key=lambda row: row["mean_log_p_gt"])
    assert s["temperature"] == best["temperature"]
    edge = best["temperature"] in (table[0]["temperature"], table[-1]["temperature"])
    assert fit["filter"]["at_scale_edge"] == edge
    assert ("is at the edge of eval.temperature_scales" in out) == edge
    assert s["mean_log_p_gt"] <= 0.0
    assert set(s["coverage"]) == {f"{m:g}" for m in sequential.MASSES}
    assert s["filter_ms_per_frame"] > 0 and sum(d["frames"] for d in s["per_drive"]) == s["frames"]
    assert s["score_ms_per_frame"] > 0  # the GT's read-out, timed apart from the filter's
    assert s["compile_ms_per_frame"] >= 0  # later compilations, timed apart
    # Two solver programs for every frame's windows: the batch of 256-pixel tiles (the tracking
    # window's frames too: the centre of their volume), and that of the 288-pixel union tiles
    # of the temperature candidates' windows a few cells apart.
    assert evaluation.TRACE_COUNTS[key] - before == 2
    assert all(d["frames_narrowed"] >= 1 for d in s["per_drive"]) and s["narrowed_pct"] > 0
    assert "in tracking window (%)" in out and "acquisition" not in out
    assert "seq_test [hd_road-building, gt] drives_val filtered" in out
    assert "GT in 90% region (%)" in out and "[seglocnet] sequential evaluation:" in out
    figures = sorted(os.listdir(os.path.join(workdir, "figures", "sequential")))
    assert figures == [
        "calibration.png",
        "drives_val_error_vs_distance.png",
        "drives_val_helsinki-drives_val-d000.png",
    ]
    arrays = np.load(os.path.join(workdir, "sequential", "drives_val.npz"))
    assert arrays["filtered"].shape == (s["frames"], 3)
    # drives_val is the temperature drives: the candidates' pass at the chosen T made its
    # tracks (single-frame poses too); they are what a run at that T alone makes (to float32
    # rounding: the candidates' windows a few cells apart are solved as one union tile, whose
    # FFT size differs; every decision is the same).
    assert s["tracked_in_temperature_pass"]
    again = build_experiment(_tree(data_root, bev_source="gt", tracker=tracker,
                                   temperature=s["temperature"]))  # fmt: skip
    eval_run.run_evaluation(again, None, str(tmp_path / "fixed"))
    fixed = np.load(os.path.join(tmp_path, "fixed", "sequential", "drives_val.npz"))
    assert not json.load(open(tmp_path / "fixed" / "results.json"))["sequential"]["drives_val"][
        "tracked_in_temperature_pass"
    ]
    assert sorted(fixed.files) == sorted(arrays.files)
    for name in arrays.files:
        if arrays[name].dtype.kind == "f":
            np.testing.assert_allclose(
                fixed[name], arrays[name], rtol=1e-4, atol=1e-4, err_msg=name
            )
        else:
            np.testing.assert_array_equal(fixed[name], arrays[name], err_msg=name)


def test_the_train_app_reports_single_frames_and_drives(data_root, tmp_path, capsys):
    # With a bank of windows (tracking.hypotheses): the app's path through several windows.
    # No pruning: every part of frame 0's box the first window leaves out gets a window.
    tracker = {"hypotheses": 3, "hypothesis_prune": 1e4}
    tree = _tree(data_root, mode="both", temperature=200.0, tracker=tracker)
    cfg = build_experiment(tree)
    assert cfg.eval.tracker.hypotheses == 3
    workdir = str(tmp_path / "run")
    results = train_run.train_and_evaluate(cfg, workdir)
    out = capsys.readouterr().out
    saved = json.load(open(os.path.join(workdir, "results.json")))
    assert set(results) == set(saved["splits"]) == {"test"}  # single-frame, as before
    s = saved["sequential"]["drives_val"]
    assert s["temperature"] == 200.0 and s["temperature_fit"] is None
    # The on-road prior, null by default: derived from the map's road channel.
    assert cfg.eval.tracker.off_road is None and s["off_road"] == seq_config.OFF_ROAD_NATS
    assert s["filtered"]["count"] == s["single"]["count"] == s["frames"] > 0
    assert "| seq_test [hd_road-building, tiny-seg] test |" in out
    assert "| seq_test [hd_road-building, tiny-seg] drives_val filtered |" in out
    # The final evaluation's phases, printed and saved: single frames, then each drive split
    # (the temperature is given: no fit to time).
    t = saved["time"]  # each figure rounded to 0.1 s: nested phases may differ by that much
    assert t["single_frame_s"] + t["sequential_s"] <= t["final_evaluation_s"] + 0.2
    assert s["seconds"] <= t["sequential_s"] + 0.1
    assert (
        f"(single-frame {t['single_frame_s']:.0f} s, sequential {t['sequential_s']:.0f} s: "
        f"drives_val {s['seconds']:.0f} s)" in out
    )
    lines = [json.loads(ln) for ln in open(os.path.join(workdir, "metrics.jsonl"))]
    assert {"test", "drives_val_sequential"} <= {ln["split"] for ln in lines}
    # Frame 0 split into windows; the count per frame is saved and printed.
    arrays = np.load(os.path.join(workdir, "sequential", "drives_val.npz"))
    assert arrays["hypotheses"].shape == (s["frames"],) and arrays["hypotheses"].max() <= 3
    assert s["hypotheses_mean"] == pytest.approx(arrays["hypotheses"].mean())
    first = arrays["frame_index"] == arrays["frame_index"].min()
    assert (arrays["hypotheses"][first] > 1).any()
    assert "windows per frame" in out
    # The odometry scale estimate (eval.tracker.scale_prior_m, on by default) per frame.
    assert cfg.eval.tracker.scale_prior_m == 200.0
    assert arrays["scale"].shape == (s["frames"],) and (np.abs(arrays["scale"] - 1) <= 0.05).all()
    assert [d["odometry_scale"] for d in s["per_drive"]] == [
        arrays["scale"][arrays["sequence_id"] == d["sequence_id"]][-1] for d in s["per_drive"]
    ]


@pytest.mark.parametrize(
    "override, key",
    [
        ({"sequential_splits": ["drives"]}, "eval.sequential_splits: split 'drives'"),
        ({"calibration_split": "kouvola"}, "eval.calibration_split: split 'kouvola'"),
        ({"temperature_split": "nowhere"}, "eval.temperature_split: split 'nowhere'"),
        ({"temperature_drives": "kouvola"}, "eval.temperature_drives: split 'kouvola'"),
        ({"temperature_scales": [4.0, 1.0]}, "eval.temperature_scales"),
        ({"temperature_scales": [0.0, 1.0]}, "eval.temperature_scales"),
        ({"tracker": {"acquire_size": 257}}, "eval.tracker.acquire_size"),  # deleted: unknown
        ({"tracker": {"sigma_xy": 0.1}}, "eval.tracker.sigma_xy"),  # from eval.odometry only
        ({"tracker": {"track_size": 64}}, "track_size"),
        ({"mode": "video"}, "eval.mode"),
        ({"temperature": -1.0}, "eval.temperature"),
        ({"max_drives": 0}, "eval.max_drives"),
        ({"tracker": {"off_road": -2.0}}, "off_road must be >= 0"),
        ({"tracker": {"floor": 1.0}}, "eval.tracker"),
        ({"tracker": {"num_rotations": 8}}, "eval.tracker.num_rotations"),
        ({"odometry": {"yaw_sigma": -1.0}}, "odometry.yaw_sigma"),
    ],
)
def test_sequential_config_errors_name_the_key(data_root, override, key):
    with pytest.raises((ConfigError, ValueError)) as err:
        build_experiment(_tree(data_root, **override))
    assert key in str(err.value)
    # A split the dataset lacks is fine when nothing sequential runs, or when T is fixed.
    if "sequential_splits" in override or "calibration_split" in override:
        build_experiment(_tree(data_root, mode="single", **override))
    if "temperature_split" in override or "temperature_drives" in override:
        build_experiment(_tree(data_root, temperature=5.0, **override))


def test_the_on_road_prior_without_a_road_channel_is_a_config_error(data_root):
    tree = _tree(data_root, tracker={"off_road": 3.0})
    tree["map"]["channels"] = ["building"]
    want = r"eval.tracker.off_road=3.0 .*map.channels=\['building'\]"
    with pytest.raises(ConfigError, match=want):
        build_experiment(tree)
    tree["eval"]["tracker"]["off_road"] = 0.0  # off: the map's channels are not read
    build_experiment(tree)
    del tree["eval"]["tracker"]["off_road"]  # null, the default: 0 without a road channel
    assert build_experiment(tree).eval.tracker.off_road is None


# --------------------------------------------------------------------------- real data


def _convert_nuscenes(tmp_path):
    root = str(tmp_path / "nuscenes")
    fx.write_nuscenes(root)
    osm = str(tmp_path / "boston.osm")
    fx.write_osm(osm, maps.Projection.topocentric(*nu.MAP_ORIGINS["boston-seaport"]).to_lonlat)
    reader = nu.NuScenesReader(
        nu.NuScenesConfig(dataroot=root, version="v1.0-mini", image_size=(12, 20))
    )
    cfg = rconv.ConvertConfig(
        name="nus_tiny",
        root=str(tmp_path / "out"),
        shard_size=2,
        splits={"train": "mini_train", "val": "mini_val"},
        osm={"boston-seaport": osm},
        map_variants=({"kind": "hd"},),
        align=ra.AlignConfig(enabled=False),
    )
    return rconv.convert(reader, cfg), "hd_road-building", ("road", "building")


def _convert_argoverse(tmp_path):
    root = str(tmp_path / "av2")
    fx.write_argoverse(root)
    reader = av.ArgoverseReader(
        av.ArgoverseConfig(dataroot=root, cities=("MIA",), image_size=(12, 20), frame_stride=2)
    )
    cfg = rconv.ConvertConfig(
        name="argo_tiny",
        root=str(tmp_path / "out"),
        shard_size=4,
        map_variants=({"kind": "hd", "channels": ("road",)},),
        align=ra.AlignConfig(enabled=False),
    )
    return rconv.convert(reader, cfg), "hd_road", ("road",)


@pytest.mark.parametrize("convert", [_convert_nuscenes, _convert_argoverse], ids=["nus", "av2"])
def test_scenes_and_logs_are_tracked_through_the_same_records(tmp_path, convert):
    ddir, variant, channels = convert(tmp_path)
    ev = sequential.EvalConfig(
        bev_source="gt",
        mode="sequential",
        sequential_splits=("val",),
        calibration_split="val",
        temperature=1000.0,  # soft: the mode's sub-cell refinement sees its neighbours
        batch_size=2,
        num_figures=1,
    )
    step = evaluation.make_localize_step(
        ModelConfig(num_classes=len(channels)), solver.SolverConfig(num_rotations=K), "gt"
    )
    mesh = step_lib.make_mesh(1)
    out = sequential.evaluate_sequential(
        step,
        None,
        dataset_dir=ddir,
        map_variant=variant,
        channels=channels,
        loader_cfg=LoaderConfig(max_points=256, num_threads=0),
        eval_cfg=ev,
        num_rotations=K,
        place=lambda b: step_lib.device_batch(b, mesh, process_local=False),
        temperature_batches=None,
        output_dir=str(tmp_path / "run"),
    )
    s = out["val"]
    assert s["drives"] == 1 and s["frames"] >= 2  # one scene / log
    arrays = np.load(tmp_path / "run" / "sequential" / "val.npz")
    assert arrays["frame_index"].tolist() == list(range(s["frames"]))  # in frame order
    assert (np.diff(arrays["timestamp"]) > 0).all()
    # Frame 0: a uniform belief over the stored prior's own tile, so the filter's answer is the
    # single-frame one; later frames are cut around the estimate.
    np.testing.assert_allclose(arrays["filtered"][0], arrays["single"][0], atol=1e-3)
    assert np.isfinite(arrays["filtered"]).all() and np.isfinite(s["filtered"]["APE"])
    assert os.path.exists(tmp_path / "run" / "figures" / "sequential" / "calibration.png")
