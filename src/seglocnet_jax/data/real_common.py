"""What the real-data readers (nuScenes, Argoverse 2) share: the reader protocol, the frame
index entry, file access with errors that name the file, and camera/pose arithmetic.

Readers parse the datasets' documented on-disk formats directly (JSON tables, feather files,
``.pcd.bin``, JPEG) with json / pyarrow / numpy / Pillow / shapely. The devkits are not used:
nuscenes-devkit 1.2 pins numpy<2 (jax 0.10 needs numpy>=2) and av2 pulls torch, so neither
installs beside jax without skipping pins (``pip check`` would fail in CI).

Frames: the world frame of a city is the dataset's own map frame (nuScenes: map x east / y north
from the map's south-west origin; Argoverse: the city frame, UTM minus a city origin). The ego
frame is x forward, y left, z up; cameras are OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Protocol

import numpy as np
from PIL import Image

from seglocnet_jax import geometry


class RealDataError(ValueError):
    """Missing or malformed dataset content; the message names the file, table, record or key."""


@dataclasses.dataclass(frozen=True)
class Frame:
    """One frame of a real dataset before its sensors are loaded (cheap to list).

    Attributes:
      key: reader-specific locator (nuScenes sample token, ``"<log_id>/<lidar timestamp ns>"``).
      city: city key of the world frame (``"boston-seaport"``, ``"MIA"``, ...).
      pose: ``(3,)`` world x, y (m) and yaw (rad, CCW from east) of the ego at the LiDAR time.
      group: scene / log the frame belongs to (for reports and splits).
      sample_id: the record's ``sample_id`` (unique within the dataset, stable).
    """

    key: str
    city: str
    pose: np.ndarray
    group: str
    sample_id: str


class RealReader(Protocol):
    """What conversion needs from a dataset reader (see ``real_convert.convert``)."""

    name: str  # dataset key, e.g. "nuscenes", "av2"

    def frames(self, split: str) -> list[Frame]:
        """The frames of a split, in a stable order."""

    def load(self, frame: Frame) -> dict:
        """The sample dict (``schema.SAMPLE_KEYS``) of a frame."""

    def drivable(self, city: str):
        """The city's HD drivable area, a shapely (Multi)Polygon in world metres."""

    def projection(self, city: str):
        """How OSM is projected into the city's world frame (``maps.projection.Projection``)."""

    def identity(self) -> dict:
        """The JSON-able config that defines the converted records (resume check)."""


# --------------------------------------------------------------------------- files


