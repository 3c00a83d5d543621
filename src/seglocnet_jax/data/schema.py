"""The record and batch schema shared by the simulator, the dataset converters, the offline
pipeline, the loader and the model.

A *sample* is one frame as a producer (simulator or converter) emits it, before any map variant
is applied. Producers return a plain ``dict`` with exactly ``SAMPLE_KEYS``; :func:`check_sample`
validates one and names the offending key. A *batch* is what the loader yields and the jitted
model consumes: fixed shapes, NumPy arrays, keys ``BATCH_KEYS``; its ``BATCH_METADATA_KEYS``
stay on the host (never placed on devices, never passed into jit).

Sequences: every sample belongs to a sequence (``sequence_id``: a simulated drive or route, a
nuScenes scene, an AV2 log) at position ``frame_index`` (0-based; consecutive 0..n-1 within a
simulated drive, the keyframe / kept sweep's index within a scene / log) and time ``timestamp``
(seconds; the dataset's clock for real data, distance along the route / the nominal speed for
the simulator). A split's frames of one sequence are stored in ``frame_index`` order.

Frames: world = the city's local metric ENU frame (see :mod:`seglocnet_jax.geometry`); ego =
x forward, y left, z up, origin on the ground below the vehicle reference point (z = 0 is the
road surface under the vehicle, so LiDAR voxel z ranges and the camera position embedding mean
the same for every producer); camera = OpenCV (x right, y down, z forward) pinhole, with
``intrinsics`` exact for the stored image (distorted images are remapped first).
``cam_to_ego`` maps homogeneous camera points to the ego frame.

A dataset whose own ego origin is not on the ground is shifted by its producer, LiDAR points and
camera mounts alike: ``EGO_HEIGHT_M`` lists the documented heights of each dataset's ego origin
above the ground (the readers' ``ego_height_m`` defaults).
"""

from __future__ import annotations

import numpy as np

# Height (m) of each source's own ego origin above the ground; producers lift their ego frame by
# it. Simulator: on the ground by construction. nuScenes: the rear-axle centre projected onto the
# ground (nuscenes-devkit). AV2: the rear-axle centre, ~0.33 m up (Argoverse maintainers; ground
# points sit at z ~ -0.34 m in real sweeps).
EGO_HEIGHT_M: dict[str, float] = {"sim": 0.0, "nuscenes": 0.0, "av2": 0.33}

# A frame's lighting: the simulator's drawn condition; nuScenes: "night" when the scene's
# description says so, else "day" (the split the paper's night figures use); "unknown" where the
# dataset does not say (AV2).
LIGHTINGS = ("day", "dusk", "night", "unknown")

# key -> (dtype, shape with symbolic dims). N cameras, H x W images, P LiDAR points.
SAMPLE_KEYS: dict[str, tuple[str, tuple]] = {
    "sample_id": ("str", ()),  # unique within a dataset, stable across runs
    "city": ("str", ()),  # city key: "helsinki", "kouvola", "boston-seaport", "MIA", ...
    "sequence_id": ("str", ()),  # drive / route / nuScenes scene name / AV2 log id
    "frame_index": ("int64", ()),  # >= 0: position of the frame in its sequence
    "timestamp": ("float64", ()),  # seconds (sim: distance along the route / nominal speed)
    "lighting": ("str", ()),  # one of LIGHTINGS
    "pose": ("float64", (3,)),  # world x (m), y (m), yaw (rad, CCW from east)
    "images": ("uint8", ("N", "H", "W", 3)),  # RGB
    "intrinsics": ("float32", ("N", 3, 3)),  # pixels of the stored image size
    "cam_to_ego": ("float32", ("N", 4, 4)),
    "lidar": ("float32", ("P", 4)),  # x, y, z (m, ego frame), intensity in [0, 1]
}

