"""Pins the conventions of seglocnet_jax.geometry with hand-made cases and NumPy references."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from seglocnet_jax import geometry as g


def test_wrap_angle_range_and_pi():
    a = np.array([math.pi, -math.pi, 3 * math.pi, 0.0, 2 * math.pi + 0.1, -0.1])
    w = g.wrap_angle(a)
    np.testing.assert_allclose(w, [math.pi, math.pi, math.pi, 0.0, 0.1, -0.1], atol=1e-12)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)


def test_angle_error_wraps():
    assert g.angle_error(math.radians(179), math.radians(-179)) == pytest.approx(math.radians(2))
    assert g.angle_error(0.0, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_grid_corner_and_centre_conventions():
    grid = g.RasterGrid(x_min=100.0, y_max=50.0, height=10, width=20)
    # Row 0 is the north edge, column 0 the west edge; integers are corners.
    x, y = grid.pixel_to_world(0, 0)
    assert (x, y) == (100.0, 50.0)
    x, y = grid.pixel_to_world(0.5, 0.5)  # centre of pixel [0, 0]
    assert (x, y) == (100.25, 49.75)
    r, c = grid.world_to_pixel(101.0, 49.0)
    assert (r, c) == (2.0, 2.0)
    assert grid.bounds == (100.0, 45.0, 110.0, 50.0)


def test_grid_covering_snaps_outward():
    grid = g.RasterGrid.covering((0.3, -0.2, 9.9, 4.1))
    assert grid.x_min == 0.0 and grid.y_max == 4.5
    assert grid.bounds[2] >= 9.9 and grid.bounds[1] <= -0.2


def test_tile_window_centre_is_snapped_corner():
    grid = g.RasterGrid(x_min=0.0, y_max=200.0, height=400, width=400)
    row0, col0, cx, cy = g.tile_window(grid, 100.1, 99.8)
    assert (cx, cy) == (100.0, 100.0)
    assert (row0, col0) == (200 - 128, 200 - 128)


def test_crop_pads_with_zeros_outside_the_array():
    a = np.arange(2 * 5 * 6).reshape(2, 5, 6) + 1  # no zeros inside
    np.testing.assert_array_equal(g.crop(a, 1, 2, 3), a[:, 1:4, 2:5])
    out = g.crop(a, -1, 4, 3)  # one row above, one column right of the array
    assert out.shape == (2, 3, 3) and out.dtype == a.dtype
    np.testing.assert_array_equal(out[:, 1:, :2], a[:, :2, 4:])
    assert not out[:, 0].any() and not out[:, :, 2].any()
    assert not g.crop(a, 10, 10, 4).any()  # entirely outside
    inside = g.crop(a, 0, 0, 2)
    inside[:] = 0  # a copy: the source is untouched
    assert a.min() == 1


def test_priors_lie_within_the_prior_range_of_the_pose():
    xy = np.array([[100.0, -50.0]] * 2000)
    priors = g.sample_priors(xy, np.random.default_rng(0))
    off = priors - xy
    assert priors.shape == xy.shape
    assert np.abs(off).max() <= g.PRIOR_RANGE and np.abs(off).max() > 0.95 * g.PRIOR_RANGE
    assert abs(off.mean()) < 1.5  # centred (the std of the mean is ~0.4 m)
    one = g.sample_priors(xy[0], np.random.default_rng(0))  # (2,): the first draws
    np.testing.assert_array_equal(one, priors[0])


def test_ego_world_round_trip_and_heading():
    pose = np.array([10.0, -5.0, math.pi / 2])  # heading north
    fwd = g.ego_to_world(pose, np.array([1.0, 0.0]))
    np.testing.assert_allclose(fwd, [10.0, -4.0], atol=1e-12)
    left = g.ego_to_world(pose, np.array([0.0, 1.0]))
    np.testing.assert_allclose(left, [9.0, -5.0], atol=1e-12)  # left of north is west
    pts = np.random.default_rng(0).normal(size=(5, 2))
    np.testing.assert_allclose(g.world_to_ego(pose, g.ego_to_world(pose, pts)), pts, atol=1e-12)


def test_bev_cells_forward_is_up_right_is_right():
    c = g.bev_cell_centers_ego()
    assert c.shape == (g.BEV_SIZE, g.BEV_SIZE, 2)
    # Top-left pixel: far front, left side.
    np.testing.assert_allclose(c[0, 0], [31.75, 31.75])
    # Pixel just below-right of the ego corner: slightly behind and to the right.
    np.testing.assert_allclose(c[64, 64], [-0.25, -0.25])
    r, col = g.ego_to_bev_pixel(c)
    np.testing.assert_allclose(r, np.arange(128)[:, None] + 0.5 + 0 * col)
    np.testing.assert_allclose(col, np.arange(128)[None, :] + 0.5 + 0 * r)


def test_heading_north_bev_is_an_unrotated_map_crop():
    # Heading north (k = 0), each BEV pixel centre is a map pixel centre of the same layout.
    grid = g.RasterGrid(x_min=0.0, y_max=100.0, height=200, width=200)
    pose = np.array([50.0, 50.0, math.pi / 2])
    world = g.ego_to_world(pose, g.bev_cell_centers_ego())
    r, c = grid.world_to_pixel(world[..., 0], world[..., 1])
    np.testing.assert_allclose(r - 0.5, 36 + np.arange(128)[:, None] + 0 * c, atol=1e-9)
    np.testing.assert_allclose(c - 0.5, 36 + np.arange(128)[None, :] + 0 * r, atol=1e-9)


def test_rotation_yaw_mapping():
    K = 256
    assert g.yaw_from_rotation(0, K) == pytest.approx(math.pi / 2)
    assert g.yaw_from_rotation(K // 4, K) == pytest.approx(math.pi)  # turned CCW 90: west
    assert g.yaw_from_rotation(3 * K // 4, K) == pytest.approx(0.0, abs=1e-12)  # east
    ks = np.arange(K)
    np.testing.assert_allclose(g.rotation_from_yaw(g.yaw_from_rotation(ks, K), K), ks, atol=1e-9)


def test_cell_offset_mapping():
    dx, dy = g.cell_to_tile_offset(64, 64)
    assert (dx, dy) == (0.0, 0.0)
    dx, dy = g.cell_to_tile_offset(0, 128)  # top-right cell: north-east of the centre
    assert (dx, dy) == (32.0, 32.0)
    h, w = g.tile_offset_to_cell(dx, dy)
    assert (h, w) == (0.0, 128.0)


def test_pose_from_matrix_reads_yaw_ccw_from_east_and_drops_tilt():
    yaw, pitch = 2.5, 0.1
    rz = np.array(
        [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    )
    ry = np.array(
        [[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]]
    )
    t = np.eye(4)
    t[:3, :3] = rz @ ry
    t[:3, 3] = [10.0, -3.0, 2.0]
    np.testing.assert_allclose(g.pose_from_matrix(t), [10.0, -3.0, yaw], atol=1e-12)
    # The ego forward axis maps to world (cos yaw, sin yaw), as ego_to_world says.
    fwd = g.ego_to_world(g.pose_from_matrix(t), np.array([1.0, 0.0])) - [10.0, -3.0]
    np.testing.assert_allclose(fwd, [math.cos(yaw), math.sin(yaw)], atol=1e-12)


def test_cell_pose_conversions_agree_in_numpy_and_jitted_jax():
    """One function per conversion: NumPy (float64) and JAX (float32, under jit) agree, and
    pose_to_cell inverts cell_to_pose."""
    K = 256
    rng = np.random.default_rng(3)
    cells = rng.uniform([0, 0, 0], [K, 128, 128], size=(50, 3))
    pose_np = g.cell_to_pose(cells, K)
    assert pose_np.dtype == np.float64
    pose_jax = jax.jit(g.cell_to_pose, static_argnums=1)(jnp.asarray(cells, jnp.float32), K)
    assert isinstance(pose_jax, jax.Array)
    np.testing.assert_allclose(np.asarray(pose_jax)[:, :2], pose_np[:, :2], atol=1e-4)
    assert np.all(g.angle_error(np.asarray(pose_jax)[:, 2], pose_np[:, 2]) < 1e-5)
    # Each column is the scalar conversion of its cell.
    dx, dy = g.cell_to_tile_offset(cells[:, 1], cells[:, 2])
    np.testing.assert_array_equal(pose_np[:, 0], dx)
    np.testing.assert_array_equal(pose_np[:, 1], dy)
    np.testing.assert_array_equal(pose_np[:, 2], g.yaw_from_rotation(cells[:, 0], K))
    np.testing.assert_allclose(g.pose_to_cell(pose_np, K), cells, atol=1e-9)
    back = jax.jit(g.pose_to_cell, static_argnums=1)(pose_jax, K)
    np.testing.assert_allclose(np.asarray(back), cells, atol=1e-3)
    # The centre cell, heading north, is the tile centre.
    np.testing.assert_allclose(g.cell_to_pose(np.array([0, 64, 64]), K), [0, 0, math.pi / 2])


def test_ego_to_bev_pixel_agrees_in_numpy_and_jax():
    pts = np.random.default_rng(1).uniform(-40, 40, size=(100, 2))
    r_np, c_np = g.ego_to_bev_pixel(pts)
    r_j, c_j = jax.jit(g.ego_to_bev_pixel)(jnp.asarray(pts, jnp.float32))
    np.testing.assert_allclose(np.asarray(r_j), r_np, atol=1e-4)
    np.testing.assert_allclose(np.asarray(c_j), c_np, atol=1e-4)
