"""Per-city similarity correction of OSM against a dataset's HD drivable area.

OSM projected into a dataset's map frame (nuScenes: topocentric about the map origin) can be off
by metres, a fraction of a degree and a small scale (survey, projection and map-making
differences). The published corrections (BLOS-BEV) are not public, so we fit one per city:

    p_dataset = centre + scale * R(rotation) @ (p_osm - centre) + shift

**Windows on the data.** A city's frames lie in clusters kilometres apart (AV2 logs, nuScenes
scenes); the bounding box of all of them is mostly empty space. So the fit places square
windows (``window`` metres) on the clusters of frames (:func:`place_windows`; without frames, on
the drivable area), and in each window correlates the drivable-area raster (the template) with
the OSM road raster, warped by each candidate rotation and scale about the window's centre, with
the project's solver (:func:`solver.score_volume`: one exhaustive shift search per candidate).
The template is ``2 * drivable - 1`` (like the solver's GT logits) restricted to a band around
the drivable area, so OSM roads outside the dataset's mapped region cost nothing.

**One correction per city from all windows together.** A city similarity about the windows'
weighted centre moves window ``w`` (centre ``c_w``) by the local shift
``shift + (scale R - I)(c_w - centre)``; the city fit maximizes the sum over windows of their
score volumes at those local shifts, over a rotation grid fine enough that the farthest window
moves by at most half a pixel per step (window volumes are interpolated between the searched
rotations) to pick scale and rotation; the rotation is then refined on exact volumes (hill climb
and a parabola fit), the shift to sub-pixel by a parabola fit. A window whose own peak is
ambiguous (a straight road) still constrains the city fit across its road.

**Quality, and refusal.** Per window: its own peak score (fraction of its template's positive
weight), peak sharpness (``1 - best score farther than max(road_width / 2, 2 px) from the peak /
peak``: 0 for a flat or ridge-shaped volume), its own local shift and its distance to the city
fit there (``residual_m``). Per city: the summed peak score and sharpness, and the share of sharp
windows that agree with the fit. A degenerate fit is refused (:class:`AlignmentError`, naming the
city and the remedies) rather than applied: a window with no OSM match (score < ``min_score``),
a peak on the search bound (shift, rotation or scale), a near-zero or flat city score, a fit
that needs a local shift beyond ``max_shift`` at a matching window, or sharp windows that
disagree (fewer than ``min_agreement`` within ``max_disagreement`` metres). ``manual`` gives a
city a correction by hand instead; ``enabled: false`` uses the identity everywhere.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from tqdm.auto import tqdm

from seglocnet_jax import geometry
from seglocnet_jax.data.real.align_windows import (  # noqa: F401 - public for callers and tests
    _shift_px,
    _template,
    _warp,
    downsample,
    fine_factor,
    place_windows,
    window_grids,
)
from seglocnet_jax.data.real.alignment import (  # noqa: F401 - the fit's types, re-used by callers
    _PREFIX,
    CHECK_KEYS,
    FIT_KEYS,
    AlignConfig,
    Alignment,
    AlignmentError,
    Similarity,
    Window,
    _fmt_xy,
    report_lines,
)

# --------------------------------------------------------------------------- the fit


def _parabola(left: float, centre: float, right: float) -> float:
    denom = left - 2 * centre + right
    return float(np.clip(0.5 * (left - right) / denom, -0.5, 0.5)) if denom < 0 else 0.0


def _subpixel(vol: np.ndarray, h: int, w: int) -> tuple[float, float]:
    n = vol.shape[0]
    dh = _parabola(vol[h - 1, w], vol[h, w], vol[h + 1, w]) if 0 < h < n - 1 else 0.0
    dw = _parabola(vol[h, w - 1], vol[h, w], vol[h, w + 1]) if 0 < w < n - 1 else 0.0
    return dh, dw


def _sharpness(vol: np.ndarray, h: int, w: int, radius_px: float) -> float:
    """``1 - (best score farther than radius_px from the peak) / peak`` in [0, 1]; 0 when the
    peak is not positive, NaN when nothing lies that far inside the search range."""
    peak = float(vol[h, w])
    if not peak > 0:
        return 0.0
    hh, ww = np.ogrid[: vol.shape[0], : vol.shape[1]]
    far = (hh - h) ** 2 + (ww - w) ** 2 > radius_px**2
    if not far.any():
        return float("nan")
    return float(np.clip(1.0 - vol[far].max() / peak, 0.0, 1.0))


def _shifted(vols: np.ndarray, dh: np.ndarray, dw: np.ndarray, cubic: bool = False) -> np.ndarray:
    """``out[b, h, w] = vols[b]`` sampled at ``(h + dh[b], w + dw[b])``, 0 outside: bilinear
    (vectorized), or a cubic spline (keeps a peak's height between pixels far better)."""
    b, n, _ = vols.shape
    if cubic:
        out = np.zeros(vols.shape, np.float32)
        for i in range(b):
            if abs(dh[i]) < n and abs(dw[i]) < n:  # else wholly outside the searched shifts
                out[i] = ndimage.shift(
                    vols[i], (-dh[i], -dw[i]), order=3, mode="grid-constant", cval=0.0
                )
        return out
    fh, fw = np.floor(dh), np.floor(dw)
    ah, aw = (dh - fh)[:, None, None], (dw - fw)[:, None, None]
    fh, fw = fh.astype(np.int64), fw.astype(np.int64)
    idx = np.arange(n)
    batch = np.arange(b)[:, None, None]
    out = np.zeros(vols.shape, np.float32)
    for oh, wh in ((0, 1 - ah), (1, ah)):
        rows = idx[None, :] + (fh + oh)[:, None]  # (B, n)
        rows_ok = (rows >= 0) & (rows < n)
        for ow, ww in ((0, 1 - aw), (1, aw)):
            cols = idx[None, :] + (fw + ow)[:, None]
            ok = rows_ok[:, :, None] & ((cols >= 0) & (cols < n))[:, None, :]
            r_idx, c_idx = np.clip(rows, 0, n - 1), np.clip(cols, 0, n - 1)
            g = vols[batch, r_idx[:, :, None], c_idx[:, None, :]]
            out += wh * ww * np.where(ok, g, 0.0)
    return out


def _rot(theta: float, scale: float) -> np.ndarray:
    c, s = math.cos(theta) * scale, math.sin(theta) * scale
    return np.array([[c, -s], [s, c]])


def fit_windows(
    windows: list[Window],
    cfg: AlignConfig = AlignConfig(),
    city: str = "map",
    progress: bool = True,
    check: bool = True,
    unchecked_frames: int = 0,
) -> Alignment:
    """One city correction from all ``windows`` together, with its quality.

    Args:
      windows: at one working resolution and window size (:func:`window_grids`).
      cfg: search ranges and acceptance thresholds.
      city: named in reports and errors.
      check: raise :class:`AlignmentError` when the fit is refused (else the problems are in
        the returned :class:`Alignment`).
      unchecked_frames: frames of windows beyond ``max_windows`` (report).
    """
    from seglocnet_jax import solver  # jax is imported only when a fit runs

    if not windows:
        raise AlignmentError(f"OSM alignment of {city!r}: no frames to place a fit window on")
    res = windows[0].template_grid.resolution
    n = windows[0].template_grid.height
    k = _shift_px(cfg, res)
    for win in windows:
        if win.target.shape != (n, n) or win.template_grid.height != n:
            raise ValueError(f"fit windows must all be ({n}, {n}), got {win.target.shape}")
    tmpls = [_template(win.target, cfg, res) for win in windows]
    weights = np.array([float(np.clip(t, 0, None).sum()) for t in tmpls])
    used = [i for i in range(len(windows)) if weights[i] > 0]
    if not used:
        raise AlignmentError(
            f"OSM alignment of {city!r}: the drivable area is empty in every fit window "
            f"({sum(w.frames for w in windows)} frames): nothing to align"
        )
    wins = [windows[i] for i in used]
    tm = np.stack([tmpls[i] for i in used])[:, None]  # (B, 1, n, n)
    wt = weights[used]
    centres = np.array([w.centre for w in wins])  # (B, 2)
    centre = (wt[:, None] * centres).sum(0) / wt.sum()
    steps = int(math.floor(cfg.max_rotation_deg / cfg.rotation_step_deg + 1e-9))
    step = math.radians(cfg.rotation_step_deg)
    angles = np.arange(-steps, steps + 1) * step
    scales = np.asarray(sorted(cfg.scales), np.float64)
    nv = 2 * k + 1
    vols = np.zeros((len(wins), len(scales), len(angles), nv, nv), np.float32)
    t = n + 2 * k
    tile_grids = [
        geometry.RasterGrid(
            w.template_grid.x_min - k * res, w.template_grid.y_max + k * res, t, t, res
        )
        for w in wins
    ]

    def volumes(scale: float, angle: float) -> np.ndarray:  # (B, nv, nv) local shift scores
        tiles = np.stack(
            [
                _warp(
                    w.source,
                    w.source_grid,
                    g,
                    Similarity(rotation=angle, scale=scale, centre=w.centre),
                )
                for w, g in zip(wins, tile_grids, strict=True)
            ]
        )[:, None]
        out = solver.score_volume_batch(tm, tiles, num_rotations=4, batch_chunk=1)
        return np.asarray(out)[:, 0]

    total = len(scales) * len(angles)
    with tqdm(total=total, desc=f"align OSM {city}", unit="cand", disable=not progress) as bar:
        for i, s in enumerate(scales):
            for j, a in enumerate(angles):
                vols[:, i, j] = volumes(float(s), float(a))
                bar.update()

    # Each window alone: its best candidate and sub-pixel local shift (at the window centre).
    radius = max(cfg.road_width / 2, 2 * res) / res
    radius = min(radius, k * 0.9) if k > 0 else radius
    own = []
    for b in range(len(wins)):
        i, j, h, w = np.unravel_index(int(np.argmax(vols[b])), vols[b].shape)
        v = vols[b, i, j]
        dh, dw = _subpixel(v, h, w)
        own.append(
            {
                "score": float(v[h, w] / wt[b]),
                "sharpness": _sharpness(v, h, w, radius),
                "shift": np.array([-(w + dw - k) * res, (h + dh - k) * res]),
                "on_bound": bool(h in (0, nv - 1) or w in (0, nv - 1)),
            }
        )

    # The city: one similarity about `centre`; window b moves by shift + (sR - I) d_b. A
    # rotation grid fine enough that the farthest window moves <= res / 2 per step, on window
    # volumes interpolated linearly between the searched rotations, picks scale and rotation;
    # then exact volumes at that rotation and its neighbours (hill climb) refine it.
    d = centres - centre  # (B, 2)
    reach = float(np.linalg.norm(d, axis=1).max())
    sub = 1 if len(angles) == 1 else max(1, math.ceil(step * reach / (res / 2)))
    fine = (len(angles) - 1) * sub + 1
    fstep = step / sub

    def joint_at(vol_b: np.ndarray, theta: float, scale: float, cubic: bool = False):
        off = d @ (_rot(theta, scale) - np.eye(2)).T  # (B, 2) metres
        return _shifted(vol_b, off[:, 1] / res, -off[:, 0] / res, cubic)

    best = None
    for i, s in enumerate(scales):
        for f in range(fine):
            j, frac = divmod(f, sub)
            theta = angles[0] + f * fstep
            contrib = joint_at(vols[:, i, j], theta, s)
            if frac:
                alpha = frac / sub
                contrib = (1 - alpha) * contrib + alpha * joint_at(vols[:, i, j + 1], theta, s)
            peak = float(contrib.sum(0).max())
            if best is None or peak > best[0]:
                best = (peak, i, f)
    _, i, f = best
    s_fit = float(scales[i])
    exact = {}

    def at(f_: float):  # exact joint at fine position f_: (peak, h, w, joint, contrib)
        if f_ not in exact:
            theta_ = float(angles[0] + f_ * fstep)
            contrib_ = joint_at(volumes(s_fit, theta_), theta_, s_fit, cubic=True)
            joint_ = contrib_.sum(0)
            h_, w_ = np.unravel_index(int(np.argmax(joint_)), joint_.shape)
            exact[f_] = (float(joint_[h_, w_]), h_, w_, joint_, contrib_)
        return exact[f_]

    for _ in range(2 * sub + 2):  # climb to a local maximum of the exact peaks
        up = at(f + 1)[0] if f < fine - 1 else -np.inf
        down = at(f - 1)[0] if f > 0 else -np.inf
        if max(up, down) <= at(f)[0]:
            break
        f = f + 1 if up > down else f - 1
    df = _parabola(at(f - 1)[0], at(f)[0], at(f + 1)[0]) if 0 < f < fine - 1 else 0.0
    on_rot_bound = len(angles) > 1 and f in (0, fine - 1)
    theta = float(angles[0] + (f + df) * fstep)
    _, h, w, joint, contrib = at(f + df)  # exact at the refined rotation
    dh, dw = _subpixel(joint, h, w)
    shift = np.array([-(w + dw - k) * res, (h + dh - k) * res])
    sim_score = float(joint[h, w] / wt.sum())
    sim = Similarity(
        shift=(float(shift[0]), float(shift[1])),
        rotation=theta,
        scale=s_fit,
        centre=(float(centre[0]), float(centre[1])),
        score=sim_score,
    )
    sharpness = _sharpness(joint, h, w, radius)
    local = shift[None] + d @ (_rot(theta, s_fit) - np.eye(2)).T  # (B, 2) at the fit

    # Per-window quality and status.
    reports = []
    min_s, min_sh = cfg.min_score, cfg.min_sharpness
    for b, win in enumerate(wins):
        o = own[b]
        outside = bool(np.abs(local[b]).max() > cfg.max_shift + res / 2)
        residual = float(np.linalg.norm(local[b] - o["shift"]))
        sharp = not o["sharpness"] < min_sh  # NaN (not measurable) counts as sharp
        if o["score"] < min_s:
            status = "empty"
        elif sharp and o["on_bound"]:
            status = "on_bound"
        elif sharp and residual > cfg.max_disagreement:
            status = "disagrees"
        elif outside:
            status = "outside_search"
        elif not sharp:
            status = "flat"
        else:
            status = "ok"
        reports.append(
            {
                "centre_m": [float(v) for v in win.centre],
                "frames": int(win.frames),
                "score": o["score"],
                "score_at_fit": float(contrib[b, h, w] / wt[b]),
                "sharpness": o["sharpness"],
                "shift_m": [float(v) for v in o["shift"]],
                "fit_shift_m": [float(v) for v in local[b]],
                "residual_m": residual,
                "on_bound": o["on_bound"],
                "status": status,
            }
        )
    for b in sorted(set(range(len(windows))) - set(used)):
        win = windows[b]
        reports.append(
            {"centre_m": [float(v) for v in win.centre], "frames": int(win.frames)}
            | {"status": "no_drivable"}
        )
    judged = [r for r in reports if r["status"] in ("ok", "disagrees")]
    agreeing = [r for r in judged if r["status"] == "ok"]
    agreement = len(agreeing) / len(judged) if judged else float("nan")
    quality = {
        "score": sim_score,
        "sharpness": sharpness,
        "windows": len(windows),
        "sharp_windows": len(judged),
        "agreement": agreement,
        "max_residual_m": max((r["residual_m"] for r in judged), default=float("nan")),
        "unchecked_frames": int(unchecked_frames),
        "resolution": res,
        "window_m": n * res,
    }

    problems, remedies = [], []
    by = {s: [r for r in reports if r.get("status") == s] for s in ("empty", "on_bound")}
    by["outside_search"] = [r for r in reports if r.get("status") == "outside_search"]

    def where(rs, extra):
        shown = ", ".join(
            f"{_fmt_xy(r['centre_m'])} ({r['frames']} frames{extra(r)})" for r in rs[:3]
        )
        return shown + (f" and {len(rs) - 3} more" if len(rs) > 3 else "")

    bigger = f"a larger search: {_PREFIX}.max_shift={2 * cfg.max_shift:g}"
    if by["empty"]:
        problems.append(
            f"no OSM road matches the drivable area (score < min_score {min_s:g}) in "
            f"{len(by['empty'])} of {len(windows)} window(s): "
            + where(by["empty"], lambda r: f", score {r['score']:.3f}")
            + " (the OSM extract does not cover these frames, or it is off by more than "
            "max_shift there)"
        )
        remedies.append(f"an OSM extract that covers these frames (dataset.convert.osm.{city})")
        remedies.append(bigger)
    on_bound = bool(h in (0, nv - 1) or w in (0, nv - 1))
    if on_bound or by["on_bound"] or by["outside_search"]:
        what = []
        if on_bound:
            what.append(f"city shift ({shift[0]:+.1f}, {shift[1]:+.1f}) m")
        if by["on_bound"]:
            what.append(
                "window(s) "
                + where(
                    by["on_bound"],
                    lambda r: f", shift ({r['shift_m'][0]:+.1f}, {r['shift_m'][1]:+.1f}) m",
                )
            )
        if by["outside_search"]:
            what.append(
                "window(s) where the city fit needs a shift beyond the search "
                + where(
                    by["outside_search"],
                    lambda r: f", ({r['fit_shift_m'][0]:+.1f}, {r['fit_shift_m'][1]:+.1f}) m",
                )
            )
        problems.append(
            f"peak on the search bound (max_shift {cfg.max_shift:g} m): " + "; ".join(what)
        )
        if bigger not in remedies:
            remedies.append(bigger)
    if on_rot_bound:
        problems.append(
            f"rotation {math.degrees(theta):+.3f} deg on the search bound (max_rotation_deg "
            f"{cfg.max_rotation_deg:g})"
        )
        remedies.append(f"a larger search: {_PREFIX}.max_rotation_deg={2 * cfg.max_rotation_deg:g}")
    if len(scales) > 1 and i in (0, len(scales) - 1):
        problems.append(
            f"scale {scales[i]:.4f} on the search bound (scales {[float(s) for s in scales]})"
        )
        remedies.append(f"a wider {_PREFIX}.scales")
    if sim_score < min_s:
        problems.append(f"near-zero score {sim_score:.3f} < min_score {min_s:g}")
    if sharpness < min_sh:
        problems.append(
            f"flat score: sharpness {sharpness:.3f} < min_sharpness {min_sh:g} (no distinct peak)"
        )
    if judged and agreement < cfg.min_agreement:
        off = [r for r in judged if r["status"] == "disagrees"]
        problems.append(
            f"windows disagree: {len(agreeing)} of {len(judged)} sharp window(s) lie within "
            f"max_disagreement {cfg.max_disagreement:g} m of the city fit (min_agreement "
            f"{cfg.min_agreement:g}); off: "
            + where(off, lambda r: f", {r['residual_m']:.1f} m")
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
    out = Alignment(city, sim, "fit", quality, tuple(reports), tuple(problems), tuple(remedies))
    return out.check() if check else out


def align_rasters(
    target: np.ndarray,
    source: np.ndarray,
    grid: geometry.RasterGrid,
    cfg: AlignConfig = AlignConfig(),
    points=None,
    city: str = "map",
    progress: bool = True,
    check: bool = True,
) -> Alignment:
    """:func:`fit_windows` on city rasters: windows on ``points (N, 2)`` (frame positions;
    None: on the drivable pixels).

    Args:
      target: ``(H, W)`` {0, 1} dataset drivable area on ``grid`` (world = dataset frame).
      source: ``(H, W)`` {0, 1} OSM road raster on the same grid, uncorrected.
      grid: placement of both rasters.
    """
    target, source = np.asarray(target), np.asarray(source)
    if target.shape != source.shape or target.shape != (grid.height, grid.width):
        raise ValueError(
            f"target {target.shape} and source {source.shape} must both match the "
            f"grid ({grid.height}, {grid.width})"
        )
    if not np.any(target):
        raise AlignmentError(f"OSM alignment of {city!r}: the drivable-area raster is empty")
    factor = max(1, round(cfg.resolution / grid.resolution))
    tgt, wgrid = downsample(target, grid, factor)
    src, _ = downsample(source, grid, factor)
    if points is None:
        rows, cols = np.nonzero(tgt > 0.5)
        if not len(rows):
            rows, cols = np.nonzero(tgt > 0)
        points = np.stack(wgrid.pixel_to_world(rows + 0.5, cols + 0.5), axis=1)
    placed, unchecked = place_windows(points, cfg)
    origin = (wgrid.x_min, wgrid.y_max)
    windows = []
    for c, frames in placed:
        t_grid, _, s_grid = window_grids(c, cfg, wgrid.resolution, origin)
        crop = Similarity()
        windows.append(
            Window(
                _warp(tgt, wgrid, t_grid, crop),
                t_grid,
                _warp(src, wgrid, s_grid, crop),
                s_grid,
                frames,
            )
        )
    return fit_windows(windows, cfg, city, progress, check, unchecked)


def fit_similarity(
    target: np.ndarray,
    source: np.ndarray,
    grid: geometry.RasterGrid,
    cfg: AlignConfig = AlignConfig(),
    progress: bool = True,
    points=None,
) -> Similarity:
    """The similarity that moves ``source`` (OSM roads) onto ``target`` (drivable area), fitted
    in windows on ``points`` (default: the drivable area) by :func:`align_rasters`; raises
    :class:`AlignmentError` when the fit is degenerate. Its ``score`` is the summed peak
    correlation divided by the templates' positive weight (1.0: every drivable pixel is OSM
    road and no OSM road lies in the band off the drivable area)."""
    return align_rasters(target, source, grid, cfg, points, progress=progress).similarity
