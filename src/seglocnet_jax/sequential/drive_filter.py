"""One drive through the filter (:class:`DriveFilter`): per frame, predict every window by the
odometry and cut its tile (:meth:`~DriveFilter.tiles`), update the windows by the likelihoods
of those tiles (:meth:`~DriveFilter.update`), read the estimate out
(:meth:`~DriveFilter.read_out`; the GT's read-out for the metrics apart,
:meth:`~DriveFilter.score`) and move to the next frame (:meth:`~DriveFilter.finish`). The
lockstep loop (:mod:`.tracks`) only feeds frames and collects the :class:`Track` s."""

from __future__ import annotations

import collections
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax import geometry, solver, tracking
from seglocnet_jax.sequential.drives import Drive
from seglocnet_jax.tracking import hypotheses
from seglocnet_jax.tracking import odometry as odometry_lib

# The log posterior of the GT cell is clamped here (and is this outside the window): ~12 nats
# below a uniform belief over the 4.3 M cells, so that one frame off the window does not
# dominate a mean over a drive.
LOG_P_FLOOR_P = 1e-12
LOG_P_FLOOR = float(np.log(LOG_P_FLOOR_P))
# A drive down to one window narrows to the tracking window once the box around the mode has
# held this much of the belief for this many frames in a row (one confident frame may be
# confidently wrong).
NARROW_MASS = 0.99
NARROW_FRAMES = 3


def filter_tile(raster, belief: tracking.Belief, cfg: tracking.TrackerConfig):
    """The map tile of the belief's window, ``(C, 256, 256)``, and its centre (world m): the
    raster cut around the filter's estimate (equal to ``raster.tile(*centre)``)."""
    tile = geometry.crop(raster.mask, *tracking.tile_corner(belief, cfg), cfg.tile_size)
    return tile, tracking.window_centre(belief, cfg)


def start_belief(raster, prior_xy, cfg: tracking.TrackerConfig) -> tracking.Belief:
    """Frame 0's belief: uniform over the window around the coarse prior (the prior box) and
    over yaw, on the lattice of the raster's pixel corners."""
    grid = raster.grid
    return tracking.init_belief(cfg, prior_xy, origin=(grid.x_min, grid.y_max))


@functools.partial(jax.jit, static_argnames="cfg")
def _readout(belief: tracking.Belief, map_cell, cfg: tracking.TrackerConfig):
    """The posterior mode ``map_cell`` refined to sub-cell (the solver's parabolas on the log
    posterior), as a world pose."""
    prob = belief.prob  # (K, N, N)
    k, h, w = map_cell[0], map_cell[1], map_cell[2]
    n_k, n = cfg.num_rotations, cfg.size
    # The 3 x 3 x 3 neighbourhood only (k wraps, h / w clipped: no refinement on the border).
    ks = jnp.mod(k + jnp.arange(-1, 2), n_k)
    hs, ws = jnp.clip(h + jnp.arange(-1, 2), 0, n - 1), jnp.clip(w + jnp.arange(-1, 2), 0, n - 1)
    near = prob[ks[:, None, None], hs[None, :, None], ws[None, None, :]]
    # 1e-30, not 1e-38: XLA on CPU flushes float32 denormals to zero (log 0 = -inf, then NaN).
    offset = solver.refine_cell(jnp.log(jnp.maximum(near, 1e-30)), jnp.array([1, 1, 1]))
    offset = offset - 1.0
    on_border = jnp.stack([False, (h == 0) | (h == n - 1), (w == 0) | (w == n - 1)])
    cell = map_cell.astype(jnp.float32) + jnp.where(on_border, 0.0, offset)
    return tracking.cell_to_world(belief, cell, cfg)


@functools.partial(jax.jit, static_argnames="cfg")
def _gt_cell_kernel(belief: tracking.Belief, gt_pose, cfg: tracking.TrackerConfig):
    return jnp.round(tracking.world_to_cell(belief, gt_pose, cfg)).astype(jnp.int32)


def _gt_cell(belief: tracking.Belief, gt_pose, cfg: tracking.TrackerConfig) -> np.ndarray:
    """The GT's rounded window cell ``(k, h, w)`` (outside ``[0, N)`` beyond the window): one
    program (eager, its dozen small ops cost more than the rest of the read-out)."""
    return np.asarray(_gt_cell_kernel(belief, jnp.asarray(gt_pose, jnp.float32), cfg), np.int64)


