"""Sequential localization: track a car along whole drives from one coarse prior.

Every sequence (a simulated drive, a nuScenes scene, an AV2 log) of a split is tracked by the
Bayes filter over the solver's pose grid (:mod:`seglocnet_jax.tracking`), frame by frame::

    frame 0:  belief = uniform over the 129 x 129 x K cells around the record's stored prior
              (the prior box); with eval.tracker.hypotheses > 1 its posterior is split among
              windows that cover it (tracking.hypotheses), every later step below then runs
              per window and the windows are weighted by their evidence
    frame t:  belief = predict(belief, odometry[t])          # the vehicle's own odometry
              tile   = the map raster cut around the belief's window centre (never the truth;
                       NM: also the OSM class raster's tile there, the neural map's input)
              volume = the one localize step (evaluation.make_localize_step, volume variant)
              belief = update(belief, log_softmax(volume / T))   # loss detection + re-widening
              (eval.tracker.off_road > 0: plus the on-road prior of the tile's road channel)
              (tracking window, eval.tracker.track_size: one window left and locked on, the
              filter narrows to the box of that many cells around the mode, its likelihood
              the centre of the volume; a detected loss widens it back)

What the filter reads: the sensors (through the network or, for ``bev_source="gt"``, the GT
labels), the map, the first frame's stored coarse prior and the odometry. The odometry is the
vehicle's measurement model: :func:`tracking.odometry.simulate` of the GT poses with a seed per
drive (``eval.odometry_seed`` and the sequence id), i.e. wheel / IMU odometry with the noise of
``eval.odometry``. The GT poses are used only to simulate that odometry and to score.

On the same frames the single-frame protocol runs too (each frame localized from its own stored
prior tile, as ``evaluation.evaluate_split`` does), through the same step.

The likelihood temperature ``T`` is fitted unless it is given: first on single frames of a
validation split (:class:`TemperatureFit`: the mean GT-cell log-likelihood accumulated per
batch over a log grid of ``T``, then a parabola through the best three points; no volume is
kept), then, with ``eval.temperature_drives``, on validation drives
(:func:`choose_filter_temperature`: the drives tracked at that ``T`` times each of
``eval.temperature_scales``, all candidates in one pass with one network pass per frame, the
best mean log posterior of the GT cell kept; a tracked split that is those drives, the
calibration split by default, takes the chosen candidate's tracks). The single-frame
fit treats every frame as independent evidence; along a drive the frames overlap, their errors
are correlated, and the filter fed the single-frame ``T`` is overconfident.

Per split (:func:`summarize`), with these definitions:

* ``filtered`` / ``single``: the paper's recalls, APE and AOE of the filtered pose (the
  posterior's mode, refined to sub-cell by the solver's parabola fit on the log posterior) and of
  the single-frame pose, over the same frames.
* ``tracked_pct``: frames whose filtered position error is <= ``TRACKED_M`` (5 m); a frame with
  a larger error is *lost*.
* ``frames_to_converge``: per drive, the index of the first frame from which the filtered error
  stays <= ``CONVERGED_M`` (2 m) to the end of the drive (0: on track from the first frame; a
  drive that never settles is not converged and counted in ``drives_not_converged``);
  ``metres_to_converge``: the distance driven until then.
* ``losses_detected``: track losses the filter detected itself (from the belief: the tracker's
  CUSUM and shape tests); ``losses_recovered``: those followed within ``RECOVERY_FRAMES`` frames
  (the detection frame included) by a frame with error <= ``CONVERGED_M``.
  ``lost_episodes``: maximal runs of lost frames; ``lost_episodes_detected``: those during which
  (or on the frame after which) the filter flagged a loss.
* ``drives_never_lost_pct``: drives without a run of more than ``MAX_LOST_RUN`` (10) consecutive
  lost frames.
* ``coverage``: for each mass ``m`` of ``MASSES``, % of frames whose GT cell lies in the
  posterior's highest-probability region of mass ``m`` over the (yaw, x, y) cells (outside the
  window: not covered); ``ellipse_coverage``: the same for the Gaussian ellipse of the (x, y)
  mean and covariance. ``coverage_90``: the 90 % region.
* ``filter_ms_per_frame`` (prediction, tile cut, update and read-outs: what a vehicle would
  run), ``score_ms_per_frame`` (the GT's read-out for the metrics: its cell's posterior and
  the mass above it; not the filter's), ``compile_ms_per_frame`` (the programs compiled after
  the first steps, e.g. a prediction kernel for a new tap width, :class:`.tracks.CompileClock`;
  not in the others) and
  ``localize_ms_per_frame`` (both localize steps; per frame of a lockstep batch), after the
  first ``WARMUP_STEPS`` lockstep steps (compilation); ``index_s``: reading the split's
  sequence metadata (every record decoded once); ``seconds``: the split, all included.

Modules: :mod:`.config` (the ``eval`` settings and the filter's config built from them),
:mod:`.drives` (the drives of a split), :mod:`.temperature` (the streamed fit),
:mod:`.drive_filter` (one drive through the filter: its windows, predict / tile / update /
read-out), :mod:`.tracks` (the lockstep loop), :mod:`.report` (numbers, arrays, figures);
:func:`evaluate_sequential` ties them for the apps.
"""

