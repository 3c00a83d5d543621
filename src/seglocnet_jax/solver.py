"""Exhaustive pose solver: rotate the BEV, correlate it with the map tile, decode the best cell.

The score volume (``geometry`` owns what its cells mean)::

    M[k, h, w] = sum_{c, i, j} F'[c, k, i, j] * T[c, h + i, w + j]      # (K, 129, 129)

where ``F'[:, k]`` is the BEV (``(C, 128, 128)``, forward = up) turned counterclockwise as
displayed by ``2 pi k / K`` about the ego point (the pixel corner at ``(64, 64)``), bilinear with
zeros outside; multiples of 90 degrees are exact ``rot90``s. ``T`` is the ``(C, 256, 256)`` tile.
Cell ``(k, h, w)`` stands for the tile-frame pose given by :func:`geometry.cell_to_pose`
(:func:`geometry.pose_to_cell` is its inverse).

Two methods compute ``M``: ``"conv"`` (``lax.conv_general_dilated``, the reference) and ``"fft"``
(the default, ~100x less work). The FFT path (:func:`_score_fft`):

- a 256-point transform holds the whole valid 129x129 correlation without wrap-around;
- only ``K/4`` angles are resampled; the other three quarters turn the *tile* instead:
  ``corr(rot90(F, q), T) = rot90(corr(F, rot90(T, -q)), q)`` for square ``F``, ``T``;
- channel pairs of a template are packed as one complex image, transformed once, and told
  apart in the spectrum by ``F_c(-f) = conj(F_c(f))``; the spectra live on the half-bin grid
  ``f + 1/2``, where ``-f`` is the reversed array (no wrap-around index), and the valid
  correlations are unchanged by that shift;
- quarter turns ``q`` and ``q + 2`` share one complex inverse (real and imaginary parts);
- transforms are 2-D XLA FFTs (one forward per angle, one inverse per quarter pair): on CPU,
  1-D passes that skip the padding rows need a transpose between passes, and XLA's transposes
  cost as much as the FFT work they save;
- the angles are looped over in chunks, each turned copy sampled straight into the corner of a
  zero-padded transform input (bilinear points tabulated once with NumPy) and each quarter's
  valid correlation written in place into the volume: per chunk, the working set stays in cache.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry

METHODS = ("fft", "conv")


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Configuration of the exhaustive solver.

    Attributes:
      num_rotations: K, rotation bins over the full turn; K % 4 == 0 (paper: 256).
      method: "fft" (default, fast) or "conv" (direct correlation, reference).
      refine: sub-cell refinement of the argmax by separable quadratic fits in h, w and k.
      rotation_chunk: fft templates transformed together (0: all K/4; see :func:`score_volume`).
      batch_chunk: samples vmapped together (0: the whole batch; see
        :func:`score_volume_batch`). The defaults are the fastest on CPU; use 0 and 0 on GPU.
    """

    num_rotations: int = geometry.NUM_ROTATIONS
    method: str = "fft"
    refine: bool = True
    rotation_chunk: int = 2
    batch_chunk: int = 1

    def __post_init__(self):
        if self.num_rotations <= 0 or self.num_rotations % 4:
            raise ValueError(
                f"solver.num_rotations must be a positive multiple of 4, got {self.num_rotations}"
            )
        if self.method not in METHODS:
            raise ValueError(f"solver.method must be one of {METHODS}, got {self.method!r}")
        for key in ("rotation_chunk", "batch_chunk"):
            if getattr(self, key) < 0:
                raise ValueError(f"solver.{key} must be >= 0, got {getattr(self, key)}")


# --------------------------------------------------------------------------- BEV rotation


def rotate_bev(bev: jax.Array, angles: jax.Array) -> jax.Array:
    """Turns a square BEV counterclockwise (as displayed) about its central pixel corner.

    Args:
      bev: ``(C, S, S)`` image, row 0 at the top.
      angles: ``(M,)`` radians.

    Returns:
      ``(M, C, S, S)``: bilinear samples, zero where the source lies outside the image.
    """
    xp = np if isinstance(angles, np.ndarray) else jnp
    return jnp.stack(_rotate_channels(bev, _source_terms(angles, bev.shape[1], xp)), axis=1)


