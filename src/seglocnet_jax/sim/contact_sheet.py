"""A PNG a user can look at: simulated frames of a city next to their maps.

    python -m seglocnet_jax.sim.contact_sheet --city helsinki --out sheet.png

One row per frame: the 6 cameras (front row FRONT_LEFT, FRONT, FRONT_RIGHT; back row
BACK_LEFT, BACK, BACK_RIGHT), a LiDAR top view (forward up, 128 m across, colour = height), and
the HD and SD map tiles (256 px = 128 m, north up) around the pose with the vehicle (red arrow)
and its 64 m BEV footprint (blue).
"""

from __future__ import annotations

import argparse

import numpy as np
from PIL import Image, ImageDraw

from seglocnet_jax import geometry as g
from seglocnet_jax.geometry import CAMERA_NAMES
from seglocnet_jax.sim.sensors import SensorConfig
from seglocnet_jax.sim.simulator import Simulator
from seglocnet_jax.sim.trajectory import drive
from seglocnet_jax.sim.world import WorldConfig, build_world

_LAYOUT = (
    ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"),
    ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"),
)
PANEL = 256  # pixels, height of a row and size of the square panels


def camera_mosaic(images: np.ndarray) -> np.ndarray:
    """``(6, H, W, 3)`` in :data:`CAMERA_NAMES` order -> ``(2H, 3W, 3)`` surround mosaic."""
    rows = [np.concatenate([images[CAMERA_NAMES.index(n)] for n in row], axis=1) for row in _LAYOUT]
    return np.concatenate(rows, axis=0)


def lidar_top_view(points: np.ndarray, size: int = PANEL, resolution: float = 0.5):
    """``(P, 4)`` ego points -> ``(size, size, 3)`` uint8, forward up, ego at the centre."""
    img = np.full((size, size, 3), 20, np.uint8)
    row, col = g.ego_to_bev_pixel(points[:, :2], size, resolution)
    r, c = np.floor(row).astype(int), np.floor(col).astype(int)
    ok = (r >= 0) & (r < size) & (c >= 0) & (c < size)
    z = points[ok, 2]
    hue = np.clip(z / 10.0, 0, 1)[:, None]
    ground = np.clip(60 + 195 * points[ok, 3:4], 0, 255) * np.array([1.0, 1.0, 1.0])
    high = np.concatenate([255 * hue, 255 * (1 - np.abs(2 * hue - 1)), 255 * (1 - hue)], 1)
    colour = np.where((z > 0.3)[:, None], high, ground).astype(np.uint8)
    order = np.argsort(z)  # higher points on top
    img[r[ok][order], c[ok][order]] = colour[order]
    img[size // 2 - 2 : size // 2 + 2, size // 2 - 1 : size // 2 + 1] = (255, 40, 40)
    return img


def map_panel(raster, pose) -> np.ndarray:
    """The map tile around ``pose`` (256 px, north up) with the vehicle and BEV footprint."""
    from seglocnet_jax.maps.render import colorize

    tile, _ = raster.tile(pose[0], pose[1])
    img = Image.fromarray(colorize(tile, raster.channels))
    row0, col0, _, _ = g.tile_window(raster.grid, pose[0], pose[1])
    draw = ImageDraw.Draw(img)

    def px(pts_ego):
        w = g.ego_to_world(pose, np.asarray(pts_ego, np.float64))
        r, c = raster.grid.world_to_pixel(w[..., 0], w[..., 1])
        return [(float(cc - col0), float(rr - row0)) for rr, cc in zip(r, c, strict=True)]

    half = g.BEV_SIZE * g.RESOLUTION / 2
    box = px([(half, half), (half, -half), (-half, -half), (-half, half), (half, half)])
    draw.line(box, fill=(30, 90, 220), width=2)
    draw.line(px([(-3, 0), (6, 0)]), fill=(230, 30, 30), width=3)
    draw.polygon(px([(8, 0), (4, 2.5), (4, -2.5)]), fill=(230, 30, 30))
    return np.asarray(img.resize((PANEL, PANEL), Image.Resampling.NEAREST))


def _label(img: np.ndarray, text: str) -> np.ndarray:
    pil = Image.fromarray(img)
    ImageDraw.Draw(pil).text((4, 2), text, fill=(255, 255, 0))
    return np.asarray(pil)


def contact_sheet(samples, hd, sd) -> np.ndarray:
    """``(rows * 256, W, 3)`` uint8 sheet for rendered ``samples`` (see the module doc)."""
    rows = []
    for s in samples:
        cams = camera_mosaic(s["images"])
        scale = PANEL / cams.shape[0]
        cams = np.asarray(
            Image.fromarray(cams).resize(
                (int(round(cams.shape[1] * scale)), PANEL), Image.Resampling.BILINEAR
            )
        )
        x, y, yaw = s["pose"]
        cams = _label(cams, f"{s['sample_id']}  x={x:.1f} y={y:.1f} yaw={np.degrees(yaw):.0f}")
        panels = [
            cams,
            _label(lidar_top_view(s["lidar"]), f"LiDAR {len(s['lidar'])} pts"),
            _label(map_panel(hd, s["pose"]), "HD tile"),
            _label(map_panel(sd, s["pose"]), "SD tile"),
        ]
        sep = np.full((PANEL, 4, 3), 255, np.uint8)
        rows.append(np.concatenate([p for panel in panels for p in (panel, sep)][:-1], axis=1))
    return np.concatenate(rows, axis=0)


def main(argv=None) -> str:
    from seglocnet_jax.maps import MapConfig, load_city, rasterize
    from seglocnet_jax.maps.render import save_png

    ap = argparse.ArgumentParser(description="Contact sheet of simulated frames and their maps.")
    ap.add_argument("--city", default="helsinki", help="embedded city or .osm(.pbf) path")
    ap.add_argument("--out", required=True, help="output PNG path")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    ap.add_argument("--sd-width", type=float, default=10.0, help="SD road width, metres")
    args = ap.parse_args(argv)

    city = load_city(args.city)
    world = build_world(args.city, WorldConfig(), args.seed)
    sensors = SensorConfig.preset(args.preset)
    poses = drive(world, np.random.default_rng(args.seed), 40 * args.frames, 4.0)
    poses = poses[np.linspace(0, len(poses) - 1, args.frames).astype(int)]
    samples = Simulator(world, sensors).render(poses, args.seed)
    hd = rasterize(city, MapConfig(kind="hd"), drivable=world.drivable)
    sd = rasterize(city, MapConfig(kind="sd", road_width=args.sd_width))
    path = save_png(contact_sheet(samples, hd, sd), args.out)
    print(path)
    return path


if __name__ == "__main__":
    main()
