"""nuScenes and Argoverse 2 readers on fixtures written in the datasets' on-disk formats."""

import json
import math
import os

import numpy as np
import pytest
from shapely.geometry import Point

import fixtures_real as fx
import fixtures_real_camera as fc
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import common as rc
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.schema import EGO_HEIGHT_M, check_sample

OUT_HW = (12, 20)  # half the fixture's 24 x 40 images


@pytest.fixture(scope="module")
def nus(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("nuscenes"))
    facts = fx.write_nuscenes(root)
    cfg = nu.NuScenesConfig(dataroot=root, version="v1.0-mini", image_size=OUT_HW)
    return nu.NuScenesReader(cfg), facts, root


@pytest.fixture(scope="module")
def av2(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("av2"))
    facts = fx.write_argoverse(root)
    return av.ArgoverseConfig(dataroot=root, image_size=OUT_HW, frame_stride=2), facts, root


def test_official_nuscenes_splits_are_complete_and_disjoint():
    sizes = {s: len(nu.official_scenes(s)) for s in ("train", "val", "test")}
    assert sizes == {"train": 700, "val": 150, "test": 150}
    all_scenes = [n for s in sizes for n in nu.official_scenes(s)]
    assert len(set(all_scenes)) == 1000
    mini = nu.official_scenes("mini_train") + nu.official_scenes("mini_val")
    assert len(mini) == 10 and set(mini) <= set(all_scenes)


def test_nuscenes_frames_follow_scenes_and_land_on_the_drivable_area(nus):
    reader, facts, root = nus
    frames = reader.frames("mini_train")
    assert [f.key for f in frames] == facts["scenes"]["scene-0061"]  # sample chain order
    drivable = reader.drivable("boston-seaport")
    for f in frames + reader.frames("mini_val"):
        np.testing.assert_allclose(f.pose, facts["poses"][f.key], atol=1e-9)
        assert f.city == "boston-seaport" and drivable.contains(Point(f.pose[:2]))
    # Sequence metadata: the scene, the keyframe's index in it, the sample time in seconds.
    samples = {r["token"]: r for r in json.load(open(os.path.join(root, "v1.0-mini/sample.json")))}
    for scene in ("scene-0061", "scene-0103"):
        mine = [f for f in frames + reader.frames("mini_val") if f.group == scene]
        assert [f.sequence_id for f in mine] == [scene] * len(mine)
        assert [f.frame_index for f in mine] == list(range(len(mine)))
        assert [f.timestamp for f in mine] == [samples[f.key]["timestamp"] / 1e6 for f in mine]
        assert np.all(np.diff([f.timestamp for f in mine]) > 0)
        # Lighting from the scene's description ("Night, ..." in the second scene).
        assert {f.lighting for f in mine} == {facts["lighting"][scene]}
    assert facts["lighting"] == {"scene-0061": "day", "scene-0103": "night"}
    s = check_sample(reader.load(frames[1]))
    assert (s["sequence_id"], s["frame_index"], s["lighting"]) == ("scene-0061", 1, "day")
    assert s["frame_index"].dtype == np.int64 and s["timestamp"] == frames[1].timestamp
    # Polygon holes are kept: the plaza is drivable, its hole is not.
    assert drivable.contains(Point(200.0, 70.0)) and not drivable.contains(Point(200.0, 135.0))
    # Official lists are filtered to the scenes this version holds.
    assert [f.group for f in reader.frames("val")] == ["scene-0103"] * 3
    with pytest.raises(rc.RealDataError, match="none of the 150 scenes of split 'test'"):
        reader.frames("test")


