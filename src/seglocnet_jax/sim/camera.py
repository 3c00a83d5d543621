"""Camera shading: ray hits (:func:`render.march`) to RGB images under seeded lighting.

Ground by surface class with per-cell grain, building facades with floor lines and window rows
(lit at night), cars with glass bands, trees, poles, pedestrians, a sky gradient and distance
haze. Lighting is drawn per frame (:func:`draw_lighting`): day, dusk or night-like.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from seglocnet_jax.sim import classes as cl
from seglocnet_jax.sim.render import SKY, THING, TOP, X_FACE, hash01

LIGHT_KEYS = ("ambient", "tint", "face_x", "face_y", "night", "sky_h", "sky_z", "fog", "lamp")
_GLASS = jnp.array([0.14, 0.17, 0.22])
_LIT = jnp.array([1.0, 0.82, 0.45])
_ROOF = jnp.array([0.33, 0.31, 0.30])
_GRAVEL = jnp.array([0.52, 0.49, 0.44])


def draw_lighting(rng: np.random.Generator, night_prob: float, dusk_prob: float) -> dict:
    """One frame's lighting (NumPy float32): ambient level, tint, per-face sun shading, night
    flag, sky colours, haze distance (m) and lamp strength (the renderer's ``LIGHT_KEYS``), and
    its ``condition``: "day", "dusk" or "night" (the record's ``lighting``)."""
    u = rng.uniform()
    night = u < night_prob
    dusk = night_prob <= u < night_prob + dusk_prob
    if night:
        ambient, sky_scale, lamp = rng.uniform(0.06, 0.16), rng.uniform(0.05, 0.12), 0.7
    elif dusk:
        ambient, sky_scale, lamp = rng.uniform(0.3, 0.55), rng.uniform(0.35, 0.6), 0.2
    else:
        ambient, sky_scale, lamp = rng.uniform(0.75, 1.25), rng.uniform(0.85, 1.1), 0.0
    tint = rng.uniform(0.9, 1.1, 3)
    if dusk:
        tint = tint * np.array([1.12, 0.95, 0.8])
    sun = rng.uniform(0, 2 * np.pi)
    return {
        "condition": "night" if night else "dusk" if dusk else "day",
        "ambient": np.float32(ambient),
        "tint": tint.astype(np.float32),
        "face_x": np.float32(0.75 + 0.25 * abs(np.cos(sun))),
        "face_y": np.float32(0.75 + 0.25 * abs(np.sin(sun))),
        "night": np.float32(night),
        "sky_h": (cl.SKY_HORIZON * sky_scale * rng.uniform(0.9, 1.1, 3)).astype(np.float32),
        "sky_z": (cl.SKY_ZENITH * sky_scale * rng.uniform(0.85, 1.15, 3)).astype(np.float32),
        "fog": np.float32(rng.uniform(80.0, 250.0)),
        "lamp": np.float32(lamp),
    }


def shade(
    hits: dict,
    slopes,
    light: dict,
    palette,
    cell0,
    resolution: float,
    key,
    pixel_noise: float,
    level_height: float = 3.2,
):
    """RGB in [0, 1] per ray, shape ``(C, R, 3)``.

    ``hits``: :func:`render.march` output; ``slopes`` (C, R); ``palette`` (Things, 256, 3);
    ``cell0`` (2,) int32 patch offset in the world raster; ``key`` a PRNG key for the noise.
    """
    kind, cls, d, z = hits["kind"], hits["cls"], hits["d"], hits["z"]
    grow = hits["row"] + cell0[0]  # global cells: textures stay put between frames
    gcol = hits["col"] + cell0[1]
    grain = hash01(grow, gcol)[..., None]  # (C, R, 1)

    # Ground: class colour, grain; grass patches turn to gravel at a coarse scale.
    g_cls = jnp.clip(cls, 0, len(cl.SURFACE_RGB) - 1)
    ground = jnp.asarray(cl.SURFACE_RGB)[g_cls] * (0.85 + 0.3 * grain)
    gravel = (hash01(grow // 24, gcol // 24, 7) > 0.65)[..., None] & (g_cls == 0)[..., None]
    ground = jnp.where(gravel, _GRAVEL * (0.8 + 0.4 * grain), ground)

    # Objects: palette colour, then class-specific texture.
    t_cls = jnp.clip(cls, 0, palette.shape[0] - 1)
    base = palette[t_cls, hits["colour"]]  # (C, R, 3)
    ge = hits["e"] + cell0[1] * resolution  # world-anchored facade coordinates
    gn = hits["n"] - cell0[0] * resolution
    along = jnp.where(hits["face"] == X_FACE, gn, ge)
    floor = jnp.floor(z / level_height)
    fz = z - floor * level_height
    win_idx = jnp.floor(along / 3.0)
    fu = along / 3.0 - win_idx
    is_bld = (cls == cl.Thing.BUILDING) & (kind == THING)
    wall = is_bld & (hits["face"] != TOP)
    window = wall & (fz > 1.0) & (fz < 2.3) & (fu > 0.2) & (fu < 0.7) & (z > 0.5)
    lit = window & (
        hash01(hits["colour"] * 131 + floor.astype(jnp.int32), win_idx.astype(jnp.int32), 3) < 0.35
    )
    line = wall & (fz < 0.18)
    obj = jnp.where(window[..., None], _GLASS, base * (0.9 + 0.15 * grain))
    obj = jnp.where(line[..., None], obj * 0.7, obj)
    obj = jnp.where((is_bld & (hits["face"] == TOP))[..., None], _ROOF * (0.8 + 0.3 * grain), obj)
    is_car = (cls == cl.Thing.CAR) & (kind == THING)
    obj = jnp.where((is_car & (z > 0.95) & (z < 1.35))[..., None], _GLASS, obj)
    obj = jnp.where((is_car & (z < 0.35))[..., None], jnp.array([0.06, 0.06, 0.06]), obj)

    face = hits["face"]
    shading = jnp.where(
        face == TOP, 1.0, jnp.where(face == X_FACE, light["face_x"], light["face_y"])
    )
    shading = jnp.where(kind == THING, shading, 1.0)[..., None]
    lamp = light["lamp"] * jnp.exp(-d / 18.0)[..., None]
    colour = jnp.where((kind == THING)[..., None], obj, ground)
    colour = colour * shading * (light["ambient"] * light["tint"] + lamp)
    colour = jnp.where(lit[..., None], colour + light["night"] * _LIT * 0.8, colour)

    up = jnp.clip(slopes * 2.5, 0.0, 1.0)[..., None]
    sky = light["sky_h"] * (1 - up) + light["sky_z"] * up
    haze = (1 - jnp.exp(-d / light["fog"]))[..., None]
    colour = colour * (1 - haze) + light["sky_h"] * haze
    colour = jnp.where((kind == SKY)[..., None], sky, colour)
    colour = colour + pixel_noise * jax.random.normal(key, colour.shape)
    return jnp.clip(colour, 0.0, 1.0)


def to_uint8(rgb):
    """[0, 1] floats to uint8."""
    return jnp.round(rgb * 255.0).astype(jnp.uint8)