def require_file(path: str | os.PathLike, what: str) -> str:
    """``path`` as str if it is a file, else :class:`RealDataError` naming it and ``what``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise RealDataError(f"{path}: missing {what}")
    return path


def read_json(path: str | os.PathLike, what: str):
    """Parsed JSON of ``path``; a missing or malformed file raises naming it."""
    path = require_file(path, what)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise RealDataError(f"{path}: unreadable {what} ({err})") from err


def field(record: dict, key: str, where: str):
    """``record[key]`` or :class:`RealDataError` naming ``where`` and the key."""
    try:
        return record[key]
    except (KeyError, TypeError):
        raise RealDataError(f"{where}: missing key {key!r}") from None


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """An image file as ``(H, W, 3)`` uint8 RGB."""
    path = require_file(path, "camera image")
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except OSError as err:
        raise RealDataError(f"{path}: unreadable camera image ({err})") from err


# --------------------------------------------------------------------------- cameras


def resize_camera(image: np.ndarray, intrinsics, size: tuple[int, int]):
    """Resizes an image to ``size = (H, W)`` and scales its intrinsics to match.

    Intrinsics follow the OpenCV convention (integer pixel coordinates are pixel centres), so
    with scales ``s = new / old`` per axis: ``f' = s f`` and ``c' = s (c + 0.5) - 0.5``.

    Returns:
      ``(H, W, 3)`` uint8 image and ``(3, 3)`` float32 intrinsics.
    """
    h, w = image.shape[:2]
    new_h, new_w = int(size[0]), int(size[1])
    k = np.asarray(intrinsics, np.float64).reshape(3, 3)
    if (h, w) != (new_h, new_w):
        pil = Image.fromarray(image).resize((new_w, new_h), Image.Resampling.BILINEAR)
        image = np.asarray(pil)
    sx, sy = new_w / w, new_h / h
    scale = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])
    return np.ascontiguousarray(image, np.uint8), (scale @ k).astype(np.float32)


def frame_sample(frame: Frame, views, image_size: tuple[int, int], lidar: np.ndarray) -> dict:
    """The sample dict (``schema.SAMPLE_KEYS``) of ``frame``.

    Args:
      frame: the frame (``sample_id``, ``city``, ``pose``).
      views: the cameras in output order, each ``(image path, (3, 3) intrinsics in the file's
        pixels, (4, 4) cam_to_ego)``; an iterable, consumed one camera at a time (so a
        generator may validate a camera before its image is read).
      image_size: ``(H, W)`` stored image size; images are resized and intrinsics scaled.
      lidar: ``(P, 4)`` float32 ego ``x, y, z, intensity``.
    """
    images, intrinsics, cam_to_ego = [], [], []
    for path, k, t in views:
        image, k = resize_camera(read_rgb(path), k, image_size)
        images.append(image)
        intrinsics.append(k)
        cam_to_ego.append(np.asarray(t, np.float32))
    return {
        "sample_id": frame.sample_id,
        "city": frame.city,
        "pose": np.asarray(frame.pose, np.float64),
        "images": np.stack(images),  # (N, H, W, 3)
        "intrinsics": np.stack(intrinsics),  # (N, 3, 3)
        "cam_to_ego": np.stack(cam_to_ego),  # (N, 4, 4)
        "lidar": lidar,  # (P, 4)
    }


# --------------------------------------------------------------------------- poses


def quat_to_matrix(qw, qx, qy, qz) -> np.ndarray:
    """Rotation ``(3, 3)`` of a unit quaternion (scalar first, Hamilton, as both datasets)."""
    q = np.array([qw, qx, qy, qz], np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise RealDataError(f"quaternion {q.tolist()} is not a rotation")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def se3(quat_wxyz, translation) -> np.ndarray:
    """``(4, 4)`` transform from a ``(w, x, y, z)`` quaternion and a ``(3,)`` translation."""
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(*quat_wxyz)
    t[:3, 3] = np.asarray(translation, np.float64).reshape(3)
    return t


def invert_se3(t: np.ndarray) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` transform."""
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def pose_of(world_from_ego: np.ndarray) -> np.ndarray:
    """``(3,)`` world ``(x, y, yaw)`` of a world-from-ego transform (:mod:`geometry` owns it)."""
    return geometry.pose_from_matrix(world_from_ego)


def points_to_ego(
    xyz: np.ndarray, intensity: np.ndarray, ego_from_sensor: np.ndarray, intensity_max: float
) -> np.ndarray:
    """LiDAR ``(n, 3)`` sensor-frame points to ``(n, 4)`` float32 ego ``x, y, z, intensity``.

    ``intensity`` is divided by ``intensity_max`` and clipped to ``[0, 1]``; non-finite points
    are dropped.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    ego = xyz @ ego_from_sensor[:3, :3].T + ego_from_sensor[:3, 3]  # (n, 3)
    inten = np.clip(np.asarray(intensity, np.float64).reshape(-1) / intensity_max, 0.0, 1.0)
    out = np.concatenate([ego, inten[:, None]], axis=1).astype(np.float32)  # (n, 4)
    return out[np.all(np.isfinite(out), axis=1)]


def check_image_size(size, key: str) -> tuple[int, int]:
    """Validates an ``(H, W)`` config value; names ``key`` in the error."""
    try:
        h, w = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be (H, W) integers, got {size!r}") from None
    if h < 8 or w < 8:
        raise ValueError(f"{key} must be at least 8x8 pixels, got {size!r}")
    return h, w
