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

import dataclasses
import math

import numpy as np
from scipy import ndimage
from tqdm.auto import tqdm

from seglocnet_jax import geometry
from seglocnet_jax.data.real import align_checks as checks
from seglocnet_jax.data.real.align_windows import (
    _shift_px,
    _template,
    _warp,
    downsample,
    place_windows,
    window_grids,
)
from seglocnet_jax.data.real.alignment import (
    AlignConfig,
    Alignment,
    AlignmentError,
    Similarity,
    Window,
)

# --------------------------------------------------------------------------- volumes and peaks


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


@dataclasses.dataclass(frozen=True)
class _Search:
    """The windows a fit searches over (those with drivable area) and the candidate grid.

    Attributes:
      windows: the used windows; templates: ``(B, 1, n, n)`` their templates; weights: ``(B,)``
        each template's positive weight.
      offsets: ``(B, 2)`` metres from the city centre (the windows' weighted centre,
        ``centre``) to each window's centre.
      tile_grids: the window grown by the shift search, where the warped OSM is drawn.
      res: working resolution (m/px); k: the shift search's half-width (px).
      angles: ``(A,)`` searched rotations (rad), ``step`` apart; scales: ``(S,)`` searched scales.
    """

    windows: list[Window]
    templates: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    centre: np.ndarray
    tile_grids: list[geometry.RasterGrid]
    res: float
    k: int
    angles: np.ndarray
    step: float
    scales: np.ndarray

    @property
    def nv(self) -> int:
        """Shifts searched per axis."""
        return 2 * self.k + 1

    def volumes(self, scale: float, angle: float) -> np.ndarray:
        """``(B, nv, nv)`` each window's local shift scores with OSM warped by one candidate
        about the window's centre."""
        from seglocnet_jax import solver  # jax is imported only when a fit runs

        tiles = np.stack(
            [
                _warp(
                    w.source,
                    w.source_grid,
                    g,
                    Similarity(rotation=angle, scale=scale, centre=w.centre),
                )
                for w, g in zip(self.windows, self.tile_grids, strict=True)
            ]
        )[:, None]
        out = solver.score_volume_batch(self.templates, tiles, num_rotations=4, batch_chunk=1)
        return np.asarray(out)[:, 0]

    def joint_at(self, vol_b: np.ndarray, theta: float, scale: float, cubic: bool = False):
        """Window volumes ``(B, nv, nv)`` moved into the city fit's frame: a city similarity
        (``theta``, ``scale``) about the centre moves window ``b`` by ``(sR - I) offsets[b]``."""
        off = self.offsets @ (_rot(theta, scale) - np.eye(2)).T  # (B, 2) metres
        return _shifted(vol_b, off[:, 1] / self.res, -off[:, 0] / self.res, cubic)


def _search(windows: list[Window], cfg: AlignConfig, city: str) -> tuple[_Search, list[int]]:
    """The search over ``windows`` and the indices of the used ones; refuses no window or no
    drivable area."""
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
    wt = weights[used]
    centres = np.array([w.centre for w in wins])  # (B, 2)
    centre = (wt[:, None] * centres).sum(0) / wt.sum()
    steps = int(math.floor(cfg.max_rotation_deg / cfg.rotation_step_deg + 1e-9))
    step = math.radians(cfg.rotation_step_deg)
    t = n + 2 * k
    tile_grids = [
        geometry.RasterGrid(
            w.template_grid.x_min - k * res, w.template_grid.y_max + k * res, t, t, res
        )
        for w in wins
    ]
    search = _Search(
        windows=wins,
        templates=np.stack([tmpls[i] for i in used])[:, None],  # (B, 1, n, n)
        weights=wt,
        offsets=centres - centre,
        centre=centre,
        tile_grids=tile_grids,
        res=res,
        k=k,
        angles=np.arange(-steps, steps + 1) * step,
        step=step,
        scales=np.asarray(sorted(cfg.scales), np.float64),
    )
    return search, used


def _all_volumes(search: _Search, city: str, progress: bool) -> np.ndarray:
    """``(B, S, A, nv, nv)`` every window's volume at every searched scale and rotation."""
    ns, na, nv = len(search.scales), len(search.angles), search.nv
    vols = np.zeros((len(search.windows), ns, na, nv, nv), np.float32)
    with tqdm(total=ns * na, desc=f"align OSM {city}", unit="cand", disable=not progress) as bar:
        for i, s in enumerate(search.scales):
            for j, a in enumerate(search.angles):
                vols[:, i, j] = search.volumes(float(s), float(a))
                bar.update()
    return vols


def _own_peak(search: _Search, vol: np.ndarray, weight: float, radius: float) -> dict:
    """One window alone (``vol``: ``(S, A, nv, nv)``): its best candidate's score, sharpness,
    sub-pixel local shift (metres, at the window centre) and whether it lies on the bound."""
    k, res, nv = search.k, search.res, search.nv
    i, j, h, w = np.unravel_index(int(np.argmax(vol)), vol.shape)
    v = vol[i, j]
    dh, dw = _subpixel(v, h, w)
    return {
        "score": float(v[h, w] / weight),
        "sharpness": _sharpness(v, h, w, radius),
        "shift": np.array([-(w + dw - k) * res, (h + dh - k) * res]),
        "on_bound": bool(h in (0, nv - 1) or w in (0, nv - 1)),
    }


# --------------------------------------------------------------------------- the city fit


