"""The likelihood temperature, fitted streaming on single frames (see the package docstring)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import geometry
from seglocnet_jax.evaluation import LocalizeStep, host_pool, row_parts, solver_threads

# Temperature grid: 8 points per decade over [1e-2, 1e5] (the raw volume sums ~1e4 terms); the
# parabola through the best three points refines it to ~1 % on smooth objectives.
TEMPERATURE_GRID = np.geomspace(1e-2, 1e5, 57)
# After the first batch only the grid points within this many of that batch's best one are
# evaluated (+-1.5 decades): the objective is concave in 1 / T, so a best point inside that
# window is the whole grid's best and the fit is the whole grid's, at 25 points per batch
# instead of 57 (each a log-sum-exp over every cell of the batch's volumes).
WINDOW_POINTS = 12


@jax.jit
def _objective(volume, cells, log_t):
    """``(B, T)``: ``log_softmax(volume / t)[cells]`` of each row at each ``t``."""
    b, k_dim, h_dim, w_dim = volume.shape  # (B, K, 129, 129)
    flat = volume.reshape(b, -1)
    idx = (cells[:, 0] * h_dim + cells[:, 1]) * w_dim + cells[:, 2]
    gt = jnp.take_along_axis(flat, idx[:, None], axis=1)[:, 0]  # (B,)

    def one(lt):  # one temperature at a time: one (B, K*H*W) temporary
        t = jnp.exp(lt)
        return gt / t - jax.nn.logsumexp(flat / t, axis=1)

    return jax.lax.map(one, log_t).T


def _row_objectives(volume, cells, log_t) -> np.ndarray:
    """:func:`_objective` ``(B, T)`` float64, its rows in parts side by side on CPU (one
    program runs on one core: :func:`~seglocnet_jax.evaluation.row_parts` of
    :func:`~seglocnet_jax.evaluation.solver_threads`); a row's values do not depend on the
    parts."""
    rows = len(cells)
    log_t = jnp.asarray(log_t, jnp.float32)

    def part(lo, hi):
        sub = volume if (lo, hi) == (0, rows) else volume[lo:hi]
        return np.asarray(_objective(sub, jnp.asarray(cells[lo:hi]), log_t), np.float64)

    spans = row_parts(rows, solver_threads())
    if len(spans) == 1:
        return part(*spans[0])
    jobs = [host_pool().submit(part, lo, hi) for lo, hi in spans]
    return np.concatenate([job.result() for job in jobs])


class TemperatureFit:
    """Streaming fit of the likelihood temperature: the ``T`` maximizing the mean
    ``log_softmax(volume / T)[gt cell]`` (the very log-likelihood the filter is fed),
    accumulated per batch on :data:`TEMPERATURE_GRID` and refined by a parabola in ``log T``
    through the best three grid points. The first batch is evaluated on the whole grid, the
    later ones on the :data:`WINDOW_POINTS` points either side of the first batch's best
    (``window``): the objective, a sum over frames of ``v_gt / T - logsumexp(v / T)``, is
    concave in ``1 / T``, so a best point inside the window is the whole grid's. A best point
    on the window's edge is reported as at the edge (``at_edge``), like one on the grid's.
    Memory: one batch of volumes at a time."""

    def __init__(self, grid=TEMPERATURE_GRID, window_points: int = WINDOW_POINTS):
        self.log_t = np.log(np.asarray(grid, np.float64))
        self.total = np.zeros(len(self.log_t))
        self.window_points = window_points
        self.window = slice(0, len(self.log_t))  # the points evaluated on every batch
        self.count = 0
        self.at_edge = False

    def add(self, volume, cells, weights=None) -> None:
        """``volume (B, K, H, W)`` (device or host), ``cells (B, 3)`` int GT cells, ``weights
        (B,)`` (0 for rows to skip: padding, a GT outside the volume)."""
        cells = np.asarray(cells, np.int32)
        weights = np.ones(len(cells)) if weights is None else np.asarray(weights, np.float64)
        if not (weights > 0).any():
            return
        out = _row_objectives(volume, cells, self.log_t[self.window])  # (B, T)
        self.total[self.window] += np.where(weights[:, None] > 0, weights[:, None] * out, 0).sum(0)
        if not self.count:  # the first batch: narrow to the window around its best point
            best, n = int(np.argmax(self.total)), len(self.log_t)
            self.window = slice(
                max(best - self.window_points, 0), min(best + self.window_points + 1, n)
            )
        self.count += int((weights > 0).sum())

    def result(self) -> float:
        if not self.count:
            raise ValueError("no frame to fit the temperature on")
        log_t = self.log_t[self.window]
        f = self.total[self.window] / self.count
        i = int(np.argmax(f))
        # At the edge the objective still rises beyond it (e.g. T -> 0 for the GT BEV, whose
        # peak is always the GT cell): the edge is returned and flagged.
        self.at_edge = i in (0, len(f) - 1)
        if not self.at_edge:
            denom = f[i - 1] - 2 * f[i] + f[i + 1]
            step = log_t[1] - log_t[0]
            offset = 0.5 * (f[i - 1] - f[i + 1]) / denom if denom < 0 else 0.0
            return float(math.exp(log_t[i] + float(np.clip(offset, -1, 1)) * step))
        return float(math.exp(log_t[i]))


def gt_cells(pose_tile, num_rotations: int) -> tuple[np.ndarray, np.ndarray]:
    """GT cells ``(B, 3)`` int of tile-frame GT poses and whether each lies in the volume."""
    cell = np.round(geometry.pose_to_cell(np.asarray(pose_tile, np.float64), num_rotations))
    cell = cell.astype(np.int64)
    cell[:, 0] %= num_rotations
    n = geometry.SCORE_SIZE
    inside = (cell[:, 1:] >= 0).all(1) & (cell[:, 1:] < n).all(1)
    return np.clip(cell, 0, [num_rotations - 1, n - 1, n - 1]), inside


def fit_temperature(
    step: LocalizeStep, params, batches, *, num_batches: int, place, num_rotations: int, desc: str
) -> tuple[float, int]:
    """Fits the temperature on ``num_batches`` evaluation batches (stored priors, single
    frames); returns ``(T, {"frames": used, "at_grid_edge": bool})``."""
    fit = TemperatureFit()
    for i, batch in enumerate(tqdm(batches, total=num_batches, desc=desc, unit="batch")):
        if i >= num_batches:
            break
        valid = np.asarray(batch.get("valid", np.ones(len(batch["pose"]), bool)), bool)
        cells, inside = gt_cells(batch["pose_tile"], num_rotations)
        out = step(params, place(batch), volume=True)
        fit.add(out["volume"], cells, valid & inside)
    return fit.result(), {"frames": fit.count, "at_grid_edge": fit.at_edge}


def choose_filter_temperature(
    track, split, drives, *, base: float, scales, single: bool = False
) -> tuple[float, list[dict], list, dict]:
    """The filter's temperature, chosen on validation drives: ``drives`` (of the
    :class:`~seglocnet_jax.sequential.drives.DriveSplit` ``split``) are tracked at
    ``base * s`` for each scale ``s``, all candidates in one pass over the drives
    (``track(split, drives, temperatures=, desc=, single=)``:
    :func:`~seglocnet_jax.sequential.tracks.track_candidates` with the run's filter: one
    network pass per frame for every candidate; with ``single`` also the frames'
    single-frame poses) and the ``T`` with the best mean log posterior of the GT cell (the
    filter's log score, clamped at ``drive_filter.LOG_P_FLOOR``: a proper score, so it rewards
    a posterior that is both sharp and calibrated) is returned, with one row per candidate
    (``scale``, ``temperature``, ``mean_log_p_gt``, ``tracked_pct``, ``R@1m``,
    ``coverage_90``), the chosen candidate's tracks (those a separate run at that ``T`` gives)
    and the pass's timings."""
    from seglocnet_jax.sequential import report  # the numbers of the tracks

    temps = [float(base) * float(scale) for scale in scales]
    desc = f"filter temperatures {', '.join(f'{t:.3g}' for t in temps)} ({split.name})"
    out, timing = track(split, drives, temperatures=temps, desc=desc, single=single)
    table = []
    for scale, t, tracks in zip(scales, temps, out, strict=True):
        s = report.summarize(tracks)
        table.append(
            {
                "scale": float(scale),
                "temperature": t,
                "mean_log_p_gt": s["mean_log_p_gt"],
                "tracked_pct": s["tracked_pct"],
                "R@1m": s["filtered"]["R@1m"],
                "coverage_90": s["coverage_90"],
            }
        )
    best = max(range(len(table)), key=lambda i: table[i]["mean_log_p_gt"])
    return table[best]["temperature"], table, out[best], timing
