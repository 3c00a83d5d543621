"""The filter's settings for a run: ``eval.tracker`` completed from ``eval.odometry`` and the
map (:func:`tracker_config`), and the map channel the on-road prior reads
(:func:`road_channels`)."""

from __future__ import annotations

import dataclasses

from seglocnet_jax import tracking
from seglocnet_jax.evaluation import TRACKER_MOTION_FIELDS, EvalConfig
from seglocnet_jax.tracking import odometry as odometry_lib

# The on-road prior (eval.tracker.off_road) when the map has a road channel and the setting is
# null: chosen on the 8 unseen-city validation drives among 3 and 10 (docs/sequential.md).
OFF_ROAD_NATS = 10.0


def tracker_config(
    eval_cfg: EvalConfig, num_rotations: int, channels=None
) -> tracking.TrackerConfig:
    """The filter's config: ``eval.tracker`` with its null motion-noise fields derived from
    ``eval.odometry`` (:func:`tracking.odometry.tracker_noise` for frames 0.5 s apart: the
    simulator's 5 m at 10 m/s, nuScenes keyframes at 2 Hz), a null ``off_road`` from the map's
    ``channels`` (:data:`OFF_ROAD_NATS` with a road channel, 0 without: a map of buildings
    alone has no road to keep to), the solver's K and the geometry's window (129 cells at
    0.5 m). One config per run: the kernels compile once."""
    section = dataclasses.asdict(eval_cfg.tracker)
    derived = odometry_lib.tracker_noise(eval_cfg.odometry)
    for key in TRACKER_MOTION_FIELDS:
        if section[key] is None:
            section[key] = float(derived[key])
    if section["off_road"] is None:
        if channels is None:
            raise ValueError(
                "eval.tracker.off_road is null (derived from the map's channels), but no map "
                "channels were given to derive it from; give them, or a number"
            )
        section["off_road"] = OFF_ROAD_NATS if "road" in channels else 0.0
    return tracking.TrackerConfig(num_rotations=num_rotations, **section)


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
