"""The simulator: a tiny hand-made city renders valid, deterministic, geometrically consistent
frames, and trajectories stay on the road respecting one-way streets."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import shapely

from seglocnet_jax import geometry
from seglocnet_jax.data.schema import check_sample
from seglocnet_jax.sim import (
    CAMERA_NAMES,
    SensorConfig,
    Simulator,
    WorldConfig,
    build_world,
    drive,
)
from seglocnet_jax.sim import render as rn
from seglocnet_jax.sim.classes import Thing
from seglocnet_jax.sim.trajectory import (
    NOMINAL_SPEED_MPS,
    build_graph,
    drive_routes,
    lane_poses,
    route,
    sample_poses,
)


@dataclasses.dataclass(frozen=True)
class _Road:
    geometry: object
    highway: str
    lanes: int | None = None
    width: float | None = None
    oneway: bool = False


@dataclasses.dataclass(frozen=True)
class _Building:
    geometry: object
    height: float | None = None
    levels: float | None = None


@dataclasses.dataclass(frozen=True)
class _City:
    name: str
    roads: tuple
    buildings: tuple
    bounds: tuple


def tiny_city() -> _City:
    """A 3x3 street grid (160 m), a 4-lane avenue, a one-way street (eastbound), 8 blocks."""
    roads = [
        _Road(shapely.LineString([(0, 0), (80, 0), (160, 0)]), "residential"),
        _Road(shapely.LineString([(0, 80), (80, 80), (160, 80)]), "secondary", lanes=4),
        _Road(shapely.LineString([(0, 160), (80, 160), (160, 160)]), "residential", oneway=True),
    ]
    roads += [
        _Road(shapely.LineString([(x, 0), (x, 80), (x, 160)]), "tertiary")
        for x in (0.0, 80.0, 160.0)
    ]
    blds = []
    for bx in (0, 80):
        for by in (0, 80):
            blds.append(_Building(shapely.box(bx + 14, by + 14, bx + 36, by + 36), levels=4.0))
            blds.append(_Building(shapely.box(bx + 44, by + 14, bx + 66, by + 66), height=12.0))
    return _City("tiny", tuple(roads), tuple(blds), (-20.0, -20.0, 180.0, 180.0))


EXACT = dict(missing_buildings=0.0, extra_buildings=0.0, shifted_buildings=0.0)
SENSORS = SensorConfig(
    image_height=32,
    image_width=80,
    lidar_beams=16,
    lidar_azimuths=256,
    max_range=50.0,
    range_noise=0.0,
    dropout=0.0,
    chunk=2,
)


@pytest.fixture(scope="module")
def city():
    return tiny_city()


@pytest.fixture(scope="module")
def world(city):
    return build_world(city, WorldConfig(**EXACT), seed=3)


@pytest.fixture(scope="module")
def sim(world):
    return Simulator(world, SENSORS)


@pytest.fixture(scope="module")
def poses(world):
    return drive(world, np.random.default_rng(0), 3, spacing_m=20.0)


@pytest.fixture(scope="module")
def arrays(sim, poses):
    return sim.render_arrays(poses, seed=11, diagnostics=True)


@pytest.fixture(scope="module")
def samples(sim, poses):
    return sim.render(poses, seed=11)


def test_render_gives_valid_samples(samples, poses):
    assert len(samples) == len(poses)
    for i, s in enumerate(samples):
        check_sample(s)
        assert s["city"] == "tiny" and s["sample_id"] == f"tiny-11-{i:04d}"
        np.testing.assert_array_equal(s["pose"], poses[i])
        assert s["images"].shape == (6, 32, 80, 3)
        assert s["images"].std() > 10  # not a blank frame
        assert len(s["lidar"]) > 500 and s["lidar"][:, 3].min() >= 0
        assert s["lidar"][:, 3].max() <= 1


def test_render_is_deterministic_per_seed(sim, poses, arrays, samples):
    again = sim.render_arrays(poses, seed=11)  # without diagnostics: the same shared outputs
    assert set(again) == {"images", "lidar", "lidar_valid", "lighting"}
    for key in again:
        np.testing.assert_array_equal(arrays[key], again[key])
    for i, s in enumerate(samples):  # the samples are these arrays
        np.testing.assert_array_equal(s["images"], again["images"][i])
        np.testing.assert_array_equal(s["lidar"], again["lidar"][i][again["lidar_valid"][i]])
        assert s["lighting"] == again["lighting"][i]
    other = sim.render_arrays(poses, seed=12)
    assert not np.array_equal(arrays["images"], other["images"])
    sim.render_arrays(poses[:1] + np.array([1.0, 0.5, 0.3]), seed=5)  # other poses, padded
    assert sim._renderer(False)._cache_size() == 1  # compiled once per sensor config
    # Another world of the same preset and seed (the next city) reuses the compiled renderer.
    other_city = dataclasses.replace(sim.world, name="other")
    assert Simulator(other_city, sim.cfg)._renderer(False) is sim._renderer(False)
    assert Simulator(other_city, dataclasses.replace(sim.cfg, pixel_noise=0.0))._renderer(
        False
    ) is not sim._renderer(False)


def test_pixels_see_what_the_stored_calibration_projects(samples, arrays):
    """The hit point of each pixel's rendered ray, projected with the intrinsics and cam_to_ego
    stored in the sample, lands on that pixel (pins the camera conventions of the samples)."""
    k = samples[0]["intrinsics"].astype(np.float64)
    t = samples[0]["cam_to_ego"].astype(np.float64)
    pts = arrays["cam_points"][0].astype(np.float64)  # (N, H, W, 3) ego
    hit = arrays["cam_kind"][0] != rn.SKY
    assert hit.mean() > 0.3
    for c in range(len(k)):
        ego_to_cam = np.linalg.inv(t[c])
        p = pts[c][hit[c]]
        cam = p @ ego_to_cam[:3, :3].T + ego_to_cam[:3, 3]
        assert np.all(cam[:, 2] > 0)
        uv = cam @ k[c].T
        uv = uv[:, :2] / uv[:, 2:]
        v, u = np.nonzero(hit[c])
        np.testing.assert_allclose(uv[:, 0], u, atol=0.05)
        np.testing.assert_allclose(uv[:, 1], v, atol=0.05)


def test_camera_rig_is_the_nuscenes_like_surround_rig(arrays):
    """Independent of the calibration arrays: CAM_FRONT looks forward with a 70 degree FOV
    (image left = ego left), CAM_BACK backward with 110 degrees, both 1.55 m above ground,
    and ground pixels hit the ground plane."""
    pts = arrays["cam_points"][0].astype(np.float64)  # (N, H, W, 3) ego
    kind = arrays["cam_kind"][0]
    np.testing.assert_allclose(pts[kind == rn.GROUND][:, 2], 0.0, atol=1e-3)
    for name, heading, fov, x in (("CAM_FRONT", 0.0, 70.0, 1.70), ("CAM_BACK", 180.0, 110.0, 0.05)):
        c = CAMERA_NAMES.index(name)
        ray = pts[c] - np.array([x, 0.0, SENSORS.camera_height])  # (H, W, 3)
        az = np.degrees(np.arctan2(ray[..., 1], ray[..., 0]))
        rel = (az - heading + 180.0) % 360.0 - 180.0  # azimuth from the optical axis
        left, right = rel[:, 0], rel[:, -1]  # first / last image column
        # Pixel centres of the outer columns lie half a pixel inside the field of view.
        edge = np.degrees(np.arctan((1 - 1 / SENSORS.image_width) * np.tan(np.radians(fov / 2))))
        np.testing.assert_allclose(left, edge, atol=0.05)  # a column is one vertical plane
        np.testing.assert_allclose(right, -edge, atol=0.05)
        # Rows go downward: the rays' slope falls from the top row to the bottom row.
        slope = ray[..., 2] / np.hypot(ray[..., 0], ray[..., 1])
        assert np.all(np.diff(slope, axis=0) < 0)


def test_lidar_returns_lie_on_map_building_walls(city, arrays, poses):
    """Without noise, elevated non-distractor returns are on the OSM buildings' walls."""
    walls = shapely.union_all([shapely.boundary(b.geometry) for b in city.buildings])
    near = 0
    for i, pose in enumerate(poses):
        pts = arrays["lidar"][i][arrays["lidar_valid"][i]]
        thing = arrays["lidar_thing"][i][arrays["lidar_valid"][i]]
        sel = (pts[:, 2] > 0.5) & (thing == Thing.BUILDING)
        xy = geometry.ego_to_world(pose, pts[sel, :2])
        dist = shapely.distance(walls, shapely.points(xy))
        assert np.quantile(dist, 0.99) < 0.5, np.quantile(dist, [0.5, 0.99])
        near += sel.sum()
        # Ground returns are on the ground plane.
        ground = arrays["lidar"][i][arrays["lidar_valid"][i] & (arrays["lidar_thing"][i] == 0)]
        np.testing.assert_allclose(ground[:, 2], 0.0, atol=1e-3)
    assert near > 200


