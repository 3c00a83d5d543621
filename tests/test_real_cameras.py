"""Camera models and the ego frame as the datasets define them, through the readers' public path
on fixtures in the real on-disk formats: AV2 radial distortion (undistortion to the stored
pinhole intrinsics), the ego-to-ground height of AV2 and nuScenes."""

import math
import os

import numpy as np
import pyarrow.feather as feather
import pytest

import fixtures_real as fx
import fixtures_real_camera as fc
from seglocnet_jax.data.real import argoverse as av
from seglocnet_jax.data.real import common as rc
from seglocnet_jax.data.real import nuscenes as nu
from seglocnet_jax.data.real.convert import ConvertConfig
from seglocnet_jax.data.schema import EGO_HEIGHT_M, check_sample

STORED_HW = (320, 800)  # the paper's stored image size
DOT_CAMS = ("ring_front_center", "ring_front_left")  # portrait and landscape


@pytest.fixture(scope="module")
def dots(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("av2_dots"))
    facts = fc.write_av2_log(root, "train", "log-dots", cameras=DOT_CAMS, dots=True)
    return root, facts


def _load(root, **cfg):
    reader = av.ArgoverseReader(
        av.ArgoverseConfig(dataroot=root, image_size=STORED_HW, frame_stride=1, **cfg)
    )
    (frame,) = reader.frames("train")
    return check_sample(reader.load(frame)), reader


def _project(sample, i, points_ego):
    """Pixels ``(n, 2)`` of emitted-ego-frame points in camera ``i``: stored pinhole model."""
    cam_from_ego = np.linalg.inv(sample["cam_to_ego"][i].astype(np.float64))
    p = np.c_[points_ego, np.ones(len(points_ego))] @ cam_from_ego.T
    uv = p[:, :3] @ sample["intrinsics"][i].astype(np.float64).T
    return uv[:, :2] / uv[:, 2:]


def _centroids(image, uv, cam):
    """Intensity centroids ``(n, 2)`` of the dots of ``image`` in windows about ``uv``."""
    h, w = fc.AV2_INTRINSICS[cam][4]
    sy, sx = STORED_HW[0] / h, STORED_HW[1] / w
    hy, hx = (math.ceil(4 * fc.DOT_SIGMA * s) + 1 for s in (sy, sx))
    grey = image.astype(np.float64).mean(axis=-1)
    out = []
    for u, v in uv:
        r0, c0 = int(round(v)), int(round(u))
        rows, cols = np.mgrid[r0 - hy : r0 + hy + 1, c0 - hx : c0 + hx + 1]
        wgt = np.clip(grey[r0 - hy : r0 + hy + 1, c0 - hx : c0 + hx + 1] - 4.0, 0.0, None)
        assert wgt.sum() > 100, f"{cam}: no dot near pixel {(u, v)}"
        out.append([(wgt * cols).sum() / wgt.sum(), (wgt * rows).sum() / wgt.sum()])
    return np.array(out)


def test_radial_model_is_opencvs_with_zero_tangential_terms():
    k = (-0.25, -0.13, 0.2)
    xy = np.array([[0.0, 0.0], [0.3, -0.4], [0.6, 0.45]])
    r2 = (xy**2).sum(1, keepdims=True)
    want = xy * (1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3)
    np.testing.assert_allclose(rc.radial_distort(xy, k), want, rtol=1e-12)


def test_undistorted_av2_image_puts_3d_points_on_the_stored_pinhole_pixels(dots):
    root, facts = dots
    s, reader = _load(root, cameras=DOT_CAMS, undistort=True)
    assert s["images"].shape == (2, *STORED_HW, 3)
    assert reader.identity()["undistort"] is True
    worst = 0.0
    for i, cam in enumerate(DOT_CAMS):
        f, cx, cy, _, (h, w) = fc.AV2_INTRINSICS[cam]
        sx, sy = STORED_HW[1] / w, STORED_HW[0] / h
        # Intrinsics describe the stored (resized) image, pixel-centre convention.
        want_k = [[f * sx, 0, sx * (cx + 0.5) - 0.5], [0, f * sy, sy * (cy + 0.5) - 0.5]]
        np.testing.assert_allclose(s["intrinsics"][i][:2], want_k, rtol=1e-6)
        # Dot centres: AV2 ego frame -> emitted (ground) ego frame -> stored pinhole camera.
        points = facts["dots"][cam] + [0.0, 0.0, EGO_HEIGHT_M["av2"]]
        uv = _project(s, i, points)
        assert np.all((uv > 8) & (uv < [STORED_HW[1] - 8, STORED_HW[0] - 8]))  # edge to edge
        residual = np.linalg.norm(_centroids(s["images"][i], uv, cam) - uv, axis=1)
        worst = max(worst, float(residual.max()))
        assert residual.max() < 0.5, (cam, residual.max())
    print(f"undistortion residual: max {worst:.3f} px")


def test_av2_images_are_kept_as_published_by_default(dots):
    """AV2 publishes undistorted images, so by default the k1..k3 are not applied: the reader
    resizes only. On this (really distorted) fixture the dots therefore stay at their distorted
    positions, 20-41 px from the pinhole prediction at the edges: what the flag is for."""
    root, facts = dots
    s, reader = _load(root, cameras=DOT_CAMS)
    assert reader.identity()["undistort"] is False
    shifts = []
    for i, cam in enumerate(DOT_CAMS):
        k = s["intrinsics"][i].astype(np.float64)
        xy = rc.radial_distort(fc.dot_rays(cam), fc.AV2_INTRINSICS[cam][3])
        distorted = xy * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
        np.testing.assert_allclose(_centroids(s["images"][i], distorted, cam), distorted, atol=0.5)
        pinhole = _project(s, i, facts["dots"][cam] + [0.0, 0.0, EGO_HEIGHT_M["av2"]])
        shifts.append(np.linalg.norm(distorted - pinhole, axis=1).max())
    assert min(shifts) > 20.0 and max(shifts) < 80.0


