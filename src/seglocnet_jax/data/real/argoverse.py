"""Argoverse 2 sensor-dataset reader: LiDAR-timed frames as sample dicts, drivable areas, city
frames.

Reads the documented on-disk format directly (see ``real_common`` for why not the av2 API)::

    {dataroot}/{split}/{log_id}/city_SE3_egovehicle.feather      # timestamp_ns, qw..qz, tx_m..tz_m
    {dataroot}/{split}/{log_id}/calibration/intrinsics.feather   # sensor_name, fx_px, ..., k1..k3
    {dataroot}/{split}/{log_id}/calibration/egovehicle_SE3_sensor.feather
    {dataroot}/{split}/{log_id}/sensors/lidar/{timestamp_ns}.feather   # x, y, z, intensity (ego)
    {dataroot}/{split}/{log_id}/sensors/cameras/{camera}/{timestamp_ns}.jpg
    {dataroot}/{split}/{log_id}/map/log_map_archive_{log_id}____{CITY}_city_{n}.json

A frame is every ``frame_stride``-th LiDAR sweep (10 Hz; stride 5 gives nuScenes' 2 Hz); its
sequence is the log (``sequence_id`` = log id, ``frame_index`` = its index among the log's kept
frames, consecutive; ``timestamp`` = the sweep's ``timestamp_ns`` / 1e9, so a skipped sweep shows
as a longer gap); each
camera contributes its image nearest in time within ``max_sync_ms`` (default 25 ms: the av2
``SensorDataloader`` matches a sweep to the nearest image within half the 20 Hz camera period)
and, like nuScenes, ``cam_to_ego`` maps it into the ego frame at the LiDAR time. Poses are in the
city frame (UTM of the city's zone minus the city origin: grid north, see datasets.md). A log id
found in two split directories is an error naming it and both splits.

Ego frame: AV2's egovehicle origin is the centre of the rear axle, ~0.33 m above the ground
(Argoverse maintainers; ground points sit at z ~ -0.34 m in real sweeps). The reader lifts the
frame it emits by ``ego_height_m`` (LiDAR z and camera mounts alike) so that its origin is on
the ground as ``schema`` says and as nuScenes' is (``real_common.frame_sample``).

Cameras: AV2 has 7 ring cameras; ``cameras`` chooses which and in what order. The default keeps
all 7 (full 360 degree coverage); for a model that expects nuScenes' 6 cameras, drop
``ring_front_center`` (the portrait one; its neighbours still cover the front). Images of every
camera are resized to ``image_size`` with intrinsics scaled per axis, so the portrait front
camera is stretched but geometrically exact.

Distortion: ``intrinsics.feather`` also lists radial coefficients ``k1, k2, k3`` (OpenCV's
radial model with p1 = p2 = 0, ``real_common.radial_distort``; k1 ~ -0.25). The published images
are already undistorted ("All camera imagery is provided in an undistorted format", AV2 user
guide, sensor suite; the av2 API projects with ``K`` alone) and the coefficients describe the
original lens, so by default they are not applied: undistorting such an image again would move
its edges by 15-48 px in a 320x800 image. ``undistort=true`` is for imagery that still
has the lens distortion (e.g. raw frames re-exported in this layout): each image is remapped to
the pinhole model of its stored (resized) intrinsics.

Argoverse 1.1 (the paper's data: 113 logs in MIA and PIT) has no API installable beside jax; AV2
stands in with the same cities and origins. A 1.1 reader only needs to implement
``real_common.RealReader`` (frames / load / drivable / projection / identity).
"""

from __future__ import annotations

import dataclasses
import glob
import os
import warnings

import numpy as np
import pyarrow.feather as feather
import shapely
from shapely.geometry import Polygon

from seglocnet_jax.data.real import common as rc
from seglocnet_jax.data.schema import EGO_HEIGHT_M
from seglocnet_jax.maps.projection import Projection

RING_CAMERAS = (
    "ring_front_center",
    "ring_front_right",
    "ring_side_right",
    "ring_rear_right",
    "ring_rear_left",
    "ring_side_left",
    "ring_front_left",
)
# City frame = UTM (zone, north) minus the projected origin (lat, lon) (datasets.md).
CITY_FRAMES = {
    "ATX": (14, (30.27464237939507, -97.7404457407424)),
    "DTW": (17, (42.29993066912924, -83.17555750783717)),
    "MIA": (17, (25.77452579915163, -80.19656914449405)),
    "PAO": (10, (37.416065, -122.13571963362166)),
    "PIT": (17, (40.44177902989321, -80.01294377242584)),
    "WDC": (18, (38.889377, -77.0355047439081)),
}
POSE_COLUMNS = ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
DISTORTION_COLUMNS = ("k1", "k2", "k3")