def test_trajectories_stay_on_road_and_respect_oneway(world):
    poses = drive(world, np.random.default_rng(5), 400, spacing_m=3.0)
    assert poses.shape == (400, 3)
    np.testing.assert_array_equal(poses, drive(world, np.random.default_rng(5), 400, 3.0))
    assert shapely.contains_xy(world.drivable, poses[:, 0], poses[:, 1]).all()
    # The one-way street at y = 160 runs east only (world road offset is <= 1.5 m).
    on_oneway = (
        (np.abs(poses[:, 1] - 160) < 4)
        & (poses[:, 0] > 10)
        & (poses[:, 0] < 150)
        & (np.abs(poses[:, 0] - 80) > 10)
    )  # away from the crossing streets
    assert on_oneway.sum() > 5
    assert np.all(np.cos(poses[on_oneway, 2]) > 0.9)
    # Two-way streets carry both directions, each on its right-hand side: on the south street
    # (y = 0) eastbound south of westbound, on the middle street (x = 80) northbound east of
    # southbound (away from the crossings).
    off_x = np.abs((poses[:, 0] + 40) % 80 - 40) > 10  # between the north-south streets
    off_y = np.abs((poses[:, 1] + 40) % 80 - 40) > 10  # between the east-west streets
    south = off_x & (np.abs(poses[:, 1]) < 5)
    east = south & (np.cos(poses[:, 2]) > 0.9)
    west = south & (np.cos(poses[:, 2]) < -0.9)
    assert east.sum() > 5 and west.sum() > 5
    assert poses[east, 1].max() < 0 < poses[west, 1].min()
    middle = off_y & (np.abs(poses[:, 0] - 80) < 5)
    north = middle & (np.sin(poses[:, 2]) > 0.9)
    southward = middle & (np.sin(poses[:, 2]) < -0.9)
    assert north.sum() > 5 and southward.sum() > 5
    assert poses[southward, 0].max() < 80 < poses[north, 0].min()
    # Consecutive frames of a route are spacing_m apart along the heading.
    step = np.diff(poses[:, :2], axis=0)
    dist = np.linalg.norm(step, axis=1)
    cont = np.abs(dist - 3.0) < 0.5
    heading = np.arctan2(step[cont, 1], step[cont, 0])
    assert np.median(np.abs(np.angle(np.exp(1j * (heading - poses[:-1][cont, 2]))))) < 0.1


