"""Evaluation, in one home: the jitted localize step and the split evaluation built on it.

:func:`make_localize_step` builds, once per ``(model config, solver config, BEV source)``, one
jitted program ``network (or GT labels) -> solver -> decoded pose``. Every evaluation goes through
it: periodic validation, best-checkpoint selection, the final tables, the figures, the
``evaluate`` app and the benchmarks. What it matches depends on the variant:

- ``seg`` models: the BEV logits ``(B, C, 128, 128)`` against the ``{0, 1}`` map tile.
- ``nm`` models (SegLocNet-NM): the BEV matching features against the neural map the network
  computes from the tile (``aux["bev_match"]`` vs ``aux["map_match"]``).
- ``bev_source="gt"`` (the GT-segmentation upper bound): the GT BEV labels as +-1 logits
  (:func:`solver.labels_to_logits`) against the tile; no network, no parameters.

Only decoded poses, peak scores and per-class IoU counts come back to the host; the likelihood
map (score volume maximized over rotations) and BEV probabilities are returned only by the
figure variant of the program, used for the batches that get figures, and the whole score volume
``(B, K, 129, 129)`` only by the volume variant (left on the device: the sequential filter's
likelihood and the temperature fit, :mod:`seglocnet_jax.sequential`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import typing
from collections.abc import Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from seglocnet_jax import metrics, solver, viz
from seglocnet_jax.model import api as model_api
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.tracking import TrackerConfig
from seglocnet_jax.tracking.odometry import OdometryConfig

BEV_SOURCES = ("model", "gt")
MODES = ("single", "sequential", "both")

# How many times each localize program was traced, keyed by the builder's arguments and the
# program: ``figures`` False (poses), True (figure maps) or "volume" (the score volume). Pinned
# by a test so that validation rounds never recompile.
TRACE_COUNTS: dict[tuple, int] = {}

# TrackerConfig fields that eval.tracker does not hold: the solver and geometry fix them.
_TRACKER_DERIVED = ("num_rotations", "size", "resolution", "bev_size", "reference_size")
# TrackerConfig's motion-noise fields: null in eval.tracker means "from eval.odometry".
TRACKER_MOTION_FIELDS = ("sigma_xy", "sigma_xy_per_m", "sigma_yaw", "sigma_yaw_per_rad")
# TrackerConfig's fields that null in eval.tracker derives from the map: the on-road prior
# (sequential.tracks.OFF_ROAD_NATS with a road channel, 0 without).
TRACKER_MAP_FIELDS = ("off_road",)
# Where the app's default differs from the filter's own (TrackerConfig: one window, no tracking
# window): a bank of 4 windows, the setting chosen on the unseen city's validation drives, and
# the 65-cell tracking window, which gave the same tracks there at a third of the filter's time,
# and windows pruned only 30 nats below the best (10 pruned the window on the truth of a
# validation drive before the model's frames turned good there; docs/sequential.md).
TRACKER_APP_DEFAULTS = {"hypotheses": 4, "hypothesis_prune": 30.0, "track_size": 65}


def _tracker_section():
    fields = []
    hints = typing.get_type_hints(TrackerConfig)
    for f in dataclasses.fields(TrackerConfig):
        if f.name in _TRACKER_DERIVED:
            continue
        if f.name in TRACKER_MOTION_FIELDS + TRACKER_MAP_FIELDS:
            fields.append((f.name, float | None, dataclasses.field(default=None)))
        else:
            default = TRACKER_APP_DEFAULTS.get(f.name, f.default)
            fields.append((f.name, hints[f.name], dataclasses.field(default=default)))
    cls = dataclasses.make_dataclass("TrackerSection", fields, frozen=True)
    cls.__module__ = __name__
    cls.__doc__ = (
        "``eval.tracker``: the motion-noise and track-loss fields of "
        ":class:`seglocnet_jax.tracking.TrackerConfig` (same names, meanings and defaults, "
        "built from its fields, except ``TRACKER_APP_DEFAULTS``: ``hypotheses`` = 4, a bank of "
        "windows, where the filter's own default is one window, ``hypothesis_prune`` = 30 nats "
        "(the filter's own: 10), and ``track_size`` = 65, the tracking window, where the "
        "filter's own has none). The motion-noise fields "
        f"({', '.join(TRACKER_MOTION_FIELDS)}) default to null: derived from ``eval.odometry`` "
        "(the noise the filter's prediction must allow for); a number overrides. ``off_road`` "
        "defaults to null: the on-road prior derived from the map (10 nats with a road channel, "
        "0 without; ``sequential.tracker_config``). K, the window size and the resolution "
        "follow the solver."
    )
    return cls


TrackerSection = _tracker_section()


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Attributes:
    bev_source: "model" (network output) or "gt" (GT-segmentation upper bound: the map cut out
      at the GT pose, as +-1 logits; needs no checkpoint).
    splits: prepared splits evaluated at the end of training / by ``evaluate`` (single-frame).
    num_figures: figures written per split (the first valid samples; sequential: the first
      drives' maps, plus the error and calibration figures when > 0).
    max_batches: cap on batches per split (None: the whole split); also caps the batches of
      the temperature fit.
    batch_size: evaluation batch size (sequential: drives localized in lockstep).
    mode: "single" (``splits``, each frame from its own prior), "sequential" (whole drives
      through the Bayes filter, :mod:`seglocnet_jax.sequential`) or "both".
    sequential_splits: splits whose sequences are tracked (simulator: ``drives``; real data:
      the scenes / logs of ``val`` or ``test``).
    calibration_split: split whose drives give the calibration report and figure (tracked too
      when not in ``sequential_splits``); None: none.
    temperature: likelihood temperature of the filter (None: fitted on
      ``temperature_split``).
    temperature_split: split the single-frame temperature is fitted on (stored priors).
    temperature_drives: split whose drives choose the filter's temperature (None: the
      single-frame one): they are tracked at the single-frame ``T`` times each of
      ``temperature_scales`` and the ``T`` with the best mean log posterior of the GT cell is
      kept. Consecutive frames of a drive see overlapping surroundings, so their errors are
      correlated and the single-frame ``T`` counts the same evidence many times over.
    temperature_scales: the factors tried (ascending, > 0).
    odometry: the vehicle's odometry noise (:class:`tracking.odometry.OdometryConfig`).
    tracker: :data:`TrackerSection`, the filter's motion-noise and track-loss settings.
    odometry_seed: seed of the simulated odometry noise (per drive: with its sequence id).
    max_drives: sequences tracked per split (None: all).
    """

    bev_source: str = "model"
    splits: tuple[str, ...] = ("test", "kouvola")
    num_figures: int = 4
    max_batches: int | None = None
    batch_size: int = 8
    mode: str = "both"
    sequential_splits: tuple[str, ...] = ("drives",)
    calibration_split: str | None = "drives_val_unseen"
    temperature: float | None = None
    temperature_split: str = "val"
    temperature_drives: str | None = "drives_val_unseen"
    temperature_scales: tuple[float, ...] = (1.0, 4.0, 16.0, 64.0)
    odometry: OdometryConfig = OdometryConfig()
    tracker: TrackerSection = TrackerSection()
    odometry_seed: int = 0
    max_drives: int | None = None

    def __post_init__(self):
        if self.bev_source not in BEV_SOURCES:
            raise ValueError(
                f"eval.bev_source must be one of {BEV_SOURCES}, got {self.bev_source!r}"
            )
        if self.batch_size < 1:
            raise ValueError(f"eval.batch_size must be >= 1, got {self.batch_size}")
        if self.num_figures < 0:
            raise ValueError(f"eval.num_figures must be >= 0, got {self.num_figures}")
        if self.max_batches is not None and self.max_batches < 1:
            raise ValueError(f"eval.max_batches must be >= 1 or null, got {self.max_batches}")
        if not self.splits:
            raise ValueError("eval.splits must name at least one split")
        if len(set(self.splits)) != len(self.splits):
            raise ValueError(f"eval.splits has duplicates: {list(self.splits)}")
        if self.mode not in MODES:
            raise ValueError(f"eval.mode must be one of {MODES}, got {self.mode!r}")
        if self.mode != "single" and not self.sequential_splits:
            raise ValueError(f"eval.mode={self.mode} needs eval.sequential_splits (got none)")
        if len(set(self.sequential_splits)) != len(self.sequential_splits):
            raise ValueError(
                f"eval.sequential_splits has duplicates: {list(self.sequential_splits)}"
            )
        if self.temperature is not None and not (
            math.isfinite(self.temperature) and self.temperature > 0
        ):
            raise ValueError(
                f"eval.temperature must be > 0 or null (fit it), got {self.temperature}"
            )
        scales = self.temperature_scales
        if (
            not scales
            or any(not (math.isfinite(v) and v > 0) for v in scales)
            or list(scales) != sorted(set(scales))
        ):
            raise ValueError(
                "eval.temperature_scales must be ascending distinct factors > 0, got "
                f"{list(scales)}"
            )
        if self.max_drives is not None and self.max_drives < 1:
            raise ValueError(f"eval.max_drives must be >= 1 or null, got {self.max_drives}")

    @property
    def single(self) -> bool:
        """Whether the single-frame splits are evaluated."""
        return self.mode in ("single", "both")

    @property
    def sequential(self) -> bool:
        """Whether drives are tracked."""
        return self.mode in ("sequential", "both")

    def tracked_splits(self) -> tuple[str, ...]:
        """The splits whose drives are tracked: ``sequential_splits`` and the calibration split."""
        extra = (self.calibration_split,) if self.calibration_split else ()
        return tuple(dict.fromkeys(self.sequential_splits + extra))