@dataclasses.dataclass
class Track:
    """Per-frame outputs of one tracked drive (``T`` frames)."""

    drive: Drive
    filtered: np.ndarray  # (T, 3) world
    single: np.ndarray  # (T, 3) world
    mean: np.ndarray  # (T, 3) posterior (x, y) mean and circular mean yaw
    cov_xy: np.ndarray  # (T, 2, 2) m^2
    above: np.ndarray  # (T,) posterior mass more probable than the GT cell (inf: outside)
    log_p_gt: np.ndarray  # (T,) log posterior of the GT cell (clamped: LOG_P_FLOOR)
    lost: np.ndarray  # (T,) bool, the filter detected a track loss at this frame
    narrowed: np.ndarray  # (T,) bool, this frame was tracked in the tracking window
    hypotheses: np.ndarray  # (T,) int, windows tracked after this frame (tracking.hypotheses)
    scale: np.ndarray  # (T,) the odometry distance scale estimated after this frame


class DriveFilter:
    """One drive in flight: its windows (one, or with ``cfg.hypotheses`` > 1 a bank of them,
    heaviest first), their log weights and each window's own odometry-scale estimate, learned
    from that window's mode track (a window that wins late keeps the scale of its own track,
    not the one learned on the window that led before it).

    ``full`` is the filter's config (the 129-cell window); ``cfg`` the windows' (the tracking
    window's once narrowed). The odometry is the vehicle's measurement model, ``(T, 3)``
    (:func:`tracking.odometry.simulate`)."""

    def __init__(self, drive: Drive, raster, odometry, full: tracking.TrackerConfig):
        self.drive, self.raster, self.odometry = drive, raster, np.asarray(odometry)
        self.full = self.cfg = full
        self.t = 0
        self.beliefs = [start_belief(raster, drive.priors[0], full)]
        self.log_w = [0.0]
        self.map_cells = [None]  # (3,) of each window's last posterior
        self.infos = [None]  # each window's last update info
        self.scales = [odometry_lib.ScaleEstimate(full.scale_prior_m)]  # one per window
        self.modes = [None]  # (3,) world, each window's last posterior mode (read out)
        self.held = 0  # consecutive frames the tracking window's box held NARROW_MASS
        self.lost = False  # a loss was detected at this frame (in any window)
        self.out = collections.defaultdict(list)

    @property
    def belief(self) -> tracking.Belief:
        """The heaviest window's belief."""
        return self.beliefs[0]

    def tiles(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Predicts every window by this frame's odometry (from frame 1 on) and returns each
        window's tile and its centre (:func:`filter_tile`: the full window's tile, also for
        the tracking window, whose likelihood is the centre of that tile's volume)."""
        out = []
        for i in range(len(self.beliefs)):
            if self.t:  # the previous estimate's MAP cell saves predict a pass
                self.beliefs[i], moved = tracking.predict(
                    self.beliefs[i],
                    self.scales[i].apply(self.odometry[self.t]),
                    self.cfg,
                    map_cell=self.map_cells[i],
                )
                if len(self.beliefs) > 1:  # the mass that left the window
                    self.log_w[i] = self.log_w[i] + jnp.log(
                        jnp.maximum(1.0 - moved["dropped"], 1e-30)
                    )
            out.append(filter_tile(self.raster, self.beliefs[i], self.full))
        return out

    def update(self, log_liks) -> None:
        """Updates each window by the log-likelihood ``(K, N, N)`` of its tile (in the order
        of :meth:`tiles`), then weighs the windows (:meth:`_weigh`)."""
        for i, log_lik in enumerate(log_liks):
            # The evidence only weighs windows against each other: one window needs none
            # (frame 0's split sets the weights afterwards).
            weigh = len(self.beliefs) > 1
            if self.cfg.size < self.full.size:  # the tracking window: the full one's filter
                self.beliefs[i], info, window = tracking.update_tracking_window(
                    self.beliefs[i], log_lik, self.cfg, self.full
                )
                if window is self.full:  # a loss: reset in the full window
                    self.cfg, self.held = self.full, 0
            else:
                self.beliefs[i], info = tracking.update(
                    self.beliefs[i], log_lik, self.cfg, evidence=weigh
                )
            self.map_cells[i] = info["estimate"]["map_cell"]
            self.infos[i] = info
            if weigh:
                self.log_w[i] = self.log_w[i] + info["log_evidence"]
        self.lost = any(bool(info["lost"]) for info in self.infos)  # in any window
        self._weigh(first=self.t == 0)

    def read_out(self) -> dict:
        """The filter's output of this frame: ``filtered`` (the heaviest window's refined
        mode, world), ``mean`` and ``cov_xy`` (its posterior's), ``modes`` (every window's)."""
        if self.infos[0] is None:  # frame 0's split: the heaviest piece's own estimate
            est = jax.device_get(tracking.estimate(self.belief, self.cfg))
        else:
            est = jax.device_get(self.infos[0]["estimate"])
        modes = [
            np.asarray(_readout(b, jnp.asarray(c), self.cfg), np.float64)
            for b, c in zip(self.beliefs, self.map_cells, strict=True)
        ]
        return {
            "filtered": modes[0],
            "mean": np.asarray(est["mean_pose"], np.float64),
            "cov_xy": np.asarray(est["cov_xy"], np.float64),
            "modes": modes,
        }

    def score(self) -> tuple[float, float]:
        """The GT's read-out the metrics need (not the filter's): the mixture's mass above the
        GT cell and its log posterior there (:func:`tracking.hypotheses.mixture_readout`)."""
        gt = self.drive.poses[self.t]
        above, log_p = hypotheses.mixture_readout(
            self.beliefs,
            self.log_w,
            [_gt_cell(b, gt, self.cfg) for b in self.beliefs],
            self.cfg,
            LOG_P_FLOOR_P,
        )
        return float(above), float(log_p)

    def finish(self, readout: dict, single, above: float, log_p: float) -> Track | None:
        """Records the frame (``single``: the single-frame pose, world), learns the odometry
        scales, picks the next frame's window (:meth:`_next_window`); the :class:`Track` once
        the drive's last frame is done, else None."""
        modes = readout["modes"]
        for scale, previous, mode in zip(self.scales, self.modes, modes, strict=True):
            if previous is not None:  # each window learns from its own mode track
                scale.observe(previous, mode, self.odometry[self.t])
        self.modes = modes
        out = self.out
        out["filtered"].append(readout["filtered"])
        out["scale"].append(self.scales[0].scale)  # the heaviest window's
        out["single"].append(np.asarray(single, np.float64))
        out["mean"].append(readout["mean"])
        out["cov_xy"].append(readout["cov_xy"])
        out["above"].append(above)
        out["log_p_gt"].append(log_p)
        out["lost"].append(self.lost)
        out["narrowed"].append(self.cfg.size < self.full.size)
        out["hypotheses"].append(len(self.beliefs))
        self._next_window()
        self.t += 1
        if self.t < len(self.drive):
            return None
        return Track(self.drive, **{k: np.asarray(v) for k, v in out.items()})

    def _weigh(self, *, first: bool) -> None:
        """After a frame's update: with ``hypotheses`` > 1, frame 0's posterior is split among
        its modes (:func:`tracking.hypotheses.split_modes`); then the windows are pruned and
        merged (:func:`tracking.hypotheses.prune_and_merge`), the heaviest first. Frame 0's
        pieces each start from the scale estimate so far (the prior); a window merged into
        another leaves the survivor's estimate."""
        full = self.full
        if full.hypotheses <= 1 or (not first and len(self.beliefs) == 1):
            return  # one window left: nothing to weigh, prune or merge (its weight is 1)
        if first:
            pieces = hypotheses.split_modes(self.belief, self.cfg)
            self.beliefs = [b for b, _ in pieces]
            self.log_w = [lw for _, lw in pieces]
            self.map_cells = [None] * len(pieces)
            self.infos = [None] * len(pieces)
            self.scales = [dataclasses.replace(self.scales[0]) for _ in pieces]
            self.modes = [self.modes[0]] * len(pieces)
        cells = [
            tracking.estimate(b, self.cfg)["map_cell"] if c is None else c
            for b, c in zip(self.beliefs, self.map_cells, strict=True)
        ]
        poses = [
            tracking.cell_to_world(b, c, self.cfg) for b, c in zip(self.beliefs, cells, strict=True)
        ]
        log_w = np.array([float(v) for v in self.log_w])
        kept, log_w = hypotheses.prune_and_merge(log_w, np.asarray(jax.device_get(poses)), full)
        self.beliefs = [self.beliefs[i] for i in kept]
        self.map_cells = [cells[i] for i in kept]
        self.infos = [self.infos[i] for i in kept]
        self.scales = [self.scales[i] for i in kept]
        self.modes = [self.modes[i] for i in kept]
        self.log_w = list(log_w)

    def _next_window(self) -> None:
        """The window of the next frame: a drive down to one full window narrows to the
        tracking window once its box around the mode has held :data:`NARROW_MASS` for
        :data:`NARROW_FRAMES` frames in a row (:func:`tracking.narrow`); a detected loss
        restarts the count (the update has reset the belief in the full window already)."""
        small = self.full.tracking_window()
        if self.lost:
            self.held = 0
            return
        if not (self.cfg is self.full and small is not None and len(self.beliefs) == 1):
            return
        belief, kept = tracking.narrow(self.belief, self.cfg, small, map_cell=self.map_cells[0])
        self.held = self.held + 1 if float(kept) >= NARROW_MASS else 0
        if self.held >= NARROW_FRAMES:
            # the next predict finds the mode in the new window
            self.beliefs, self.map_cells, self.infos = [belief], [None], [None]
            self.scales, self.modes = self.scales[:1], self.modes[:1]
            self.cfg, self.held = small, 0