def _angle(a):
    return np.abs(np.angle(np.exp(1j * np.asarray(a))))


def test_drive_routes_reports_each_frames_route_without_changing_the_poses(world):
    traj = drive_routes(world, np.random.default_rng(5), 400, 3.0)
    np.testing.assert_array_equal(traj.poses, drive(world, np.random.default_rng(5), 400, 3.0))
    assert traj.route.dtype == traj.index.dtype == np.int64 and len(traj) == 400
    same = np.diff(traj.route) == 0
    assert np.all(np.diff(traj.route) >= 0) and len(np.unique(traj.route)) > 5
    assert np.all(np.diff(traj.index)[same] == 1) and np.all(traj.index[1:][~same] == 0)
    step = np.linalg.norm(np.diff(traj.poses[:, :2], axis=0), axis=1)
    assert np.median(np.abs(step[same] - 3.0)) < 0.3  # a route's frames are 3 m apart
    np.testing.assert_array_equal(traj.timestamps, traj.index * 3.0 / NOMINAL_SPEED_MPS)


def test_routes_are_continuous_on_road_and_respect_oneway(world):
    traj = route(world, np.random.default_rng(3), 1000.0, 5.0)
    again = route(world, np.random.default_rng(3), 1000.0, 5.0)
    np.testing.assert_array_equal(traj.poses, again.poses)  # deterministic for the rng
    assert not np.array_equal(traj.poses, route(world, np.random.default_rng(4), 1000.0).poses)
    assert len(traj) == 201 and traj.index.tolist() == list(range(201))
    np.testing.assert_allclose(traj.timestamps, np.arange(201) * 5.0 / NOMINAL_SPEED_MPS)
    poses = traj.poses
    assert shapely.contains_xy(world.drivable, poses[:, 0], poses[:, 1]).all()
    # No jumps: each frame is 5 m along the lane from the previous one (corners cut a little).
    step = np.diff(poses[:, :2], axis=0)
    dist = np.linalg.norm(step, axis=1)
    assert dist.min() > 1.0 and dist.max() < 9.0 and np.median(np.abs(dist - 5.0)) < 0.1
    # The yaw points along the travel, and the car never turns back (no dead end here).
    heading = np.arctan2(step[:, 1], step[:, 0])
    straight = np.abs(dist - 5.0) < 0.3
    assert np.quantile(_angle(heading[straight] - poses[:-1][straight, 2]), 0.9) < 0.1
    assert _angle(np.diff(poses[:, 2])).max() < 2.0
    # A long drive takes the one-way street (y = 160, away from crossings) only eastward.
    longer = route(world, np.random.default_rng(11), 5000.0, 5.0).poses
    on_oneway = (np.abs(longer[:, 1] - 160) < 4) & (np.abs((longer[:, 0] + 40) % 80 - 40) > 10)
    assert on_oneway.sum() > 5 and np.all(np.cos(longer[on_oneway, 2]) > 0.9)


