"""Evaluation, in one home: the jitted localize step and the split evaluation built on it.

:func:`make_localize_step` builds, once per ``(model config, solver config, BEV source)``, the
localize step ``network (or GT labels) -> solver -> decoded pose``: two jitted programs, the
network's side (:meth:`LocalizeStep.network`: the BEV, which no tile changes) and the tile's
(:meth:`LocalizeStep.solve`: the map side and the solver), so that a frame matched against
several tiles (the sequential filter's windows and the single-frame prior tile) runs the
network once. Every evaluation goes through it: periodic validation, best-checkpoint
selection, the final tables, the figures, the ``evaluate`` app, the sequential filter and the
benchmarks. What it matches depends on the variant:

- ``seg`` models: the BEV logits ``(B, C, 128, 128)`` against the ``{0, 1}`` map tile.
- ``nm`` models (SegLocNet-NM): the BEV matching features against the neural map the network
  computes from the OSM class tile ``batch["nm_tile"]`` (``aux["bev_match"]`` vs
  ``aux["map_match"]``).
- ``bev_source="gt"`` (the GT-segmentation upper bound): the GT BEV labels as +-1 logits
  (:func:`solver.labels_to_logits`) against the tile; no network, no parameters.

Only decoded poses, peak scores and per-class IoU counts come back to the host; the likelihood
map (score volume maximized over rotations) and BEV probabilities are returned only by the
figure variant of the program, used for the batches that get figures, and the whole score volume
``(B, K, 129, 129)`` only by the volume variant (left on the device: the sequential filter's
likelihood and the temperature fit, :mod:`seglocnet_jax.sequential`). The ``eval`` group's
settings are :class:`seglocnet_jax.sequential.config.EvalConfig` (with the filter's: the
evaluation floor below it does not know the filter).
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
from collections.abc import Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import metrics, solver, viz
from seglocnet_jax.model import api as model_api
from seglocnet_jax.model.config import ModelConfig

BEV_SOURCES = ("model", "gt")

# How many times each localize program was traced, keyed by the builder's arguments and the
# program: "network", or the solver's ``figures`` False (poses), True (figure maps) or "volume"
# (the score volume), followed by "rows" for the solver of gathered BEV rows (several tiles per
# frame). Pinned by tests so that validation rounds never recompile.
TRACE_COUNTS: dict[tuple, int] = {}


def _network(params, batch, *, model_cfg: ModelConfig, bev_source: str, key) -> dict:
    """The network's side of a batch, which no tile changes: ``template (B, C', 128, 128)``
    (the BEV logits; NM: the BEV matching features; GT: the labels as +-1 logits) and, for a
    network, its ``logits (B, C, 128, 128)``."""
    TRACE_COUNTS[key] = TRACE_COUNTS.get(key, 0) + 1  # runs only while tracing
    if bev_source == "gt":
        return {"template": solver.labels_to_logits(batch["bev_gt"].astype(jnp.float32))}
    logits, aux = model_api.forward(params, batch, model_cfg, map_side=False)
    template = aux["bev_match"] if model_cfg.variant == "nm" else logits
    return {"template": template, "logits": logits}


def _solve(params, bev, batch, rows, *, model_cfg, solver_cfg, bev_source, figures, key):
    """The tile's side: ``bev`` (:func:`_network`, rows ``rows`` of it when given: a tile per
    row of ``batch``) against ``batch["tile"]`` (NM: the neural map of ``batch["nm_tile"]``)
    -> decoded pose; without ``rows`` also the IoU counts of the BEV (and the figure maps)."""
    TRACE_COUNTS[key] = TRACE_COUNTS.get(key, 0) + 1  # runs only while tracing
    template = bev["template"] if rows is None else bev["template"][rows]  # (B, C', 128, 128)
    if model_cfg.variant == "nm" and bev_source == "model":
        tile = model_api.encode_map(params, batch, model_cfg)  # (B, D', 256, 256)
    else:
        tile = batch["tile"].astype(jnp.float32)  # (B, C, 256, 256)
    out = solver.localize(template, tile, solver_cfg, return_volume=bool(figures))
    result = {"pose_tile": out["pose_tile"], "score": out["score"]}  # (B, 3), (B,)
    logits = bev.get("logits")
    if rows is None:
        labels = batch["bev_gt"].astype(jnp.float32)  # (B, C, 128, 128)
        if logits is not None:
            pred = (logits > 0).astype(jnp.float32)
            result["inter"] = jnp.sum(pred * labels, axis=(2, 3))  # (B, C)
            result["union"] = jnp.sum(jnp.maximum(pred, labels), axis=(2, 3))  # (B, C)
        if figures is True:
            result["probs"] = labels if logits is None else jax.nn.sigmoid(logits)
    if figures == "volume":
        result["volume"] = out["volume"]  # (B, K, 129, 129)
    elif figures:
        result["likelihood"] = out["volume"].max(axis=1)  # (B, 129, 129)
    return result


class LocalizeStep:
    """The one localize step: ``step(params, batch, figures=False, volume=False)`` is
    :meth:`network` then :meth:`solve` of the same batch; a caller with several tiles per
    frame (the sequential filter) runs :meth:`network` once per frame and :meth:`solve` per
    tile. See :func:`make_localize_step`."""

    def __init__(self, model_cfg: ModelConfig, solver_cfg: solver.SolverConfig, bev_source: str):
        base = (model_cfg, solver_cfg, bev_source)
        self.threads = solver_threads()
        self._compiled: set = set()  # (program, part size, ...) already traced and compiled
        # The tiles' batch key the map side reads besides ``tile``: an NM network's neural map
        # reads the OSM class tile (the loaders yield it only when asked).
        self.reads_nm_tile = model_cfg.variant == "nm" and bev_source == "model"
        self._network = jax.jit(
            functools.partial(
                _network, model_cfg=model_cfg, bev_source=bev_source, key=base + ("network",)
            )
        )
        self._solve = {}
        for figures in (False, True, "volume"):
            for gathered in (False, True):
                key = base + ((figures, "rows") if gathered else (figures,))
                self._solve[figures, gathered] = jax.jit(
                    functools.partial(
                        _solve,
                        model_cfg=model_cfg,
                        solver_cfg=solver_cfg,
                        bev_source=bev_source,
                        figures=figures,
                        key=key,
                    )
                )

    def network(self, params, batch) -> dict:
        """The network's side of a device batch (device arrays, :func:`_network`); ``params``
        is ignored (pass None) for ``bev_source="gt"``."""
        return self._network(params, batch)

    def solve(self, params, bev, batch, rows=None, *, figures=False, volume=False) -> dict:
        """The tiles of ``batch`` against ``bev`` (:meth:`network`'s output): the outputs of
        :func:`make_localize_step`. ``rows``: ``(B,)`` int, the row of ``bev`` each tile is
        matched with (None: row i with tile i; then also the IoU counts and figure maps)."""
        if volume and figures:
            raise ValueError("a localize step returns either the figure maps or the volume")
        if rows is not None and figures:
            raise ValueError("figure maps come with the batch's own rows (rows=None)")
        program = self._solve["volume" if volume else bool(figures), rows is not None]
        n = len(rows) if rows is not None else len(batch["tile"])
        parts = min(self.threads, n)
        if parts <= 1:
            return self._run(program, params, bev, batch, rows, 0, n)
        # One solver program runs on one core on CPU (its FFTs are single-threaded): the rows
        # are split into ``parts`` near-equal parts (sizes differ by at most one: at most two
        # programs per batch size), solved side by side by host threads and joined. A row's
        # outputs do not depend on the split: the fft path solves sample after sample.
        spans = row_parts(n, parts)
        # A program's first call for a shape traces and compiles it: in this thread, one part
        # after the other (threads calling it at once would each trace and compile it).
        shapes = jax.tree.map(lambda x: x.shape, (bev, batch))
        signatures = {(program, hi - lo, rows is None, str(shapes)) for lo, hi in spans}
        if not signatures <= self._compiled:
            outs = [self._run(program, params, bev, batch, rows, lo, hi) for lo, hi in spans]
            self._compiled |= signatures
        else:
            jobs = [
                host_pool().submit(self._run, program, params, bev, batch, rows, lo, hi)
                for lo, hi in spans
            ]
            outs = [job.result() for job in jobs]
        return jax.tree.map(lambda *parts: jnp.concatenate(parts), *outs)

    @staticmethod
    def _run(program, params, bev, batch, rows, lo: int, hi: int) -> dict:
        """``program`` on rows ``lo:hi`` (the whole batch when that is all of it), finished:
        an execution runs on the thread that waits for it."""
        n = len(rows) if rows is not None else len(batch["tile"])
        if (lo, hi) != (0, n):
            batch = jax.tree.map(lambda x: x[lo:hi], batch)
            if rows is None:
                bev = jax.tree.map(lambda x: x[lo:hi], bev)
        if rows is None:
            out = program(params, bev, batch, None)
        else:
            out = program(params, bev, batch, jnp.asarray(np.asarray(rows)[lo:hi], jnp.int32))
        return jax.block_until_ready(out)

    def __call__(self, params, batch, figures: bool = False, volume: bool = False) -> dict:
        return self.solve(
            params, self.network(params, batch), batch, figures=figures, volume=volume
        )


def solver_threads() -> int:
    """Host threads the localize step solves a batch with: the usable cores on CPU, where XLA
    runs a solver program on one core (two side by side solve a batch of 8 in ~55 ms per
    sample against ~100 on 2 cores); 1 on accelerators, which run a batch in one program."""
    if jax.default_backend() != "cpu":
        return 1
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def row_parts(n: int, parts: int) -> list[tuple[int, int]]:
    """``(lo, hi)`` of ``min(parts, n)`` (at least one) near-equal parts of ``n`` rows: sizes
    differ by at most one, so a batch size gives at most two part sizes (programs)."""
    bounds = np.linspace(0, n, max(1, min(parts, n)) + 1).round().astype(int)
    return [(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]


@functools.cache
def host_pool() -> concurrent.futures.ThreadPoolExecutor:
    """The host threads that run a batch's parts side by side (:func:`solver_threads`; the
    localize step's solver, the temperature fit's objective), started on first use."""
    return concurrent.futures.ThreadPoolExecutor(solver_threads(), thread_name_prefix="parts")


@functools.lru_cache(maxsize=16)
def make_localize_step(
    model_cfg: ModelConfig, solver_cfg: solver.SolverConfig, bev_source: str = "model"
) -> LocalizeStep:
    """``step(params, device_batch, figures=False, volume=False) -> dict`` of device arrays:
    ``pose_tile (B, 3)`` (tile frame: dx, dy m, yaw rad), ``score (B,)``, for a network also
    ``inter`` / ``union (B, C)`` pixel counts of the thresholded BEV vs the GT labels; with
    ``figures=True`` also ``likelihood (B, 129, 129)`` and ``probs (B, C, 128, 128)``; with
    ``volume=True`` (not with figures) also the raw score volume ``volume (B, K, 129, 129)``.

    Two jitted programs per call: the network (:meth:`LocalizeStep.network`, no tile but the
    NM map side) and the solver (:meth:`LocalizeStep.solve`), each compiled once per variant
    and shape; on CPU the solver's rows are split among :func:`solver_threads` host threads.
    Built once per argument triple (cached). ``params`` is ignored (pass None) for
    ``bev_source="gt"``."""
    if bev_source not in BEV_SOURCES:
        raise ValueError(f"bev_source must be one of {BEV_SOURCES}, got {bev_source!r}")
    return LocalizeStep(model_cfg, solver_cfg, bev_source)


def evaluate_split(
    step: LocalizeStep,
    params,
    batches: Iterable[dict],
    *,
    num_batches: int,
    place: Callable[[dict], dict],
    desc: str,
    channels: tuple[str, ...],
    figure_dir: str | None = None,
    num_figures: int = 0,
) -> dict:
    """Localizes every valid sample of the first ``num_batches`` host ``batches`` (``place``
    puts one on the devices) and returns the metric summary: the paper's keys and ``count``,
    ``IoU_<channel>`` (percent, pooled over the split; network only), ``prior`` (position
    recalls / APE of answering the tile centre) and, when the records know their lighting,
    ``lighting``: the same keys over each condition's frames (``{"day": {...}, "night": ...}``;
    frames of unknown lighting are left out of it). Writes ``num_figures`` figures."""
    acc = metrics.MetricAccumulator()
    by_lighting: dict[str, metrics.MetricAccumulator] = {}
    prior_err = []
    inter = union = None
    figures = 0
    for i, batch in enumerate(tqdm(batches, total=num_batches, desc=desc, unit="batch")):
        if i >= num_batches:
            break
        valid = np.asarray(batch.get("valid", np.ones(len(batch["pose"]), bool)), bool)
        want = min(num_figures - figures, int(valid.sum())) if figure_dir else 0
        out = jax.device_get(step(params, place(batch), figures=want > 0))
        pose_tile = np.asarray(out["pose_tile"], np.float64)  # (B, 3)
        pred_world = solver.tile_pose_to_world(pose_tile, batch["tile_center"])
        gt_world = np.asarray(batch["pose"], np.float64)[valid]
        acc.update(pred_world[valid], gt_world)
        lighting = np.asarray(batch["lighting"])[valid]
        for name in np.unique(lighting):
            here = lighting == name
            by_lighting.setdefault(str(name), metrics.MetricAccumulator()).update(
                pred_world[valid][here], gt_world[here]
            )
        centre = np.asarray(batch["tile_center"], np.float64)[valid]
        prior_err.append(np.hypot(*(centre - gt_world[:, :2]).T))
        if "inter" in out:
            i_b = np.asarray(out["inter"], np.float64)[valid].sum(0)
            u_b = np.asarray(out["union"], np.float64)[valid].sum(0)
            inter = i_b if inter is None else inter + i_b
            union = u_b if union is None else union + u_b
        for j in np.flatnonzero(valid)[:want]:
            _figure(figure_dir, batch, j, out, pose_tile, channels)
            figures += 1
    result = acc.result()
    if inter is not None:
        for c, name in enumerate(channels):
            result[f"IoU_{name}"] = float(100.0 * inter[c] / max(union[c], 1.0))
    result["prior"] = metrics.position_summary(np.concatenate(prior_err) if prior_err else [])
    known = sorted(k for k in by_lighting if k != "unknown")
    if known:
        result["lighting"] = {k: by_lighting[k].result() for k in known}
    return result


def _figure(figure_dir, batch, j, out, pose_tile, channels):
    sid = str(batch["sample_id"][j])
    viz.sample_figure(
        os.path.join(figure_dir, f"{sid}.png"),
        tile=np.asarray(batch["tile"][j]),
        bev_pred=np.asarray(out["probs"][j]),
        bev_gt=np.asarray(batch["bev_gt"][j]),
        likelihood=np.asarray(out["likelihood"][j]),
        pose_gt=np.asarray(batch["pose_tile"][j], np.float64),
        pose_pred=pose_tile[j],
        images=np.asarray(batch["images"][j]) if "images" in batch else None,
        channels=channels,
        title=sid,
    )