from __future__ import annotations

import functools
import os
import time

from seglocnet_jax import viz
from seglocnet_jax.evaluation import LocalizeStep
from seglocnet_jax.sequential.config import EvalConfig, TrackerSettings, tracker_config
from seglocnet_jax.sequential.drive_filter import DriveFilter, Track, filter_tile, start_belief
from seglocnet_jax.sequential.drives import Drive, DriveSplit, drive_seed
from seglocnet_jax.sequential.report import (
    CONVERGED_M,
    MASSES,
    MAX_LOST_RUN,
    RECOVERY_FRAMES,
    TRACKED_M,
    drive_summary,
    scalars,
    summarize,
    write_arrays,
    write_figures,
)
from seglocnet_jax.sequential.temperature import (
    TemperatureFit,
    choose_filter_temperature,
    fit_temperature,
    gt_cells,
)
from seglocnet_jax.sequential.tracks import track_candidates, track_split

__all__ = [
    "TRACKED_M",
    "CONVERGED_M",
    "MAX_LOST_RUN",
    "RECOVERY_FRAMES",
    "MASSES",
    "EvalConfig",
    "TrackerSettings",
    "tracker_config",
    "drive_seed",
    "TemperatureFit",
    "gt_cells",
    "fit_temperature",
    "choose_filter_temperature",
    "Drive",
    "DriveSplit",
    "Track",
    "DriveFilter",
    "filter_tile",
    "start_belief",
    "track_split",
    "track_candidates",
    "drive_summary",
    "summarize",
    "scalars",
    "write_figures",
    "write_arrays",
    "evaluate_sequential",
]


def evaluate_sequential(
    step: LocalizeStep,
    params,
    *,
    dataset_dir: str,
    map_variant: str,
    channels,
    loader_cfg,
    eval_cfg: EvalConfig,
    num_rotations: int,
    place,
    temperature_batches,
    output_dir: str | None,
) -> dict:
    """Tracks the drives of ``eval_cfg.tracked_splits()`` and returns ``{split: summary}``.

    ``temperature_batches``: ``() -> (batches, num_batches)`` of the temperature split (called
    only when ``eval.temperature`` is null). ``output_dir``: per-frame arrays
    (``sequential/<split>.npz``) and, with ``eval.num_figures > 0``, figures
    (``figures/sequential/``: drives, error vs distance, the calibration figure)."""
    cfg = tracker_config(eval_cfg, num_rotations, channels)
    open_split = functools.partial(
        DriveSplit,
        dataset_dir,
        map_variant=map_variant,
        loader_cfg=loader_cfg,
        threads=max(1, loader_cfg.num_threads),
        nm_tiles=step.reads_nm_tile,
    )
    common = {
        "cfg": cfg,
        "odometry_cfg": eval_cfg.odometry,
        "odometry_seed": eval_cfg.odometry_seed,
        "batch_size": eval_cfg.batch_size,
        "place": place,
    }
    run = functools.partial(track_split, step, params, **common)
    candidates = functools.partial(track_candidates, step, params, **common)
    t_fit = time.time()
    temperature, fit, reused = _temperature(
        step, params, eval_cfg, candidates, open_split, place, num_rotations, temperature_batches
    )
    t_fit = time.time() - t_fit
    results = {}
    for name in eval_cfg.tracked_splits():
        t0 = time.time()
        split = open_split(name)
        t_index = time.time() - t0  # every record decoded once for its sequence metadata
        try:
            drives = split.drives[: eval_cfg.max_drives]
            if name in reused:  # tracked at the chosen T by the candidates' pass
                tracks, timing = reused[name]
            else:
                desc = f"sequential {name}"
                tracks, timing = run(split, drives, temperature=temperature, desc=desc)
            summary = summarize(tracks)
            _write(tracks, summary, split, eval_cfg, output_dir, channels, temperature)
        finally:
            split.close()
        frames = timing["frames"]
        per_frame = {
            f"{k}_ms_per_frame": 1e3 * timing[f"{k}_s"] / frames if frames else None
            for k in ("filter", "score", "compile", "localize", "data")
        }
        summary.update(
            temperature=temperature,
            off_road=cfg.off_road,  # the on-road prior the filter ran with (nats per frame)
            temperature_fit=fit,
            temperature_fit_s=round(t_fit, 1),
            tracked_in_temperature_pass=name in reused,
            calibration=name == eval_cfg.calibration_split,
            **per_frame,
            index_s=round(t_index, 1),
            seconds=round(time.time() - t0, 1),
        )
        results[name] = summary
    return results