def test_routes_turn_back_at_a_dead_end_and_stop_when_stuck():
    def stub(oneway):  # one 100 m road east from the origin, nothing else
        road = SimpleNamespace(
            centerline=np.array([[0.0, 0.0], [100.0, 0.0]]), width=8.0, lanes=2, oneway=oneway
        )
        return SimpleNamespace(name="stub", roads=[road], graph=None)

    two_way = route(stub(False), np.random.default_rng(0), 450.0, 5.0)
    poses = two_way.poses
    assert len(poses) == 91 and np.all((poses[:, 0] >= 0) & (poses[:, 0] <= 100))
    east = np.cos(poses[:, 2]) > 0.9
    assert east.any() and (~east).any()  # it drove both ways: U-turns at the ends
    assert np.all(poses[east, 1] < 0) and np.all(poses[~east, 1] > 0)  # right-hand lanes
    dist = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    assert dist.max() < 5.0 + 4.0 + 1.0  # a U-turn crosses the road (lane centres 4 m apart)
    stuck = route(stub(True), np.random.default_rng(0), 450.0, 5.0)
    assert 1 <= len(stuck) <= 21 and np.all(np.cos(stuck.poses[:, 2]) > 0.9)  # ends at x=100
    assert len(build_graph(stub(True).roads).arcs) == 1


def test_region_and_enumeration_apis(world):
    region = shapely.box(60, 60, 170, 170)
    p = drive(world, np.random.default_rng(1), 50, 4.0, region=region)
    assert len(p) == 50 and shapely.contains_xy(region, p[:, 0], p[:, 1]).all()
    q = sample_poses(world, np.random.default_rng(2), 30, region=region)
    assert len(q) == 30 and shapely.contains_xy(world.drivable, q[:, 0], q[:, 1]).all()
    e = lane_poses(world, 5.0, region=region)
    assert len(e) > 50 and shapely.contains_xy(region, e[:, 0], e[:, 1]).all()