@dataclasses.dataclass(frozen=True)
class _FineRotations:
    """The city fit's rotation grid: ``sub`` positions per searched rotation step, so that the
    farthest window moves at most half a pixel per position; ``count`` positions ``step``
    apart from the first searched rotation."""

    first: float
    sub: int
    count: int
    step: float

    @classmethod
    def of(cls, search: _Search) -> _FineRotations:
        angles, res = search.angles, search.res
        reach = float(np.linalg.norm(search.offsets, axis=1).max())
        sub = 1 if len(angles) == 1 else max(1, math.ceil(search.step * reach / (res / 2)))
        return cls(angles[0], sub, (len(angles) - 1) * sub + 1, search.step / sub)

    def theta(self, f: float):
        return self.first + f * self.step


def _coarse_fit(search: _Search, vols: np.ndarray, fine: _FineRotations) -> tuple[int, int]:
    """``(scale index, fine rotation)`` whose joint peak is highest, with each window's volume
    interpolated linearly between the searched rotations."""
    best = None
    for i, s in enumerate(search.scales):
        for f in range(fine.count):
            j, frac = divmod(f, fine.sub)
            theta = fine.theta(f)
            contrib = search.joint_at(vols[:, i, j], theta, s)
            if frac:
                alpha = frac / fine.sub
                contrib = (1 - alpha) * contrib + alpha * search.joint_at(
                    vols[:, i, j + 1], theta, s
                )
            peak = float(contrib.sum(0).max())
            if best is None or peak > best[0]:
                best = (peak, i, f)
    return best[1], best[2]


class _ExactJoint:
    """The joint volume at fine rotation positions from exact (not interpolated) window
    volumes at one scale, each computed once: ``at(f) -> (peak, h, w, joint, contrib)``."""

    def __init__(self, search: _Search, fine: _FineRotations, scale: float):
        self.search, self.fine, self.scale = search, fine, scale
        self.cache: dict[float, tuple] = {}

    def __call__(self, f: float) -> tuple:
        if f not in self.cache:
            theta = float(self.fine.theta(f))
            vols = self.search.volumes(self.scale, theta)
            contrib = self.search.joint_at(vols, theta, self.scale, cubic=True)
            joint = contrib.sum(0)
            h, w = np.unravel_index(int(np.argmax(joint)), joint.shape)
            self.cache[f] = (float(joint[h, w]), h, w, joint, contrib)
        return self.cache[f]


def _refine_rotation(at: _ExactJoint, f: int) -> tuple[int, float]:
    """Hill climb from fine position ``f`` to a local maximum of the exact peaks, then a
    parabola through it and its neighbours: ``(f, sub-position offset)``."""
    count = at.fine.count
    for _ in range(2 * at.fine.sub + 2):
        up = at(f + 1)[0] if f < count - 1 else -np.inf
        down = at(f - 1)[0] if f > 0 else -np.inf
        if max(up, down) <= at(f)[0]:
            break
        f = f + 1 if up > down else f - 1
    df = _parabola(at(f - 1)[0], at(f)[0], at(f + 1)[0]) if 0 < f < count - 1 else 0.0
    return f, df


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
    search, used = _search(windows, cfg, city)
    res, k, nv = search.res, search.k, search.nv
    vols = _all_volumes(search, city, progress)
    radius = max(cfg.road_width / 2, 2 * res) / res
    radius = min(radius, k * 0.9) if k > 0 else radius
    own = [_own_peak(search, vols[b], search.weights[b], radius) for b in range(len(used))]

    # Scale and rotation on interpolated volumes, then the rotation refined on exact ones.
    fine = _FineRotations.of(search)
    i, f = _coarse_fit(search, vols, fine)
    s_fit = float(search.scales[i])
    at = _ExactJoint(search, fine, s_fit)
    f, df = _refine_rotation(at, f)
    theta = float(fine.theta(f + df))
    _, h, w, joint, contrib = at(f + df)  # exact at the refined rotation
    dh, dw = _subpixel(joint, h, w)
    shift = np.array([-(w + dw - k) * res, (h + dh - k) * res])
    sim_score = float(joint[h, w] / search.weights.sum())
    centre = search.centre
    sim = Similarity(
        shift=(float(shift[0]), float(shift[1])),
        rotation=theta,
        scale=s_fit,
        centre=(float(centre[0]), float(centre[1])),
        score=sim_score,
    )
    peak = checks.CityPeak(
        shift=shift,
        rotation=theta,
        scale=s_fit,
        score=sim_score,
        sharpness=_sharpness(joint, h, w, radius),
        shift_on_bound=bool(h in (0, nv - 1) or w in (0, nv - 1)),
        rotation_on_bound=len(search.angles) > 1 and f in (0, fine.count - 1),
        scale_on_bound=len(search.scales) > 1 and i in (0, len(search.scales) - 1),
        scales=tuple(float(s) for s in search.scales),
    )
    local = shift[None] + search.offsets @ (_rot(theta, s_fit) - np.eye(2)).T  # (B, 2) at fit
    reports = [
        checks.window_report(win, own[b], local[b], contrib[b, h, w] / search.weights[b], cfg, res)
        for b, win in enumerate(search.windows)
    ]
    reports += [
        checks.unused_report(windows[b]) for b in sorted(set(range(len(windows))) - set(used))
    ]
    n = windows[0].template_grid.height
    quality = checks.quality(reports, peak, len(windows), unchecked_frames, res, n * res)
    problems, remedies = checks.problems(reports, peak, len(windows), cfg, city)
    out = Alignment(city, sim, "fit", quality, tuple(reports), tuple(problems), tuple(remedies))
    return out.check() if check else out


# --------------------------------------------------------------------------- on rasters


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
