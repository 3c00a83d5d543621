"""Model pure functions against NumPy references, stage shapes, configuration errors."""

from __future__ import annotations

import dataclasses
import functools
import math
import os

import jax
import numpy as np
import pytest
import yaml

from seglocnet_jax import geometry, maps
from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.model import api, camera, lidar, neural_map, synthetic
from seglocnet_jax.model.config import ModelConfig, preset

CONF_DIR = os.path.join(os.path.dirname(__file__), "..", "conf", "model")


def _random_rig(rng, n):
    intr = np.zeros((n, 3, 3), np.float32)
    intr[:, 0, 0] = rng.uniform(50, 120, n)
    intr[:, 1, 1] = rng.uniform(50, 120, n)
    intr[:, 0, 2] = rng.uniform(60, 100, n)
    intr[:, 1, 2] = rng.uniform(20, 40, n)
    intr[:, 0, 1] = rng.uniform(-1, 1, n)  # skew: the inverse must handle a full K
    intr[:, 2, 2] = 1
    mats = []
    for _ in range(n):
        q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        q *= np.sign(np.linalg.det(q))
        m = np.eye(4)
        m[:3, :3] = q
        m[:3, 3] = rng.normal(size=3)
        mats.append(m)
    return intr, np.asarray(mats, np.float32)


def test_frustum_points_reproject_to_their_pixels_and_depths():
    rng = np.random.default_rng(0)
    intr, cam = _random_rig(rng, 3)
    depths = camera.depth_bins(5, 1.0, 40.0)
    pts = np.asarray(camera.frustum_points_ego(intr, cam, (2, 4), 16, depths))  # (3,2,4,5,3)
    assert pts.shape == (3, 2, 4, 5, 3)
    for n in range(3):
        # NumPy reference: ego -> camera with the inverse extrinsics, then pinhole projection.
        ego_to_cam = np.linalg.inv(cam[n].astype(np.float64))
        p = pts[n].reshape(-1, 3).astype(np.float64)
        pc = p @ ego_to_cam[:3, :3].T + ego_to_cam[:3, 3]
        uvw = pc @ intr[n].astype(np.float64).T
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        uu, vv = np.meshgrid(np.arange(4) * 16 + 7.5, np.arange(2) * 16 + 7.5, indexing="xy")
        want_u = np.repeat(uu.reshape(-1), 5)
        want_v = np.repeat(vv.reshape(-1), 5)
        np.testing.assert_allclose(u, want_u, atol=2e-3)
        np.testing.assert_allclose(v, want_v, atol=2e-3)
        np.testing.assert_allclose(pc[:, 2], np.tile(depths, 8), rtol=1e-5)


def test_frustum_of_forward_camera_points_forward_in_ego():
    intr, cam = synthetic.camera_rig(1, 64, 160)
    pts = np.asarray(camera.frustum_points_ego(intr, cam, (4, 10), 16, np.array([10.0])))
    pts = pts[0, :, :, 0]  # (4, 10, 3): the only camera at the only depth
    # Camera 0 looks along ego +x at 1.5 m: depth 10 m is 10 m forward, left half of the image
    # is the vehicle's left (+y), the lower rows are below the camera.
    np.testing.assert_allclose(pts[..., 0], 10.0, atol=1e-4)
    assert np.all(pts[:, :5, 1] > 0) and np.all(pts[:, 5:, 1] < 0)
    assert np.all(pts[2:, :, 2] < synthetic.CAMERA_HEIGHT)