def test_nuscenes_sample_sensors_are_in_the_lidar_time_ego_frame(nus):
    reader, facts, _ = nus
    frame = reader.frames("mini_val")[1]
    s = check_sample(reader.load(frame))
    assert s["images"].shape == (6, *OUT_HW, 3) and s["sample_id"] == f"scene-0103/{frame.key}"
    # Camera order follows the config; each camera's solid colour survives JPEG and resizing.
    mean = s["images"].reshape(6, -1, 3).mean(axis=1)
    np.testing.assert_allclose(mean, np.array(fx.CAM_COLOURS[:6]), atol=6)
    # Intrinsics scaled by 1/2 (pixel-centre convention).
    np.testing.assert_allclose(s["intrinsics"][0], [[10, 0, 9.75], [0, 10, 5.75], [0, 0, 1]])
    # LiDAR: sensor turned 90 degrees about z and mounted at (0.9, 0, 1.8); intensity / 255.
    pts = facts["lidar"][frame.key]
    want = pts[:, :3] @ fx.rot_z(fx.LIDAR_YAW).T + [0.9, 0.0, 1.8]
    np.testing.assert_allclose(s["lidar"][:, :3], want, atol=1e-4)
    np.testing.assert_allclose(s["lidar"][:, 3], pts[:, 3] / 255.0, atol=1e-6)
    # Cameras fired after the ego moved CAM_EGO_DX forward: their mount shifts forward too.
    for i, ch in enumerate(fx.NUS_CAMERAS):
        t = s["cam_to_ego"][i]
        np.testing.assert_allclose(
            t[:3, :3], fx.rot_z(fx.NUS_CAM_YAW[ch]) @ fx.CAM_FORWARD, atol=1e-6
        )
        np.testing.assert_allclose(t[:3, 3], [1.5 + fx.CAM_EGO_DX, 0, 1.6], atol=1e-5)
    # A point 10 m ahead of CAM_FRONT at its height projects to the principal point.
    cam_from_ego = np.linalg.inv(s["cam_to_ego"][0].astype(np.float64))
    p = cam_from_ego @ [11.5 + fx.CAM_EGO_DX, 0.0, 1.6, 1.0]
    uv = s["intrinsics"][0] @ p[:3]
    np.testing.assert_allclose(uv[:2] / uv[2], [9.75, 5.75], atol=1e-4)


def test_nuscenes_user_split_file_and_missing_files_are_named(nus, tmp_path):
    reader, _, root = nus
    split_file = tmp_path / "splits.json"
    split_file.write_text(json.dumps({"mine": ["scene-0103"]}))
    cfg = nu.NuScenesConfig(
        dataroot=root, version="v1.0-mini", image_size=OUT_HW, split_file=str(split_file)
    )
    user = nu.NuScenesReader(cfg)
    assert {f.group for f in user.frames("mine")} == {"scene-0103"}
    with pytest.raises(rc.RealDataError, match="no split 'train'"):
        user.frames("train")
    with pytest.raises(rc.RealDataError, match=r"v1\.0-nope: missing nuScenes table directory"):
        nu.NuScenesReader(nu.NuScenesConfig(dataroot=root, version="v1.0-nope"))
    frame = reader.frames("mini_train")[0]
    lidar = os.path.join(root, "samples/LIDAR_TOP", f"sd-{frame.key}-LIDAR_TOP.pcd.bin")
    os.rename(lidar, lidar + ".moved")
    try:
        with pytest.raises(rc.RealDataError, match=f"{frame.key}-LIDAR_TOP.pcd.bin: missing"):
            reader.load(frame)
    finally:
        os.rename(lidar + ".moved", lidar)
    with pytest.raises(rc.RealDataError, match=r"expansion/singapore-onenorth\.json: missing"):
        reader.drivable("singapore-onenorth")


def test_nuscenes_missing_table_is_named(tmp_path):
    fx.write_nuscenes(str(tmp_path))
    os.remove(tmp_path / "v1.0-mini" / "ego_pose.json")
    with pytest.raises(rc.RealDataError, match=r"ego_pose\.json: missing nuScenes table"):
        nu.NuScenesReader(nu.NuScenesConfig(dataroot=str(tmp_path), version="v1.0-mini"))


