"""The exhaustive solver: signs pinned by a round trip, fft == conv, exact quarter turns,
sub-cell decoding, and the batched jitted entry point."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from seglocnet_jax import geometry as g
from seglocnet_jax import solver

K = g.NUM_ROTATIONS


class SyntheticRaster:
    """A CityRaster-like test double: a binary (C, H, W) mask on a RasterGrid, tiles around
    a point and BEVs cut at a pose by sampling the pixel under each BEV pixel centre."""

    def __init__(self, mask: np.ndarray, grid: g.RasterGrid):
        self.mask, self.grid = mask, grid

    def tile(self, x, y):
        row0, col0, cx, cy = g.tile_window(self.grid, x, y)
        return g.crop(self.mask, row0, col0, g.TILE_SIZE), (float(cx), float(cy))

    def cut_bev(self, pose):
        world = g.ego_to_world(pose, g.bev_cell_centers_ego())  # (128, 128, 2)
        row, col = self.grid.world_to_pixel(world[..., 0], world[..., 1])
        row, col = np.floor(row).astype(int), np.floor(col).astype(int)
        inside = (row >= 0) & (row < self.grid.height) & (col >= 0) & (col < self.grid.width)
        row, col = np.clip(row, 0, self.grid.height - 1), np.clip(col, 0, self.grid.width - 1)
        return self.mask[:, row, col] * inside


def blob_raster(seed: int = 0, size: int = 640) -> SyntheticRaster:
    """Random binary blobs (~5 px features) in 2 channels, 0.5 m/px, origin at the SW corner."""
    rng = np.random.default_rng(seed)
    mask = uniform_filter(rng.random((2, size, size)), size=(1, 9, 9)) > 0.5
    grid = g.RasterGrid(x_min=0.0, y_max=size * g.RESOLUTION, height=size, width=size)
    return SyntheticRaster(mask.astype(np.uint8), grid)


@pytest.fixture(scope="module")
def raster():
    return blob_raster()


@pytest.mark.parametrize("k", [0, K // 4, K // 2, 37, 201])
def test_round_trip_recovers_exact_cell(raster, k):
    # Yaw exactly on bin k, position on a pixel corner: argmax must return exactly that cell.
    yaw = float(g.yaw_from_rotation(k, K))
    pose = np.array([160.0 + k * 0.5 % 7, 150.5, yaw])
    prior = pose[:2] + np.array([-21.5, 30.0]) * (1 if k % 2 else -1)
    tile, (cx, cy) = raster.tile(*prior)
    bev = solver.labels_to_logits(raster.cut_bev(pose))
    out = solver.localize(bev[None], jnp.asarray(tile)[None], solver.SolverConfig(refine=False))
    h, w = g.tile_offset_to_cell(pose[0] - cx, pose[1] - cy)
    np.testing.assert_array_equal(np.asarray(out["cell"][0]), [k, h, w])
    np.testing.assert_allclose(out["pose_tile"][0, :2], [pose[0] - cx, pose[1] - cy], atol=1e-5)
    assert g.angle_error(float(out["pose_tile"][0, 2]), yaw) < 1e-5


@pytest.mark.parametrize(
    "num_rotations,size,tsize,channels,chunk",
    [
        (8, 128, 256, 2, 2),
        (256, 24, 48, 2, 2),
        (4, 32, 64, 2, 2),
        (16, 24, 48, 1, 0),
        (16, 24, 48, 3, 1),
        (4, 40, 48, 1, 2),  # tile < twice the BEV, one channel: the OSM alignment's shapes
    ],
)
def test_fft_matches_conv(num_rotations, size, tsize, channels, chunk):
    # Odd channel counts take the packing's zero channel; every rotation_chunk the same volume.
    rng = np.random.default_rng(num_rotations)
    bev = rng.normal(size=(channels, size, size)).astype(np.float32)
    tile = (rng.random((channels, tsize, tsize)) < 0.4).astype(np.float32)
    fft = solver.score_volume(bev, tile, num_rotations, "fft", rotation_chunk=chunk)
    conv = solver.score_volume(bev, tile, num_rotations, "conv")
    assert fft.shape == (num_rotations, tsize - size + 1, tsize - size + 1)
    scale = float(jnp.abs(conv).max())
    assert scale > 1.0
    np.testing.assert_allclose(fft, conv, atol=2e-6 * scale)


def test_batch_is_each_sample_alone():
    # The fft batch loops over the samples itself (batch_chunk=1): every volume is that
    # sample's own, also against the vmapped (0) and chunked (2) batches.
    rng = np.random.default_rng(3)
    bevs = rng.normal(size=(3, 2, 24, 24)).astype(np.float32)
    tiles = (rng.random((3, 2, 48, 48)) < 0.4).astype(np.float32)
    alone = np.stack([solver.score_volume(b, t, 8) for b, t in zip(bevs, tiles, strict=True)])
    np.testing.assert_array_equal(solver.score_volume_batch(bevs, tiles, 8), alone)
    scale = float(np.abs(alone).max())
    for batch_chunk in (0, 2):
        batch = solver.score_volume_batch(bevs, tiles, 8, batch_chunk=batch_chunk)
        np.testing.assert_allclose(batch, alone, atol=1e-6 * scale)


def test_quarter_turns_are_exact_rot90():
    rng = np.random.default_rng(1)
    bev = jnp.asarray(rng.normal(size=(2, 16, 16)).astype(np.float32))
    templates = solver.rotated_templates(bev, 16)  # (16, 2, 16, 16)
    for q in range(4):
        np.testing.assert_array_equal(templates[4 * q], np.rot90(bev, q, axes=(1, 2)))
    # The bilinear path turns the same way (counterclockwise as displayed).
    turned = solver.rotate_bev(bev, jnp.array([math.pi / 2, -math.pi / 2]))
    np.testing.assert_allclose(turned[0], np.rot90(bev, 1, axes=(1, 2)), atol=1e-5)
    np.testing.assert_allclose(turned[1], np.rot90(bev, -1, axes=(1, 2)), atol=1e-5)


def test_rotating_the_bev_by_90_shifts_the_volume_by_a_quarter():
    rng = np.random.default_rng(2)
    bev = rng.normal(size=(2, 32, 32)).astype(np.float32)
    tile = (rng.random((2, 64, 64)) < 0.4).astype(np.float32)
    base = solver.score_volume(bev, tile, 16)
    turned = solver.score_volume(np.rot90(bev, 1, axes=(1, 2)).copy(), tile, 16)
    np.testing.assert_allclose(turned, jnp.roll(base, -4, axis=0), atol=1e-3)


def test_bilinear_rotation_keeps_zeros_outside():
    bev = jnp.ones((1, 16, 16))
    turned = solver.rotate_bev(bev, jnp.array([math.pi / 4]))[0, 0]
    assert float(turned[0, 0]) == 0.0  # corner comes from outside the image
    assert float(turned[8, 8]) == pytest.approx(1.0)


def _quadratic_volume(k0, h0, w0, num_k=16, n=9):
    k = np.arange(num_k)[:, None, None]
    dk = (k - k0 + num_k / 2) % num_k - num_k / 2  # wrapped distance in bins
    h = np.arange(n)[None, :, None]
    w = np.arange(n)[None, None, :]
    return jnp.asarray(-(dk**2) - 2 * (h - h0) ** 2 - 3 * (w - w0) ** 2, jnp.float32)


@pytest.mark.parametrize("k0", [5.2, 15.3, -0.4])
def test_decode_refines_quadratic_peak_with_k_wrap(k0):
    vol = _quadratic_volume(k0, 3.7, 4.1)
    cell, _ = solver.decode_cell(vol, refine=True)
    np.testing.assert_allclose(cell, [k0, 3.7, 4.1], atol=1e-4)
    cell, peak = solver.decode_cell(vol, refine=False)
    np.testing.assert_array_equal(cell, [round(k0) % 16, 4, 4])
    assert float(peak) == float(vol.max())


def test_decode_does_not_refine_on_the_border():
    vol = _quadratic_volume(3.0, -0.3, 8.4)
    cell, _ = solver.decode_cell(vol[None].repeat(2, 0), refine=True)  # batched
    np.testing.assert_allclose(cell, [[3.0, 0.0, 8.0]] * 2, atol=1e-5)


def test_log_softmax_volume_normalizes_and_differentiates():
    vol = jnp.asarray(np.random.default_rng(4).normal(size=(2, 4, 5, 5)), jnp.float32)
    logp = solver.log_softmax_volume(vol, temperature=0.5)
    np.testing.assert_allclose(jnp.exp(logp).sum(axis=(1, 2, 3)), [1.0, 1.0], rtol=1e-5)
    grad = jax.grad(lambda v: -solver.log_softmax_volume(v)[0, 1, 2, 3])(vol)
    assert float(grad[0, 1, 2, 3]) < 0 and bool(jnp.all(jnp.isfinite(grad)))
    assert float(jnp.abs(grad[1]).max()) == 0.0  # samples are independent


def test_labels_to_logits_is_plus_minus_one():
    np.testing.assert_array_equal(solver.labels_to_logits(np.array([0, 1, 1])), [-1.0, 1.0, 1.0])


def test_localize_batch_shapes_and_single_compile(raster):
    cfg = solver.SolverConfig(num_rotations=8)
    bev = solver.labels_to_logits(np.stack([raster.cut_bev([100.0, 100.0, 0.3])] * 2))
    tile = np.stack([raster.tile(100.0, 100.0)[0]] * 2).astype(np.float32)
    before = solver.localize._cache_size()
    out = solver.localize(bev, tile, cfg, return_volume=True)
    out = solver.localize(bev + 0.0, tile * 1.0, cfg, return_volume=True)
    assert solver.localize._cache_size() == before + 1
    assert out["pose_tile"].shape == (2, 3) and out["cell"].shape == (2, 3)
    assert out["volume"].shape == (2, 8, 129, 129) and out["score"].shape == (2,)
    np.testing.assert_allclose(out["score"], out["volume"].max(axis=(1, 2, 3)))


def test_bad_config_and_shapes_are_reported():
    with pytest.raises(ValueError, match="num_rotations"):
        solver.SolverConfig(num_rotations=6)
    with pytest.raises(ValueError, match="method"):
        solver.SolverConfig(method="dft")
    with pytest.raises(ValueError, match="square"):
        solver.score_volume(np.zeros((2, 8, 6)), np.zeros((2, 16, 16)), 4)


def test_gradients_of_fft_and_conv_agree():
    # The neural-map variant trains through the volume (NLL of the GT cell): both paths must
    # give the same gradients to the BEV and to the tile.
    rng = np.random.default_rng(5)
    bev = jnp.asarray(rng.normal(size=(1, 2, 16, 16)), jnp.float32)
    tile = jnp.asarray(rng.random((1, 2, 32, 32)), jnp.float32)

    def nll(bev, tile, method):
        vol = solver.score_volume_batch(bev, tile, 8, method)
        return -solver.log_softmax_volume(vol, temperature=10.0)[0, 3, 5, 7]

    ffts = jax.grad(nll, argnums=(0, 1))(bev, tile, "fft")  # to the BEV and to the tile
    convs = jax.grad(nll, argnums=(0, 1))(bev, tile, "conv")
    for fft, conv in zip(ffts, convs, strict=True):
        assert float(jnp.abs(conv).max()) > 1e-3
        np.testing.assert_allclose(fft, conv, atol=1e-4 * float(jnp.abs(conv).max()))