def test_geometric_attention_bias_matches_a_numpy_projection_of_each_pillar():
    """Each query's bias for each token is -d^2/2 (floored), d the feature-pixel distance from
    the token's centre to the nearest point of the query cell's pillar in that camera."""
    rng = np.random.default_rng(1)
    intr, cam = _random_rig(rng, 2)
    cam[:, :3, 3] = [[1.0, 0.0, 1.5], [-1.0, 0.5, 1.5]]
    bias = np.asarray(camera.geometric_attention_bias(intr[None], cam[None], (2, 4), 16))[0]
    assert bias.shape == (256, 2 * 2 * 4)
    cells = camera.bev_reference_points().reshape(-1, 2) * 32.0
    uu, vv = np.meshgrid(np.arange(4) * 16 + 7.5, np.arange(2) * 16 + 7.5, indexing="xy")
    for q in rng.choice(256, 12, replace=False):
        for n in range(2):
            ego_to_cam = np.linalg.inv(cam[n].astype(np.float64))
            pts = np.array([[*cells[q], z] for z in camera.PILLAR_HEIGHTS])
            pc = pts @ ego_to_cam[:3, :3].T + ego_to_cam[:3, 3]
            uvw = pc @ intr[n].astype(np.float64).T
            uv = uvw[:, :2] / np.maximum(uvw[:, 2:], 1e-3)
            d2 = ((uv[:, None, None, 0] - uu) ** 2 + (uv[:, None, None, 1] - vv) ** 2) / 256
            d2[pc[:, 2] <= 0.1] = np.inf
            want = np.maximum(-0.5 * d2.min(axis=0), camera.BIAS_FLOOR).reshape(-1)
            np.testing.assert_allclose(bias[q, n * 8 : (n + 1) * 8], want, rtol=1e-4, atol=1e-3)


def test_stride_8_tokens_and_the_geometric_bias_keep_the_latent_shapes():
    batch = synthetic.make_batch(0, 2, num_cams=3, image_hw=(32, 96), num_points=256)
    cfg = preset("tiny", modality="camera", token_stride=8, geometric_attention=True)
    (logits, aux), _ = _shapes(cfg, batch)
    assert logits.shape == (2, 2, 128, 128) and aux["bev_latent"].shape == (2, 16, 16, 64)
    assert aux["camera_latent"].shape == (2, 16, 16, 64)


def test_a_32x32_query_grid_is_averaged_onto_the_latent_and_a_decoder_skip():
    batch = synthetic.make_batch(0, 2, num_cams=3, image_hw=(32, 96), num_points=256)
    cfg = preset("tiny", modality="fused", geometric_attention=True, camera_queries=32)
    (logits, aux), variables = _shapes(cfg, batch)
    assert logits.shape == (2, 2, 128, 128) and aux["camera_latent"].shape == (2, 16, 16, 64)
    decoder = variables["params"]["decoder"]
    assert {"camera_skip32", "skip32", "skip64"} <= set(decoder), sorted(decoder)
    assert "camera_skip32" not in _shapes(preset("tiny"), batch)[1]["params"]["decoder"]


@pytest.mark.parametrize("fine", [32, 64])
def test_a_fine_camera_grid_is_a_decoder_skip_at_its_size(fine):
    batch = synthetic.make_batch(0, 2, num_cams=3, image_hw=(32, 96), num_points=256)
    cfg = preset("tiny", modality="camera", token_stride=8, camera_fine_grid=fine)
    (logits, aux), variables = _shapes(cfg, batch)
    assert logits.shape == (2, 2, 128, 128) and aux["camera_latent"].shape == (2, 16, 16, 64)
    assert f"camera_skip{fine}" in variables["params"]["decoder"]
    assert "fine_decoder" in variables["params"]["camera"]
    for bad in ({"camera_fine_grid": 48}, {"camera_fine_grid": 32, "camera_queries": 32}):
        with pytest.raises(ValueError, match="camera_fine_grid"):
            preset("tiny", **bad)
    with pytest.raises(ValueError, match="geometric_attention"):
        preset("tiny", camera_fine_grid=64, geometric_attention=False)