def test_argoverse_frames_cities_and_drivable_area(av2):
    cfg, facts, _ = av2
    reader = av.ArgoverseReader(av.ArgoverseConfig(**{**cfg.__dict__, "cities": ("MIA",)}))
    frames = reader.frames("train")
    assert {f.group for f in frames} == {"log-mia-a"}  # PIT filtered out
    assert len(frames) == fx.AV2_SWEEPS // 2  # frame_stride 2
    frames += reader.frames("val")
    drivable = reader.drivable("MIA")
    for f in frames:
        log_id, t = f.key.rsplit("|", 1)
        np.testing.assert_allclose(
            f.pose, facts["poses"][f"{os.path.basename(log_id)}/{t}"], atol=1e-9
        )
        assert f.city == "MIA" and drivable.contains(Point(f.pose[:2]))
        # Sequence metadata: the log, the frame's index among its kept sweeps, sweep time (s).
        assert f.sequence_id == os.path.basename(log_id) == f.group
        assert f.timestamp == int(t) / 1e9
        assert f.lighting == "unknown"  # AV2 does not say
    for log_id in {f.group for f in frames}:
        mine = [f for f in frames if f.group == log_id]
        assert [f.frame_index for f in mine] == list(range(len(mine)))
        assert np.allclose(np.diff([f.timestamp for f in mine]), 0.2)  # stride 2 x 100 ms
    assert not drivable.contains(Point(200.0, 135.0))
    # The city frame is UTM 17N minus the origin: the origin itself maps to (0, 0).
    proj = reader.projection("MIA")
    lat, lon = av.CITY_FRAMES["MIA"][1]
    np.testing.assert_allclose(proj.to_metric(lon, lat), [0.0, 0.0], atol=1e-6)
    pit = av.ArgoverseReader(av.ArgoverseConfig(**{**cfg.__dict__, "cities": ("PIT",)}))
    assert {f.city for f in pit.frames("train")} == {"PIT"}


def test_argoverse_sample_has_chosen_cameras_and_ego_lidar(av2):
    cfg, facts, _ = av2
    six = av.RING_CAMERAS[1:]  # nuScenes-like count: drop the portrait front camera
    reader = av.ArgoverseReader(av.ArgoverseConfig(**{**cfg.__dict__, "cameras": six}))
    frame = reader.frames("val")[1]
    s = check_sample(reader.load(frame))
    assert s["images"].shape == (6, *OUT_HW, 3) and s["city"] == "MIA"
    mean = s["images"].reshape(6, -1, 3).mean(axis=1)
    np.testing.assert_allclose(mean, np.array(fx.CAM_COLOURS[1:7]), atol=6)
    pts = facts["lidar"][s["sample_id"]]
    lift = np.array([0.0, 0.0, EGO_HEIGHT_M["av2"]], np.float32)  # ego origin onto the ground
    np.testing.assert_allclose(s["lidar"][:, :3], pts[:, :3].astype(np.float16) + lift, atol=1e-5)
    np.testing.assert_allclose(s["lidar"][:, 3], np.floor(pts[:, 3]) / 255.0, atol=1e-6)
    # Cameras fire 10 ms after the sweep: the ego moved 0.1 m east while heading 0.02 rad.
    moved = 0.1 * np.array([math.cos(0.02), -math.sin(0.02), 0.0])
    for i, yaw in enumerate(fx.camera_yaws(7)[1:]):
        t = s["cam_to_ego"][i]
        np.testing.assert_allclose(t[:3, :3], fx.rot_z(yaw) @ fx.CAM_FORWARD, atol=1e-6)
        np.testing.assert_allclose(t[:3, 3], [1.0, 0.0, 1.5] + moved + lift, atol=1e-5)
    assert math.isclose(s["pose"][2], 0.02, abs_tol=1e-9)


def test_argoverse_missing_calibration_is_named(tmp_path):
    fx.write_argoverse(str(tmp_path))
    os.remove(tmp_path / "val" / "log-mia-b" / "calibration" / "intrinsics.feather")
    reader = av.ArgoverseReader(av.ArgoverseConfig(dataroot=str(tmp_path)))
    with pytest.raises(
        rc.RealDataError,
        match=r"log-mia-b/calibration/intrinsics\.feather: "
        r"missing AV2 camera intrinsics",
    ):
        reader.frames("val")
    with pytest.raises(rc.RealDataError, match="test: missing AV2 split directory"):
        reader.frames("test")


