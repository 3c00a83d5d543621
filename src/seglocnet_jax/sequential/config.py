"""The evaluation's settings, in one place: the ``eval`` group (:class:`EvalConfig`, single
frames and drives), its ``eval.tracker`` section (:class:`TrackerSettings`, the filter's
settings, with the one set of defaults that ``conf/eval/default.yaml`` repeats and
``tests/test_config.py`` pins), the filter's config built from them for a run
(:func:`tracker_config`) and the map channel the on-road prior reads (:func:`road_channels`).
"""

from __future__ import annotations

import dataclasses
import math

from seglocnet_jax import tracking
from seglocnet_jax.evaluation import BEV_SOURCES
from seglocnet_jax.tracking.odometry import OdometryConfig, tracker_noise

MODES = ("single", "sequential", "both")

# The on-road prior (eval.tracker.off_road) when the map has a road channel and the setting is
# null: chosen on the 8 unseen-city validation drives among 3 and 10 (docs/sequential.md).
OFF_ROAD_NATS = 10.0


@dataclasses.dataclass(frozen=True)
class TrackerSettings:
    """``eval.tracker``: the filter's settings (the meanings: :class:`tracking.TrackerConfig`).
    K, the window (129 cells at 0.5 m) and the motion noise are not settings: the solver, the
    geometry and ``eval.odometry`` fix them (:func:`tracker_config`).

    Attributes:
      floor: weight of a uniform mixed into the prior at every update.
      lost_log_odds: nats; a loss when the CUSUM of the prior-vs-uniform evidence falls below
        ``-lost_log_odds`` (0 disables).
      lock_peak_mass: the filter locks on once the mass within ``peak_radius`` of the mode
        reaches this.
      lost_peak_mass: when locked, a loss when that mass falls below this (0 disables).
      lost_entropy: when locked, a loss when the normalized (x, y) entropy exceeds this.
      peak_radius: m, the box of the peak mass (and of merging windows whose modes meet).
      track_size: cells of the tracking window (a locked drive down to one window runs the full
        window's filter on the box around the mode); 0: none.
      hypotheses: windows per drive (> 1: frame 0's posterior split among windows,
        :mod:`tracking.hypotheses`; chosen on the unseen city's validation drives).
      hypothesis_prune: nats; a window this far below the best one's log weight is dropped
        (10 pruned the window on the truth of a validation drive).
      scale_prior_m: m of prior weight on 1 in the online odometry-scale estimate
        (:class:`tracking.ScaleEstimate`); 0: off.
      off_road: nats per frame against a pose off the map's road channel (the on-road prior,
        :func:`tracking.road_log_prior`); None: :data:`OFF_ROAD_NATS` with a road channel, 0
        without; 0: off.
    """

    floor: float = 1e-9
    lost_log_odds: float = 10.0
    lock_peak_mass: float = 0.5
    lost_peak_mass: float = 0.05
    lost_entropy: float = 0.9
    peak_radius: float = 2.0
    track_size: int = 65
    hypotheses: int = 4
    hypothesis_prune: float = 30.0
    scale_prior_m: float = 200.0
    off_road: float | None = None


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
    odometry: the vehicle's odometry noise (:class:`tracking.odometry.OdometryConfig`; the
      filter's motion noise is derived from it, :func:`tracker_config`).
    tracker: :class:`TrackerSettings`, the filter's settings.
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
    tracker: TrackerSettings = TrackerSettings()
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


def tracker_config(
    eval_cfg: EvalConfig, num_rotations: int, channels=None
) -> tracking.TrackerConfig:
    """The filter's config: ``eval.tracker`` with the motion noise derived from
    ``eval.odometry`` (:func:`tracking.odometry.tracker_noise` for frames 0.5 s apart: the
    simulator's 5 m at 10 m/s, nuScenes keyframes at 2 Hz), a null ``off_road`` from the map's
    ``channels`` (:data:`OFF_ROAD_NATS` with a road channel, 0 without: a map of buildings
    alone has no road to keep to), the solver's K and the geometry's window (129 cells at
    0.5 m). One config per run: the kernels compile once."""
    section = dataclasses.asdict(eval_cfg.tracker)
    if section["off_road"] is None:
        if channels is None:
            raise ValueError(
                "eval.tracker.off_road is null (derived from the map's channels), but no map "
                "channels were given to derive it from; give them, or a number"
            )
        section["off_road"] = OFF_ROAD_NATS if "road" in channels else 0.0
    noise = tracker_noise(eval_cfg.odometry)
    return tracking.TrackerConfig(num_rotations=num_rotations, **noise, **section)


def road_channels(rasters: dict, cfg: tracking.TrackerConfig) -> dict[str, int] | None:
    """The road channel's index in each city's raster when the filter reads it
    (``cfg.off_road`` > 0; None otherwise); a raster without one is an error naming it."""
    if cfg.off_road <= 0:
        return None
    out = {}
    for city, raster in rasters.items():
        if "road" not in raster.channels:
            raise ValueError(
                f"eval.tracker.off_road = {cfg.off_road} needs a 'road' channel in the map, but "
                f"the {city!r} raster has channels {list(raster.channels)} (map.channels); set "
                "eval.tracker.off_road=0 for maps without roads"
            )
        out[city] = raster.channels.index("road")
    return out