def test_local_cross_attention_is_dense_attention_over_each_querys_tokens():
    """Each query reads only its k tokens: the same projections as a dense multi-head
    attention whose logits are -inf elsewhere (and the bias added on the chosen ones)."""
    import flax.linen as nn

    from seglocnet_jax.model.transformer import LocalCrossAttention

    rng = np.random.default_rng(0)
    b, q, t, d, k = 2, 5, 9, 8, 3
    x = [jax.numpy.asarray(rng.normal(size=s).astype(np.float32)) for s in [(b, q, d), (b, t, d)]]
    index = jax.numpy.asarray(np.stack([[rng.permutation(t)[:k] for _ in range(q)]] * b))
    bias = jax.numpy.asarray(rng.normal(size=(b, q, k)).astype(np.float32))
    local = LocalCrossAttention(num_heads=2)
    params = local.init(jax.random.key(0), x[0], x[1], x[1], index, bias)
    got = local.apply(params, x[0], x[1], x[1], index, bias)
    dense_bias = np.full((b, q, t), -np.inf, np.float32)
    for i in range(b):
        for j in range(q):
            dense_bias[i, j, np.asarray(index[i, j])] = np.asarray(bias[i, j])
    dense = nn.MultiHeadDotProductAttention(
        num_heads=2,
        attention_fn=functools.partial(nn.dot_product_attention, bias=dense_bias[:, None]),
    )
    p = params["params"]
    renamed = {"params": {n: p[n] for n in ("query", "key", "value", "out")}}
    want = dense.apply(renamed, x[0], x[1], x[1])
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)


def test_depth_bins_increase_to_max_with_growing_spacing():
    d = camera.depth_bins(16, 1.0, 45.0)
    gaps = np.diff(d)
    assert d[0] > 1.0 and math.isclose(float(d[-1]), 45.0, rel_tol=1e-6)
    assert np.all(gaps > 0) and np.all(np.diff(gaps) > 0)


def test_bev_reference_points_follow_the_bev_convention():
    ref = camera.bev_reference_points()  # (16, 16, 2) normalized (forward, left)
    assert ref.shape == (16, 16, 2)
    assert ref[0, 8, 0] > 0.9 and ref[-1, 8, 0] < -0.9  # row 0 far front
    assert ref[8, 0, 1] > 0.9 and ref[8, -1, 1] < -0.9  # column 0 far left
    np.testing.assert_allclose(ref.mean(axis=(0, 1)), 0.0, atol=1e-6)


@pytest.mark.parametrize(
    "shape,kernel,strides",
    [((2, 16, 12, 7, 3), (3, 3, 3), (2, 2, 2)), ((1, 9, 10, 5, 4), (3, 3, 2), (2, 1, 1))],
)  # fmt: skip
def test_z_folded_3d_conv_is_flax_conv(shape, kernel, strides):
    """The LiDAR stage's 3D convolution as one 2D convolution: same parameter (name, shape,
    initial values), same output and kernel gradient as ``nn.Conv`` with "SAME" padding."""
    import flax.linen as nn

    from seglocnet_jax.model.layers import ZFoldedConv3D

    x = jax.numpy.asarray(np.random.default_rng(0).normal(size=shape).astype(np.float32))
    ref = nn.Conv(5, kernel, strides=strides, padding="SAME", use_bias=False)
    ours = ZFoldedConv3D(5, kernel, strides)
    params = ref.init(jax.random.key(1), x)
    got = ours.init(jax.random.key(1), x)
    assert jax.tree.map(np.shape, got) == jax.tree.map(np.shape, params)
    np.testing.assert_array_equal(got["params"]["kernel"], params["params"]["kernel"])
    np.testing.assert_allclose(ours.apply(params, x), ref.apply(params, x), atol=1e-5)

    def grad(m):
        return jax.jit(jax.grad(lambda p: jax.numpy.sum(jax.numpy.sin(m.apply(p, x)))))(params)

    np.testing.assert_allclose(
        grad(ours)["params"]["kernel"], grad(ref)["params"]["kernel"], rtol=1e-4, atol=1e-4
    )