# What the loader yields per batch (B = batch size, C = map channels, P = max points).
BATCH_KEYS: dict[str, tuple[str, tuple]] = {
    "images": ("uint8", ("B", "N", "H", "W", 3)),
    "intrinsics": ("float32", ("B", "N", 3, 3)),
    "cam_to_ego": ("float32", ("B", "N", 4, 4)),
    "points": ("float32", ("B", "P", 4)),  # zero-padded
    "points_mask": ("bool", ("B", "P")),  # True for real points
    "bev_gt": ("float32", ("B", "C", 128, 128)),  # {0, 1} map cut out at the GT pose
    "tile": ("float32", ("B", "C", 256, 256)),  # {0, 1} map tile around the prior
    # NM models only (OPTIONAL_BATCH_KEYS): the same tile of the OSM class raster
    # (maps.OSM_CLASSES), {0, 1}
    "nm_tile": ("uint8", ("B", "C_osm", 256, 256)),
    "pose_tile": ("float32", ("B", 3)),  # GT (dx, dy, yaw) relative to the tile centre
    # Metadata kept in NumPy (never passed into jit): BATCH_METADATA_KEYS.
    "tile_center": ("float64", ("B", 2)),  # world (x, y) of the tile centre (snapped prior)
    "pose": ("float64", ("B", 3)),  # GT world pose
    "valid": ("bool", ("B",)),  # False for the rows that pad the last evaluation batch
    "sample_id": ("str", ("B",)),  # NumPy unicode arrays (dtype kind "U")
    "city": ("str", ("B",)),
    "sequence_id": ("str", ("B",)),
    "frame_index": ("int64", ("B",)),
    "timestamp": ("float64", ("B",)),  # seconds
    "lighting": ("str", ("B",)),  # LIGHTINGS
}
# Batch keys that stay on the host: ``training.step.device_batch`` never places them on devices.
BATCH_METADATA_KEYS = (
    "tile_center",
    "pose",
    "valid",
    "sample_id",
    "city",
    "sequence_id",
    "frame_index",
    "timestamp",
    "lighting",
)


# Batch keys the loader yields only when asked (``make_loader(nm_tiles=True)``: an NM model).
OPTIONAL_BATCH_KEYS = ("nm_tile",)


class SchemaError(ValueError):
    """A sample or batch does not follow the schema; the message names the key."""


def check_sample(sample: dict, where: str = "sample") -> dict:
    """Validates a producer's sample dict; returns it. ``where`` names the source in errors."""
    missing = set(SAMPLE_KEYS) - set(sample)
    extra = set(sample) - set(SAMPLE_KEYS)
    if missing or extra:
        raise SchemaError(f"{where}: missing keys {sorted(missing)}, unexpected {sorted(extra)}")
    dims: dict[str, int] = {}
    for key, (dtype, shape) in SAMPLE_KEYS.items():
        value = sample[key]
        if dtype == "str":
            if not isinstance(value, str) or not value:
                raise SchemaError(f"{where}: key {key!r} must be a non-empty str, got {value!r}")
            continue
        arr = np.asarray(value)
        if arr.dtype != np.dtype(dtype):
            raise SchemaError(f"{where}: key {key!r} has dtype {arr.dtype}, expected {dtype}")
        if arr.ndim != len(shape):
            raise SchemaError(f"{where}: key {key!r} has shape {arr.shape}, expected {shape}")
        for size, want in zip(arr.shape, shape, strict=True):
            if isinstance(want, str):
                if dims.setdefault(want, size) != size:
                    raise SchemaError(
                        f"{where}: key {key!r} dim {want}={size} disagrees with {dims[want]}"
                    )
            elif size != want:
                raise SchemaError(f"{where}: key {key!r} has shape {arr.shape}, expected {shape}")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise SchemaError(f"{where}: key {key!r} has non-finite values")
    if sample["lighting"] not in LIGHTINGS:
        raise SchemaError(
            f"{where}: key 'lighting' must be one of {LIGHTINGS}, got {sample['lighting']!r}"
        )
    if int(sample["frame_index"]) < 0:
        raise SchemaError(f"{where}: key 'frame_index' must be >= 0, got {sample['frame_index']}")
    return sample