def _temperature(step, params, eval_cfg, candidates, open_split, place, num_rotations, batches_of):
    """The filter's temperature, the record of its fit (None when given) and
    ``{split: (tracks, timings)}`` of the tracked splits whose tracks at that temperature the
    fit already made: fitted on single frames of ``eval.temperature_split``, then chosen on the
    drives of ``eval.temperature_drives`` (:func:`choose_filter_temperature`; ``candidates``:
    the tracking of a split at several temperatures with the run's filter). When that split is
    also tracked (the calibration split, by default), its candidates' pass localizes the frames
    single-frame too and the chosen candidate's tracks are its tracks: the same filter, frames
    and odometry as a pass of its own, which is not run."""
    if eval_cfg.temperature is not None:
        return float(eval_cfg.temperature), None, {}
    batches, n = batches_of()
    temperature, info = fit_temperature(
        step,
        params,
        batches,
        num_batches=n,
        place=place,
        num_rotations=num_rotations,
        desc=f"temperature fit ({eval_cfg.temperature_split})",
    )
    fit = {"split": eval_cfg.temperature_split, **info, "single_frame": temperature}
    if not eval_cfg.temperature_drives:
        return temperature, fit, {}
    name = eval_cfg.temperature_drives
    tracked = name in eval_cfg.tracked_splits()
    split = open_split(name)
    try:
        drives = split.drives[: eval_cfg.max_drives]
        temperature, table, tracks, timing = choose_filter_temperature(
            candidates,
            split,
            drives,
            base=temperature,
            scales=eval_cfg.temperature_scales,
            single=tracked,
        )
    finally:
        split.close()
    # The best at either end of the scales: the optimum may lie beyond them (flagged).
    temps = [row["temperature"] for row in table]
    edge = len(temps) > 1 and temperature in (temps[0], temps[-1])
    if edge:
        print(
            f"[seglocnet] warning: the filter temperature {temperature:.3g} is at the edge of "
            f"eval.temperature_scales {list(eval_cfg.temperature_scales)} on {name}; the best "
            "may lie beyond them",
            flush=True,
        )
    fit["filter"] = {"split": name, "candidates": table, "at_scale_edge": edge}
    return temperature, fit, {name: (tracks, timing)} if tracked else {}


def _write(tracks, summary, split, eval_cfg, output_dir, channels, temperature) -> None:
    """The split's per-frame arrays and, with ``eval.num_figures``, its figures (and the
    calibration figure of the calibration split)."""
    if not output_dir:
        return
    name = split.name
    write_arrays(tracks, os.path.join(output_dir, "sequential", f"{name}.npz"))
    if not eval_cfg.num_figures:
        return
    figure_dir = os.path.join(output_dir, "figures", "sequential")
    write_figures(tracks, split, figure_dir, num_drives=eval_cfg.num_figures, channels=channels)
    if name == eval_cfg.calibration_split:
        viz.reliability_figure(
            os.path.join(figure_dir, "calibration.png"),
            MASSES,
            [summary["coverage"][f"{m:g}"] for m in MASSES],
            [summary["ellipse_coverage"][f"{m:g}"] for m in MASSES],
            title=f"calibration on {name} ({summary['frames']} frames, T = {temperature:.3g})",
        )
