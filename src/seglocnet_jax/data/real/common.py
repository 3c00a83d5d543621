"""What the real-data readers (nuScenes, Argoverse 2) share: the reader protocol, the frame
index entry, file access with errors that name the file, and camera/pose arithmetic.

Readers parse the datasets' documented on-disk formats directly (JSON tables, feather files,
``.pcd.bin``, JPEG) with json / pyarrow / numpy / Pillow / shapely. The devkits are not used:
nuscenes-devkit 1.2 pins numpy<2 (jax 0.10 needs numpy>=2) and av2 pulls torch, so neither
installs beside jax without skipping pins (``pip check`` would fail in CI).

Frames: the world frame of a city is the dataset's own map frame (nuScenes: map x east / y north
from the map's south-west origin; Argoverse: the city frame, UTM minus a city origin). The ego
frame is x forward, y left, z up, origin on the ground (``schema``): a dataset whose ego origin
sits above the ground (AV2: the rear-axle centre, ~0.33 m up) is lifted by its reader's
``ego_height_m`` in :func:`frame_sample`, LiDAR and camera mounts alike. Cameras are OpenCV
(x right, y down, z forward) pinhole cameras; a radially distorted image is remapped to the
pinhole model of its own intrinsics matrix (:func:`undistort_radial`).

Splits: a scene / log belongs to one split; :func:`check_disjoint_groups` makes a group in two
splits an error naming it and both splits.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Iterable, Mapping
from typing import Protocol

import numpy as np
from PIL import Image
from scipy import ndimage

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
      sequence_id: the record's ``sequence_id`` (nuScenes scene name, AV2 log id).
      frame_index: the frame's position in its sequence (0-based, consecutive over the frames
        the reader lists).
      timestamp: seconds on the dataset's clock (nuScenes sample time, AV2 sweep time).
      lighting: ``schema.LIGHTINGS``: nuScenes "night" or "day" from the scene description,
        AV2 "unknown".
    """

    key: str
    city: str
    pose: np.ndarray
    group: str
    sample_id: str
    sequence_id: str
    frame_index: int
    timestamp: float
    lighting: str = "unknown"


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


def radial_distort(xy: np.ndarray, coeffs) -> np.ndarray:
    """The radial distortion model of AV2's ``intrinsics.feather`` (OpenCV / Brown-Conrady
    with the tangential terms zero): ``(..., 2)`` undistorted normalized image coordinates
    ``(x, y) = (X / Z, Y / Z)`` to distorted ones, ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6)``
    with ``r^2 = x^2 + y^2``. Pixels are then ``u = fx x_d + cx``, ``v = fy y_d + cy``.
    """
    xy = np.asarray(xy, np.float64)
    k1, k2, k3 = (float(c) for c in coeffs)
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    return xy * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))


