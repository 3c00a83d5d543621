"""What an OSM alignment is: its config (:class:`AlignConfig`, validated manual corrections), the
similarity it fits, its windows, the per-city result with its quality and refusal
(:class:`Alignment`, :class:`AlignmentError`) and the conversion-log lines of a stored one.
The fit itself is :mod:`seglocnet_jax.data.real.align_fit`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from seglocnet_jax import geometry
from seglocnet_jax.data.real.common import RealDataError

# Keys of AlignConfig that define the fitted values (stored in the manifest and compared on
# resume); the acceptance thresholds and the manual corrections are not among them.
FIT_KEYS = (
    "enabled",
    "resolution",
    "max_shift",
    "max_rotation_deg",
    "rotation_step_deg",
    "scales",
    "band",
    "road_width",
    "window",
    "max_windows",
)
CHECK_KEYS = ("min_score", "min_sharpness", "max_disagreement", "min_agreement")
MANUAL_KEYS = ("shift", "rotation_deg", "scale", "centre")
_PREFIX = "dataset.convert.align"


class AlignmentError(RealDataError):
    """An OSM alignment that is refused (degenerate fit) or impossible; names city and remedy."""


def _number(value, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{key} must be a finite number, got {value!r}")
    return float(value)


def _pair(value, key: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"{key} must be [x, y] metres, got {value!r}")
    return [_number(v, f"{key}[{i}]") for i, v in enumerate(value)]


def _check_manual(manual) -> dict:
    """Validated ``{city: {shift, rotation_deg, scale, centre}}`` with every key filled in."""
    if manual is None:
        return {}
    if not isinstance(manual, Mapping):
        raise ValueError(
            f"{_PREFIX}.manual must map city -> {{shift: [dx, dy], rotation_deg: r, scale: s, "
            f"centre: [x, y]}}, got {manual!r}"
        )
    out = {}
    for city, entry in manual.items():
        key = f"{_PREFIX}.manual.{city}"
        entry = {} if entry is None else entry
        if not isinstance(entry, Mapping):
            raise ValueError(
                f"{key} must be a mapping {{shift: [dx, dy], rotation_deg: r, scale: s, "
                f"centre: [x, y]}} (all optional), got {entry!r}"
            )
        unknown = sorted(set(entry) - set(MANUAL_KEYS))
        if unknown:
            raise ValueError(
                f"unknown key(s) {[f'{key}.{k}' for k in unknown]}; {key} accepts "
                f"{', '.join(MANUAL_KEYS)}"
            )
        rotation = _number(entry.get("rotation_deg", 0.0), f"{key}.rotation_deg")
        scale = _number(entry.get("scale", 1.0), f"{key}.scale")
        if abs(rotation) > 45.0:
            raise ValueError(f"{key}.rotation_deg must be within [-45, 45], got {rotation}")
        if not 0.5 <= scale <= 2.0:
            raise ValueError(f"{key}.scale must be within [0.5, 2], got {scale}")
        out[str(city)] = {
            "shift": _pair(entry.get("shift", (0.0, 0.0)), f"{key}.shift"),
            "rotation_deg": rotation,
            "scale": scale,
            "centre": _pair(entry.get("centre", (0.0, 0.0)), f"{key}.centre"),
        }
    return out


@dataclasses.dataclass(frozen=True)
class AlignConfig:
    """The ``dataset.convert.align`` config.

    Attributes:
      enabled: fit a correction (else the identity is used and reported, for every city).
      resolution: working resolution, metres per pixel (rasters are block-averaged to it).
      max_shift: search radius per axis, metres (per window: the local shift).
      max_rotation_deg, rotation_step_deg: rotations searched, degrees (symmetric about 0).
      scales: scales searched (1.0 must be among them to allow "no scale error").
      band: template band around the drivable area, metres.
      road_width: width (m) the OSM centrelines are buffered to for the fit.
      window: side (m) of the square fit windows placed on the clusters of frames.
      max_windows: most windows per city (those with the most frames; the rest are reported
        as unchecked).
      min_score: refuse a window, or the city, whose peak score (fraction of the template's
        positive weight) is below this (no OSM road matches the drivable area there).
      min_sharpness: refuse a city fit whose summed score volume is flatter than this; a
        window below it is "flat" (e.g. one straight road) and is left out of the agreement.
      max_disagreement: metres a sharp window's own shift may differ from the city fit there.
      min_agreement: share of the sharp windows that must agree (else: refused).
      manual: city -> ``{shift: [dx, dy], rotation_deg: r, scale: s, centre: [x, y]}`` (metres
        in the dataset frame, degrees; each optional: 0 shift, 0 deg, scale 1, centre = the
        frame's origin): used instead of a fit for that city (``{}``: the identity there).
    """

    enabled: bool = True
    resolution: float = 2.0
    max_shift: float = 48.0
    max_rotation_deg: float = 2.0
    rotation_step_deg: float = 0.25
    scales: tuple[float, ...] = (0.99, 0.995, 1.0, 1.005, 1.01)
    band: float = 20.0
    road_width: float = 10.0
    window: float = 512.0
    max_windows: int = 128
    min_score: float = 0.1
    min_sharpness: float = 0.05
    max_disagreement: float = 10.0
    min_agreement: float = 0.8
    manual: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if min(self.resolution, self.max_shift, self.road_width) <= 0 or self.band < 0:
            raise ValueError(
                f"{_PREFIX}.resolution, max_shift and road_width must be > 0, band >= 0"
            )
        if self.rotation_step_deg <= 0 or self.max_rotation_deg < 0:
            raise ValueError(f"{_PREFIX}.rotation_step_deg must be > 0, max_rotation_deg >= 0")
        if not self.scales or min(self.scales) <= 0:
            raise ValueError(f"{_PREFIX}.scales must be positive, got {self.scales}")
        if self.window < 8 * self.resolution:
            raise ValueError(
                f"{_PREFIX}.window must be >= 8 x resolution ({8 * self.resolution} m), "
                f"got {self.window}"
            )
        if isinstance(self.max_windows, bool) or not isinstance(self.max_windows, int):
            raise ValueError(f"{_PREFIX}.max_windows must be an integer, got {self.max_windows!r}")
        if self.max_windows < 1:
            raise ValueError(f"{_PREFIX}.max_windows must be >= 1, got {self.max_windows}")
        if not (0 <= self.min_score < 1 and 0 <= self.min_sharpness < 1):
            raise ValueError(f"{_PREFIX}.min_score and min_sharpness must be in [0, 1)")
        if self.max_disagreement <= 0 or not 0 <= self.min_agreement <= 1:
            raise ValueError(
                f"{_PREFIX}.max_disagreement must be > 0 and min_agreement in [0, 1], got "
                f"{self.max_disagreement}, {self.min_agreement}"
            )
        object.__setattr__(self, "manual", _check_manual(self.manual))

    def identity(self) -> dict:
        """The keys that define the fitted values (JSON-able), stored in the manifest."""
        d = {k: getattr(self, k) for k in FIT_KEYS}
        d["scales"] = [float(s) for s in self.scales]
        return d

    def checks(self) -> dict:
        """The acceptance thresholds (JSON-able)."""
        return {k: getattr(self, k) for k in CHECK_KEYS}


@dataclasses.dataclass(frozen=True)
class Similarity:
    """``p' = centre + scale * R(rotation) (p - centre) + shift`` in world metres / radians."""

    shift: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    scale: float = 1.0
    centre: tuple[float, float] = (0.0, 0.0)
    score: float = float("nan")  # normalized peak (fraction of the template's weight), report

    def matrix(self) -> np.ndarray:
        """``(3, 3)`` homogeneous world transform."""
        c, s = math.cos(self.rotation) * self.scale, math.sin(self.rotation) * self.scale
        a = np.array([[c, -s], [s, c]])
        centre = np.asarray(self.centre, np.float64)
        out = np.eye(3)
        out[:2, :2] = a
        out[:2, 2] = centre - a @ centre + np.asarray(self.shift, np.float64)
        return out

    def apply(self, xy) -> np.ndarray:
        """Transforms world points ``(..., 2)``."""
        m = self.matrix()
        xy = np.asarray(xy, np.float64)
        return xy @ m[:2, :2].T + m[:2, 2]

    def shapely_params(self) -> list[float]:
        """``[a, b, d, e, xoff, yoff]`` for ``shapely.affinity.affine_transform``."""
        m = self.matrix()
        return [m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[0, 2], m[1, 2]]

    def as_dict(self) -> dict:
        """JSON-able report: shift (m), rotation (deg), scale, centre (m), score."""
        return {
            "shift_m": [float(v) for v in self.shift],
            "rotation_deg": math.degrees(self.rotation),
            "scale": float(self.scale),
            "centre_m": [float(v) for v in self.centre],
            "score": float(self.score),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Similarity:
        return cls(
            shift=tuple(d["shift_m"]),
            rotation=math.radians(d["rotation_deg"]),
            scale=float(d["scale"]),
            centre=tuple(d["centre_m"]),
            score=float(d.get("score", float("nan"))),
        )

    @classmethod
    def from_manual(cls, entry: dict) -> Similarity:
        """From a validated ``AlignConfig.manual`` entry."""
        return cls(
            shift=tuple(entry["shift"]),
            rotation=math.radians(entry["rotation_deg"]),
            scale=float(entry["scale"]),
            centre=tuple(entry["centre"]),
        )


@dataclasses.dataclass(frozen=True)
class Window:
    """One fit window at the working resolution.

    Attributes:
      target: ``(S, S)`` drivable-area fraction on ``template_grid`` (S even).
      template_grid: the window; its centre is the centre of the candidate rotations.
      source: OSM road fraction on ``source_grid``, which covers the window grown by
        ``max_shift`` plus the rotation margin (:func:`window_grids`).
      source_grid: placement of ``source``.
      frames: frames (points) the window was placed on (report).
    """

    target: np.ndarray
    template_grid: geometry.RasterGrid
    source: np.ndarray
    source_grid: geometry.RasterGrid
    frames: int = 0

    @property
    def centre(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.template_grid.bounds
        return ((x0 + x1) / 2, (y0 + y1) / 2)


@dataclasses.dataclass(frozen=True)
class Alignment:
    """A city's correction with its quality (:meth:`report` goes into the manifest).

    Attributes:
      city: the dataset's city / map name.
      similarity: the correction (OSM -> dataset frame).
      method: "fit", "manual", "disabled" (``enabled: false``) or "no_osm" (no extract).
      quality: city figures (score, sharpness, windows, agreement, ...).
      windows: per-window figures (centre, frames, score, sharpness, shift, residual, status).
      problems: why the fit is refused (empty: accepted).
      remedies: what to change, for the error message.
    """

    city: str
    similarity: Similarity
    method: str
    quality: dict = dataclasses.field(default_factory=dict)
    windows: tuple = ()
    problems: tuple = ()
    remedies: tuple = ()

    @classmethod
    def identity(cls, city: str, method: str, centre=(0.0, 0.0)) -> Alignment:
        return cls(city, Similarity(centre=(float(centre[0]), float(centre[1]))), method)

    @classmethod
    def manual(cls, city: str, entry: dict) -> Alignment:
        return cls(city, Similarity.from_manual(entry), "manual")

    def report(self) -> dict:
        """JSON-able manifest entry: :meth:`Similarity.as_dict` plus method, quality, windows."""
        return dict(
            self.similarity.as_dict(),
            method=self.method,
            quality=dict(self.quality),
            windows=[dict(w) for w in self.windows],
        )

    def error(self) -> AlignmentError:
        q, sim = self.quality, self.similarity
        fit = (
            f"shift ({sim.shift[0]:+.2f}, {sim.shift[1]:+.2f}) m, rotation "
            f"{math.degrees(sim.rotation):+.3f} deg, scale {sim.scale:.4f} about centre "
            f"({sim.centre[0]:.1f}, {sim.centre[1]:.1f}) m, score "
            f"{q.get('score', float('nan')):.3f}, sharpness "
            f"{q.get('sharpness', float('nan')):.3f} over {q.get('windows', 0)} window(s)"
        )
        return AlignmentError(
            f"OSM alignment of {self.city!r} refused: {'; '.join(self.problems)}. The fit (not "
            f"applied): {fit}. Remedies: {'; '.join(self.remedies)}"
        )

    def check(self) -> Alignment:
        """``self``, or raises :meth:`error` when the fit has problems."""
        if self.problems:
            raise self.error()
        return self


def _fmt_xy(xy) -> str:
    return f"({xy[0]:.0f}, {xy[1]:.0f}) m"


# --------------------------------------------------------------------------- report


def report_lines(city: str, a: dict, max_windows: int = 8) -> list[str]:
    """Conversion-log lines of a manifest alignment entry (:meth:`Alignment.report`)."""

    def num(v, fmt):  # -0.00 prints as +0.00
        return format(round(float(v), 6) + 0.0, fmt)

    sx, sy = (round(float(v), 2) + 0.0 for v in a["shift_m"])
    line = (
        f"  OSM correction {city}: shift ({sx:+.2f}, {sy:+.2f}) m, rotation "
        f"{num(a['rotation_deg'], '+.3f')} deg, scale {a['scale']:.4f}, score {a['score']:.3f}"
    )
    method = a.get("method")
    q = a.get("quality") or {}
    if method == "fit" and q:
        cx, cy = a["centre_m"]
        agree = q.get("agreement", float("nan"))
        line += (
            f" [fit about ({cx:.1f}, {cy:.1f}) m; sharpness {q['sharpness']:.3f}; "
            f"{q['windows']} window(s), {q['sharp_windows']} sharp"
            + (
                f", agreement {100 * agree:.0f}% (max residual {q['max_residual_m']:.2f} m)"
                if agree == agree
                else ""
            )
            + (f"; {q['unchecked_frames']} frames unchecked" if q.get("unchecked_frames") else "")
            + "]"
        )
    elif method:
        line += f" [{method}]"
    lines = [line]
    windows = a.get("windows") or []
    order = sorted(windows, key=lambda r: (r.get("status") == "ok", r.get("score", 0.0)))
    for r in order[:max_windows]:
        if "score" not in r:
            lines.append(
                f"    window {_fmt_xy(r['centre_m'])}, {r['frames']} frames: {r['status']}"
            )
            continue
        lines.append(
            f"    window {_fmt_xy(r['centre_m'])}, {r['frames']} frames: score {r['score']:.3f} "
            f"(at fit {r['score_at_fit']:.3f}), sharpness {r['sharpness']:.3f}, shift "
            f"({r['shift_m'][0]:+.2f}, {r['shift_m'][1]:+.2f}) m, residual "
            f"{r['residual_m']:.2f} m: {r['status']}"
        )
    if len(order) > max_windows:
        rest = order[max_windows:]
        statuses = sorted({r.get("status") for r in rest})
        lines.append(f"    ... {len(rest)} more window(s): {', '.join(statuses)}")
    return lines