def test_undistort_needs_the_distortion_columns(tmp_path):
    fc.write_av2_log(str(tmp_path), "train", "log-a")
    path = tmp_path / "train" / "log-a" / "calibration" / "intrinsics.feather"
    table = feather.read_table(str(path))
    feather.write_feather(table.drop_columns(["k1", "k2", "k3"]), str(path))
    cfg = {"dataroot": str(tmp_path), "cameras": DOT_CAMS, "frame_stride": 1}
    assert av.ArgoverseReader(av.ArgoverseConfig(**cfg)).frames("train")  # not needed: fine
    with pytest.raises(
        rc.RealDataError,
        match=r"intrinsics\.feather: AV2 camera intrinsics "
        r"lacks columns \['k1', 'k2', 'k3'\]",
    ):
        av.ArgoverseReader(av.ArgoverseConfig(**cfg, undistort=True)).frames("train")


def test_av2_ego_frame_is_lifted_onto_the_ground_for_lidar_and_cameras(tmp_path):
    facts = fc.write_av2_log(str(tmp_path), "train", "log-a", cameras=fc.AV2_MOUNTS)
    cams = tuple(fc.AV2_MOUNTS)
    s, reader = _load(str(tmp_path), cameras=cams)
    raw, _ = _load(str(tmp_path), cameras=cams, ego_height_m=0.0)
    h = EGO_HEIGHT_M["av2"]
    assert reader.identity()["ego_height_m"] == h == 0.33
    assert ConvertConfig().identity(reader)["reader"]["ego_height_m"] == h  # manifest identity
    # LiDAR: the AV2 ground (z = -0.33 in its ego frame) is at z = 0, objects keep their height.
    n_ground = 24
    np.testing.assert_allclose(raw["lidar"][:n_ground, 2], fc.GROUND_Z, atol=1e-3)
    np.testing.assert_allclose(s["lidar"][:n_ground, 2], 0.0, atol=1e-3)
    np.testing.assert_allclose(s["lidar"][n_ground:, 2], 1.0, atol=1e-3)
    np.testing.assert_allclose(s["lidar"][:, :2], raw["lidar"][:, :2])
    np.testing.assert_allclose(s["lidar"][:, :2], facts["lidar"][:, :2], atol=1e-2)
    # Cameras: mounts lifted by the same height, rotations unchanged.
    for i, cam in enumerate(cams):
        np.testing.assert_allclose(s["cam_to_ego"][i][:3, :3], raw["cam_to_ego"][i][:3, :3])
        want = np.asarray(fc.AV2_MOUNTS[cam][0]) + [0.0, 0.0, h]
        np.testing.assert_allclose(s["cam_to_ego"][i][:3, 3], want, atol=1e-5)
        # Consistency: every LiDAR point projects to the same pixel in both frames.
        np.testing.assert_allclose(
            _project(s, i, s["lidar"][:, :3]), _project(raw, i, raw["lidar"][:, :3]), atol=1e-3
        )
    np.testing.assert_array_equal(s["pose"], raw["pose"])
    with pytest.raises(ValueError, match="dataset.reader.ego_height_m"):
        av.ArgoverseConfig(ego_height_m=float("nan"))


def test_nuscenes_ego_origin_is_on_the_ground_and_the_height_is_applied_alike(tmp_path):
    fx.write_nuscenes(str(tmp_path))
    base = {"dataroot": str(tmp_path), "version": "v1.0-mini", "image_size": (12, 20)}
    default = nu.NuScenesReader(nu.NuScenesConfig(**base))
    assert default.identity()["ego_height_m"] == EGO_HEIGHT_M["nuscenes"] == 0.0
    frame = default.frames("mini_val")[0]
    s = default.load(frame)
    pts = fx.lidar_points(10)  # scene 1, sample 0
    want = pts[:, :3] @ fx.rot_z(fx.LIDAR_YAW).T + [0.9, 0.0, 1.8]
    np.testing.assert_allclose(s["lidar"][:, :3], want, atol=1e-4)  # unchanged
    lifted = nu.NuScenesReader(nu.NuScenesConfig(**base, ego_height_m=0.5)).load(frame)
    np.testing.assert_allclose(lifted["lidar"][:, 2], s["lidar"][:, 2] + 0.5, atol=1e-5)
    np.testing.assert_allclose(lifted["cam_to_ego"][:, 2, 3], s["cam_to_ego"][:, 2, 3] + 0.5)
    np.testing.assert_array_equal(lifted["images"], s["images"])  # rectified: resized only
    np.testing.assert_array_equal(lifted["intrinsics"], s["intrinsics"])


def test_dataset_presets_record_each_datasets_camera_and_ego_defaults():
    import yaml

    from seglocnet_jax.config_util import from_dict

    conf = os.path.join(os.path.dirname(__file__), "..", "conf", "dataset")
    for name, cls in (
        ("argo_mia", av.ArgoverseConfig),
        ("argo_pit", av.ArgoverseConfig),
        ("nuscenes", nu.NuScenesConfig),
    ):
        with open(os.path.join(conf, f"{name}.yaml")) as f:
            reader_cfg = from_dict(cls, yaml.safe_load(f)["reader"], "dataset.reader")
        for key in ("ego_height_m", "max_sync_ms", "undistort"):
            if hasattr(cls, key):
                assert getattr(reader_cfg, key) == getattr(cls(), key), (name, key)
    assert av.ArgoverseConfig().max_sync_ms == 25.0
    assert av.ArgoverseConfig().undistort is False
