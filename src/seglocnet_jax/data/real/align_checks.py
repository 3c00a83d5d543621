"""The checks of an OSM alignment fit (:mod:`.align_fit`): each window's status against the city
fit, the fit's quality, and the problems that refuse it, each with its remedies.

A window's status: ``empty`` (its own peak score < ``min_score``: no OSM road matches), then,
for a sharp window (peak sharpness >= ``min_sharpness``, or not measurable), ``on_bound`` (its
own peak on the shift search's bound) or ``disagrees`` (its own shift farther than
``max_disagreement`` from the city fit's there); ``outside_search`` (the city fit needs a local
shift beyond ``max_shift`` there), ``flat`` (not sharp), else ``ok``. A window without drivable
area is ``no_drivable``. The sharp windows that are ``ok`` or ``disagrees`` are judged: the
share that is ``ok`` is the fit's agreement.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seglocnet_jax.data.real.alignment import _PREFIX, AlignConfig, Window, _fmt_xy

JUDGED = ("ok", "disagrees")


@dataclasses.dataclass(frozen=True)
class CityPeak:
    """The city fit as the checks see it.

    Attributes:
      shift: ``(2,)`` metres (dataset frame); rotation: radians; scale: the fitted scale.
      score: the joint peak over the templates' positive weight; sharpness: of the joint peak.
      shift_on_bound, rotation_on_bound, scale_on_bound: the peak lies on that search bound.
      scales: the searched scales (report).
    """

    shift: np.ndarray
    rotation: float
    scale: float
    score: float
    sharpness: float
    shift_on_bound: bool
    rotation_on_bound: bool
    scale_on_bound: bool
    scales: tuple[float, ...]


def _status(own: dict, local: np.ndarray, residual: float, cfg: AlignConfig, res: float) -> str:
    outside = bool(np.abs(local).max() > cfg.max_shift + res / 2)
    sharp = not own["sharpness"] < cfg.min_sharpness  # NaN (not measurable) counts as sharp
    if own["score"] < cfg.min_score:
        return "empty"
    if sharp and own["on_bound"]:
        return "on_bound"
    if sharp and residual > cfg.max_disagreement:
        return "disagrees"
    if outside:
        return "outside_search"
    if not sharp:
        return "flat"
    return "ok"


def window_report(
    win: Window, own: dict, local: np.ndarray, score_at_fit, cfg: AlignConfig, res: float
) -> dict:
    """One used window's report: its own peak (``own``: score, sharpness, shift, on_bound), the
    city fit's local shift there (``local``, metres) and score, and its status."""
    residual = float(np.linalg.norm(local - own["shift"]))
    return {
        "centre_m": [float(v) for v in win.centre],
        "frames": int(win.frames),
        "score": own["score"],
        "score_at_fit": float(score_at_fit),
        "sharpness": own["sharpness"],
        "shift_m": [float(v) for v in own["shift"]],
        "fit_shift_m": [float(v) for v in local],
        "residual_m": residual,
        "on_bound": own["on_bound"],
        "status": _status(own, local, residual, cfg, res),
    }


def unused_report(win: Window) -> dict:
    """The report of a window without drivable area (not part of the fit)."""
    return {"centre_m": [float(v) for v in win.centre], "frames": int(win.frames)} | {
        "status": "no_drivable"
    }


def _judged(reports: list[dict]) -> tuple[list[dict], list[dict], float]:
    """The judged windows, those that agree, and the agreement (NaN: none judged)."""
    judged = [r for r in reports if r["status"] in JUDGED]
    agreeing = [r for r in judged if r["status"] == "ok"]
    return judged, agreeing, len(agreeing) / len(judged) if judged else float("nan")


def quality(
    reports: list[dict],
    peak: CityPeak,
    num_windows: int,
    unchecked_frames: int,
    res: float,
    window_m: float,
) -> dict:
    """The fit's quality as stored in the manifest."""
    judged, _, agreement = _judged(reports)
    return {
        "score": peak.score,
        "sharpness": peak.sharpness,
        "windows": num_windows,
        "sharp_windows": len(judged),
        "agreement": agreement,
        "max_residual_m": max((r["residual_m"] for r in judged), default=float("nan")),
        "unchecked_frames": int(unchecked_frames),
        "resolution": res,
        "window_m": window_m,
    }


def _where(rs: list[dict], extra) -> str:
    """The first three windows of ``rs`` with ``extra(report)``, and how many more."""
    shown = ", ".join(f"{_fmt_xy(r['centre_m'])} ({r['frames']} frames{extra(r)})" for r in rs[:3])
    return shown + (f" and {len(rs) - 3} more" if len(rs) > 3 else "")


