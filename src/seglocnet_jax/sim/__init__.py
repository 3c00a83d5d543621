"""Driving simulator over real OSM cities: a 2.5D world, trajectories and sensors.

``build_world(city, WorldConfig(), seed)`` -> :class:`World` (``world.drivable`` is the HD
drivable area); ``drive(world, rng, num_frames, spacing_m)`` -> poses (N, 3);
``Simulator(world, SensorConfig.preset("cpu")).render(poses, seed)`` -> sample dicts of
:mod:`seglocnet_jax.data.schema`.
"""

from seglocnet_jax.sim.sensors import CAMERA_NAMES, SensorConfig
from seglocnet_jax.sim.simulator import Simulator
from seglocnet_jax.sim.trajectory import drive, lane_poses, sample_poses
from seglocnet_jax.sim.world import World, WorldConfig, build_world

__all__ = [
    "CAMERA_NAMES",
    "SensorConfig",
    "Simulator",
    "World",
    "WorldConfig",
    "build_world",
    "drive",
    "lane_poses",
    "sample_poses",
]