def _source_terms(angles, size: int, xp=np) -> tuple:
    """Where each pixel of the turned BEV samples the BEV, as four ``(M, S)`` tables:
    ``col[m, i, j] = cu[m, j] - sv[m, i]`` and ``row[m, i, j] = su[m, j] + cv[m, i]`` (source
    pixel centres at integers; the inverse rotation, image y down). Static angles (``np``) are
    tabulated in float64 and rounded once, so every path samples at the same float32 points
    (one subtraction or addition each, nothing for XLA to contract or fold differently)."""
    half = size / 2
    centre = xp.arange(size) + 0.5 - half  # pixel centres about the ego
    cos, sin = xp.cos(angles)[:, None], xp.sin(angles)[:, None]
    terms = (cos * centre + half - 0.5, sin * centre, sin * centre + half - 0.5, cos * centre)
    return tuple(xp.asarray(t, xp.float32) for t in terms)


def _rotate_channels(bev: jax.Array, terms: tuple) -> list[jax.Array]:
    """:func:`rotate_bev` at the :func:`_source_terms` ``terms``, as ``C`` arrays ``(M, S, S)``,
    one per channel (scalar gathers: the fast kind on CPU)."""
    c_dim, size, _ = bev.shape
    cu, sv, su, cv = (jnp.asarray(t) for t in terms)
    col, row = _sample_points(cu, sv, su, cv)  # (M, S, S), u: right, v: down
    col0, row0 = jnp.floor(col), jnp.floor(row)
    fc, fr = col - col0, row - row0
    col0, row0 = col0.astype(jnp.int32), row0.astype(jnp.int32)
    flat = bev.reshape(c_dim, size * size)
    out = [jnp.zeros(col.shape, bev.dtype)] * c_dim
    for dr, dc, weight in (
        (0, 0, (1 - fr) * (1 - fc)),
        (0, 1, (1 - fr) * fc),
        (1, 0, fr * (1 - fc)),
        (1, 1, fr * fc),
    ):
        r, c = row0 + dr, col0 + dc
        inside = (r >= 0) & (r < size) & (c >= 0) & (c < size)
        idx = jnp.clip(r, 0, size - 1) * size + jnp.clip(c, 0, size - 1)
        weight = jnp.where(inside, weight, 0.0).astype(bev.dtype)
        out = [o + flat[ch][idx] * weight for ch, o in enumerate(out)]
    return out


def rotated_templates(bev: jax.Array, num_rotations: int) -> jax.Array:
    """All K turned copies ``F'``: ``(C, S, S)`` -> ``(K, C, S, S)``; k = 0 is ``bev`` itself."""
    base = _quarter_templates(bev, num_rotations)  # (K/4, C, S, S)
    return jnp.concatenate([jnp.rot90(base, q, axes=(2, 3)) for q in range(4)], axis=0)


def _quarter_templates(bev: jax.Array, num_rotations: int) -> jax.Array:
    """Turned copies for k in [0, K/4): ``(K/4, C, S, S)``; k = 0 is exact."""
    quarter = num_rotations // 4
    if quarter == 1:
        return bev[None]
    angles = geometry.rotation_angle(np.arange(1, quarter), num_rotations)
    return jnp.concatenate([bev[None], rotate_bev(bev, angles)], axis=0)


# --------------------------------------------------------------------------- score volume


def _check_shapes(bev, tile):
    if bev.ndim != 3 or tile.ndim != 3 or bev.shape[0] != tile.shape[0]:
        raise ValueError(
            f"score_volume expects bev (C, S, S) and tile (C, T, T), got "
            f"{bev.shape} and {tile.shape}"
        )
    if bev.shape[1] != bev.shape[2] or tile.shape[1] != tile.shape[2]:
        raise ValueError(f"bev and tile must be square, got {bev.shape} and {tile.shape}")
    if bev.shape[1] % 2 or tile.shape[1] % 2 or tile.shape[1] < bev.shape[1]:
        raise ValueError(
            f"bev and tile sizes must be even with tile >= bev, got "
            f"{bev.shape[1]} and {tile.shape[1]}"
        )


def _score_conv(bev, tile, num_rotations):
    templates = rotated_templates(bev, num_rotations)  # (K, C, S, S)
    out = jax.lax.conv_general_dilated(
        tile[None],
        templates,
        window_strides=(1, 1),
        padding="VALID",
        dimension_numbers=("NCHW", "OIHW", "NCHW"),
        precision=jax.lax.Precision.HIGHEST,
    )
    return out[0]  # (K, T-S+1, T-S+1)