def _bound_problem(by: dict, peak: CityPeak, cfg: AlignConfig) -> str | None:
    """The shift search's bound: the city peak, windows' own peaks, or local shifts beyond it."""
    if not (peak.shift_on_bound or by["on_bound"] or by["outside_search"]):
        return None
    what = []
    if peak.shift_on_bound:
        what.append(f"city shift ({peak.shift[0]:+.1f}, {peak.shift[1]:+.1f}) m")
    if by["on_bound"]:
        what.append(
            "window(s) "
            + _where(
                by["on_bound"],
                lambda r: f", shift ({r['shift_m'][0]:+.1f}, {r['shift_m'][1]:+.1f}) m",
            )
        )
    if by["outside_search"]:
        what.append(
            "window(s) where the city fit needs a shift beyond the search "
            + _where(
                by["outside_search"],
                lambda r: f", ({r['fit_shift_m'][0]:+.1f}, {r['fit_shift_m'][1]:+.1f}) m",
            )
        )
    return f"peak on the search bound (max_shift {cfg.max_shift:g} m): " + "; ".join(what)


def _search_problems(
    reports: list[dict], peak: CityPeak, num_windows: int, cfg: AlignConfig, city: str
) -> tuple[list[str], list[str]]:
    """Windows without a match and peaks on a search bound (shift, rotation, scale)."""
    problems, remedies = [], []
    by = {s: [r for r in reports if r.get("status") == s] for s in ("empty", "on_bound")}
    by["outside_search"] = [r for r in reports if r.get("status") == "outside_search"]
    bigger = f"a larger search: {_PREFIX}.max_shift={2 * cfg.max_shift:g}"
    if by["empty"]:
        problems.append(
            f"no OSM road matches the drivable area (score < min_score {cfg.min_score:g}) in "
            f"{len(by['empty'])} of {num_windows} window(s): "
            + _where(by["empty"], lambda r: f", score {r['score']:.3f}")
            + " (the OSM extract does not cover these frames, or it is off by more than "
            "max_shift there)"
        )
        remedies.append(f"an OSM extract that covers these frames (dataset.convert.osm.{city})")
        remedies.append(bigger)
    bound = _bound_problem(by, peak, cfg)
    if bound is not None:
        problems.append(bound)
        if bigger not in remedies:
            remedies.append(bigger)
    if peak.rotation_on_bound:
        problems.append(
            f"rotation {math.degrees(peak.rotation):+.3f} deg on the search bound "
            f"(max_rotation_deg {cfg.max_rotation_deg:g})"
        )
        remedies.append(f"a larger search: {_PREFIX}.max_rotation_deg={2 * cfg.max_rotation_deg:g}")
    if peak.scale_on_bound:
        problems.append(f"scale {peak.scale:.4f} on the search bound (scales {list(peak.scales)})")
        remedies.append(f"a wider {_PREFIX}.scales")
    return problems, remedies


def problems(
    reports: list[dict], peak: CityPeak, num_windows: int, cfg: AlignConfig, city: str
) -> tuple[list[str], list[str]]:
    """Why the fit is refused (none: accepted) and what would help, in the order shown."""
    problems, remedies = _search_problems(reports, peak, num_windows, cfg, city)
    min_s, min_sh = cfg.min_score, cfg.min_sharpness
    if peak.score < min_s:
        problems.append(f"near-zero score {peak.score:.3f} < min_score {min_s:g}")
    if peak.sharpness < min_sh:
        problems.append(
            f"flat score: sharpness {peak.sharpness:.3f} < min_sharpness {min_sh:g} "
            "(no distinct peak)"
        )
    judged, agreeing, agreement = _judged(reports)
    if judged and agreement < cfg.min_agreement:
        off = [r for r in judged if r["status"] == "disagrees"]
        problems.append(
            f"windows disagree: {len(agreeing)} of {len(judged)} sharp window(s) lie within "
            f"max_disagreement {cfg.max_disagreement:g} m of the city fit (min_agreement "
            f"{cfg.min_agreement:g}); off: "
            + _where(off, lambda r: f", {r['residual_m']:.1f} m")
            + " (one correction cannot serve these areas)"
        )
        remedies.append(
            f"if the OSM is known to be this inaccurate, a looser {_PREFIX}.max_disagreement "
            "or min_agreement"
        )
    if problems:
        remedies.append(
            f"a manual correction: '+{_PREFIX}.manual.{city}={{shift: [dx, dy], rotation_deg: r, "
            "scale: s, centre: [x, y]}' (metres in the dataset frame, degrees; {} for none in "
            "this city)"
        )
        remedies.append(f"no correction at all: {_PREFIX}.enabled=false")
    return problems, remedies