def _match_inputs(params, batch, model_cfg: ModelConfig, bev_source: str):
    """``(template (B, C', 128, 128), tile (B, C', 256, 256), bev logits or None)``."""
    tile = batch["tile"].astype(jnp.float32)
    if bev_source == "gt":
        return solver.labels_to_logits(batch["bev_gt"].astype(jnp.float32)), tile, None
    logits, aux = model_api.forward(params, batch, model_cfg)
    if model_cfg.variant == "nm":
        return aux["bev_match"], aux["map_match"], logits
    return logits, tile, logits


def _localize(params, batch, *, model_cfg, solver_cfg, bev_source, figures, key):
    TRACE_COUNTS[key] = TRACE_COUNTS.get(key, 0) + 1  # runs only while tracing
    template, tile, logits = _match_inputs(params, batch, model_cfg, bev_source)
    out = solver.localize(template, tile, solver_cfg, return_volume=bool(figures))
    result = {"pose_tile": out["pose_tile"], "score": out["score"]}  # (B, 3), (B,)
    labels = batch["bev_gt"].astype(jnp.float32)  # (B, C, 128, 128)
    if logits is not None:
        pred = (logits > 0).astype(jnp.float32)
        result["inter"] = jnp.sum(pred * labels, axis=(2, 3))  # (B, C)
        result["union"] = jnp.sum(jnp.maximum(pred, labels), axis=(2, 3))  # (B, C)
    if figures == "volume":
        result["volume"] = out["volume"]  # (B, K, 129, 129)
    elif figures:
        result["likelihood"] = out["volume"].max(axis=1)  # (B, 129, 129)
        result["probs"] = labels if logits is None else jax.nn.sigmoid(logits)
    return result


