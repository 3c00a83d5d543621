"""Tiny nuScenes and Argoverse 2 datasets in their real on-disk formats, written by the tests.

Both fixtures drive along an east-west road (y = 100 in the map / city frame, 8 m wide) with a
plaza that has a hole, so tests can check that poses land on the drivable area, that polygon
holes are kept, and that sensor frames line up. Cameras look outwards at known azimuths; each
camera's image is a solid, distinct colour so tests can tell them apart after decoding.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from PIL import Image
from shapely.geometry import LineString

ROAD_Y = 100.0
ROAD_HALF_WIDTH = 4.0
PLAZA = (150.0, 60.0, 250.0, 160.0)  # x0, y0, x1, y1
HOLE = (180.0, 120.0, 220.0, 150.0)
# Road centrelines (world metres): crossing, non-parallel, so an alignment is well determined.
ROADS = [
    ((0.0, ROAD_Y), (400.0, ROAD_Y)),
    ((100.0, -20.0), (100.0, 300.0)),
    ((0.0, 260.0), (400.0, 190.0)),
    ((300.0, 0.0), (340.0, 300.0)),
]
BUILDINGS = [(40.0, 40.0, 60.0, 60.0), (200.0, 20.0, 230.0, 40.0), (360.0, 20.0, 390.0, 50.0)]
IMAGE_HW = (24, 40)
FX = 20.0
CAM_COLOURS = [
    (250, 20, 20),
    (20, 250, 20),
    (20, 20, 250),
    (250, 250, 20),
    (20, 250, 250),
    (250, 20, 250),
    (128, 128, 128),
]
# OpenCV camera (x right, y down, z forward) looking along ego +x: columns are the camera axes.
CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
LIDAR_YAW = math.pi / 2  # nuScenes LIDAR_TOP is mounted turned 90 degrees


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_wxyz(r: np.ndarray) -> list[float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (test helper, trace > -1 cases)."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    if w < 1e-6:  # 180-degree turns: pick the largest diagonal axis
        i = int(np.argmax(np.diag(r)))
        v = np.zeros(3)
        v[i] = math.sqrt(max(0.0, 1 + 2 * r[i, i] - np.trace(r))) / 2
        for j in range(3):
            if j != i:
                v[j] = (r[i, j] + r[j, i]) / (4 * v[i])
        return [0.0, *v.tolist()]
    return [
        w,
        (r[2, 1] - r[1, 2]) / (4 * w),
        (r[0, 2] - r[2, 0]) / (4 * w),
        (r[1, 0] - r[0, 1]) / (4 * w),
    ]


def _write_jpg(path: str, colour) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    Image.new("RGB", (IMAGE_HW[1], IMAGE_HW[0]), tuple(colour)).save(path, quality=95)


def lidar_points(seed: int, n: int = 64) -> np.ndarray:
    """``(n, 4)`` sensor-frame x, y, z, intensity (0-255) points."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    return np.concatenate([xyz, rng.uniform(0, 255, (n, 1)).astype(np.float32)], axis=1)


def camera_yaws(n: int) -> list[float]:
    return [2 * math.pi * i / n for i in range(n)]


def drivable_polygons():
    """Shell rings and holes of the fixture's drivable area (world metres): each road as a
    rectangle, and the plaza with its hole."""
    out = []
    for a, b in ROADS:
        rect = LineString([a, b]).buffer(ROAD_HALF_WIDTH, cap_style="flat")
        out.append((list(rect.exterior.coords)[:-1], []))
    x0, y0, x1, y1 = PLAZA
    hx0, hy0, hx1, hy1 = HOLE
    plaza = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    hole = [(hx0, hy0), (hx0, hy1), (hx1, hy1), (hx1, hy0)]
    return out + [(plaza, [hole])]


