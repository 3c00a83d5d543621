"""Driving simulator over real OSM cities: a 2.5D world, trajectories and sensors.

``build_world(city, WorldConfig(), seed)`` -> :class:`World` (``world.drivable`` is the HD
drivable area); ``drive(world, rng, num_frames, spacing_m)`` -> poses (N, 3) of many short
routes (``drive_routes``: with each frame's route and index along it); ``route(world, rng,
length_m, spacing_m)`` -> one continuous drive (:class:`Trajectory`);
``Simulator(world, SensorConfig.preset("cpu")).render(poses, seed)`` -> sample dicts of
:mod:`seglocnet_jax.data.schema`.
"""

from seglocnet_jax.geometry import CAMERA_NAMES
from seglocnet_jax.sim.sensors import SensorConfig
from seglocnet_jax.sim.simulator import Simulator
from seglocnet_jax.sim.trajectory import (
    NOMINAL_SPEED_MPS,
    Trajectory,
    drive,
    drive_routes,
    lane_poses,
    route,
    sample_poses,
)
from seglocnet_jax.sim.world import World, WorldConfig, build_world

__all__ = [
    "CAMERA_NAMES",
    "NOMINAL_SPEED_MPS",
    "SensorConfig",
    "Simulator",
    "Trajectory",
    "World",
    "WorldConfig",
    "build_world",
    "drive",
    "drive_routes",
    "lane_poses",
    "route",
    "sample_poses",
]
