"""Update by a frame's likelihood, estimates, credible regions, track-loss detection and
recovery (see the package docstring)."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from seglocnet_jax import geometry
from seglocnet_jax.tracking.belief import (
    Belief,
    TrackerConfig,
    _cell_offsets,
    cell_to_world,
    init_belief,
    window_centre,
)
from seglocnet_jax.tracking.motion import _map_cell


@functools.partial(jax.jit, static_argnames="bev_size")
def road_log_prior(road, off_road, bev_size: int = geometry.BEV_SIZE):
    """The on-road prior of windows (``TrackerConfig.off_road``): ``(..., T, T)`` road channels
    of their map tiles -> ``(..., N, N)``, ``N = T - bev_size + 1``: 0 at each cell whose ego
    point is on the road, ``-off_road`` elsewhere. Cell ``(h, w)``'s ego point is the tile's
    pixel corner ``(h + bev_size / 2, w + bev_size / 2)`` (:func:`geometry.cell_to_pose`); it is
    on the road when any of the 4 pixels around that corner is."""
    half = bev_size // 2
    n = road.shape[-1] - bev_size + 1
    px = road[..., half - 1 : half + n, half - 1 : half + n] > 0  # (..., N + 1, N + 1)
    on = px[..., :-1, :-1] | px[..., 1:, :-1] | px[..., :-1, 1:] | px[..., 1:, 1:]
    return jnp.where(on, 0.0, -jnp.asarray(off_road, jnp.float32))


def _marginal_xy(prob):
    """``sum_k prob[k]`` as ``(N, N)``: a matrix-vector product (XLA's CPU reduction over the
    major axis is ~30x slower)."""
    k_dim, n, _ = prob.shape
    ones = jnp.ones((1, k_dim), prob.dtype)
    return (ones @ prob.reshape(k_dim, n * n)).reshape(n, n)


def _estimate(belief: Belief, cfg: TrackerConfig, p_k=None) -> dict:
    """See :func:`estimate`; ``p_k``: the yaw marginal ``(K,)`` when the caller has it."""
    prob = belief.prob
    cell = _map_cell(prob)
    p_xy = _marginal_xy(prob)  # (N, N)
    if p_k is None:
        p_k = prob.sum(axis=(1, 2))  # (K,)
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
        # normalized by the reference window's count (a tracking window's: the full one's)
        "entropy": entropy / math.log(cfg.reference_cells // cfg.num_rotations),
        "locked": belief.locked,
        "losses": belief.losses,
    }


def _likelihood(log_lik):
    """The frame's likelihood over the cells, up to a constant: ``exp(log_lik - max)`` in
    (0, 1]."""
    return jnp.exp(log_lik - log_lik.max())  # (K, N, N), max 1


@functools.partial(jax.jit, static_argnames="cfg")
def _update_kernel(belief: Belief, log_lik, log_mean, cfg: TrackerConfig):
    n = cfg.num_cells
    lik = _likelihood(log_lik)
    # the prior with the floor (spread over the reference window's cells: a tracking window's
    # cells get the full window's floor)
    prior = (1.0 - cfg.floor) * belief.prob + cfg.floor / cfg.reference_cells
    # Per slice: the unnormalized posterior's yaw marginal, whose sum is the evidence
    # z = (1 - floor) sum prior * L + floor * mean L (the prior sums to 1), and the
    # likelihood's, in one pass. The barrier keeps XLA from turning z or z_mean into a
    # reduction (a pass over the volume) of its own.
    p_k, l_k = jax.lax.optimization_barrier(
        (jnp.sum(prior * lik, axis=(1, 2)), jnp.sum(lik, axis=(1, 2)))
    )  # (K,) each
    # sum uniform * L: over this window, or (log_mean) over the reference window, whose
    # volume this window's log-likelihood is the centre of (in units of exp(max) here)
    if log_mean is None:
        log_z_mean = jnp.log(l_k.sum() / n)
    else:
        log_z_mean = log_mean - log_lik.max()
    # z = 0 only when floor = 0 and the prior misses every cell the likelihood allows: then
    # the agreement is -inf and the loss test below resets the belief.
    z = jnp.maximum(p_k.sum(), 1e-38)
    post = prior * lik / z
    stats = _estimate(belief._replace(prob=post), cfg, p_k / z)
    agreement = jnp.log(z) - log_z_mean  # log Bayes factor, this frame (nats)
    cusum = jnp.minimum(0.0, belief.cusum + agreement)
    by_odds = (cfg.lost_log_odds > 0) & (cusum < -cfg.lost_log_odds)
    by_shape = belief.locked & (
        (stats["peak_mass"] < cfg.lost_peak_mass) | (stats["entropy"] > cfg.lost_entropy)
    )
    lost = by_odds | by_shape
    locked = belief.locked | (stats["peak_mass"] >= cfg.lock_peak_mass)
    new = belief._replace(prob=post, cusum=cusum, locked=locked)
    stats.update(locked=locked)
    return new, {
        "agreement": agreement,
        # log sum prior * exp(log_lik - max): update() adds the maximum on request. (Used here,
        # the maximum would leave the fused pass that takes it and the exponential together:
        # that pass is ~2 ms faster on CPU than a maximum and an exponential pass.)
        "log_z": jnp.log(z),
        "lost": lost,
        "estimate": stats,
    }


@functools.partial(jax.jit, static_argnames="cfg")
def _reset_kernel(belief: Belief, log_lik, cfg: TrackerConfig):
    # the re-widened prior: uniform over the window's (x, y) and over yaw
    post = jnp.float32(1.0 / (cfg.size * cfg.size)) * _likelihood(log_lik)
    new = belief._replace(
        prob=post / post.sum(),
        cusum=jnp.zeros((), jnp.float32),
        locked=jnp.zeros((), bool),
        losses=belief.losses + 1,
    )
    return new, _estimate(new, cfg)


@jax.jit
def _max(log_lik):
    return jnp.max(log_lik, axis=(1, 2)).max()  # per slice first (XLA CPU)


def update(
    belief: Belief,
    log_likelihood,
    cfg: TrackerConfig,
    *,
    evidence: bool = False,
    log_mean=None,
    reset: bool = True,
) -> tuple[Belief, dict]:
    """Bayes update with one frame's log-likelihood over the window's cells.

    Args:
      log_likelihood: ``(K, N, N)`` float, up to an additive constant: e.g.
        ``solver.log_softmax_volume(volume, temperature)`` of the frame's score volume, the
        tile cut around this belief's window.
      evidence: also return ``log_evidence`` (one more pass over the volume).
      log_mean: the log of the mean of ``exp(log_likelihood)`` over the reference window's
        cells (``cfg.reference_size``: a tracking window's likelihood is the centre of that
        window's volume), the uniform alternative of the loss test; None: this window's.
      reset: on a detected loss, reset the belief (re-widened prior times the likelihood);
        False: return it as updated, ``lost`` set, for the caller to reset (:func:`reset`: a
        tracking window resets the full window with the frame's whole volume).

    Returns:
      The posterior and ``{"agreement": log Bayes factor of this frame (prior vs uniform,
      nats), "log_evidence" (with ``evidence`` only): log sum over the cells of prior *
      exp(log_likelihood), the floor included (the weight of a window among several
      hypotheses), "lost": a track loss was detected (the posterior is
      then the re-widened prior times this frame's likelihood), "estimate": :func:`estimate`
      of the returned posterior}``.
    """
    log_lik = jnp.asarray(log_likelihood, jnp.float32)
    expected = (cfg.num_rotations, cfg.size, cfg.size)
    if log_lik.shape != expected:
        raise ValueError(f"log_likelihood must be {expected}, got {log_lik.shape}")
    if log_mean is not None:
        log_mean = jnp.asarray(log_mean, jnp.float32)
    new, info = _update_kernel(belief, log_lik, log_mean, cfg)
    log_z = info.pop("log_z")
    if evidence:
        info["log_evidence"] = log_z + _max(log_lik)
    if reset and bool(info["lost"]):  # the one host sync of a frame: rare path, its own program
        new, est = _reset_kernel(new, log_lik, cfg)
        info = {**info, "estimate": est}
    return new, info


@functools.partial(jax.jit, static_argnames="cfg")
def crop_likelihood(log_likelihood, cfg: TrackerConfig) -> tuple[jax.Array, jax.Array]:
    """A tracking window's likelihood from the volume of the full tile around its centre:
    ``(the central (K, size, size) cells, the log of the mean of exp over the whole volume)``,
    the second the loss test's uniform alternative (``update(..., log_mean=)``; ``cfg``: the
    tracking window's, ``cfg.reference_size`` the volume's side)."""
    ref = cfg.reference_size or cfg.size
    expected = (cfg.num_rotations, ref, ref)
    if log_likelihood.shape != expected:
        raise ValueError(f"log_likelihood must be {expected}, got {log_likelihood.shape}")
    o = (ref - cfg.size) // 2
    log_mean = jax.nn.logsumexp(log_likelihood) - math.log(log_likelihood.size)
    return log_likelihood[:, o : o + cfg.size, o : o + cfg.size], log_mean


def update_tracking_window(
    belief: Belief, log_likelihood, cfg: TrackerConfig, full: TrackerConfig
) -> tuple[Belief, dict, TrackerConfig]:
    """The update of a tracking window (``cfg = full.tracking_window()``) by the volume of the
    full window's tile around its centre, ``(K, full.size, full.size)``: the full window's
    filter on the window's cells (:func:`crop_likelihood`, the loss test against the whole
    volume). On a detected loss the belief becomes the full window's, around the same centre,
    reset with the whole volume (:func:`reset`), as the full window would be.

    Returns the belief, the :func:`update` info and the config of the window it is in
    (``cfg``, or ``full`` after a loss)."""
    centre, log_mean = crop_likelihood(log_likelihood, cfg)
    new, info = update(belief, centre, cfg, log_mean=log_mean, reset=False)
    if not bool(info["lost"]):
        return new, info, cfg
    start = init_belief(full, window_centre(new, cfg), tuple(new.origin))
    new, est = reset(start._replace(losses=new.losses), log_likelihood, full)
    return new, {**info, "estimate": est}, full


def reset(belief: Belief, log_likelihood, cfg: TrackerConfig) -> tuple[Belief, dict]:
    """The belief after a detected loss: the re-widened prior (uniform over the window and
    over yaw) times the frame's likelihood, the loss counted, CUSUM and lock cleared (what
    :func:`update` does on a loss). Returns the belief and its :func:`estimate`."""
    log_lik = jnp.asarray(log_likelihood, jnp.float32)
    expected = (cfg.num_rotations, cfg.size, cfg.size)
    if log_lik.shape != expected:
        raise ValueError(f"log_likelihood must be {expected}, got {log_lik.shape}")
    return _reset_kernel(belief, log_lik, cfg)


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
