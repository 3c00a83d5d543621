"""Sequential localization: a Bayes filter over the solver's pose grid.

The belief is a probability volume ``prob (K, N, N)`` over the cells of a world-aligned window
(``N = 129`` by default, ``0.5 m`` cells, ``K`` rotations): exactly the cells of the solver's
score volume for a map tile centred on the window centre, so a frame's score volume is the
likelihood of the belief's own cells. ``geometry`` owns what a cell means: cell ``(k, h, w)``
is the pose ``window centre + geometry.cell_to_tile_offset(h, w)`` with
``yaw = geometry.yaw_from_rotation(k)``.

Cells sit on a *lattice* of pixel corners: lattice corner ``(row, col)`` is the world point
``(origin_x + col * res, origin_y - row * res)``. With ``origin = (grid.x_min, grid.y_max)``
of a :class:`geometry.RasterGrid` the lattice is that raster's pixel corners, the window centre
is the centre of the tile ``geometry.crop(raster, *tile_corner(belief, cfg), tile_size)`` and
``geometry.tile_window`` of :func:`window_centre` returns the same tile.

One frame of a drive::

    belief, info = predict(belief, odometry, cfg, map_cell=est["map_cell"])  # move + widen
    tile = crop(raster, *tile_corner(belief, cfg), tile_size)          # around the estimate
    volume = solver.score_volume(bev, tile, K)                          # (K, N, N)
    belief, info = update(belief, solver.log_softmax_volume(volume, T), cfg)
    est = info["estimate"]                                              # = estimate(belief)

* predict: each yaw slice is translated by the odometry rotated by that slice's yaw (bilinear
  for the sub-cell part, blurred by a Gaussian whose sigma grows with the distance), then the
  slices move along ``k`` by the yaw change (with wrap, blurred by the yaw noise). The window
  moves by the integer cells that put the predicted MAP cell at its centre (``map_cell``: the
  previous estimate's, else found by a pass over the volume); mass that leaves is dropped
  (reported) and the rest renormalized.
* update: ``posterior ~ prior * exp(log_likelihood)``, with the maximum subtracted before the
  exponential (log-sum-exp); ``floor`` mixes a uniform into the prior so that no cell is ever
  impossible.
* track loss: a CUSUM of the per-frame log Bayes factor "the prior predicted this frame" vs "a
  uniform prior did" (``log sum prior * L - log mean L``), plus belief-shape tests (peak mass,
  entropy) once the filter has locked on. A loss re-widens the prior (uniform over the window)
  and reapplies the frame's likelihood; losses are counted.
* tracking window (``track_size``, 65 cells): a drive down to one window that has locked on
  (its ``track_size`` box around the mode held nearly all the belief for a few frames) is cut
  to that box by :func:`narrow`. It runs the full window's filter on a quarter
  of the cells: its likelihood is the centre of the volume of the full tile around the window
  centre (:func:`crop_likelihood`), the floor is spread over the full window's cells, the loss
  test compares against a uniform belief over the full window (``update(..., log_mean=)``)
  and the entropy is normalized by its count; a detected loss resets the full window with the
  frame's whole volume (:func:`reset`): :func:`update_tracking_window`. Only mass more than
  ``track_size // 2`` cells from the mode is dropped.
* several hypotheses (``hypotheses`` > 1, :mod:`~seglocnet_jax.tracking.hypotheses`): frame
  0's posterior is split among windows that cover it greedily (the first is the single
  window's), each tracked as a filter of its own; the
  windows are weighted by their evidence (a mixture, exact up to the cells that leave a window)
  and pruned / merged; the estimate is the heaviest window's mode.
* on-road prior (``off_road`` nats, 0: off): :func:`road_log_prior` of the window's map tile
  is added to every frame's log-likelihood, ``-off_road`` at each cell whose ego point is off
  the map's road channel: a vehicle drives on the road, so a window whose mass sits off it
  loses that much evidence per frame against one on it.
* odometry (:mod:`~seglocnet_jax.tracking.odometry`): the motion between frames as wheel
  odometry + a MEMS gyro measure it (:func:`simulate`), dead reckoning (:func:`compose`) and
  the filter's motion noise that covers it (:func:`tracker_noise`).

Speed (the filter runs per frame on a ``(256, 129, 129)`` volume, 17 MB: every pass over it
counts, and on CPU the passes are memory-bound). The kernels are jitted once per config and
kernel width (static shapes) and composed in Python: predict is three programs (plan + row
pass, column pass, rotation pass), update one. Inside a single XLA program the CPU backend
fuses the per-slice gathers into their producers and runs ~10x slower; where two stages share
a program an optimization barrier keeps them apart. No pads (a slow pass on XLA CPU): the row
pass writes the zero margins the column pass shifts into. Gaussian taps below 1e-7 of the
central weight are dropped (usual noise is below a cell or a bin: 4 taps per axis, not 8).
Sums over the volume go per slice first (a full reduction to a scalar is several times slower
on XLA CPU), and the update's evidence and yaw marginal come from the same per-slice sums.
"""

from seglocnet_jax.tracking import hypotheses
from seglocnet_jax.tracking.belief import (
    Belief,
    TrackerConfig,
    cell_to_world,
    init_belief,
    tile_corner,
    window_centre,
    world_to_cell,
)
from seglocnet_jax.tracking.motion import narrow, predict, recentre
from seglocnet_jax.tracking.odometry import (
    OdometryConfig,
    ScaleEstimate,
    compose,
    relative_motion,
    simulate,
    tracker_noise,
)
from seglocnet_jax.tracking.posterior import (
    crop_likelihood,
    estimate,
    in_credible_region,
    reset,
    road_log_prior,
    update,
    update_tracking_window,
)

__all__ = [
    "TrackerConfig",
    "Belief",
    "init_belief",
    "window_centre",
    "tile_corner",
    "world_to_cell",
    "cell_to_world",
    "predict",
    "recentre",
    "narrow",
    "hypotheses",
    "update",
    "reset",
    "crop_likelihood",
    "road_log_prior",
    "update_tracking_window",
    "estimate",
    "in_credible_region",
    "OdometryConfig",
    "ScaleEstimate",
    "relative_motion",
    "simulate",
    "compose",
    "tracker_noise",
]