def _numpy_voxelize(points, mask, grid, voxel_size, z_min):
    rows, cols, nz = grid
    count = np.zeros(grid)
    inten = np.zeros(grid)
    height = np.zeros(grid)
    for p, m in zip(points.astype(np.float64), mask, strict=True):
        row, col = geometry.ego_to_bev_pixel(p[:2], rows, voxel_size)
        r, c = int(np.floor(row)), int(np.floor(col))
        zf = (p[2] - z_min) / voxel_size
        z = int(np.floor(zf))
        if not m or not (0 <= r < rows and 0 <= c < cols and 0 <= z < nz):
            continue
        count[r, c, z] += 1
        inten[r, c, z] += p[3]
        height[r, c, z] += zf - z
    safe = np.maximum(count, 1)
    return np.stack([np.log1p(count), inten / safe, height / safe], axis=-1)


def test_voxelize_matches_numpy_reference():
    rng = np.random.default_rng(1)
    n = 3000
    pts = np.concatenate(
        [rng.uniform(-40, 40, (n, 2)), rng.uniform(-3, 5, (n, 1)), rng.uniform(0, 1, (n, 1))],
        axis=1,
    ).astype(np.float32)
    pts[:200] = pts[200:400]  # duplicates: several points per voxel
    pts[400, :3] = (32.0, 32.0, 4.0)  # exactly on the far edges: outside
    mask = rng.random(n) > 0.2
    grid = (128, 128, 12)
    got = np.asarray(jax.jit(lidar.voxelize, static_argnums=(2, 3, 4))(pts, mask, grid, 0.5, -2.0))
    want = _numpy_voxelize(pts, mask, grid, 0.5, -2.0)
    assert got.shape == (128, 128, 12, 3)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert got[..., 0].sum() > 0


def test_voxel_grid_orientation_is_the_bevs():
    pts = np.array([[10.0, 5.0, 0.2, 1.0], [-10.0, -5.0, 0.2, 1.0]], np.float32)
    vox = np.asarray(lidar.voxelize(pts, np.ones(2, bool), (128, 128, 12), 0.5, -2.0))
    occupied = np.argwhere(vox[..., 0] > 0)
    # forward 10 m -> 20 rows above the ego corner; left 5 m -> 10 columns left of it
    np.testing.assert_array_equal(sorted(map(tuple, occupied)), [(44, 54, 4), (84, 74, 4)])


def _shapes(cfg, batch):
    model = api.build(cfg)
    inputs = {k: batch[k] for k in api.required_keys(cfg)}
    return jax.eval_shape(lambda: model.init_with_output(jax.random.key(0), inputs))


@pytest.mark.parametrize("modality", ["fused", "camera", "lidar"])
def test_stage_output_shapes(modality):
    batch = synthetic.make_batch(0, 2, num_cams=3, image_hw=(32, 96), num_points=256)
    cfg = preset("tiny", modality=modality)
    (logits, aux), variables = _shapes(cfg, batch)
    d = cfg.embed_dim
    assert logits.shape == (2, 2, 128, 128)
    assert aux["bev_latent"].shape == (2, 16, 16, d)
    assert ("camera_latent" in aux) == (modality != "lidar")
    assert ("lidar_latent" in aux) == (modality != "camera")
    for key in ("camera_latent", "lidar_latent"):
        if key in aux:
            assert aux[key].shape == (2, 16, 16, d)
    assert aux["bev_features"].shape == (2, 128, 128, cfg.decoder_widths[-1])
    groups = set(variables["params"])
    assert ("camera" in groups) == (modality != "lidar")
    assert ("lidar" in groups) == (modality != "camera")