def write_osm(path: str, to_lonlat, warp=None, origins=((0.0, 0.0),)) -> None:
    """An OSM XML extract of the fixture's roads (centrelines) and buildings.

    ``to_lonlat(x, y)`` is the dataset frame's inverse projection; ``warp(xy (N, 2))`` moves the
    world points first (a synthetic OSM misalignment). ``origins``: the fixture's map is written
    once per origin (world metres added to every point before ``warp``), e.g. around each log of
    :func:`write_argoverse` ``(origins=...)``; leave one out for an area without OSM.
    """
    warp = warp or (lambda xy: xy)
    osm = OsmXml("fixture")

    def nodes(points):
        xy = warp(np.asarray(points, np.float64))
        return osm.nodes(*to_lonlat(xy[:, 0], xy[:, 1]))

    for ox, oy in origins:
        o = np.array([ox, oy], np.float64)
        for a, b in ROADS:
            a, b = np.asarray(a) + o, np.asarray(b) + o
            osm.way(nodes([a + t * (b - a) for t in np.linspace(0, 1, 5)]), highway="residential")
        for x0, y0, x1, y1 in BUILDINGS:
            ids = nodes(np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]) + o)
            osm.way(ids + ids[:1], building="yes")
    osm.write(path)


class OsmXml:
    """An OSM XML file built node by node and way by way (the fixtures' one OSM writer)."""

    def __init__(self, generator: str = "test"):
        self.lines = [
            '<?xml version="1.0" encoding="UTF-8"?>',
            f'<osm version="0.6" generator="{generator}">',
        ]
        self.ways: list[tuple[list[int], dict]] = []
        self.node_id = 0

    def nodes(self, lon, lat) -> list[int]:
        """Adds nodes at ``lon``, ``lat`` (degrees); returns their ids."""
        ids = []
        for lo, la in zip(lon, lat, strict=True):
            self.node_id += 1
            self.lines.append(
                f' <node id="{self.node_id}" version="1" lat="{la:.9f}" lon="{lo:.9f}"/>'
            )
            ids.append(self.node_id)
        return ids

    def way(self, ids: list[int], **tags) -> None:
        self.ways.append((list(ids), tags))

    def write(self, path) -> str:
        lines = list(self.lines)
        for i, (ids, tags) in enumerate(self.ways):
            lines.append(f' <way id="{1000 + i}" version="1">')
            lines += [f'  <nd ref="{n}"/>' for n in ids]
            lines += [f'  <tag k="{k}" v="{v}"/>' for k, v in tags.items()]
            lines.append(" </way>")
        lines.append("</osm>")
        with open(path, "w") as f:
            f.write("\n".join(lines) + "\n")
        return str(path)


# --------------------------------------------------------------------------- nuScenes

NUS_CAMERAS = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_FRONT_LEFT",
)
NUS_CAM_YAW = {
    "CAM_FRONT": 0.0,
    "CAM_FRONT_RIGHT": -1.0,
    "CAM_BACK_RIGHT": -2.0,
    "CAM_BACK": math.pi,
    "CAM_BACK_LEFT": 2.0,
    "CAM_FRONT_LEFT": 1.0,
}
NUS_SCENES = {"scene-0061": 20.0, "scene-0103": 330.0}  # mini_train / mini_val, start x
NUS_SAMPLES_PER_SCENE = 3
CAM_EGO_DX = 0.3  # the ego moved this far (m, forward) between LiDAR and camera timestamps