@dataclasses.dataclass(frozen=True)
class ArgoverseConfig:
    """The ``dataset`` config of Argoverse 2 (``argo_mia`` / ``argo_pit`` presets).

    Attributes:
      dataroot: directory holding the AV2 split directories (``train/``, ``val/``, ``test/``).
      cities: keep only logs of these cities (``("MIA",)``, ``("PIT",)``); None keeps all.
      image_size: ``(H, W)`` stored image size; intrinsics are scaled to it.
      cameras: ring cameras in output order (see the module docstring for 6 vs 7).
      frame_stride: keep every n-th LiDAR sweep of a log.
      max_sync_ms: largest camera / pose time offset from the sweep accepted, milliseconds
        (AV2's own: half the 20 Hz camera period, 25 ms).
      ego_height_m: height of AV2's ego origin (rear-axle centre) above the ground, metres;
        the emitted ego frame is lifted by it so that its origin is on the ground.
      undistort: remap images through the ``k1, k2, k3`` radial model to a pinhole image. Off:
        the published AV2 images are already undistorted (module docstring).
    """

    dataroot: str = "data/av2/sensor"
    cities: tuple[str, ...] | None = None
    image_size: tuple[int, int] = (320, 800)
    cameras: tuple[str, ...] = RING_CAMERAS
    frame_stride: int = 5
    max_sync_ms: float = 25.0
    ego_height_m: float = EGO_HEIGHT_M["av2"]
    undistort: bool = False

    def __post_init__(self):
        rc.check_image_size(self.image_size, "dataset.reader.image_size")
        rc.check_ego_height(self.ego_height_m, "dataset.reader.ego_height_m")
        if not self.cameras:
            raise ValueError("dataset.reader.cameras must name at least one ring camera")
        if self.frame_stride < 1 or self.max_sync_ms <= 0:
            raise ValueError(
                f"dataset.reader.frame_stride must be >= 1 and max_sync_ms > 0, "
                f"got {self.frame_stride}, {self.max_sync_ms}"
            )
        for city in self.cities or ():
            if city not in CITY_FRAMES:
                raise ValueError(
                    f"dataset.reader.cities: unknown city {city!r}; have {sorted(CITY_FRAMES)}"
                )


def _read_feather(path: str, columns, what: str) -> dict:
    rc.require_file(path, what)
    try:
        table = feather.read_table(path)
    except Exception as err:  # pyarrow raises several types for a damaged file
        raise rc.RealDataError(f"{path}: unreadable {what} ({err})") from err
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise rc.RealDataError(f"{path}: {what} lacks columns {missing} (has {table.column_names})")
    return {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.column_names}


def _timestamps(directory: str, suffix: str) -> np.ndarray:
    names = [os.path.basename(p)[: -len(suffix)] for p in glob.glob(f"{directory}/*{suffix}")]
    return np.array(sorted(int(n) for n in names if n.isdigit()), np.int64)


def log_city(log_dir: str) -> tuple[str, str]:
    """``(map path, city)`` of a log, from ``map/log_map_archive_<log>____<CITY>_city_<n>.json``
    (or the map's ``city_name`` key)."""
    maps = sorted(glob.glob(os.path.join(log_dir, "map", "log_map_archive_*.json")))
    if not maps:
        raise rc.RealDataError(f"{log_dir}/map/log_map_archive_*.json: missing log map")
    stem = os.path.basename(maps[0])[: -len(".json")]
    city = stem.split("____")[1].split("_")[0] if "____" in stem else None
    if city is None:
        city = rc.read_json(maps[0], "AV2 log map").get("city_name")
    if city not in CITY_FRAMES:
        raise rc.RealDataError(
            f"{maps[0]}: city {city!r} not in {sorted(CITY_FRAMES)} "
            "(expected log_map_archive_<log>____<CITY>_city_<n>.json)"
        )
    return maps[0], city