def test_nm_variant_shapes_and_channels_follow_config():
    batch = synthetic.make_batch(0, 1, num_cams=2, image_hw=(32, 64), num_points=128)
    batch["bev_gt"] = np.zeros((1, 3, 128, 128), np.float32)
    cfg = preset("tiny", variant="nm", num_classes=3, nm_dim=4)
    (logits, aux), _ = _shapes(cfg, batch)
    assert logits.shape == (1, 3, 128, 128)
    assert aux["bev_match"].shape == (1, 4, 128, 128)
    assert aux["map_match"].shape == (1, 4, 256, 256)
    assert aux["match_scale"].shape == ()


def test_nm_reads_the_osm_class_tile_and_names_it_when_missing():
    """SegLocNet-NM's map side reads ``nm_tile`` (the OSM class raster's tile), not the binary
    ``tile``; a batch without it is refused naming the key (and where it comes from)."""
    batch = synthetic.make_batch(0, 1, num_cams=2, image_hw=(32, 64), num_points=128)
    assert batch["nm_tile"].shape == (1, len(maps.OSM_CLASSES), 256, 256)
    assert batch["nm_tile"].dtype == np.uint8
    assert synthetic.NUM_OSM_CLASSES == len(maps.OSM_CLASSES)
    names = maps.OSM_CLASS_NAMES
    assert (names[synthetic.OSM_ROAD], names[synthetic.OSM_BUILDING]) == ("road_minor", "building")
    cfg = preset("tiny", variant="nm", nm_dim=4, nm_widths=(4, 8))
    assert "nm_tile" in api.required_keys(cfg) and "tile" not in api.required_keys(cfg)
    without = {k: v for k, v in batch.items() if k != "nm_tile"}
    with pytest.raises(KeyError, match=r"\['nm_tile'\].*make_loader\(nm_tiles=True\)"):
        api.init(jax.random.key(0), without, cfg)
    # random parameters of the right shapes (compiling the initializers would take seconds)
    shapes = jax.eval_shape(
        neural_map.NeuralMapEncoder(cfg).init, jax.random.key(1), batch["nm_tile"]
    )["params"]
    rng = np.random.default_rng(0)
    params = {"neural_map": jax.tree.map(lambda x: rng.normal(0, 0.3, x.shape), shapes)}
    with pytest.raises(KeyError, match="nm_tile"):
        api.encode_map(params, without, cfg)
    encode = jax.jit(lambda p, tiles: api.encode_map(p, tiles, cfg))
    maps_of = {k: batch[k] for k in ("tile", "nm_tile")}
    base = np.asarray(encode(params, maps_of))
    assert base.shape == (1, 4, 256, 256)
    other_tile = dict(maps_of, tile=1.0 - batch["tile"])
    np.testing.assert_array_equal(encode(params, other_tile), base)
    other_classes = dict(maps_of, nm_tile=batch["nm_tile"][:, ::-1].copy())
    assert not np.allclose(encode(params, other_classes), base)


def test_missing_modality_is_configuration_not_a_crash():
    batch = synthetic.make_batch(0, 1, num_cams=2, image_hw=(32, 64), num_points=128)
    lidar_only = {k: v for k, v in batch.items() if k not in ("images", "intrinsics")}
    (logits, _), _ = _shapes(preset("tiny", modality="lidar"), lidar_only)
    assert logits.shape == (1, 2, 128, 128)
    with pytest.raises(KeyError, match="images"):
        _shapes(preset("tiny", modality="fused"), lidar_only)


def test_image_size_must_be_divisible_by_16():
    batch = synthetic.make_batch(0, 1, num_cams=1, image_hw=(40, 64), num_points=16)
    with pytest.raises(ValueError, match="divisible by 16"):
        _shapes(preset("tiny", modality="camera"), batch)


def test_bad_config_values_name_the_key():
    with pytest.raises(ValueError, match="model.modality"):
        ModelConfig(modality="radar")
    with pytest.raises(ValueError, match="model.lidar_widths"):
        ModelConfig(lidar_widths=(16, 32))
    with pytest.raises(ConfigError, match="model.embed_dim"):
        from_dict(ModelConfig, {"embed_dim": 30, "num_heads": 4}, "model")


