"""nuScenes reader: keyframe samples as sample dicts, drivable area, map frames, scene splits.

Reads the documented on-disk format directly (see ``real_common`` for why not the devkit)::

    {dataroot}/{version}/{scene,log,sample,sample_data,calibrated_sensor,sensor,ego_pose}.json
    {dataroot}/samples/LIDAR_TOP/*.pcd.bin         # float32 x 5: x, y, z, intensity, ring
    {dataroot}/samples/CAM_*/*.jpg
    {dataroot}/maps/expansion/{location}.json      # map expansion: node / polygon / drivable_area

A frame is a keyframe ``sample``; its pose is the ``ego_pose`` of its LIDAR_TOP sample_data, in
the map frame of the log's location (x east, y north, metres from the map's south-west origin).
Its sequence is the scene (``sequence_id`` = scene name, ``frame_index`` = the keyframe's index in
the scene's sample chain, ``timestamp`` = the sample's timestamp in microseconds / 1e6). Its
``lighting`` is "night" when the scene's description says night (as nuScenes' night subsets are
drawn), else "day".
LiDAR points go to that ego frame through LIDAR_TOP's ``calibrated_sensor``. Cameras fire up to
~40 ms apart from the LiDAR; ``cam_to_ego`` therefore maps each camera into the ego frame *at
the LiDAR time* (camera -> ego at camera time -> map -> ego at LiDAR time), so the 6 cameras and
the point cloud share one frame while the vehicle moves. The camera / LiDAR association is the
dataset's own (the keyframe ``sample_data`` of each channel), so no sync tolerance applies.

Cameras: the published images are already undistorted and rectified (nuscenes-devkit; the
tables carry no distortion coefficients), so ``camera_intrinsic`` is an exact pinhole model and
images are only resized. Ego frame: nuScenes' ego origin is the rear-axle centre projected onto
the ground, already the schema's; ``ego_height_m`` (default 0) exists so that both readers
record and apply their ego-to-ground height the same way (``real_common.frame_sample``).

Splits: a scene that a ``split_file`` lists in two splits is an error naming it and both splits.
The official lists are disjoint except ``mini_*``, which lie inside train / val; a conversion
that combines overlapping lists must check its splits (``real_common.check_disjoint_groups``).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import shapely
from shapely.geometry import Polygon

from seglocnet_jax.data.real import common as rc
from seglocnet_jax.data.schema import EGO_HEIGHT_M
from seglocnet_jax.geometry import CAMERA_NAMES
from seglocnet_jax.maps.projection import Projection

LIDAR = "LIDAR_TOP"
TABLES = ("scene", "log", "sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose")
# South-west reference corner (lat, lon) of each map frame (nuscenes-devkit, datasets.md).
MAP_ORIGINS = {
    "boston-seaport": (42.336849169438615, -71.05785369873047),
    "singapore-onenorth": (1.2882100868743724, 103.78475189208984),
    "singapore-hollandvillage": (1.2993652317780957, 103.78217697143555),
    "singapore-queenstown": (1.2782562240223188, 103.76741409301758),
}
# Official scene splits (nuscenes-devkit utils/splits.py): scene-NNNN number ranges.
# train 700 scenes (28,130 samples), val 150 (6,019), test 150 (6,008), mini 8 + 2.
OFFICIAL_SPLITS = {
    "train": "1-2,4-11,19-34,41-76,120-135,138-139,149-152,154-155,157-168,170-185,187-188,"
    "190-196,199-200,202-204,206-214,218-220,222,224-264,283-306,315-318,321,323-324,328,"
    "347-386,388-403,405-408,410-459,461-465,467-469,471-472,474-480,499-502,504-515,517-518,"
    "525-539,541-546,566,568,570-578,580,582-600,639-679,681,683-689,695-698,700-701,703-719,"
    "726-728,730-731,733-741,744,746-747,749-752,757-765,767-769,786-787,789-792,803-806,"
    "808-813,815-817,819-822,847-856,858,860-866,868-873,875-878,880,882-903,945,947,949,"
    "952-953,955-961,975-984,988-992,994-1025,1044-1058,1074-1102,1104-1110",
    "val": "3,12-18,35-36,38-39,92-110,221,268-278,329-332,344-346,519-524,552-565,625-627,"
    "629-630,632-638,770-771,775,777-778,780-784,794-800,802,904-917,919-931,962-963,966-969,"
    "971-972,1059-1073",
    "test": "77-91,111-119,140,142-148,265-266,279-282,307-314,333-343,481-498,547-551,"
    "601-604,606-624,827-831,833-842,844-846,932-933,935-943,1026-1043",
    "mini_train": "61,553,655,757,796,1077,1094,1100",
    "mini_val": "103,916",
}


def official_scenes(split: str) -> list[str]:
    """Scene names (``scene-0001``) of an official nuScenes split."""
    if split not in OFFICIAL_SPLITS:
        raise KeyError(f"no official nuScenes split {split!r}; have {sorted(OFFICIAL_SPLITS)}")
    names = []
    for part in OFFICIAL_SPLITS[split].split(","):
        lo, _, hi = part.partition("-")
        names += [f"scene-{n:04d}" for n in range(int(lo), int(hi or lo) + 1)]
    return names


@dataclasses.dataclass(frozen=True)
class NuScenesConfig:
    """The ``dataset`` config of nuScenes.

    Attributes:
      dataroot: directory holding ``{version}/``, ``samples/`` and ``maps/expansion/``.
      version: table directory, ``v1.0-trainval`` or ``v1.0-mini``.
      image_size: ``(H, W)`` stored image size (paper 320x800); intrinsics are scaled to it.
      cameras: channels in output order (default: the 6 surround cameras).
      split_file: optional JSON ``{split: [scene names]}`` replacing the official lists.
      ego_height_m: height (m) of the ego origin above the ground; nuScenes' is on the ground.
    """

    dataroot: str = "data/nuscenes"
    version: str = "v1.0-trainval"
    image_size: tuple[int, int] = (320, 800)
    cameras: tuple[str, ...] = CAMERA_NAMES
    split_file: str | None = None
    ego_height_m: float = EGO_HEIGHT_M["nuscenes"]

    def __post_init__(self):
        rc.check_image_size(self.image_size, "dataset.reader.image_size")
        rc.check_ego_height(self.ego_height_m, "dataset.reader.ego_height_m")
        if not self.cameras:
            raise ValueError("dataset.reader.cameras must name at least one camera channel")


class NuScenesReader:
    """Keyframe samples of a nuScenes version (:class:`real_common.RealReader`)."""

    name = "nuscenes"

    def __init__(self, cfg: NuScenesConfig):
        self.cfg = cfg
        table_dir = os.path.join(cfg.dataroot, cfg.version)
        if not os.path.isdir(table_dir):
            raise rc.RealDataError(
                f"{table_dir}: missing nuScenes table directory "
                f"(dataset.reader.dataroot / dataset.reader.version)"
            )
        t = {n: self._table(table_dir, n) for n in TABLES}
        self._ego = {r["token"]: r for r in t["ego_pose"]}
        self._sample = {r["token"]: r for r in t["sample"]}
        channel = {r["token"]: rc.field(r, "channel", "sensor.json") for r in t["sensor"]}
        self._calib = {}
        for r in t["calibrated_sensor"]:
            where = f"{table_dir}/calibrated_sensor.json record {r.get('token')!r}"
            self._calib[r["token"]] = dict(
                channel=channel[rc.field(r, "sensor_token", where)],
                ego_from_sensor=rc.se3(
                    rc.field(r, "rotation", where), rc.field(r, "translation", where)
                ),
                intrinsic=r.get("camera_intrinsic") or None,
            )
        self._keyframe = {}  # (sample token, channel) -> sample_data record
        for r in t["sample_data"]:
            if r.get("is_key_frame"):
                calib = self._calib.get(r.get("calibrated_sensor_token"))
                if calib is None:
                    raise rc.RealDataError(
                        f"{table_dir}/sample_data.json record {r.get('token')!r}: unknown "
                        f"calibrated_sensor_token {r.get('calibrated_sensor_token')!r}"
                    )
                self._keyframe[(r["sample_token"], calib["channel"])] = r
        logs = {r["token"]: r for r in t["log"]}
        self._scenes = {}  # scene name -> (record, location)
        for r in t["scene"]:
            location = rc.field(logs[r["log_token"]], "location", f"{table_dir}/log.json")
            if location not in MAP_ORIGINS:
                raise rc.RealDataError(
                    f"{table_dir}/log.json: unknown location {location!r} "
                    f"(have {sorted(MAP_ORIGINS)})"
                )
            self._scenes[r["name"]] = (r, location)
        self._table_dir = table_dir

    @staticmethod
    def _table(table_dir: str, name: str) -> list[dict]:
        rows = rc.read_json(os.path.join(table_dir, f"{name}.json"), f"nuScenes table {name!r}")
        if not isinstance(rows, list):
            raise rc.RealDataError(f"{table_dir}/{name}.json: expected a list of records")
        return rows

    def identity(self) -> dict:
        d = dataclasses.asdict(self.cfg)
        d.pop("dataroot")
        d["image_size"], d["cameras"] = list(d["image_size"]), list(d["cameras"])
        return {"dataset": self.name, **d}

    # ----------------------------------------------------------------------- splits and frames

    def split_scenes(self, split: str) -> list[str]:
        """Scene names of ``split`` present in this version (user file or official lists).

        With ``split_file``, a scene of ``split`` that another split of the file also lists,
        or that ``split`` lists twice, is an error naming it (and both splits)."""
        if self.cfg.split_file:
            table = rc.read_json(self.cfg.split_file, "nuScenes split file")
            if split not in table:
                raise rc.RealDataError(
                    f"{self.cfg.split_file}: no split {split!r} (have {sorted(table)})"
                )
            wanted = list(table[split])
            twice = sorted({s for s in wanted if wanted.count(s) > 1})
            if twice:
                raise rc.RealDataError(
                    f"{self.cfg.split_file}: nuScenes scene {twice[0]!r} is listed twice in "
                    f"split {split!r}"
                )
            others = {k: [s for s in v if s in wanted] for k, v in table.items() if k != split}
            rc.check_disjoint_groups(
                {split: wanted, **others},
                "nuScenes scene",
                hint=f"fix dataset.reader.split_file {self.cfg.split_file}",
            )
        else:
            wanted = official_scenes(split)
        present = [s for s in wanted if s in self._scenes]
        if not present:
            raise rc.RealDataError(
                f"{self._table_dir}: none of the {len(wanted)} scenes of split {split!r} are in "
                f"this version (has {sorted(self._scenes)[:5]}...); for v1.0-mini use "
                "mini_train / mini_val or dataset.split_file"
            )
        return present

    def frames(self, split: str) -> list[rc.Frame]:
        out = []
        for scene in self.split_scenes(split):
            record, location = self._scenes[scene]
            token = record["first_sample_token"]
            description = rc.field(record, "description", f"{self._table_dir}/scene.json")
            lighting = "night" if "night" in str(description).lower() else "day"
            index = 0
            while token:
                if token not in self._sample:
                    raise rc.RealDataError(
                        f"{self._table_dir}/sample.json: scene {scene!r} "
                        f"names missing sample {token!r}"
                    )
                sd = self._sd(token, LIDAR)
                pose = rc.pose_of(self._world_from_ego(sd))
                stamp = rc.field(self._sample[token], "timestamp", f"{self._table_dir}/sample.json")
                out.append(
                    rc.Frame(
                        key=token,
                        city=location,
                        pose=pose,
                        group=scene,
                        sample_id=f"{scene}/{token}",
                        sequence_id=scene,
                        frame_index=index,
                        timestamp=int(stamp) / 1e6,  # microseconds
                        lighting=lighting,
                    )
                )
                token = self._sample[token]["next"]
                index += 1
        return out

    def _sd(self, sample_token: str, channel: str) -> dict:
        try:
            return self._keyframe[(sample_token, channel)]
        except KeyError:
            raise rc.RealDataError(
                f"{self._table_dir}/sample_data.json: sample "
                f"{sample_token!r} has no keyframe {channel}"
            ) from None

    def _world_from_ego(self, sd: dict) -> np.ndarray:
        ego = self._ego.get(sd["ego_pose_token"])
        if ego is None:
            raise rc.RealDataError(
                f"{self._table_dir}/ego_pose.json: missing token "
                f"{sd['ego_pose_token']!r} (sample_data {sd['token']!r})"
            )
        return rc.se3(ego["rotation"], ego["translation"])

    # ----------------------------------------------------------------------- sensors

    def load(self, frame: rc.Frame) -> dict:
        lidar_sd = self._sd(frame.key, LIDAR)
        world_from_ego = self._world_from_ego(lidar_sd)
        ego_from_world = rc.invert_se3(world_from_ego)
        path = os.path.join(self.cfg.dataroot, lidar_sd["filename"])
        raw = np.fromfile(rc.require_file(path, "LiDAR sweep"), dtype=np.float32)
        if raw.size % 5:
            raise rc.RealDataError(
                f"{path}: {raw.size} floats, expected x,y,z,intensity,ring "
                "records (a multiple of 5)"
            )
        raw = raw.reshape(-1, 5)
        calib = self._calib[lidar_sd["calibrated_sensor_token"]]
        lidar = rc.points_to_ego(raw[:, :3], raw[:, 3], calib["ego_from_sensor"], 255.0)

        def views():
            for channel in self.cfg.cameras:
                sd = self._sd(frame.key, channel)
                calib = self._calib[sd["calibrated_sensor_token"]]
                if calib["intrinsic"] is None:
                    raise rc.RealDataError(
                        f"{self._table_dir}/calibrated_sensor.json: {channel} has no "
                        "camera_intrinsic"
                    )
                path = os.path.join(self.cfg.dataroot, sd["filename"])
                t = ego_from_world @ self._world_from_ego(sd) @ calib["ego_from_sensor"]
                yield path, calib["intrinsic"], t, None  # published images are rectified

        return rc.frame_sample(
            frame, views(), self.cfg.image_size, lidar, ego_height=self.cfg.ego_height_m
        )

    # ----------------------------------------------------------------------- maps

    def drivable(self, city: str):
        """Union of the ``drivable_area`` polygons (with holes) of a map, map-frame metres."""
        path = os.path.join(self.cfg.dataroot, "maps", "expansion", f"{city}.json")
        data = rc.read_json(path, "nuScenes map expansion")
        where = path
        nodes = {n["token"]: (n["x"], n["y"]) for n in rc.field(data, "node", where)}
        polygons = {p["token"]: p for p in rc.field(data, "polygon", where)}
        parts = []
        for area in rc.field(data, "drivable_area", where):
            for token in rc.field(area, "polygon_tokens", f"{where} drivable_area"):
                if token not in polygons:
                    raise rc.RealDataError(
                        f"{where}: drivable_area {area.get('token')!r} "
                        f"names missing polygon {token!r}"
                    )
                parts.append(_polygon(polygons[token], nodes, where))
        if not parts:
            raise rc.RealDataError(f"{where}: no drivable_area polygons")
        return shapely.unary_union([shapely.make_valid(p) for p in parts])

    def projection(self, city: str) -> Projection:
        """The map frame: the local tangent plane at the map's south-west origin."""
        if city not in MAP_ORIGINS:
            raise rc.RealDataError(f"no nuScenes map origin for {city!r}")
        return Projection.topocentric(*MAP_ORIGINS[city])


def _polygon(record: dict, nodes: dict, where: str) -> Polygon:
    def ring(tokens):
        try:
            return [nodes[t] for t in tokens]
        except KeyError as err:
            raise rc.RealDataError(
                f"{where}: polygon {record.get('token')!r} names missing node {err.args[0]!r}"
            ) from None

    shell = ring(rc.field(record, "exterior_node_tokens", f"{where} polygon"))
    holes = [ring(h["node_tokens"]) for h in record.get("holes", []) if h.get("node_tokens")]
    return Polygon(shell, holes)