def write_nuscenes(root: str, version: str = "v1.0-mini") -> dict:
    """Writes the fixture; returns facts for the tests (poses per sample token, ...)."""
    tables = {
        n: []
        for n in (
            "scene",
            "log",
            "sample",
            "sample_data",
            "calibrated_sensor",
            "sensor",
            "ego_pose",
        )
    }
    facts = {"poses": {}, "lidar": {}, "scenes": {}, "lighting": {}}
    calib = {}
    for ch in ("LIDAR_TOP", *NUS_CAMERAS):
        modality = "lidar" if ch == "LIDAR_TOP" else "camera"
        tables["sensor"].append({"token": f"sensor-{ch}", "channel": ch, "modality": modality})
        if ch == "LIDAR_TOP":
            rot, trans, intr = rot_z(LIDAR_YAW), [0.9, 0.0, 1.8], []
        else:
            rot, trans = rot_z(NUS_CAM_YAW[ch]) @ CAM_FORWARD, [1.5, 0.0, 1.6]
            intr = [[FX, 0.0, IMAGE_HW[1] / 2], [0.0, FX, IMAGE_HW[0] / 2], [0.0, 0.0, 1.0]]
        calib[ch] = f"calib-{ch}"
        tables["calibrated_sensor"].append(
            {
                "token": calib[ch],
                "sensor_token": f"sensor-{ch}",
                "translation": trans,
                "rotation": quat_wxyz(rot),
                "camera_intrinsic": intr,
            }
        )
    tables["log"].append(
        {
            "token": "log-0",
            "logfile": "n008-fixture",
            "vehicle": "n008",
            "date_captured": "2018-08-01",
            "location": "boston-seaport",
        }
    )
    t = 1_533_000_000_000_000
    for s_idx, (scene, x_start) in enumerate(NUS_SCENES.items()):
        tokens = [f"sample-{s_idx}-{i}" for i in range(NUS_SAMPLES_PER_SCENE)]
        facts["scenes"][scene] = tokens
        facts["lighting"][scene] = "night" if s_idx else "day"
        tables["scene"].append(
            {
                "token": f"scene-tok-{s_idx}",
                "name": scene,
                "log_token": "log-0",
                "nbr_samples": len(tokens),
                "first_sample_token": tokens[0],
                "last_sample_token": tokens[-1],
                # nuScenes scene descriptions name night scenes: the second one is one
                "description": "Night, fixture" if s_idx else "fixture, parking lot",
            }
        )
        for i, tok in enumerate(tokens):
            t += 500_000
            x, yaw = x_start + 10.0 * i, 0.05 * (i - 1)
            pose = np.array([x, ROAD_Y + 0.5 * i - 0.5, yaw])
            facts["poses"][tok] = pose
            tables["sample"].append(
                {
                    "token": tok,
                    "timestamp": t,
                    "scene_token": f"scene-tok-{s_idx}",
                    "prev": tokens[i - 1] if i else "",
                    "next": tokens[i + 1] if i + 1 < len(tokens) else "",
                }
            )
            for ch in ("LIDAR_TOP", *NUS_CAMERAS):
                sd_tok = f"sd-{tok}-{ch}"
                dx = 0.0 if ch == "LIDAR_TOP" else CAM_EGO_DX
                ex, ey = pose[0] + dx * math.cos(yaw), pose[1] + dx * math.sin(yaw)
                tables["ego_pose"].append(
                    {
                        "token": f"ego-{sd_tok}",
                        "timestamp": t,
                        "translation": [ex, ey, 0.0],
                        "rotation": quat_wxyz(rot_z(yaw)),
                    }
                )
                if ch == "LIDAR_TOP":
                    fname = f"samples/LIDAR_TOP/{sd_tok}.pcd.bin"
                    pts = lidar_points(s_idx * 10 + i)
                    full = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], axis=1)
                    os.makedirs(os.path.join(root, "samples/LIDAR_TOP"), exist_ok=True)
                    full.astype(np.float32).tofile(os.path.join(root, fname))
                    facts["lidar"][tok] = pts
                else:
                    fname = f"samples/{ch}/{sd_tok}.jpg"
                    _write_jpg(os.path.join(root, fname), CAM_COLOURS[NUS_CAMERAS.index(ch)])
                tables["sample_data"].append(
                    {
                        "token": sd_tok,
                        "sample_token": tok,
                        "ego_pose_token": f"ego-{sd_tok}",
                        "calibrated_sensor_token": calib[ch],
                        "timestamp": t,
                        "fileformat": "pcd" if ch == "LIDAR_TOP" else "jpg",
                        "is_key_frame": True,
                        "height": 0 if ch == "LIDAR_TOP" else IMAGE_HW[0],
                        "width": 0 if ch == "LIDAR_TOP" else IMAGE_HW[1],
                        "filename": fname,
                        "prev": "",
                        "next": "",
                    }
                )
            # A non-keyframe sweep that readers must ignore (its file does not even exist).
            tables["sample_data"].append(
                {
                    "token": f"sweep-{tok}",
                    "sample_token": tok,
                    "ego_pose_token": f"ego-sd-{tok}-LIDAR_TOP",
                    "calibrated_sensor_token": calib["LIDAR_TOP"],
                    "timestamp": t + 50_000,
                    "fileformat": "pcd",
                    "is_key_frame": False,
                    "height": 0,
                    "width": 0,
                    "filename": f"sweeps/LIDAR_TOP/missing-{tok}.pcd.bin",
                    "prev": "",
                    "next": "",
                }
            )
    os.makedirs(os.path.join(root, version), exist_ok=True)
    for name, rows in tables.items():
        with open(os.path.join(root, version, f"{name}.json"), "w") as f:
            json.dump(rows, f)
    _write_nus_map(os.path.join(root, "maps", "expansion", "boston-seaport.json"))
    return facts