def test_argoverse_camera_sync_follows_av2s_25_ms(tmp_path):
    root = str(tmp_path)
    fc.write_av2_log(root, "train", "log-20ms", cam_dt_ns=20_000_000, sweeps=2)
    fc.write_av2_log(root, "train", "log-30ms", cam_dt_ns=30_000_000, sweeps=2, x=60.0)
    cams = ("ring_front_center",)
    reader = av.ArgoverseReader(av.ArgoverseConfig(dataroot=root, cameras=cams, frame_stride=1))
    assert reader.identity()["max_sync_ms"] == 25.0
    with pytest.warns(UserWarning, match=r"skipped 2 sweeps .* within 25 ms"):
        frames = reader.frames("train")
    assert [f.group for f in frames] == ["log-20ms"] * 2
    loose = av.ArgoverseConfig(dataroot=root, cameras=cams, frame_stride=1, max_sync_ms=50.0)
    assert {f.group for f in av.ArgoverseReader(loose).frames("train")} == {"log-20ms", "log-30ms"}


def test_argoverse_log_in_two_splits_is_named(tmp_path):
    root = str(tmp_path)
    fc.write_av2_log(root, "train", "log-dup")
    fc.write_av2_log(root, "train", "log-ok", x=60.0)
    fc.write_av2_log(root, "val", "log-dup")
    fc.write_av2_log(root, "test", "log-pit", city="PIT")
    cfg = av.ArgoverseConfig(dataroot=root, cameras=fc.DOT_CAMERAS, frame_stride=1)
    for split, other in (("train", "val"), ("val", "train")):  # whichever is listed
        with pytest.raises(
            rc.RealDataError,
            match=rf"AV2 log 'log-dup' is in two splits, '{split}' and '{other}'.*"
            rf"remove it from one of the split directories under {root}",
        ):
            av.ArgoverseReader(cfg).frames(split)
    assert {f.group for f in av.ArgoverseReader(cfg).frames("test")} == {"log-pit"}
    # Only logs kept by the city filter count.
    mia = av.ArgoverseConfig(dataroot=root, cameras=fc.DOT_CAMERAS, cities=("PIT",))
    assert {f.group for f in av.ArgoverseReader(mia).frames("test")} == {"log-pit"}


def test_nuscenes_scene_in_two_splits_is_named(nus, tmp_path):
    _, _, root = nus
    split_file = tmp_path / "splits.json"
    split_file.write_text(
        json.dumps({"a": ["scene-0061"], "b": ["scene-0103", "scene-0061"], "c": ["scene-0103"]})
    )
    base = {"dataroot": root, "version": "v1.0-mini", "image_size": OUT_HW}
    user = nu.NuScenesReader(nu.NuScenesConfig(**base, split_file=str(split_file)))
    with pytest.raises(
        rc.RealDataError,
        match=r"nuScenes scene 'scene-0061' is in two splits, 'a' and 'b'.*split_file",
    ):
        user.frames("a")
    with pytest.raises(rc.RealDataError, match=r"'scene-0103' is in two splits, 'c' and 'b'"):
        user.frames("c")
    split_file.write_text(json.dumps({"twice": ["scene-0103", "scene-0103"]}))
    with pytest.raises(rc.RealDataError, match=r"'scene-0103' is listed twice in split 'twice'"):
        user.frames("twice")
    # Official lists: mini_train lies inside train; the frames of both name the scene.
    official = nu.NuScenesReader(nu.NuScenesConfig(**base))
    frames = {s: [f.group for f in official.frames(s)] for s in ("mini_train", "train")}
    with pytest.raises(
        rc.RealDataError, match=r"nuScenes scene 'scene-0061' is in two splits, 'mini_train' and"
    ):
        rc.check_disjoint_groups(frames, "nuScenes scene")
    rc.check_disjoint_groups({s: frames[s] for s in ("mini_train",)}, "nuScenes scene")