@pytest.mark.parametrize("name", ["tiny", "paper"])
def test_hydra_presets_match_python_presets(name):
    with open(os.path.join(CONF_DIR, f"{name}.yaml")) as f:
        tree = yaml.safe_load(f)
    tree.pop("defaults", None)
    if name == "tiny":  # null: build_experiment derives it from map.channels (2 by default)
        assert tree["num_classes"] is None
        tree["num_classes"] = 2
    cfg = from_dict(ModelConfig, tree, "model")
    assert cfg == preset(name)
    assert dataclasses.replace(cfg, modality="camera").use_lidar is False


def test_ground_features_sample_each_cell_where_the_cameras_see_it():
    """Feature maps that are linear in the pixel coordinates (plus the camera's index) are
    interpolated exactly: each cell's sample is the feature-pixel coordinates of its projection
    into the camera that sees it most frontally, computed here in NumPy; unseen points read 0."""
    h, w, stride, size, heights, n = 16, 40, 4, 8, (0.0, 2.0), 3
    intr, cam = synthetic.camera_rig(n, 4 * h, 4 * w)
    vv, uu = np.meshgrid(*(np.arange(k, dtype=np.float32) for k in (h, w)), indexing="ij")
    stage = np.stack([np.stack([uu, vv, np.full_like(uu, i)], -1) for i in range(n)])[None]
    got = np.asarray(
        camera.ground_features(
            jax.numpy.asarray(stage), intr[None], cam[None], stride, size, heights
        )
    )
    assert got.shape == (1, size, size, len(heights) * 4)
    cells = camera.bev_reference_points(size).reshape(-1, 2) * 32.0
    want = np.zeros((size * size, len(heights), 3))
    best = np.full((size * size, len(heights)), -2.0)
    for i in range(n):
        to_cam = np.linalg.inv(np.asarray(cam[i], np.float64))
        for k, z in enumerate(heights):
            pts = np.concatenate([cells, np.full((len(cells), 1), z)], 1)
            c = pts @ to_cam[:3, :3].T + to_cam[:3, 3]
            uv = c @ np.asarray(intr[i], np.float64).T
            with np.errstate(divide="ignore", invalid="ignore"):
                f = (uv[:, :2] / c[:, 2:] - (stride - 1) / 2) / stride
            ok = (c[:, 2] > 0.1) & (f >= 0).all(1) & (f[:, 0] <= w - 1) & (f[:, 1] <= h - 1)
            cosine = np.where(ok, c[:, 2] / np.linalg.norm(c, axis=1), -2.0)
            better = cosine > best[:, k]
            best[better, k] = cosine[better]
            want[better, k] = np.concatenate([f, np.full((len(f), 1), i)], 1)[better]
    seen = best > -2
    assert 0 < seen.sum() < seen.size and len(np.unique(want[..., 2][seen])) == n
    feats = got[..., : 3 * len(heights)].reshape(size * size, len(heights), 3)
    np.testing.assert_allclose(feats, want, atol=2e-3)
    np.testing.assert_array_equal(got[..., 3 * len(heights) :].reshape(-1, len(heights)), seen)


def test_the_ground_skip_enters_the_decoder_at_64():
    batch = synthetic.make_batch(0, 2, num_cams=3, image_hw=(32, 96), num_points=256)
    for modality in ("camera", "fused"):
        cfg = preset("tiny", modality=modality, camera_ground_skip=True)
        (logits, _), variables = _shapes(cfg, batch)
        assert logits.shape == (2, 2, 128, 128)
        assert "ground_skip64" in variables["params"]["decoder"]
    off = preset("tiny", camera_ground_skip=False)
    assert "ground_skip64" not in _shapes(off, batch)[1]["params"]["decoder"]