def _write_nus_map(path: str) -> None:
    nodes, polygons = [], []

    def add_ring(ring):
        tokens = []
        for x, y in ring:
            tokens.append(f"node-{len(nodes)}")
            nodes.append({"token": tokens[-1], "x": x, "y": y})
        return tokens

    for shell, holes in drivable_polygons():
        polygons.append(
            {
                "token": f"poly-{len(polygons)}",
                "exterior_node_tokens": add_ring(shell),
                "holes": [{"node_tokens": add_ring(h)} for h in holes],
            }
        )
    data = {
        "version": "1.3",
        "canvas_edge": [3000.0, 2000.0],
        "node": nodes,
        "line": [],
        "polygon": polygons,
        "drivable_area": [{"token": "da-0", "polygon_tokens": [p["token"] for p in polygons]}],
    }
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(data, f)


# --------------------------------------------------------------------------- Argoverse 2

AV2_CAMERAS = (
    "ring_front_center",
    "ring_front_right",
    "ring_side_right",
    "ring_rear_right",
    "ring_rear_left",
    "ring_side_left",
    "ring_front_left",
)
AV2_LOGS = {  # split -> [(log id, city, start x)]
    "train": [("log-mia-a", "MIA", 20.0), ("log-pit-a", "PIT", 40.0)],
    "val": [("log-mia-b", "MIA", 330.0)],
}
AV2_SWEEPS = 6  # LiDAR sweeps per log, 100 ms apart
AV2_CAM_DT = 10_000_000  # cameras fire 10 ms after each sweep
AV2_EGO_SPEED = 10.0  # m/s along +x


