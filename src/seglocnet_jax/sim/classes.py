"""The simulator's class vocabulary and colour tables (shared by world, cameras and LiDAR)."""

from __future__ import annotations

import enum

import numpy as np


class Surface(enum.IntEnum):
    """Ground classes of the world's ``surface`` raster."""

    OTHER = 0  # grass / gravel / plazas
    ROAD = 1
    MARKING = 2
    SIDEWALK = 3


class Thing(enum.IntEnum):
    """Object classes of the world's ``thing`` raster (0: no object in the cell)."""

    NONE = 0
    BUILDING = 1
    CAR = 2
    TREE = 3
    POLE = 4
    PEDESTRIAN = 5


# Colour id used for tree trunks (canopies use the others).
TRUNK_COLOUR = 255

# LiDAR reflectivity in [0, 1] by material.
SURFACE_INTENSITY = np.array([0.08, 0.12, 0.75, 0.18], np.float32)  # by Surface
THING_INTENSITY = np.array([0.0, 0.30, 0.55, 0.15, 0.65, 0.22], np.float32)  # by Thing

# RGB in [0, 1].
SURFACE_RGB = np.array(
    [
        [0.30, 0.42, 0.20],  # OTHER: grass (texture varies it to gravel)
        [0.30, 0.30, 0.32],  # ROAD: asphalt
        [0.88, 0.88, 0.85],  # MARKING
        [0.58, 0.56, 0.52],  # SIDEWALK
    ],
    np.float32,
)
SKY_HORIZON = np.array([0.80, 0.85, 0.92], np.float32)
SKY_ZENITH = np.array([0.35, 0.55, 0.85], np.float32)

_FACADES = np.array(
    [
        [0.85, 0.80, 0.68],
        [0.75, 0.72, 0.66],
        [0.90, 0.90, 0.88],
        [0.62, 0.34, 0.26],
        [0.82, 0.68, 0.40],
        [0.60, 0.66, 0.72],
        [0.55, 0.55, 0.55],
        [0.78, 0.56, 0.46],
        [0.70, 0.75, 0.62],
        [0.45, 0.40, 0.38],
        [0.92, 0.84, 0.74],
        [0.66, 0.60, 0.72],
    ],
    np.float32,
)
_CARS = np.array(
    [
        [0.9, 0.9, 0.9],
        [0.1, 0.1, 0.1],
        [0.55, 0.56, 0.58],
        [0.7, 0.1, 0.1],
        [0.1, 0.2, 0.55],
        [0.85, 0.85, 0.8],
        [0.25, 0.25, 0.27],
        [0.2, 0.4, 0.25],
        [0.75, 0.65, 0.2],
    ],
    np.float32,
)


def thing_palette(seed: int = 0) -> np.ndarray:
    """``(len(Thing), 256, 3)`` RGB for each object class and colour id."""
    rng = np.random.default_rng([seed, 0xC0])
    pal = np.zeros((len(Thing), 256, 3), np.float32)
    jitter = rng.uniform(0.9, 1.1, size=(256, 3))
    pal[Thing.BUILDING] = np.clip(_FACADES[np.arange(256) % len(_FACADES)] * jitter, 0, 1)
    pal[Thing.CAR] = np.clip(_CARS[np.arange(256) % len(_CARS)] * jitter, 0, 1)
    pal[Thing.TREE] = np.clip(np.array([0.18, 0.35, 0.14]) * rng.uniform(0.7, 1.3, (256, 1)), 0, 1)
    pal[Thing.TREE, TRUNK_COLOUR] = [0.35, 0.25, 0.16]
    pal[Thing.POLE] = [0.45, 0.46, 0.48]
    pal[Thing.PEDESTRIAN] = rng.uniform(0.1, 0.8, size=(256, 3))
    return pal