def undistort_radial(image: np.ndarray, intrinsics, coeffs) -> np.ndarray:
    """Remaps an ``(H, W, 3)`` uint8 image taken through :func:`radial_distort` with
    ``(3, 3)`` ``intrinsics`` to the pinhole camera with the same intrinsics matrix.

    Each output pixel centre ``(u, v)`` is turned into its pinhole ray, distorted, and sampled
    bilinearly (``scipy.ndimage.map_coordinates``, vectorized; no OpenCV dependency) from the
    input; samples outside the input are black. Keeping the matrix means the stored intrinsics
    describe the output exactly; with barrel distortion (``k1 < 0``, AV2) the output covers
    the input's central part, so a few degrees of the field of view at the edges are cropped.
    30-60 ms per 320x800 camera on one core (the sampling map is cached per calibration).
    """
    k = np.asarray(intrinsics, np.float64).reshape(3, 3)
    h, w = image.shape[:2]
    key = (h, w, *(float(k[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))))
    rows, cols = _undistort_map(key, tuple(float(c) for c in coeffs))
    out = np.empty((h, w, image.shape[2]), np.float32)
    for c in range(image.shape[2]):
        out[..., c] = ndimage.map_coordinates(
            image[..., c], (rows, cols), output=np.float32, order=1, mode="constant", cval=0.0
        )
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=16)
def _undistort_map(key: tuple, coeffs: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Input ``(rows, cols)`` (each ``(H, W)`` float32) sampled by each output pixel centre."""
    h, w, fx, fy, cx, cy = key
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = radial_distort(np.stack([(u - cx) / fx, (v - cy) / fy], axis=-1), coeffs)  # (H, W, 2)
    rows = (fy * xy[..., 1] + cy).astype(np.float32)
    cols = (fx * xy[..., 0] + cx).astype(np.float32)
    rows.setflags(write=False)
    cols.setflags(write=False)
    return rows, cols


def camera_image(path, intrinsics, size: tuple[int, int], distortion=None):
    """A camera's stored image and intrinsics: read, resized to ``size = (H, W)`` (intrinsics
    scaled, :func:`resize_camera`) and, if ``distortion = (k1, k2, k3)`` is given and non-zero,
    remapped to the pinhole model of the scaled intrinsics (:func:`undistort_radial`).

    Resizing first is exact: the radial model acts on normalized coordinates, which a per-axis
    resize of pixel centres leaves unchanged; and the antialiased resize keeps the remap from
    aliasing at the 2.6x downscale of AV2's 2048 px images.
    """
    image, k = resize_camera(read_rgb(path), intrinsics, size)
    if distortion is not None and np.any(np.asarray(distortion, np.float64) != 0):
        image = undistort_radial(image, k, distortion)
    return image, k


def lift_to_ground(ego_height: float) -> np.ndarray:
    """``(4, 4)`` transform from a dataset's ego frame to the schema's (origin on the ground):
    a translation by ``ego_height`` (m, the dataset's ego origin above the ground) along z."""
    t = np.eye(4)
    t[2, 3] = float(ego_height)
    return t


def frame_sample(
    frame: Frame, views, image_size: tuple[int, int], lidar: np.ndarray, ego_height: float = 0.0
) -> dict:
    """The sample dict (``schema.SAMPLE_KEYS``) of ``frame``.

    Args:
      frame: the frame (``sample_id``, ``city``, ``pose`` and the sequence metadata).
      views: the cameras in output order, each ``(image path, (3, 3) intrinsics in the file's
        pixels, (4, 4) cam_to_ego in the dataset's ego frame, radial distortion (k1, k2, k3)
        to undo or None for a pinhole image)``; an iterable, consumed one camera at a time (so
        a generator may validate a camera before its image is read).
      image_size: ``(H, W)`` stored image size; images are resized and intrinsics scaled.
      lidar: ``(P, 4)`` float32 ``x, y, z, intensity`` in the dataset's ego frame.
      ego_height: height (m) of the dataset's ego origin above the ground. The emitted ego frame
        is the dataset's lifted by it (:func:`lift_to_ground`): LiDAR z and every camera's
        mount z grow by ``ego_height``, so the origin is on the ground as ``schema`` says and
        LiDAR voxel z ranges and the camera position embedding mean the same for every dataset.
        The pose (x, y, yaw) is unchanged.
    """
    lift = lift_to_ground(ego_height)
    images, intrinsics, cam_to_ego = [], [], []
    for path, k, t, distortion in views:
        image, k = camera_image(path, k, image_size, distortion)
        images.append(image)
        intrinsics.append(k)
        cam_to_ego.append((lift @ np.asarray(t, np.float64)).astype(np.float32))
    lidar = np.array(lidar, np.float32, copy=True)
    lidar[:, 2] += np.float32(ego_height)
    return {
        "sample_id": frame.sample_id,
        "city": frame.city,
        "sequence_id": frame.sequence_id,
        "frame_index": np.int64(frame.frame_index),
        "timestamp": np.float64(frame.timestamp),
        "lighting": frame.lighting,
        "pose": np.asarray(frame.pose, np.float64),
        "images": np.stack(images),  # (N, H, W, 3)
        "intrinsics": np.stack(intrinsics),  # (N, 3, 3)
        "cam_to_ego": np.stack(cam_to_ego),  # (N, 4, 4)
        "lidar": lidar,  # (P, 4)
    }


# --------------------------------------------------------------------------- splits


def check_disjoint_groups(groups_by_split: Mapping[str, Iterable[str]], what: str, hint: str = ""):
    """Raises :class:`RealDataError` naming a group (AV2 log, nuScenes scene) that belongs to
    two splits, and both splits; repeats within one split are allowed (a group has many frames).

    A group's frames are strongly correlated, so a group in two splits leaks training frames
    into evaluation. The readers check what they can see alone (AV2: the split directories;
    nuScenes: the split file); a conversion should also check the splits it combines, e.g.
    ``check_disjoint_groups({out: [f.group for f in fr] for out, fr in frames.items()}, ...)``.
    """
    split_of: dict[str, str] = {}
    for split, groups in groups_by_split.items():
        for group in dict.fromkeys(groups):
            other = split_of.setdefault(group, split)
            if other != split:
                raise RealDataError(
                    f"{what} {group!r} is in two splits, {other!r} and {split!r}: it must "
                    f"belong to one split (its frames would leak between them)"
                    f"{'; ' + hint if hint else ''}"
                )


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


def check_ego_height(value, key: str) -> float:
    """Validates an ``ego_height_m`` config value (finite, within 3 m); names ``key``."""
    try:
        h = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be a number of metres, got {value!r}") from None
    if not np.isfinite(h) or abs(h) > 3.0:
        raise ValueError(f"{key} must be a finite height within 3 m of the ground, got {value!r}")
    return h