class _Log:
    """Calibration, poses and file timestamps of one log (loaded once, on demand)."""

    def __init__(self, log_dir: str, cameras, undistort: bool = False):
        self.dir = log_dir
        self.id = os.path.basename(log_dir)
        self.map_path, self.city = log_city(log_dir)
        poses = _read_feather(
            os.path.join(log_dir, "city_SE3_egovehicle.feather"),
            POSE_COLUMNS,
            "AV2 city_SE3_egovehicle poses",
        )
        order = np.argsort(poses["timestamp_ns"])
        self.pose_t = poses["timestamp_ns"].astype(np.int64)[order]
        self.pose_q = np.stack([poses[c] for c in ("qw", "qx", "qy", "qz")], 1)[order]
        self.pose_xyz = np.stack([poses[c] for c in ("tx_m", "ty_m", "tz_m")], 1)[order]
        calib_dir = os.path.join(log_dir, "calibration")
        ext = _read_feather(
            os.path.join(calib_dir, "egovehicle_SE3_sensor.feather"),
            ("sensor_name", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"),
            "AV2 egovehicle_SE3_sensor calibration",
        )
        intr = _read_feather(
            os.path.join(calib_dir, "intrinsics.feather"),
            ("sensor_name", "fx_px", "fy_px", "cx_px", "cy_px")
            + (DISTORTION_COLUMNS if undistort else ()),
            "AV2 camera intrinsics",
        )
        self.ego_from_cam, self.intrinsics, self.distortion, self.cam_t = {}, {}, {}, {}
        for cam in cameras:
            i = np.flatnonzero(ext["sensor_name"] == cam)
            j = np.flatnonzero(intr["sensor_name"] == cam)
            if not len(i) or not len(j):
                raise rc.RealDataError(f"{calib_dir}: no calibration for camera {cam!r}")
            i, j = int(i[0]), int(j[0])
            self.ego_from_cam[cam] = rc.se3(
                [ext[c][i] for c in ("qw", "qx", "qy", "qz")],
                [ext[c][i] for c in ("tx_m", "ty_m", "tz_m")],
            )
            fx, fy, cx, cy = (float(intr[c][j]) for c in ("fx_px", "fy_px", "cx_px", "cy_px"))
            self.intrinsics[cam] = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
            if undistort:
                dist = tuple(float(intr[c][j]) for c in DISTORTION_COLUMNS)
                if not np.all(np.isfinite(dist)):
                    raise rc.RealDataError(
                        f"{calib_dir}/intrinsics.feather: {cam} has non-finite k1..k3 {dist}"
                    )
                self.distortion[cam] = dist
            else:
                self.distortion[cam] = None  # published images are undistorted
            self.cam_t[cam] = _timestamps(os.path.join(log_dir, "sensors", "cameras", cam), ".jpg")
        self.lidar_t = _timestamps(os.path.join(log_dir, "sensors", "lidar"), ".feather")

    def nearest(self, times: np.ndarray, t: int, max_ns: float, what: str) -> int:
        """Index of the entry of sorted ``times`` nearest to ``t``; raises if none is close."""
        if not len(times):
            raise rc.RealDataError(f"{self.dir}: no {what}")
        i = int(np.clip(np.searchsorted(times, t), 1, len(times) - 1)) if len(times) > 1 else 0
        if len(times) > 1 and abs(times[i - 1] - t) <= abs(times[i] - t):
            i -= 1
        if abs(int(times[i]) - t) > max_ns:
            raise rc.RealDataError(
                f"{self.dir}: no {what} within {max_ns / 1e6:g} ms of "
                f"{t} ns (nearest {int(times[i])})"
            )
        return i

    def world_from_ego(self, t: int, max_ns: float) -> np.ndarray:
        i = self.nearest(self.pose_t, t, max_ns, "city_SE3_egovehicle pose")
        return rc.se3(self.pose_q[i], self.pose_xyz[i])


class ArgoverseReader:
    """LiDAR-timed frames of the AV2 sensor dataset (:class:`real_common.RealReader`)."""

    name = "av2"

    def __init__(self, cfg: ArgoverseConfig):
        self.cfg = cfg
        self._logs: dict[str, _Log] = {}
        self._max_ns = cfg.max_sync_ms * 1e6

    def identity(self) -> dict:
        d = dataclasses.asdict(self.cfg)
        d.pop("dataroot")
        for key in ("image_size", "cameras", "cities"):
            d[key] = None if d[key] is None else list(d[key])
        return {"dataset": self.name, **d}

    def _log(self, log_dir: str) -> _Log:
        if log_dir not in self._logs:
            self._logs[log_dir] = _Log(log_dir, self.cfg.cameras, self.cfg.undistort)
        return self._logs[log_dir]

    def logs(self, split: str) -> list[_Log]:
        """Logs of an AV2 split directory, filtered by ``cities``, sorted by log id.

        A kept log whose id is also a log directory of another split directory under
        ``dataroot`` is an error naming it and both splits."""
        split_dir = os.path.join(self.cfg.dataroot, split)
        if not os.path.isdir(split_dir):
            raise rc.RealDataError(
                f"{split_dir}: missing AV2 split directory "
                "(dataset.reader.dataroot / dataset.convert.splits)"
            )
        dirs = sorted(d for d in glob.glob(os.path.join(split_dir, "*")) if os.path.isdir(d))
        keep = [d for d in dirs if self.cfg.cities is None or log_city(d)[1] in self.cfg.cities]
        if not keep:
            raise rc.RealDataError(
                f"{split_dir}: no logs of cities {self.cfg.cities} among {len(dirs)} logs"
            )
        self._check_other_splits(split, [os.path.basename(d) for d in keep])
        return [self._log(d) for d in keep]

    def _check_other_splits(self, split: str, log_ids: list[str]) -> None:
        ids, others = set(log_ids), {}
        for entry in sorted(os.scandir(self.cfg.dataroot), key=lambda e: e.name):
            if entry.is_dir() and entry.name != split:
                others[entry.name] = [
                    e.name for e in os.scandir(entry.path) if e.is_dir() and e.name in ids
                ]
        rc.check_disjoint_groups(
            {split: log_ids, **others},
            "AV2 log",
            hint=f"remove it from one of the split directories under {self.cfg.dataroot}",
        )

    def frames(self, split: str) -> list[rc.Frame]:
        """Every ``frame_stride``-th sweep of the split's logs that has every camera and a pose
        within ``max_sync_ms``; sweeps without (at a log's ends) are skipped with a warning."""
        out, skipped = [], []
        for log in self.logs(split):
            if not len(log.lidar_t):
                raise rc.RealDataError(f"{log.dir}/sensors/lidar: no LiDAR sweeps (*.feather)")
            index = 0  # position among the log's kept frames
            for t in log.lidar_t[:: self.cfg.frame_stride]:
                try:
                    for cam in self.cfg.cameras:
                        log.nearest(log.cam_t[cam], int(t), self._max_ns, f"{cam} image")
                    pose = rc.pose_of(log.world_from_ego(int(t), self._max_ns))
                except rc.RealDataError as err:
                    skipped.append(str(err))
                    continue
                out.append(
                    rc.Frame(
                        key=f"{log.dir}|{int(t)}",
                        city=log.city,
                        pose=pose,
                        group=log.id,
                        sample_id=f"{log.id}/{int(t)}",
                        sequence_id=log.id,
                        frame_index=index,
                        timestamp=int(t) / 1e9,  # nanoseconds
                    )
                )
                index += 1
        if skipped:
            warnings.warn(
                f"AV2 {split}: skipped {len(skipped)} sweeps without every camera / "
                f"a pose within {self.cfg.max_sync_ms:g} ms, e.g. {skipped[0]}",
                stacklevel=2,
            )
        return out

    def load(self, frame: rc.Frame) -> dict:
        log_dir, t = frame.key.rsplit("|", 1)
        log, t = self._log(log_dir), int(t)
        path = os.path.join(log_dir, "sensors", "lidar", f"{t}.feather")
        sweep = _read_feather(path, ("x", "y", "z", "intensity"), "AV2 LiDAR sweep")
        xyz = np.stack([sweep[c] for c in ("x", "y", "z")], axis=1)
        lidar = rc.points_to_ego(xyz, sweep["intensity"], np.eye(4), 255.0)  # already ego frame
        ego_from_world = rc.invert_se3(log.world_from_ego(t, self._max_ns))

        def views():
            for cam in self.cfg.cameras:
                i = log.nearest(log.cam_t[cam], t, self._max_ns, f"{cam} image")
                tc = int(log.cam_t[cam][i])
                path = os.path.join(log_dir, "sensors", "cameras", cam, f"{tc}.jpg")
                # The ego frame at the LiDAR time, through the world, from the camera's time.
                t_cam = ego_from_world @ log.world_from_ego(tc, self._max_ns)
                yield path, log.intrinsics[cam], t_cam @ log.ego_from_cam[cam], log.distortion[cam]

        return rc.frame_sample(
            frame, views(), self.cfg.image_size, lidar, ego_height=self.cfg.ego_height_m
        )

    def drivable(self, city: str):
        """Union of the drivable areas of every loaded log in ``city`` (city-frame metres).

        Call after :meth:`frames` / :meth:`logs` of the splits to convert: AV2 maps are per log.
        """
        parts = []
        for log in sorted(self._logs.values(), key=lambda g: g.id):
            if log.city != city:
                continue
            data = rc.read_json(log.map_path, "AV2 log map")
            areas = rc.field(data, "drivable_areas", log.map_path)
            for area in areas.values() if isinstance(areas, dict) else areas:
                pts = rc.field(area, "area_boundary", f"{log.map_path} drivable area")
                ring = [(float(p["x"]), float(p["y"])) for p in pts]
                if len(ring) >= 3:
                    parts.append(shapely.make_valid(Polygon(ring)))
        if not parts:
            raise rc.RealDataError(f"no AV2 drivable areas for city {city!r} in the loaded logs")
        return shapely.unary_union(parts)

    def projection(self, city: str) -> Projection:
        """The city frame: UTM of the city's zone minus the projected city origin."""
        if city not in CITY_FRAMES:
            raise rc.RealDataError(f"no AV2 city frame for {city!r}")
        zone, origin = CITY_FRAMES[city]
        return Projection.utm(zone, origin_latlon=origin)