def test_world_widths_offsets_and_discrepancies(city):
    world = build_world(city, WorldConfig(), seed=1)
    widths = {r.highway: r.width for r in world.roads}
    assert widths["secondary"] == pytest.approx(4 * 3.25)  # lanes=4 tag
    assert widths["residential"] < widths["secondary"]
    lateral = []
    for road in world.roads:  # world centre is displaced 0.5-1.5 m from the OSM centreline
        np.testing.assert_array_equal(
            road.osm_centerline[[0, -1]],
            np.asarray(city.roads[road.osm_index].geometry.coords)[[0, -1]],
        )
        shift = np.linalg.norm(road.centerline - road.osm_centerline, axis=1)
        assert shift.min() >= 0.5 - 1e-9 and shift.max() <= 1.5 + 1e-9
        assert np.abs(np.diff(shift)).max() < 0.1  # smoothly (vertices 2 m apart)
        osm = city.roads[road.osm_index].geometry
        lateral.append(shapely.distance(osm, shapely.points(road.centerline)))
    assert np.mean(np.concatenate(lateral)) > 0.3
    extra = build_world(city, WorldConfig(**dict(EXACT, extra_buildings=0.5)), seed=1)
    assert len(extra.buildings) == len(city.buildings) + 4  # extra buildings no map has
    assert not any(extra.drivable.intersects(b) for b in extra.buildings[len(city.buildings) :])
    world = build_world(city, WorldConfig(missing_buildings=0.3, extra_buildings=0.0), seed=1)
    present = set()
    for i, b in enumerate(city.buildings):  # missing buildings are not in the raster
        row, col = world.grid.world_to_pixel(*b.geometry.centroid.coords[0])
        if world.thing[int(row), int(col)] == Thing.BUILDING:
            present.add(i)
    assert 0 < len(present) < len(city.buildings)  # some, not all, OSM buildings are built
    assert set(world.osm_buildings_kept.tolist()) == present
    assert len(world.buildings) == len(present)


def test_distractors_exist_off_the_road_and_outside_buildings(world):
    """Parked cars, trees, poles and pedestrians are in the world (no map has them), never on
    the HD drivable area nor inside a building."""
    rows, cols = np.nonzero(world.thing >= Thing.CAR)
    kinds = world.thing[rows, cols]
    assert set(kinds.tolist()) == {Thing.CAR, Thing.TREE, Thing.POLE, Thing.PEDESTRIAN}
    x, y = world.grid.pixel_to_world(rows + 0.5, cols + 0.5)  # cell centres
    assert not shapely.contains_xy(world.drivable, x, y).any()
    assert not shapely.contains_xy(shapely.union_all(world.buildings), x, y).any()
    # Cars park beside the carriageway: within 3 m of the drivable area.
    car = kinds == Thing.CAR
    assert shapely.distance(world.drivable, shapely.points(x[car], y[car])).max() < 3.0


def test_bad_input_is_reported(sim):
    with pytest.raises(ValueError, match="outside the world"):
        sim.render(np.array([[5000.0, 5000.0, 0.0]]), seed=0)
    with pytest.raises(ValueError, match="unknown sensor preset"):
        SensorConfig.preset("gpu-huge")
    assert SensorConfig.preset("paper").image_width == 800


def test_each_frame_records_the_lighting_it_was_drawn_with(sim, poses):
    """The record's ``lighting`` is the condition the frame was rendered under: the conditions
    come in the configured proportions, and the night frames are the dark ones."""
    from seglocnet_jax.sim import camera as cam

    night_p, dusk_p = sim.cfg.night_prob, sim.cfg.dusk_prob
    assert night_p > 0.05 and dusk_p > 0.05
    drawn = [
        cam.draw_lighting(np.random.default_rng([7, i, 0x5E]), night_p, dusk_p)["condition"]
        for i in range(4000)
    ]
    assert drawn.count("night") / len(drawn) == pytest.approx(night_p, abs=0.02)
    assert drawn.count("dusk") / len(drawn) == pytest.approx(dusk_p, abs=0.02)
    # Frames at one pose, rendered with seed 7: frame i has the condition drawn for index i.
    n = max(drawn.index("night"), drawn.index("day")) + 1
    out = sim.render_arrays(np.repeat(poses[:1], n, axis=0), seed=7)
    assert list(out["lighting"]) == drawn[:n]
    night, day = drawn.index("night"), drawn.index("day")
    assert out["images"][night].mean() < 0.5 * out["images"][day].mean()
