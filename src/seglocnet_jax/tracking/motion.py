"""Prediction: move the belief by the odometry, widen it by the motion noise, re-centre the
window (see the package docstring)."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.tracking.belief import Belief, TrackerConfig


def _tap_weights(frac, sigma, radius: int):
    """Weights ``(..., 2R+2)`` of taps ``t = -R .. R+1`` that shift by ``floor + frac`` cells
    and blur by a Gaussian of ``sigma`` cells: ``(1 - frac) G[t] + frac G[t - 1]`` with ``G``
    the normalized Gaussian on ``[-R, R]`` (a delta when ``sigma`` is 0). Each row sums to 1
    and its mean is ``frac`` (the bilinear split is exact for the mean)."""
    d = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
    g = jnp.exp(-0.5 * (d / jnp.maximum(sigma, 1e-3)) ** 2)
    g = g / g.sum()  # (2R+1,)
    zero = jnp.zeros((1,), jnp.float32)
    g0, g1 = jnp.concatenate([g, zero]), jnp.concatenate([zero, g])  # G[t], G[t-1]
    frac = jnp.asarray(frac, jnp.float32)[..., None]
    return (1.0 - frac) * g0 + frac * g1


def _margin_rows(n: int, radius: int) -> int:
    """Zero rows above and below the row pass's output: enough that the column pass, which
    shifts each flattened slice by up to ``n + radius + 1`` columns plus its taps, never
    reads past them (no pad: an XLA CPU pad is a slow extra pass)."""
    return -(-(n + 2 * radius + 2) // n)


def _shift_rows(prob, shift, weights, radius: int, rot=0):
    """``out[k, i] = sum_t weights[k, t] prob[j, i - shift[k] - t]`` with ``j = (k - rot) mod K``
    (zero outside), t = -R..R+1: slices move by the integer rotation ``rot`` while their rows
    shift (``shift``, ``weights`` are per output slice). One row gather (contiguous rows: fast
    on CPU), then static taps. Returns ``(K, M + N + M, N)``: ``M`` zero rows
    (:func:`_margin_rows`) each side, the margin :func:`_shift_cols` needs."""
    k_dim, n, _ = prob.shape
    m = _margin_rows(n, radius)
    taps = 2 * radius + 2
    length = n + 2 * m + taps - 1
    src_k = jnp.mod(jnp.arange(k_dim) - rot, k_dim)  # (K,) source slice of each output slice
    src = jnp.arange(length)[None] - m - shift[:, None] - (radius + 1)  # (K, L) source rows
    valid = (src >= 0) & (src < n)
    rows = prob[src_k[:, None], jnp.clip(src, 0, n - 1)]  # (K, L, N): a gather of rows
    rows = rows * valid[:, :, None]
    out = 0.0
    for t in range(-radius, radius + 2):
        off = radius + 1 - t
        out = out + weights[:, t + radius, None, None] * rows[:, off : off + n + 2 * m]
    i = np.arange(n + 2 * m)
    keep = jnp.asarray((i >= m) & (i < n + m), prob.dtype)  # static: the margins stay zero
    return out * keep[None, :, None]


def _shift_cols(rows, shift, weights, radius: int):
    """Like :func:`_shift_rows` along the last axis, on its output ``rows`` ``(K, M + N + M, N)``.
    A column shift of a row-major slice is a shift of the flattened slice, with the columns
    that wrapped into the next row masked: one contiguous block per slice (a dynamic slice
    into the zero margins) instead of a gather per element. Returns ``(K, N, N)``."""
    k_dim, padded, n = rows.shape
    m = (padded - n) // 2
    taps = 2 * radius + 2
    shift = jnp.clip(shift, -(n + radius + 1), n + radius + 1)  # beyond: all masked anyway
    flat = rows.reshape(k_dim, padded * n)
    length = n * n + taps - 1
    start = m * n - shift - (radius + 1)
    block = jax.vmap(lambda a, s: jax.lax.dynamic_slice_in_dim(a, s, length))(flat, start)
    col = jnp.arange(n)
    out = 0.0
    for t in range(-radius, radius + 2):
        src = col[None] - shift[:, None] - t  # (K, N) source column of each output column
        w = ((src >= 0) & (src < n)).astype(rows.dtype) * weights[:, t + radius, None]
        off = radius + 1 - t
        out = out + w[:, None, :] * block[:, off : off + n * n].reshape(k_dim, n, n)
    return out


def _blur_rotations(prob, weights, radius: int):
    """``out[k] = sum_t weights[t] prob[(k - t) mod K]``, t = -R..R+1 (static, with wrap)."""
    k_dim = prob.shape[0]
    idx = np.mod(np.arange(-(radius + 1), k_dim + radius), k_dim)  # static slab order
    slabs = prob[idx]  # (K + 2R + 1, N, N)
    out = 0.0
    for t in range(-radius, radius + 2):
        off = radius + 1 - t
        out = out + weights[t + radius] * slabs[off : off + k_dim]
    return out


def _map_cell(prob):
    """Argmax ``(k, h, w)`` int32 of ``(K, N, N)``: row maxima first (a 3-D argmax is ~10x
    slower on CPU)."""
    k_dim, n, _ = prob.shape
    rowmax = prob.max(axis=2)  # (K, N)
    kh = jnp.argmax(rowmax.reshape(-1))
    k, h = kh // n, kh % n
    w = jnp.argmax(prob[k, h])
    return jnp.stack([k, h, w]).astype(jnp.int32)


# A Gaussian tap below this fraction of the central weight is dropped: next to the central tap
# float32 cannot tell it from zero. Small noise (the usual, well below a cell or a yaw bin)
# then needs 2-4 taps per axis instead of 2 * kernel_radius + 2.
_TAP_EPS = 1e-7
_TAP_REACH = math.sqrt(2.0 * math.log(1.0 / _TAP_EPS))  # 5.7 sigmas


def _noise(odometry, cfg: TrackerConfig, xp=jnp):
    """Motion noise of one step: sigma in cells (x, y) and in yaw bins."""
    fwd, left, dyaw = odometry[0], odometry[1], odometry[2]
    dist = xp.hypot(fwd, left)
    sigma_xy = xp.sqrt(cfg.sigma_xy**2 + (cfg.sigma_xy_per_m * dist) ** 2) / cfg.resolution
    bin_width = 2 * math.pi / cfg.num_rotations
    sigma_k = xp.sqrt(cfg.sigma_yaw**2 + (cfg.sigma_yaw_per_rad * dyaw) ** 2) / bin_width
    return sigma_xy, sigma_k


def _widths(odometry: np.ndarray, cfg: TrackerConfig) -> tuple[int, int]:
    """Tap half-widths ``(xy, yaw)`` of one step (host side: the kernels' static shapes):
    the Gaussian out to :data:`_TAP_REACH` sigmas, at most ``kernel_radius``."""
    sigma_xy, sigma_k = _noise(odometry.astype(np.float64), cfg, np)
    reach = lambda sigma: min(cfg.kernel_radius, int(math.floor(sigma * _TAP_REACH)))  # noqa: E731
    return reach(sigma_xy), reach(sigma_k)


def _motion_plan(prob, odometry, cfg: TrackerConfig, widths, map_cell=None):
    """Per-slice shifts (cells) and kernels of one prediction, and the window shift."""
    r_xy, r_k = widths
    res = cfg.resolution
    fwd, left, dyaw = odometry[0], odometry[1], odometry[2]
    yaws = geometry.yaw_from_rotation(jnp.arange(cfg.num_rotations), cfg.num_rotations)
    cos, sin = jnp.cos(yaws), jnp.sin(yaws)
    dh = -(sin * fwd + cos * left) / res  # (K,) rows: north is -h
    dw = (cos * fwd - sin * left) / res  # (K,) cols: east is +w
    k, h, w = _map_cell(prob) if map_cell is None else map_cell
    # The window follows the predicted MAP: the MAP cell moved by its own slice's motion.
    move = jnp.round(jnp.stack([h + dh[k], w + dw[k]]) - cfg.centre).astype(jnp.int32)
    sh, sw = dh - move[0], dw - move[1]
    sigma_xy, sigma_k = _noise(odometry, cfg)
    dk = dyaw / (2 * math.pi / cfg.num_rotations)
    rot = jnp.floor(dk).astype(jnp.int32)
    # Translate first (each slice by its own yaw), then rotate: the integer part of the turn
    # relabels the slices inside the row gather, so output slice k takes the translation of
    # its source slice (k - rot) mod K; the fractional part and the yaw noise are taps.
    src = jnp.mod(jnp.arange(cfg.num_rotations) - rot, cfg.num_rotations)
    sh, sw = sh[src], sw[src]
    plan = {
        "rows": jnp.floor(sh).astype(jnp.int32),
        "row_w": _tap_weights(sh - jnp.floor(sh), sigma_xy, r_xy),  # (K, 2 r_xy + 2)
        "cols": jnp.floor(sw).astype(jnp.int32),
        "col_w": _tap_weights(sw - jnp.floor(sw), sigma_xy, r_xy),
        "rot": rot,
        "rot_w": _tap_weights(dk - jnp.floor(dk), sigma_k, r_k),  # (2 r_k + 2,)
    }
    return plan, move


@functools.partial(jax.jit, static_argnames=("cfg", "widths"))
def _plan_rows_kernel(prob, odometry, map_cell, cfg: TrackerConfig, widths):
    """The plan and the row pass: one program (the barrier keeps the plan's small arrays from
    being recomputed inside the row pass's loop)."""
    plan, move = jax.lax.optimization_barrier(_motion_plan(prob, odometry, cfg, widths, map_cell))
    rows = _shift_rows(prob, plan["rows"], plan["row_w"], widths[0], plan["rot"])
    return rows, plan, move


@functools.partial(jax.jit, static_argnames="radius")
def _rows_kernel(prob, shift, weights, rot, radius):
    return _shift_rows(prob, shift, weights, radius, rot)


@functools.partial(jax.jit, static_argnames="radius")
def _cols_kernel(rows, shift, weights, radius):
    out = _shift_cols(rows, shift, weights, radius)
    # Rotations keep the mass: this is what stays in the window. Per slice first (a full
    # reduction to a scalar is several times slower on XLA CPU).
    return out, out.sum(axis=(1, 2)).sum()


@functools.partial(jax.jit, static_argnames="radius")
def _rotations_kernel(prob, mass, weights, radius):
    return _blur_rotations(prob, weights / jnp.maximum(mass, 1e-30), radius)


def predict(belief: Belief, odometry, cfg: TrackerConfig, *, map_cell=None) -> tuple[Belief, dict]:
    """Moves the belief by one frame's odometry and re-centres the window on the estimate.

    Each yaw slice is translated by the odometry rotated by its yaw and blurred by the motion
    noise, then the slices rotate (see the package docstring); the kernels span the Gaussian
    out to 5.7 sigmas (weights below 1e-7 of the central one are dropped), at most
    ``cfg.kernel_radius`` cells or bins: one compiled program per width (a handful).

    Args:
      odometry: ``(3,)`` ``(forward m, left m, dyaw rad)``: the new pose in the frame of the old
        one (``x' = x + R(yaw) (forward, left)``, ``yaw' = yaw + dyaw``).
      map_cell: the MAP cell ``(k, h, w)`` of ``belief`` when the caller has it (the
        ``estimate["map_cell"]`` that :func:`update` returned with this belief): saves a pass
        over the volume. ``None``: computed here.

    Returns:
      The predicted belief (window moved so that the predicted MAP cell is its centre) and
      ``{"dropped": mass that left the window (renormalized away), "shift": (2,) int32 window
      move (rows, cols)}``.
    """
    odometry = np.asarray(odometry, np.float32).reshape(3)
    widths = _widths(odometry, cfg)
    if map_cell is not None:
        map_cell = jnp.asarray(map_cell, jnp.int32)
    rows, plan, move = _plan_rows_kernel(belief.prob, odometry, map_cell, cfg, widths)
    prob, mass = _cols_kernel(rows, plan["cols"], plan["col_w"], widths[0])
    prob = _rotations_kernel(prob, mass, plan["rot_w"], widths[1])
    belief = belief._replace(prob=prob, centre=belief.centre + move)
    return belief, {"dropped": 1.0 - mass, "shift": move}


def recentre(belief: Belief, shift, cfg: TrackerConfig) -> tuple[Belief, jax.Array]:
    """Moves the window by ``shift = (rows, cols)`` lattice cells (the belief stays put in the
    world); returns the renormalized belief and the mass that left the window."""
    k_dim = cfg.num_rotations
    shift = jnp.asarray(shift, jnp.int32)
    none = _tap_weights(jnp.zeros(k_dim), 0.0, 0)  # identity taps: (1, 0)
    rows = _rows_kernel(belief.prob, jnp.full((k_dim,), -shift[0]), none, jnp.int32(0), 0)
    prob, mass = _cols_kernel(rows, jnp.full((k_dim,), -shift[1]), none, 0)
    prob = prob / jnp.maximum(mass, 1e-30)
    return belief._replace(prob=prob, centre=belief.centre + shift), 1.0 - mass


@functools.partial(jax.jit, static_argnames=("wide", "cfg"))
def _narrow_kernel(prob, centre, map_cell, wide: TrackerConfig, cfg: TrackerConfig):
    k_dim, n_wide, _ = prob.shape
    cell = _map_cell(prob) if map_cell is None else map_cell
    half = cfg.centre
    # The size x size box around the mode, clipped into the wide window (a mode near its edge
    # keeps the box inside: the window centre is then not the mode, as after any clipped move).
    top = jnp.clip(cell[1:] - half, 0, n_wide - cfg.size)
    box = jax.lax.dynamic_slice(prob, (0, top[0], top[1]), (k_dim, cfg.size, cfg.size))
    mass = box.sum(axis=(1, 2)).sum()  # per slice first (XLA CPU)
    move = top + half - wide.centre
    return box / jnp.maximum(mass, 1e-30), centre + move.astype(jnp.int32), mass


def narrow(
    belief: Belief, wide: TrackerConfig, cfg: TrackerConfig, *, map_cell=None
) -> tuple[Belief, jax.Array]:
    """The belief of the window ``wide`` cut to the smaller ``cfg`` window around its mode
    (``wide.size`` > ``cfg.size``, same lattice: the tracking window of a full one): returns
    the renormalized belief and the mass it kept (the sequential loop narrows once that stays
    near 1). The world pose of every kept cell is unchanged. ``map_cell``: the mode ``(k, h,
    w)`` when the caller has it (the estimate :func:`update` returned with this belief): saves
    a pass over the volume."""
    if wide.size <= cfg.size or (wide.num_rotations, wide.resolution, wide.bev_size) != (
        cfg.num_rotations,
        cfg.resolution,
        cfg.bev_size,
    ):
        raise ValueError(
            f"narrow needs a wider window of the same lattice and K: {wide.size} -> {cfg.size}"
        )
    if map_cell is not None:
        map_cell = jnp.asarray(map_cell, jnp.int32)
    prob, centre, mass = _narrow_kernel(belief.prob, belief.centre, map_cell, wide, cfg)
    return belief._replace(prob=prob, centre=centre), mass