def _half_phase(rows: int, cols: int, length: int, sign: int) -> np.ndarray:
    """``exp(sign i pi (a + b) / length)`` on a ``(rows, cols)`` grid: the half-bin shift."""
    a, b = np.arange(rows)[:, None], np.arange(cols)[None, :]
    return np.exp(sign * 1j * np.pi * (a + b) / length).astype(np.complex64)


@functools.lru_cache(maxsize=8)
def _sampling_tables(num_rotations: int, size: int) -> tuple[np.ndarray, tuple]:
    """Where the ``K/4`` turned copies sample the BEV, tabulated once per ``(K, S)``.

    Returns ``base`` ``(K/4, S, S)`` int32, the flat index of each sample's top-left neighbour
    in the BEV padded with one zero row and column before and two after (``(S + 3)^2``
    pixels; a neighbourhood wholly outside points at the all-zero bottom-right block), and
    :func:`_source_terms` ``(K/4, S)`` of the same angles, from which :func:`_turn_pairs`
    forms the fractions: the points are :func:`rotate_bev`'s, in the same float32 arithmetic.
    """
    angles = geometry.rotation_angle(np.arange(num_rotations // 4), num_rotations)
    terms = _source_terms(angles, size)
    col, row = _sample_points(*terms)
    col0, row0 = np.floor(col), np.floor(row)
    width = size + 3
    near = (row0 >= -1) & (row0 <= size - 1) & (col0 >= -1) & (col0 <= size - 1)
    base = np.where(near, (row0 + 1) * width + col0 + 1, (size + 1) * (width + 1))
    return base.astype(np.int32), terms


def _sample_points(cu, sv, su, cv):
    """Columns and rows ``(M, S, S)`` sampled by the turned copies (see :func:`_source_terms`;
    NumPy or JAX, the same float32 arithmetic)."""
    return cu[:, None, :] - sv[:, :, None], su[:, None, :] + cv[:, :, None]


def _turn_pairs(pairs: jax.Array, base: jax.Array, terms: tuple) -> jax.Array:
    """Turned copies of channel pairs packed as complex images, bilinear at the
    :func:`_sampling_tables` rows ``base`` ``(M, S, S)`` and ``terms`` ``(M, S)``:
    ``(C/2, S, S)`` complex -> ``(M, C/2, S, S)``. Four scalar gathers per sample (both
    channels at once); a neighbour outside the BEV reads a zero instead of being weighted by
    zero, as :func:`_rotate_channels` does."""
    size = pairs.shape[-1]
    width = size + 3
    col, row = _sample_points(*terms)
    fc, fr = col - jnp.floor(col), row - jnp.floor(row)
    flat = jnp.pad(pairs, ((0, 0), (1, 2), (1, 2))).reshape(pairs.shape[0], -1)
    gather = jax.vmap(lambda idx: flat[:, idx])  # (M, S, S) -> (M, C/2, S, S)

    def corner(offset, weight):
        return gather(base + offset) * weight[:, None]

    out = corner(0, (1 - fr) * (1 - fc)) + corner(1, (1 - fr) * fc)
    return out + corner(width, fr * (1 - fc)) + corner(width + 1, fr * fc)


def _tile_spectra(tile: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The tile side of the fft path, once per sample: ``A, B`` ``(C/2, 2, T, T)``.

    For channel pair ``j`` and quarter pair ``p`` (quarters ``p`` and ``p + 2``), with
    ``h_c = rot90(T_c, -p) + i rot90(T_c, -p - 2)``: ``A`` is the spectrum of
    ``(h_2j + i h_2j+1) / 2`` and ``B`` that of ``(h_2j - i h_2j+1) / 2``, on the half-bin grid.
    Only quarters 0 and 1 are transformed (channel pairs packed, ``G``): on the half-bin grid
    a half turn of a real image ``x`` has the spectrum ``phi * conj(X)``,
    ``phi[k, l] = exp(2 pi i (k + l + 1) / T)``, so ``A = (G + i phi G(-f)) / 2`` and
    ``B = (conj(G(-f)) + i phi conj(G)) / 2``.
    """
    c_dim, tsize = tile.shape[0], tile.shape[1]
    turned = [[jnp.rot90(tile[ch], -p) for p in range(2)] for ch in range(c_dim)]
    pairs = range(c_dim // 2)
    parts = [turned[2 * j][p] + 1j * turned[2 * j + 1][p] for j in pairs for p in (0, 1)]
    g = jnp.fft.fft2(jnp.stack(parts) * _half_phase(tsize, tsize, tsize, -1))
    g = g.reshape(c_dim // 2, 2, tsize, tsize)  # (C/2, 2, T, T)
    g_rev = jnp.flip(g, (-2, -1))  # G(-f) on the half-bin grid
    omega = np.exp(2j * np.pi * (np.arange(tsize) + 0.5) / tsize)
    i_phi = (1j * omega[:, None] * omega[None, :]).astype(np.complex64)
    return (g + i_phi * g_rev) / 2, (jnp.conj(g_rev) + i_phi * jnp.conj(g)) / 2


def _score_fft(bevs, tiles, num_rotations, rotation_chunk):
    """The fft path over samples in sequence: ``(B, C, S, S)``, ``(B, C, T, T)`` ->
    ``(B, K, T - S + 1, T - S + 1)``, each sample's quarters written in place into the one
    output (no per-sample volume to initialize and copy into a stacked result)."""
    if bevs.shape[1] % 2:  # channels go in pairs: one zero channel more changes no score
        bevs, tiles = (jnp.concatenate([x, jnp.zeros_like(x[:, :1])], 1) for x in (bevs, tiles))
    batch, c_dim, size, tsize = bevs.shape[0], bevs.shape[1], bevs.shape[2], tiles.shape[2]
    n_valid = tsize - size + 1
    quarter = num_rotations // 4
    chunk = math.gcd(quarter, rotation_chunk) if rotation_chunk else quarter
    mod_in = _half_phase(size, size, tsize, -1)
    mod_out = _half_phase(n_valid, n_valid, tsize, 1)
    base, terms = _sampling_tables(num_rotations, size)
    base = base.reshape(-1, chunk, size, size)
    terms = [t.reshape(-1, chunk, size) for t in terms]

    def sample(b, carry):
        a_hat, b_hat = _tile_spectra(tiles[b])  # (C/2, 2, T, T)
        pairs = jax.lax.complex(bevs[b, 0::2], bevs[b, 1::2])  # (C/2, S, S)

        def step(i, carry):  # chunk i of the quarter's angles
            padded, out = carry
            turned = _turn_pairs(pairs, jnp.asarray(base)[i], [jnp.asarray(t)[i] for t in terms])
            turned = turned * mod_in
            # Only the template's corner changes: the zero padding of the carry stays as it is.
            padded = jax.lax.dynamic_update_slice(padded, turned, (0, 0, 0, 0))
            z = jnp.fft.fft2(padded)  # (chunk, C/2, T, T)
            # Z(-f) is the reversed array on the half-bin grid: conj(F_c) = (conj(Z) + Z(-f))/2...
            spec = jnp.conj(z)[:, :, None] * a_hat + jnp.flip(z, (-2, -1))[:, :, None] * b_hat
            corr = jnp.fft.ifft2(spec.sum(axis=1))  # (chunk, 2, T, T): quarters (0, 2), (1, 3)
            for q in range(4):  # in place, one quarter at a time: no assembly pass
                part = corr[:, q % 2, :n_valid, :n_valid] * mod_out
                part = jnp.rot90(jnp.real(part) if q < 2 else jnp.imag(part), q, axes=(1, 2))
                out = jax.lax.dynamic_update_slice(out, part[None, None], (b, q, i * chunk, 0, 0))
            return padded, out

        return jax.lax.fori_loop(0, quarter // chunk, step, carry)

    padded = jnp.zeros((chunk, c_dim // 2, tsize, tsize), jnp.complex64)
    out = jnp.zeros((batch, 4, quarter, n_valid, n_valid), jnp.float32)
    _, out = jax.lax.fori_loop(0, batch, sample, (padded, out))
    return out.reshape(batch, num_rotations, n_valid, n_valid)


@functools.partial(jax.jit, static_argnames=("num_rotations", "method", "rotation_chunk"))
def score_volume(
    bev: jax.Array,
    tile: jax.Array,
    num_rotations: int = geometry.NUM_ROTATIONS,
    method: str = "fft",
    rotation_chunk: int = 2,
) -> jax.Array:
    """Raw score volume of one sample.

    Args:
      bev: ``(C, 128, 128)`` BEV logits in the ego frame (forward = up).
      tile: ``(C, 256, 256)`` map tile, north-up, centred on the snapped prior.
      num_rotations: K (multiple of 4).
      method: "fft" or "conv"; they agree to float32 tolerance.
      rotation_chunk: fft only: templates transformed together (0: all ``K/4`` at once, best on
        accelerators; 1-2 is fastest on CPU). Rounded down to a divisor of ``K/4``.

    Returns:
      ``(K, 129, 129)`` float32, ``M[k, h, w]`` as in the module docstring. No normalization.
    """
    SolverConfig(num_rotations=num_rotations, method=method)  # validates
    bev = jnp.asarray(bev, jnp.float32)
    tile = jnp.asarray(tile, jnp.float32)
    _check_shapes(bev, tile)
    if method == "conv":
        return _score_conv(bev, tile, num_rotations)
    return _score_fft(bev[None], tile[None], num_rotations, rotation_chunk)[0]


@functools.partial(
    jax.jit, static_argnames=("num_rotations", "method", "rotation_chunk", "batch_chunk")
)
def score_volume_batch(
    bevs: jax.Array,
    tiles: jax.Array,
    num_rotations: int = geometry.NUM_ROTATIONS,
    method: str = "fft",
    rotation_chunk: int = 2,
    batch_chunk: int = 1,
) -> jax.Array:
    """:func:`score_volume` over a batch: ``(B, C, 128, 128)``, ``(B, C, 256, 256)`` ->
    ``(B, K, 129, 129)``.

    ``batch_chunk`` samples are vmapped together and the chunks run in sequence
    (``lax.map``); 0 vmaps the whole batch (accelerators). One sample at a time is fastest on
    CPU, where a sample already fills the caches; the fft method then loops over the samples
    itself and writes every volume in place (``lax.map`` zero-fills each sample's volume and
    copies it into the stacked result: ~9 ms of ~90 per sample at batch 8).
    """
    if method == "fft" and batch_chunk == 1 and bevs.shape[0] > 1:
        bevs = jnp.asarray(bevs, jnp.float32)
        tiles = jnp.asarray(tiles, jnp.float32)
        SolverConfig(num_rotations=num_rotations, method=method)  # validates
        _check_shapes(bevs[0], tiles[0])
        return _score_fft(bevs, tiles, num_rotations, rotation_chunk)
    fn = functools.partial(
        score_volume, num_rotations=num_rotations, method=method, rotation_chunk=rotation_chunk
    )
    if not batch_chunk or batch_chunk >= bevs.shape[0]:
        return jax.vmap(fn)(bevs, tiles)
    return jax.lax.map(lambda x: fn(*x), (bevs, tiles), batch_size=batch_chunk)


def log_softmax_volume(volume: jax.Array, temperature: float = 1.0) -> jax.Array:
    """Log-probabilities over all cells of each ``(K, H, W)`` volume (leading dims are batch).

    Differentiable; ``temperature`` divides the scores first (the raw volume sums ~10^4 terms).
    """
    k, h, w = volume.shape[-3:]
    flat = volume.reshape(volume.shape[:-3] + (k * h * w,)) / temperature
    return jax.nn.log_softmax(flat, axis=-1).reshape(volume.shape)


def labels_to_logits(labels) -> jax.Array:
    """{0, 1} labels to +-1 logits: a confident network that penalizes road on non-road."""
    return 2.0 * jnp.asarray(labels, jnp.float32) - 1.0


# --------------------------------------------------------------------------- decoding


def _parabola_offset(left, centre, right):
    """Vertex of the parabola through (-1, left), (0, centre), (1, right), in [-0.5, 0.5];
    0 where the three points do not form a maximum."""
    denom = left - 2.0 * centre + right
    safe = jnp.where(denom < 0, denom, -1.0)
    return jnp.where(denom < 0, jnp.clip(0.5 * (left - right) / safe, -0.5, 0.5), 0.0)


def decode_cell(volume: jax.Array, refine: bool = True) -> tuple[jax.Array, jax.Array]:
    """Best cell of ``(..., K, H, W)`` volumes.

    Returns:
      ``cell (..., 3)`` float32 ``(k, h, w)``, fractional when ``refine`` (k wraps into
      ``[-0.5, K - 0.5)``; h, w are not refined on the volume's border), and the peak score
      ``(...)``.
    """
    if volume.ndim > 3:
        fn = functools.partial(decode_cell, refine=refine)
        for _ in range(volume.ndim - 3):
            fn = jax.vmap(fn)
        return fn(volume)
    flat_idx = jnp.argmax(volume.reshape(-1))
    k, h, w = jnp.unravel_index(flat_idx, volume.shape)
    peak = volume[k, h, w]
    cell = jnp.stack([k, h, w]).astype(jnp.float32)
    if not refine:
        return cell, peak
    return refine_cell(volume, jnp.stack([k, h, w])), peak


def refine_cell(volume: jax.Array, cell: jax.Array) -> jax.Array:
    """Sub-cell refinement of the integer peak ``cell (3,)`` ``(k, h, w)`` of a ``(K, H, W)``
    volume: separable parabolas through its neighbours in k (wrapping), h and w (not on the
    border); ``(3,)`` float32 (k in ``[-0.5, K - 0.5)``)."""
    num_k, num_h, num_w = volume.shape
    k, h, w = cell[0], cell[1], cell[2]
    peak = volume[k, h, w]
    dk = _parabola_offset(volume[(k - 1) % num_k, h, w], peak, volume[(k + 1) % num_k, h, w])
    hm, hp = jnp.clip(h - 1, 0, num_h - 1), jnp.clip(h + 1, 0, num_h - 1)
    wm, wp = jnp.clip(w - 1, 0, num_w - 1), jnp.clip(w + 1, 0, num_w - 1)
    dh = _parabola_offset(volume[k, hm, w], peak, volume[k, hp, w])
    dw = _parabola_offset(volume[k, h, wm], peak, volume[k, h, wp])
    dh = jnp.where((h > 0) & (h < num_h - 1), dh, 0.0)
    dw = jnp.where((w > 0) & (w < num_w - 1), dw, 0.0)
    return cell.astype(jnp.float32) + jnp.stack([dk, dh, dw])


def decode(volume: jax.Array, num_rotations: int | None = None, refine: bool = True):
    """Best pose in the tile frame ``(..., 3)`` = ``(dx, dy, yaw)`` (m, m, rad) of
    ``(..., K, H, W)`` score volumes; ``num_rotations`` defaults to the volume's K."""
    num_rotations = num_rotations or volume.shape[-3]
    cell, _ = decode_cell(volume, refine=refine)
    return geometry.cell_to_pose(cell, num_rotations, size=volume.shape[-1])


@functools.partial(jax.jit, static_argnames=("cfg", "return_volume"))
def localize(
    bev_logits: jax.Array,
    tiles: jax.Array,
    cfg: SolverConfig = SolverConfig(),
    *,
    return_volume: bool = False,
):
    """Solves a batch (inside :func:`seglocnet_jax.evaluation.make_localize_step` for every
    evaluation).

    Args:
      bev_logits: ``(B, C, 128, 128)`` BEV logits (or :func:`labels_to_logits` of labels).
      tiles: ``(B, C, 256, 256)`` {0, 1} map tiles around the priors.
      cfg: solver configuration (static).

    Returns:
      dict with ``pose_tile (B, 3)`` (dx, dy, yaw) in the tile frame, ``cell (B, 3)`` the
      (possibly refined) ``(k, h, w)``, ``score (B,)`` the peak raw score, and ``volume
      (B, K, 129, 129)`` when ``return_volume``.
    """
    volume = score_volume_batch(
        bev_logits, tiles, cfg.num_rotations, cfg.method, cfg.rotation_chunk, cfg.batch_chunk
    )
    cell, peak = decode_cell(volume, refine=cfg.refine)
    out = {
        "pose_tile": geometry.cell_to_pose(cell, cfg.num_rotations, size=volume.shape[-1]),
        "cell": cell,
        "score": peak,
    }
    if return_volume:
        out["volume"] = volume
    return out


def tile_pose_to_world(pose_tile, tile_center) -> np.ndarray:
    """Tile-frame poses ``(B, 3)`` plus tile centres ``(B, 2)`` (world m) -> world ``(B, 3)``."""
    pose_tile = np.asarray(pose_tile, np.float64)
    centre = np.asarray(tile_center, np.float64)
    return np.concatenate([pose_tile[..., :2] + centre, pose_tile[..., 2:]], axis=-1)


__all__ = [
    "SolverConfig",
    "rotate_bev",
    "rotated_templates",
    "score_volume",
    "score_volume_batch",
    "log_softmax_volume",
    "labels_to_logits",
    "decode_cell",
    "refine_cell",
    "decode",
    "localize",
    "tile_pose_to_world",
]
