"""The simulator as a :class:`data.prepare.FrameSource` (the embedded default producer).

Thin adapter over :mod:`seglocnet_jax.sim`: ``build_world(city, cfg, seed)``,
``drive(world, rng, num_frames, spacing_m)`` and ``Simulator(world, sensor_cfg).render(poses,
seed)``. ``PrepareConfig.sim`` is a plain dict: ``spacing_m`` (metres between consecutive
poses), ``world`` and ``sensors`` (sub-dicts for the simulator's own config dataclasses).
"""

from __future__ import annotations

import numpy as np

SIM_KEYS = ("spacing_m", "world", "sensors")


class SimSource:
    """Frames of one simulated city (world frame metres/radians)."""

    def __init__(self, city: str, sim_cfg: dict, seed: int):
        from seglocnet_jax import sim
        from seglocnet_jax.config_util import ConfigError, from_dict

        unknown = sorted(set(sim_cfg) - set(SIM_KEYS))
        if unknown:
            raise ConfigError(f"unknown config key(s) data.prepare.sim.{unknown}; has {SIM_KEYS}")
        self._sim = sim
        self.spacing_m = float(sim_cfg.get("spacing_m", 4.0))
        world_cfg = from_dict(sim.WorldConfig, sim_cfg.get("world"), "data.prepare.sim.world")
        sensor_cfg = from_dict(sim.SensorConfig, sim_cfg.get("sensors"), "data.prepare.sim.sensors")
        self.world = sim.build_world(city, world_cfg, seed)
        self.simulator = sim.Simulator(self.world, sensor_cfg)

    @property
    def drivable(self):
        """The world's drivable area (shapely, world metres): the HD map's road channel."""
        return self.world.drivable

    def drive(self, rng: np.random.Generator, num_frames: int) -> np.ndarray:
        return np.asarray(self._sim.drive(self.world, rng, num_frames, self.spacing_m))

    def render(self, poses: np.ndarray, seed: int) -> list[dict]:
        return self.simulator.render(poses, seed)
