"""The belief: the filter's config, the probability volume over a re-centred window of the
solver's pose cells, its construction and the cell <-> world mapping (see the package docstring)."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry


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
      kernel_radius: most half-width (cells, bins) of the blur kernels: a larger sigma is
        truncated; a smaller one uses fewer taps (out to 5.7 sigmas, see :func:`predict`).
      floor: weight of a uniform mixed into the prior at every update.
      lost_log_odds: nats; a loss when the CUSUM of the prior-vs-uniform log Bayes factor falls
        below ``-lost_log_odds`` (0 disables).
      lock_peak_mass: the filter locks on once the peak mass reaches this.
      lost_peak_mass: when locked, a loss when the peak mass falls below this (0 disables).
      lost_entropy: when locked, a loss when the normalized (x, y) entropy exceeds this
        (1 disables).
      peak_radius: m; the peak mass is the posterior mass within this (box) of the MAP (x, y).
      track_size: cells per axis of the *tracking window* (odd, < ``size``; 0: none): once a
        drive is down to one window whose ``track_size`` box around the mode has held nearly
        all the belief for a few frames (:func:`narrow`; the sequential loop decides when),
        the filter narrows to that box (its likelihood: the centre of the ``size`` window's
        volume, the tile the network was trained on cut around the same point); a detected
        loss widens it back to the ``size`` window. Locked, the belief spans a few metres: the
        ``size`` window's far cells cost every pass over the volume and hold nothing. The
        tracking window runs the ``size`` window's filter on fewer cells: its floor, loss test
        and entropy are the ``size`` window's (``reference_size``, the update's ``log_mean``),
        and a loss there resets the ``size`` window with the frame's whole volume.
      reference_size: cells per axis of the window whose filter this one runs (0: this one;
        the tracking window's is ``size``): the floor is spread over its cells and the
        entropy normalized by its count. Derived, not a setting.
      hypotheses: most windows tracked at once per drive (1: one window). With more, the
        first frame's posterior (over the prior box) is split among windows that cover it
        greedily, each centred on the strongest cell not yet covered (the first one is the
        single window's; :func:`split_modes`), and the windows are weighted by their evidence
        (a mixture: see :mod:`~seglocnet_jax.tracking.hypotheses`).
      scale_prior_m: metres of prior weight on 1 in the filter's running estimate of the
        drive's odometry distance scale (:class:`~seglocnet_jax.tracking.odometry.
        ScaleEstimate`: the filtered track's along-track steps against the odometry's
        distances, one estimate per window of a bank; the prediction then scales the
        odometry by it); 0: the raw odometry.
      hypothesis_prune: nats; a window whose log weight falls this far below the best one's
        is dropped.
      off_road: nats; the *on-road prior*: every frame's log-likelihood is lowered by this at
        each cell whose ego point is off the map's road channel (none of the 4 raster pixels
        around the cell's corner is road; :func:`~seglocnet_jax.tracking.road_log_prior`), so
        a window whose mass sits off the drivable area loses this much evidence per frame
        against one on it. A vehicle drives on the road: the HD map's drivable area holds it,
        an SD map's buffered roads nearly. 0: off (the map's road channel is then not read).
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
    hypotheses: int = 1
    hypothesis_prune: float = 10.0
    scale_prior_m: float = 200.0
    track_size: int = 0
    reference_size: int = 0
    off_road: float = 0.0

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
        if self.lost_log_odds < 0 or self.peak_radius < 0:
            raise ValueError("lost_log_odds and peak_radius must be >= 0")
        if self.track_size and (
            self.track_size < 3 or self.track_size >= self.size or self.track_size % 2 == 0
        ):
            raise ValueError(
                f"track_size must be 0 (no tracking window) or odd, >= 3 and < size "
                f"({self.size}), got {self.track_size}"
            )
        if self.reference_size and self.reference_size < self.size:
            raise ValueError(
                f"reference_size must be 0 or >= size ({self.size}), got {self.reference_size}"
            )
        if self.hypotheses < 1:
            raise ValueError(f"hypotheses must be >= 1, got {self.hypotheses}")
        if self.scale_prior_m < 0:
            raise ValueError(f"scale_prior_m must be >= 0, got {self.scale_prior_m}")
        if not 0.0 <= self.off_road < math.inf:
            raise ValueError(f"off_road must be >= 0 and finite (nats), got {self.off_road}")
        if self.hypothesis_prune <= 0:
            raise ValueError(f"hypothesis_prune must be > 0, got {self.hypothesis_prune}")

    def tracking_window(self) -> TrackerConfig | None:
        """The config of the tracking window (``size = track_size``; None without one)."""
        if not self.track_size:
            return None
        return dataclasses.replace(
            self,
            size=self.track_size,
            track_size=0,
            reference_size=self.reference_size or self.size,
        )

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

    @property
    def reference_cells(self) -> int:
        """Cells of the window whose filter this one runs (:attr:`num_cells` but for a
        tracking window: the full window's)."""
        ref = self.reference_size or self.size
        return self.num_rotations * ref * ref


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