LocalizeStep = Callable[..., dict]


@functools.lru_cache(maxsize=16)
def make_localize_step(
    model_cfg: ModelConfig, solver_cfg: solver.SolverConfig, bev_source: str = "model"
) -> LocalizeStep:
    """``step(params, device_batch, figures=False, volume=False) -> dict`` of device arrays:
    ``pose_tile (B, 3)`` (tile frame: dx, dy m, yaw rad), ``score (B,)``, for a network also
    ``inter`` / ``union (B, C)`` pixel counts of the thresholded BEV vs the GT labels; with
    ``figures=True`` also ``likelihood (B, 129, 129)`` and ``probs (B, C, 128, 128)``; with
    ``volume=True`` (not with figures) also the raw score volume ``volume (B, K, 129, 129)``.

    Built once per argument triple (cached); each of the three programs compiles once.
    ``params`` is ignored (pass None) for ``bev_source="gt"``."""
    if bev_source not in BEV_SOURCES:
        raise ValueError(f"bev_source must be one of {BEV_SOURCES}, got {bev_source!r}")
    compiled = {}
    for figures in (False, True, "volume"):
        key = (model_cfg, solver_cfg, bev_source, figures)
        compiled[figures] = jax.jit(
            functools.partial(
                _localize,
                model_cfg=model_cfg,
                solver_cfg=solver_cfg,
                bev_source=bev_source,
                figures=figures,
                key=key,
            )
        )

    def step(params, batch, figures: bool = False, volume: bool = False):
        if volume and figures:
            raise ValueError("a localize step returns either the figure maps or the volume")
        return compiled["volume" if volume else bool(figures)](params, batch)

    return step


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
    ``IoU_<channel>`` (percent, pooled over the split; network only) and ``prior`` (position
    recalls / APE of answering the tile centre). Writes ``num_figures`` figures."""
    acc = metrics.MetricAccumulator()
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
