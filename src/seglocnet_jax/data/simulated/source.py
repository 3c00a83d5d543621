"""The simulator as a :class:`data.simulated.config.FrameSource` (the embedded default producer).

Thin adapter over :mod:`seglocnet_jax.sim`: ``build_world(city, cfg, seed)``,
``drive(world, rng, num_frames, spacing_m)`` (``drive_routes``: with the routes), ``route(world,
rng, length_m, spacing_m)`` (continuous drives) and ``Simulator(world, sensor_cfg).render(poses,
seed)``. ``PrepareConfig.sim`` is a plain dict: ``spacing_m`` (metres between consecutive
poses), ``world`` and ``sensors`` (sub-dicts for the simulator's own config dataclasses).

The world is named (and seeded) by the city key (:func:`seglocnet_jax.maps.city_key`): an
embedded city's name, ``<stem>-<content hash>`` for a user's OSM file, so the records' ``city``
matches the manifest and the world does not depend on where the file lies.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from seglocnet_jax.data.schema import check_sample

SIM_KEYS = ("spacing_m", "world", "sensors")
DEFAULT_SPACING_M = 4.0


def parse_sim_config(sim_cfg: dict | None, prefix: str = "sim"):
    """``(spacing_m, sim.WorldConfig, sim.SensorConfig)`` of the plain ``sim`` section (the
    ``sim=cpu|paper`` group); unknown keys and bad values raise ``ConfigError`` naming
    ``<prefix>.<key>``. Called when the experiment config is built, before any simulation."""
    from seglocnet_jax import sim
    from seglocnet_jax.config_util import ConfigError, from_dict

    sim_cfg = dict(sim_cfg or {})
    unknown = sorted(set(sim_cfg) - set(SIM_KEYS))
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(f'{prefix}.{k}' for k in unknown)}; {prefix} "
            f"accepts: {', '.join(SIM_KEYS)}"
        )
    spacing = sim_cfg.get("spacing_m", DEFAULT_SPACING_M)
    if isinstance(spacing, bool) or not isinstance(spacing, int | float) or not spacing > 0:
        raise ConfigError(f"{prefix}.spacing_m must be a number > 0 (metres), got {spacing!r}")
    world_cfg = from_dict(sim.WorldConfig, sim_cfg.get("world"), f"{prefix}.world")
    sensor_cfg = from_dict(sim.SensorConfig, sim_cfg.get("sensors"), f"{prefix}.sensors")
    from seglocnet_jax.data.records import LIDAR_RANGE

    if not 0 < sensor_cfg.max_range < LIDAR_RANGE:  # stored LiDAR is fixed point within it
        raise ConfigError(
            f"{prefix}.sensors.max_range must be in (0, {LIDAR_RANGE:g}) m (the records' LiDAR "
            f"range), got {sensor_cfg.max_range}"
        )
    return float(spacing), world_cfg, sensor_cfg


class SimSource:
    """Frames of one simulated city (world frame metres/radians); ``city`` is an embedded
    city's name or an OSM file path."""

    def __init__(self, city: str, sim_cfg: dict, seed: int):
        from seglocnet_jax import maps, sim

        self._sim = sim
        self.spacing_m, world_cfg, sensor_cfg = parse_sim_config(sim_cfg)
        geometry = dataclasses.replace(maps.load_city(city), name=maps.city_key(city))
        self.world = sim.build_world(geometry, world_cfg, seed)
        self.simulator = sim.Simulator(self.world, sensor_cfg)

    @property
    def drivable(self):
        """The world's drivable area (shapely, world metres): the HD map's road channel."""
        return self.world.drivable

    def drive(self, rng: np.random.Generator, num_frames: int) -> np.ndarray:
        return np.asarray(self._sim.drive(self.world, rng, num_frames, self.spacing_m))

    def drive_routes(self, rng: np.random.Generator, num_frames: int):
        """:meth:`drive`'s frames (same draws, same poses) with their routes
        (``sim.Trajectory``)."""
        return self._sim.drive_routes(self.world, rng, num_frames, self.spacing_m)

    def route(self, rng: np.random.Generator, length_m: float, spacing_m: float):
        """One continuous drive (``sim.Trajectory``; see ``sim.trajectory.route``)."""
        return self._sim.route(self.world, rng, length_m, spacing_m)

    def render(self, poses: np.ndarray, seed: int) -> list[dict]:
        """Sample dicts (``schema.SAMPLE_KEYS``) of ``poses``, each validated."""
        return [
            check_sample(s, where=f"simulator {s['sample_id']}")
            for s in self.simulator.render(poses, seed)
        ]
