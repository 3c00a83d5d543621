"""Sequential localization: a Bayes filter over the solver's pose grid.

The belief is a probability volume ``prob (K, N, N)`` over the cells of a world-aligned window
(``N = 129`` by default, ``0.5 m`` cells, ``K`` rotations): exactly the cells of the solver's
score volume for a map tile centred on the window centre, so a frame's score volume is the
likelihood of the belief's own cells. ``geometry`` owns what a cell means: cell ``(k, h, w)``
is the pose ``window centre + geometry.cell_to_tile_offset(h, w)`` with
``yaw = geometry.yaw_from_rotation(k)``.

Cells sit on a *lattice* of pixel corners: lattice corner ``(row, col)`` is the world point
``(origin_x + col * res, origin_y - row * res)``. With ``origin = (grid.x_min, grid.y_max)``
of a :class:`geometry.RasterGrid` the lattice is that raster's pixel corners, the window centre
is the centre of the tile ``geometry.crop(raster, *tile_corner(belief, cfg), tile_size)`` and
``geometry.tile_window`` of :func:`window_centre` returns the same tile.

One frame of a drive::

    belief, info = predict(belief, odometry, cfg)   # move + widen; window follows the estimate
    tile = crop(raster, *tile_corner(belief, cfg), tile_size)          # around the estimate
    volume = solver.score_volume(bev, tile, K)                          # (K, N, N)
    belief, info = update(belief, solver.log_softmax_volume(volume, T), cfg)
    est = estimate(belief, cfg)

* predict: each yaw slice is translated by the odometry rotated by that slice's yaw (bilinear
  for the sub-cell part, blurred by a Gaussian whose sigma grows with the distance), then the
  slices move along ``k`` by the yaw change (with wrap, blurred by the yaw noise). The window
  moves by the integer cells that put the predicted MAP cell at its centre; mass that leaves is
  dropped (reported) and the rest renormalized.
* update: ``posterior ~ prior * exp(log_likelihood)``, with the maximum subtracted before the
  exponential (log-sum-exp); ``floor`` mixes a uniform into the prior so that no cell is ever
  impossible.
* track loss: a CUSUM of the per-frame log Bayes factor "the prior predicted this frame" vs "a
  uniform prior did" (``log sum prior * L - log mean L``), plus belief-shape tests (peak mass,
  entropy) once the filter has locked on. A loss re-widens the prior (uniform, or a Gaussian
  around the last estimate) and reapplies the frame's likelihood; losses are counted.

All kernels are jitted once per config (static shapes). They are composed in Python: inside a
single XLA program the CPU backend fuses the per-slice gathers into their producers and runs
~10x slower, so each stage is its own program (one dispatch each, no host sync except the
loss test of :func:`update`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry, solver


@dataclasses.dataclass(frozen=True)
class TrackerConfig:
    """Configuration of the filter (hashable: the jitted kernels take it as a static argument).

    Attributes:
      num_rotations: K, yaw bins over the full turn (the solver's K).
      size: window cells per axis, odd (the score volume's H = W: 129).
      resolution: metres per cell.
      bev_size: BEV pixels per side (tile side = size - 1 + bev_size: 256).
      sigma_xy: m, translation noise (1 sigma, per axis) added every frame.
      sigma_xy_per_m: m of translation noise per m travelled (added in quadrature).
      sigma_yaw: rad, yaw noise added every frame.
      sigma_yaw_per_rad: rad of yaw noise per rad turned (added in quadrature).
      kernel_radius: half-width (cells, bins) of the blur kernels; a larger sigma is truncated.
      floor: weight of a uniform mixed into the prior at every update.
      lost_log_odds: nats; a loss when the CUSUM of the prior-vs-uniform log Bayes factor falls
        below ``-lost_log_odds`` (0 disables).
      lock_peak_mass: the filter locks on once the peak mass reaches this.
      lost_peak_mass: when locked, a loss when the peak mass falls below this (0 disables).
      lost_entropy: when locked, a loss when the normalized (x, y) entropy exceeds this
        (1 disables).
      peak_radius: m; the peak mass is the posterior mass within this (box) of the MAP (x, y).
      recover_sigma: m; the prior after a loss: a Gaussian of this sigma around the window
        centre (the last estimate), uniform over yaw; 0 means uniform over the window.
    """

    num_rotations: int = geometry.NUM_ROTATIONS
    size: int = geometry.SCORE_SIZE
    resolution: float = geometry.RESOLUTION
    bev_size: int = geometry.BEV_SIZE
    sigma_xy: float = 0.1
    sigma_xy_per_m: float = 0.05
    sigma_yaw: float = 0.005
    sigma_yaw_per_rad: float = 0.05
    kernel_radius: int = 3
    floor: float = 1e-9
    lost_log_odds: float = 10.0
    lock_peak_mass: float = 0.5
    lost_peak_mass: float = 0.05
    lost_entropy: float = 0.9
    peak_radius: float = 2.0
    recover_sigma: float = 0.0

    def __post_init__(self):
        if self.num_rotations < 1:
            raise ValueError(f"num_rotations must be >= 1, got {self.num_rotations}")
        if self.size < 3 or self.size % 2 == 0:
            raise ValueError(f"size must be odd and >= 3, got {self.size}")
        if self.resolution <= 0:
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if self.kernel_radius < 0:
            raise ValueError(f"kernel_radius must be >= 0, got {self.kernel_radius}")
        if not 0.0 <= self.floor < 1.0:
            raise ValueError(f"floor must be in [0, 1), got {self.floor}")
        for key in ("sigma_xy", "sigma_xy_per_m", "sigma_yaw", "sigma_yaw_per_rad"):
            if getattr(self, key) < 0:
                raise ValueError(f"{key} must be >= 0, got {getattr(self, key)}")
        if self.lost_log_odds < 0 or self.recover_sigma < 0 or self.peak_radius < 0:
            raise ValueError("lost_log_odds, recover_sigma and peak_radius must be >= 0")

    @property
    def centre(self) -> int:
        """Index of the window's central cell along h and w (64)."""
        return (self.size - 1) // 2

    @property
    def tile_size(self) -> int:
        """Side of the map tile whose score volume is the window (256)."""
        return self.size - 1 + self.bev_size

    @property
    def num_cells(self) -> int:
        return self.num_rotations * self.size * self.size


class Belief(NamedTuple):
    """The filter state (a pytree).

    Attributes:
      prob: ``(K, N, N)`` float32, sums to 1: ``prob[k, h, w]`` of the window's cells.
      centre: ``(2,)`` int32 lattice corner ``(row, col)`` of the window centre (= tile centre).
      origin: ``(2,)`` float32 world ``(x, y)`` of lattice corner ``(0, 0)``.
      cusum: ``()`` float32 <= 0, running CUSUM of the log Bayes factor (nats).
      locked: ``()`` bool, the filter has locked on since the last loss.
      losses: ``()`` int32, track losses detected so far.
    """

    prob: jax.Array
    centre: jax.Array
    origin: jax.Array
    cusum: jax.Array
    locked: jax.Array
    losses: jax.Array


# --------------------------------------------------------------------------- construction


def _cell_offsets(cfg: TrackerConfig, xp=jnp):
    """World ``(dx, dy)`` metres of each window column / row relative to the centre."""
    idx = xp.arange(cfg.size)
    dx, dy = geometry.cell_to_tile_offset(
        idx, idx, cfg.resolution, bev_size=cfg.bev_size, tile_size=cfg.tile_size
    )
    return dx, dy  # (N,) over w, (N,) over h


def init_belief(
    cfg: TrackerConfig,
    xy,
    origin=(0.0, 0.0),
    *,
    sigma: float | None = None,
    yaw: float | None = None,
    yaw_sigma: float | None = None,
) -> Belief:
    """The belief before the first frame, its window centred on the prior ``xy`` (world m)
    snapped to the nearest lattice corner.

    Args:
      xy: ``(2,)`` coarse position prior, world metres.
      origin: world ``(x, y)`` of lattice corner ``(0, 0)``: ``(grid.x_min, grid.y_max)`` puts
        the lattice on a raster's pixel corners.
      sigma: m; ``None``: uniform over the window, else a Gaussian around ``xy``.
      yaw, yaw_sigma: rad; a wrapped Gaussian over yaw (``None``: uniform).
    """
    x, y = (float(v) for v in xy)
    ox, oy = (float(v) for v in origin)
    row = int(np.round((oy - y) / cfg.resolution))
    col = int(np.round((x - ox) / cfg.resolution))
    dx, dy = _cell_offsets(cfg, np)
    cx, cy = ox + col * cfg.resolution, oy - row * cfg.resolution
    log_xy = np.zeros((cfg.size, cfg.size))
    if sigma is not None:
        ex, ey = cx + dx[None, :] - x, cy + dy[:, None] - y
        log_xy = -0.5 * (ex**2 + ey**2) / max(sigma, 1e-6) ** 2
    log_k = np.zeros(cfg.num_rotations)
    if yaw is not None:
        yaws = geometry.yaw_from_rotation(np.arange(cfg.num_rotations), cfg.num_rotations)
        err = geometry.wrap_angle(yaws - yaw)
        log_k = -0.5 * err**2 / max(yaw_sigma or 0.0, 1e-6) ** 2
    logp = log_k[:, None, None] + log_xy[None]
    prob = np.exp(logp - logp.max())
    return Belief(
        prob=jnp.asarray(prob / prob.sum(), jnp.float32),
        centre=jnp.asarray([row, col], jnp.int32),
        origin=jnp.asarray([ox, oy], jnp.float32),
        cusum=jnp.zeros((), jnp.float32),
        locked=jnp.zeros((), bool),
        losses=jnp.zeros((), jnp.int32),
    )


def window_centre(belief: Belief, cfg: TrackerConfig) -> np.ndarray:
    """World ``(x, y)`` of the window centre (the tile centre), float64 on the host."""
    row, col = np.asarray(belief.centre, np.int64)
    ox, oy = np.asarray(belief.origin, np.float64)
    return np.array([ox + col * cfg.resolution, oy - row * cfg.resolution])


def tile_corner(belief: Belief, cfg: TrackerConfig) -> tuple[int, int]:
    """Top-left pixel ``(row0, col0)`` of the tile to cut (``geometry.crop``) from a raster
    whose pixel corners are the lattice."""
    row, col = (int(v) for v in np.asarray(belief.centre))
    half = cfg.tile_size // 2
    return row - half, col - half


def world_to_cell(belief: Belief, pose, cfg: TrackerConfig) -> jax.Array:
    """World poses ``(..., 3)`` to continuous window cells ``(..., 3)`` ``(k in [0, K), h, w)``
    (round for the GT cell; outside ``[0, N)`` when the pose is outside the window)."""
    pose = jnp.asarray(pose, jnp.float32)
    c = belief.centre.astype(jnp.float32)
    cx = belief.origin[0] + c[1] * cfg.resolution
    cy = belief.origin[1] - c[0] * cfg.resolution
    h, w = geometry.tile_offset_to_cell(
        pose[..., 0] - cx,
        pose[..., 1] - cy,
        cfg.resolution,
        bev_size=cfg.bev_size,
        tile_size=cfg.tile_size,
    )
    k = geometry.rotation_from_yaw(pose[..., 2], cfg.num_rotations)
    k = jnp.where(k >= cfg.num_rotations, k - cfg.num_rotations, k)  # float32 mod can give K
    return jnp.stack([k, h, w], axis=-1)


def cell_to_world(belief: Belief, cell, cfg: TrackerConfig) -> jax.Array:
    """Window cells ``(..., 3)`` ``(k, h, w)`` (may be fractional) to world poses ``(..., 3)``."""
    cell = jnp.asarray(cell, jnp.float32)
    c = belief.centre.astype(jnp.float32)
    dx, dy = geometry.cell_to_tile_offset(
        cell[..., 1], cell[..., 2], cfg.resolution, bev_size=cfg.bev_size, tile_size=cfg.tile_size
    )
    x = belief.origin[0] + c[1] * cfg.resolution + dx
    y = belief.origin[1] - c[0] * cfg.resolution + dy
    yaw = geometry.yaw_from_rotation(cell[..., 0], cfg.num_rotations)
    return jnp.stack([x, y, yaw], axis=-1)


# --------------------------------------------------------------------------- transport kernels


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


def _shift_rows(prob, shift, weights, radius: int, rot=0):
    """``out[k, i] = sum_t weights[k, t] prob[j, i - shift[k] - t]`` with ``j = (k - rot) mod K``
    (zero outside), t = -R..R+1: slices move by the integer rotation ``rot`` while their rows
    shift (``shift``, ``weights`` are per output slice). One row gather (contiguous rows: fast
    on CPU), then static taps."""
    k_dim, n, _ = prob.shape
    taps = 2 * radius + 2
    length = n + taps - 1
    src_k = jnp.mod(jnp.arange(k_dim) - rot, k_dim)  # (K,) source slice of each output slice
    src = jnp.arange(length)[None] - shift[:, None] - (radius + 1)  # (K, L) source rows
    valid = (src >= 0) & (src < n)
    rows = prob[src_k[:, None], jnp.clip(src, 0, n - 1)]  # (K, L, N): a gather of rows
    rows = rows * valid[:, :, None]
    out = 0.0
    for t in range(-radius, radius + 2):
        off = radius + 1 - t
        out = out + weights[:, t + radius, None, None] * rows[:, off : off + n]
    return out


def _shift_cols(prob, shift, weights, radius: int):
    """Like :func:`_shift_rows` along the last axis. A column shift of a row-major slice is a
    shift of the flattened slice, with the columns that wrapped into the next row masked: one
    contiguous block per slice instead of a gather per element."""
    k_dim, n, _ = prob.shape
    taps = 2 * radius + 2
    pad = n + taps  # beyond this every column is masked anyway
    shift = jnp.clip(shift, -(n + radius + 1), n + radius + 1)
    flat = jnp.pad(prob.reshape(k_dim, n * n), ((0, 0), (pad, pad)))
    length = n * n + taps - 1
    start = pad - shift - (radius + 1)
    block = jax.vmap(lambda a, s: jax.lax.dynamic_slice_in_dim(a, s, length))(flat, start)
    col = jnp.arange(n)
    out = 0.0
    for t in range(-radius, radius + 2):
        src = col[None] - shift[:, None] - t  # (K, N) source column of each output column
        w = ((src >= 0) & (src < n)).astype(prob.dtype) * weights[:, t + radius, None]
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


@functools.partial(jax.jit, static_argnames="cfg")
def _motion_plan(prob, odometry, cfg: TrackerConfig):
    """Per-slice shifts (cells) and kernels of one prediction, and the window shift."""
    res, radius = cfg.resolution, cfg.kernel_radius
    fwd, left, dyaw = odometry[0], odometry[1], odometry[2]
    yaws = geometry.yaw_from_rotation(jnp.arange(cfg.num_rotations), cfg.num_rotations)
    cos, sin = jnp.cos(yaws), jnp.sin(yaws)
    dh = -(sin * fwd + cos * left) / res  # (K,) rows: north is -h
    dw = (cos * fwd - sin * left) / res  # (K,) cols: east is +w
    k, h, w = _map_cell(prob)
    # The window follows the predicted MAP: the MAP cell moved by its own slice's motion.
    move = jnp.round(jnp.stack([h + dh[k], w + dw[k]]) - cfg.centre).astype(jnp.int32)
    sh, sw = dh - move[0], dw - move[1]
    dist = jnp.hypot(fwd, left)
    sigma_xy = jnp.sqrt(cfg.sigma_xy**2 + (cfg.sigma_xy_per_m * dist) ** 2) / res
    bin_width = 2 * math.pi / cfg.num_rotations
    sigma_k = jnp.sqrt(cfg.sigma_yaw**2 + (cfg.sigma_yaw_per_rad * dyaw) ** 2) / bin_width
    dk = dyaw / bin_width
    rot = jnp.floor(dk).astype(jnp.int32)
    # Translate first (each slice by its own yaw), then rotate: the integer part of the turn
    # relabels the slices inside the row gather, so output slice k takes the translation of
    # its source slice (k - rot) mod K; the fractional part and the yaw noise are taps.
    src = jnp.mod(jnp.arange(cfg.num_rotations) - rot, cfg.num_rotations)
    sh, sw = sh[src], sw[src]
    plan = {
        "rows": jnp.floor(sh).astype(jnp.int32),
        "row_w": _tap_weights(sh - jnp.floor(sh), sigma_xy, radius),  # (K, 2R+2)
        "cols": jnp.floor(sw).astype(jnp.int32),
        "col_w": _tap_weights(sw - jnp.floor(sw), sigma_xy, radius),
        "rot": rot,
        "rot_w": _tap_weights(dk - jnp.floor(dk), sigma_k, radius),  # (2R+2,)
    }
    return plan, move


@functools.partial(jax.jit, static_argnames="radius")
def _rows_kernel(prob, shift, weights, rot, radius):
    return _shift_rows(prob, shift, weights, radius, rot)


@functools.partial(jax.jit, static_argnames="radius")
def _cols_kernel(prob, shift, weights, radius):
    out = _shift_cols(prob, shift, weights, radius)
    return out, out.sum()  # rotations keep the mass: this is what stays in the window


@functools.partial(jax.jit, static_argnames="radius")
def _rotations_kernel(prob, mass, weights, radius):
    return _blur_rotations(prob, weights / jnp.maximum(mass, 1e-30), radius)


def _transport(belief: Belief, plan, move, cfg: TrackerConfig):
    radius = cfg.kernel_radius
    prob = _rows_kernel(belief.prob, plan["rows"], plan["row_w"], plan["rot"], radius)
    prob, mass = _cols_kernel(prob, plan["cols"], plan["col_w"], radius)
    prob = _rotations_kernel(prob, mass, plan["rot_w"], radius)
    belief = belief._replace(prob=prob, centre=belief.centre + move)
    return belief, {"dropped": 1.0 - mass, "shift": move}


def predict(belief: Belief, odometry, cfg: TrackerConfig) -> tuple[Belief, dict]:
    """Moves the belief by one frame's odometry and re-centres the window on the estimate.

    Args:
      odometry: ``(3,)`` ``(forward m, left m, dyaw rad)``: the new pose in the frame of the old
        one (``x' = x + R(yaw) (forward, left)``, ``yaw' = yaw + dyaw``).

    Returns:
      The predicted belief (window moved so that the predicted MAP cell is its centre) and
      ``{"dropped": mass that left the window (renormalized away), "shift": (2,) int32 window
      move (rows, cols)}``.
    """
    odometry = jnp.asarray(odometry, jnp.float32)
    plan, move = _motion_plan(belief.prob, odometry, cfg)
    return _transport(belief, plan, move, cfg)


def recentre(belief: Belief, shift, cfg: TrackerConfig) -> tuple[Belief, jax.Array]:
    """Moves the window by ``shift = (rows, cols)`` lattice cells (the belief stays put in the
    world); returns the renormalized belief and the mass that left the window."""
    k_dim = cfg.num_rotations
    shift = jnp.asarray(shift, jnp.int32)
    none = _tap_weights(jnp.zeros(k_dim), 0.0, cfg.kernel_radius)  # identity taps
    plan = {
        "rows": jnp.full((k_dim,), -shift[0], jnp.int32),
        "row_w": none,
        "cols": jnp.full((k_dim,), -shift[1], jnp.int32),
        "col_w": none,
        "rot": jnp.zeros((), jnp.int32),
        "rot_w": none[0],
    }
    belief, info = _transport(belief, plan, shift, cfg)
    return belief, info["dropped"]


# --------------------------------------------------------------------------- update, estimate


def _marginal_xy(prob):
    """``sum_k prob[k]`` as ``(N, N)``: a matrix-vector product (XLA's CPU reduction over the
    major axis is ~30x slower)."""
    k_dim, n, _ = prob.shape
    ones = jnp.ones((1, k_dim), prob.dtype)
    return (ones @ prob.reshape(k_dim, n * n)).reshape(n, n)


def _estimate(belief: Belief, cfg: TrackerConfig) -> dict:
    """See :func:`estimate`."""
    prob = belief.prob
    cell = _map_cell(prob)
    p_xy = _marginal_xy(prob)  # (N, N)
    p_k = prob.reshape(cfg.num_rotations, -1).sum(axis=1)  # (K,)
    r = int(round(cfg.peak_radius / cfg.resolution))
    box = jax.lax.dynamic_slice(jnp.pad(p_xy, r), (cell[1], cell[2]), (2 * r + 1, 2 * r + 1))
    entropy = -jnp.sum(jnp.where(p_xy > 0, p_xy * jnp.log(jnp.maximum(p_xy, 1e-38)), 0.0))
    dx, dy = _cell_offsets(cfg)
    centre = cell_to_world(belief, jnp.array([0.0, cfg.centre, cfg.centre]), cfg)[:2]
    m_x, m_y = jnp.sum(p_xy.sum(0) * dx), jnp.sum(p_xy.sum(1) * dy)
    ex, ey = dx[None, :] - m_x, dy[:, None] - m_y
    cxx, cyy, cxy = jnp.sum(p_xy * ex * ex), jnp.sum(p_xy * ey * ey), jnp.sum(p_xy * ex * ey)
    yaws = geometry.yaw_from_rotation(jnp.arange(cfg.num_rotations), cfg.num_rotations)
    cs, sn = jnp.sum(p_k * jnp.cos(yaws)), jnp.sum(p_k * jnp.sin(yaws))
    resultant = jnp.clip(jnp.hypot(cs, sn), 1e-12, 1.0)
    return {
        "map_cell": cell,
        "map_pose": cell_to_world(belief, cell, cfg),
        "mean_pose": jnp.stack([centre[0] + m_x, centre[1] + m_y, jnp.arctan2(sn, cs)]),
        "cov_xy": jnp.array([[cxx, cxy], [cxy, cyy]]),
        "yaw_std": jnp.sqrt(-2.0 * jnp.log(resultant)),
        "peak_mass": box.sum(),
        "entropy": entropy / math.log(cfg.size * cfg.size),
        "locked": belief.locked,
        "losses": belief.losses,
    }


def _reset_prior(cfg: TrackerConfig):
    """The re-widened prior ``(N, N)`` over (x, y) after a loss (uniform over yaw)."""
    if cfg.recover_sigma <= 0:
        return jnp.full((cfg.size, cfg.size), 1.0 / (cfg.size * cfg.size), jnp.float32)
    dx, dy = _cell_offsets(cfg)
    g = jnp.exp(-0.5 * (dx[None, :] ** 2 + dy[:, None] ** 2) / cfg.recover_sigma**2)
    return (g / g.sum()).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames="cfg")
def _update_kernel(belief: Belief, log_lik, cfg: TrackerConfig):
    n = cfg.num_cells
    lik = jnp.exp(log_lik - log_lik.max())  # (K, N, N) in (0, 1], max 1
    prior = belief.prob
    z_prior = jnp.sum(prior * lik)  # sum prior * L (prior sums to 1)
    z_mean = jnp.sum(lik) / n  # sum uniform * L
    # z = 0 only when floor = 0 and the prior misses every cell the likelihood allows: then
    # the agreement is -inf and the loss test below resets the belief.
    z = jnp.maximum((1.0 - cfg.floor) * z_prior + cfg.floor * z_mean, 1e-38)
    post = ((1.0 - cfg.floor) * prior + cfg.floor / n) * lik / z
    stats = _estimate(belief._replace(prob=post), cfg)
    agreement = jnp.log(z) - jnp.log(z_mean)  # log Bayes factor, this frame (nats)
    cusum = jnp.minimum(0.0, belief.cusum + agreement)
    by_odds = (cfg.lost_log_odds > 0) & (cusum < -cfg.lost_log_odds)
    by_shape = belief.locked & (
        (stats["peak_mass"] < cfg.lost_peak_mass) | (stats["entropy"] > cfg.lost_entropy)
    )
    lost = by_odds | by_shape
    locked = belief.locked | (stats["peak_mass"] >= cfg.lock_peak_mass)
    new = belief._replace(prob=post, cusum=cusum, locked=locked)
    stats.update(locked=locked)
    return new, {"agreement": agreement, "lost": lost, "estimate": stats}


@functools.partial(jax.jit, static_argnames="cfg")
def _reset_kernel(belief: Belief, log_lik, cfg: TrackerConfig):
    lik = jnp.exp(log_lik - log_lik.max())
    post = _reset_prior(cfg)[None] * lik
    new = belief._replace(
        prob=post / post.sum(),
        cusum=jnp.zeros((), jnp.float32),
        locked=jnp.zeros((), bool),
        losses=belief.losses + 1,
    )
    return new, _estimate(new, cfg)


def update(belief: Belief, log_likelihood, cfg: TrackerConfig) -> tuple[Belief, dict]:
    """Bayes update with one frame's log-likelihood over the window's cells.

    Args:
      log_likelihood: ``(K, N, N)`` float, up to an additive constant: e.g.
        ``solver.log_softmax_volume(volume, temperature)`` of the frame's score volume, the
        tile cut around this belief's window (see :func:`fit_temperature`).

    Returns:
      The posterior and ``{"agreement": log Bayes factor of this frame (prior vs uniform,
      nats), "lost": a track loss was detected (the posterior is then the re-widened prior
      times this frame's likelihood), "estimate": :func:`estimate` of the returned
      posterior}``.
    """
    log_lik = jnp.asarray(log_likelihood, jnp.float32)
    expected = (cfg.num_rotations, cfg.size, cfg.size)
    if log_lik.shape != expected:
        raise ValueError(f"log_likelihood must be {expected}, got {log_lik.shape}")
    new, info = _update_kernel(belief, log_lik, cfg)
    if bool(info["lost"]):  # the one host sync of a frame: rare path, its own program
        new, est = _reset_kernel(new, log_lik, cfg)
        info = {**info, "estimate": est}
    return new, info


@functools.partial(jax.jit, static_argnames="cfg")
def estimate(belief: Belief, cfg: TrackerConfig) -> dict:
    """Point estimates and spread of a belief, world frame.

    Returns:
      ``map_cell (3,)`` int32 ``(k, h, w)``; ``map_pose (3,)`` its world pose ``(x, y, yaw)``;
      ``mean_pose (3,)`` the (x, y) mean and the circular mean yaw; ``cov_xy (2, 2)`` m^2;
      ``yaw_std`` rad (circular, ``sqrt(-2 ln R)``); ``peak_mass`` (mass within
      ``peak_radius`` of the MAP (x, y), all yaws); ``entropy`` of the (x, y) marginal
      normalized to [0, 1]; ``locked``; ``losses``.
    """
    return _estimate(belief, cfg)


@functools.partial(jax.jit, static_argnames="mass")
def in_credible_region(belief: Belief, cell, mass: float = 0.9) -> jax.Array:
    """Whether window cell ``(k, h, w)`` (int) lies in the smallest set of cells holding
    ``mass`` of the belief (the highest-probability cells, accumulated in descending order).

    Equal to sorting the probabilities, accumulating until ``mass`` is reached and testing
    ``p[cell] >= threshold``, but one pass: the cell is inside iff the mass of the cells
    strictly more probable than it is below ``mass``. False outside the window.
    """
    cell = jnp.asarray(cell, jnp.int32)
    k_dim, n, _ = belief.prob.shape
    inside = (cell[1] >= 0) & (cell[1] < n) & (cell[2] >= 0) & (cell[2] < n)
    h, w = jnp.clip(cell[1], 0, n - 1), jnp.clip(cell[2], 0, n - 1)
    p = belief.prob[cell[0] % k_dim, h, w]  # k wraps (a rounded k may be K)
    above = jnp.sum(jnp.where(belief.prob > p, belief.prob, 0.0))
    return inside & (above < mass)


# --------------------------------------------------------------------------- temperature


def fit_temperature(
    volumes, gt_cells, bounds: tuple[float, float] = (1e-2, 1e5), iters: int = 40
) -> float:
    """The temperature ``T`` maximizing the mean log-likelihood of the GT cells,
    ``mean_b log_softmax(volumes[b] / T)[gt_cells[b]]`` (fit it on a validation split).

    The objective is concave in ``1 / T``, so a log-spaced grid over ``bounds`` brackets the
    optimum and a golden-section search on ``log T`` refines it.

    Args:
      volumes: ``(B, K, H, W)`` raw score volumes.
      gt_cells: ``(B, 3)`` int GT cells ``(k, h, w)`` (inside the volumes).
    """
    volumes = jnp.asarray(volumes, jnp.float32)
    cells = np.asarray(gt_cells, np.int64)
    b_dim, k_dim, h_dim, w_dim = volumes.shape
    if cells.shape != (b_dim, 3):
        raise ValueError(f"gt_cells must be ({b_dim}, 3), got {cells.shape}")
    if (cells < 0).any() or (cells >= np.array([k_dim, h_dim, w_dim])).any():
        raise ValueError("gt_cells must lie inside the volumes")
    index = (np.arange(b_dim), cells[:, 0], cells[:, 1], cells[:, 2])

    @jax.jit
    def mean_ll(log_t):  # the very log-likelihood that update() is fed
        return jnp.mean(solver.log_softmax_volume(volumes, jnp.exp(log_t))[index])

    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    grid = np.linspace(lo, hi, 25)
    values = [float(mean_ll(t)) for t in grid]
    i = int(np.argmax(values))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    ratio = (math.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = float(mean_ll(c)), float(mean_ll(d))
    for _ in range(iters):
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = float(mean_ll(c))
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = float(mean_ll(d))
    return float(math.exp((a + b) / 2))


__all__ = [
    "TrackerConfig",
    "Belief",
    "init_belief",
    "window_centre",
    "tile_corner",
    "world_to_cell",
    "cell_to_world",
    "predict",
    "recentre",
    "update",
    "estimate",
    "in_credible_region",
    "fit_temperature",
]