def write_argoverse(root: str, logs: dict | None = None, origins: dict | None = None) -> dict:
    """Writes the AV2 fixture under ``root/{train,val}``; returns facts for the tests.

    ``logs``: split -> ``[(log id, city, start x)]`` (default :data:`AV2_LOGS`); ``origins``:
    log id -> ``(x, y)`` metres added to that log's trajectory and map (default 0), so logs of
    one city can lie kilometres apart.
    """
    facts = {"poses": {}, "lidar": {}}
    origins = origins or {}
    for split, split_logs in (AV2_LOGS if logs is None else logs).items():
        for log_id, city, x_start in split_logs:
            ox, oy = origins.get(log_id, (0.0, 0.0))
            d = os.path.join(root, split, log_id)
            t0 = 315_969_000_000_000_000
            sweeps = [t0 + k * 100_000_000 for k in range(AV2_SWEEPS)]
            times = sorted(sweeps + [t + AV2_CAM_DT for t in sweeps])
            rows = {c: [] for c in ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
            for t in times:
                x = x_start + AV2_EGO_SPEED * (t - t0) / 1e9
                q = quat_wxyz(rot_z(0.02))
                for key, v in zip(rows, [t, *q, x + ox, ROAD_Y + oy, 0.0], strict=True):
                    rows[key].append(v)
                if t in sweeps:
                    facts["poses"][f"{log_id}/{t}"] = np.array([x + ox, ROAD_Y + oy, 0.02])
            _feather(os.path.join(d, "city_SE3_egovehicle.feather"), rows)
            ext = {c: [] for c in ("sensor_name", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
            intr = {
                c: []
                for c in (
                    "sensor_name",
                    "fx_px",
                    "fy_px",
                    "cx_px",
                    "cy_px",
                    "k1",
                    "k2",
                    "k3",
                    "height_px",
                    "width_px",
                )
            }
            for i, (cam, yaw) in enumerate(zip(AV2_CAMERAS, camera_yaws(7), strict=True)):
                q = quat_wxyz(rot_z(yaw) @ CAM_FORWARD)
                for key, v in zip(ext, [cam, *q, 1.0, 0.0, 1.5], strict=True):
                    ext[key].append(v)
                for key, v in zip(
                    intr,
                    [
                        cam,
                        FX,
                        FX,
                        IMAGE_HW[1] / 2,
                        IMAGE_HW[0] / 2,
                        0.0,
                        0.0,
                        0.0,
                        IMAGE_HW[0],
                        IMAGE_HW[1],
                    ],
                    strict=True,
                ):
                    intr[key].append(v)
                for t in sweeps:
                    _write_jpg(
                        os.path.join(d, "sensors", "cameras", cam, f"{t + AV2_CAM_DT}.jpg"),
                        CAM_COLOURS[i],
                    )
            _feather(os.path.join(d, "calibration", "egovehicle_SE3_sensor.feather"), ext)
            _feather(os.path.join(d, "calibration", "intrinsics.feather"), intr)
            for k, t in enumerate(sweeps):
                pts = lidar_points(100 + k)
                facts["lidar"][f"{log_id}/{t}"] = pts
                write_av2_sweep(os.path.join(d, "sensors", "lidar", f"{t}.feather"), pts)
            _write_av2_map(
                os.path.join(d, "map", f"log_map_archive_{log_id}____{city}_city_00000.json"),
                (ox, oy),
            )
    return facts


def _feather(path: str, columns: dict) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    feather.write_feather(pa.table(columns), path)


def write_av2_sweep(path: str, pts: np.ndarray) -> None:
    """One AV2 LiDAR sweep feather (float16 x, y, z; uint8 intensity) of ``(P, 4)`` points."""
    table = pa.table(
        {
            "x": pa.array(pts[:, 0].astype(np.float16)),
            "y": pa.array(pts[:, 1].astype(np.float16)),
            "z": pa.array(pts[:, 2].astype(np.float16)),
            "intensity": pa.array(pts[:, 3].astype(np.uint8)),
            "laser_number": pa.array(np.zeros(len(pts), np.uint8)),
            "offset_ns": pa.array(np.zeros(len(pts), np.uint32)),
        }
    )
    os.makedirs(os.path.dirname(path), exist_ok=True)
    feather.write_feather(table, path)


def _write_av2_map(path: str, origin=(0.0, 0.0)) -> None:
    ox, oy = origin
    areas = {}
    polys = drivable_polygons()
    for i, (shell, _holes) in enumerate(polys):  # AV2 areas have no holes
        if i == len(polys) - 1:  # the plaza as two areas around the hole's column
            x0, y0, x1, y1 = PLAZA
            hx0, _, hx1, _ = HOLE
            parts = [
                [(x0, y0), (hx0, y0), (hx0, y1), (x0, y1)],
                [(hx1, y0), (x1, y0), (x1, y1), (hx1, y1)],
            ]
        else:
            parts = [shell]
        for ring in parts:
            aid = len(areas) + 1
            areas[str(aid)] = {
                "id": aid,
                "area_boundary": [{"x": x + ox, "y": y + oy, "z": 0.0} for x, y in ring],
            }
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"drivable_areas": areas, "lane_segments": {}, "pedestrian_crossings": {}}, f)
