"""Sample serialization and ArrayRecord shards: the one seam to array_record.

Record format, version ``RECORD_VERSION`` = 4 (a record is one frame, bytes):

* ``MAGIC`` (4 bytes, ``b"SLR1"``) then a msgpack map (``use_bin_type``) with
  ``"v"`` (int, the record version) and ``"f"`` (a map field name -> encoded field).
* Fields: the producer's sample (``schema.SAMPLE_KEYS``) plus ``EXTRA_KEYS`` (``prior``: the
  seeded world (x, y) prior in metres that evaluation uses). An encoded field is one of

  ``{"t": "str", "v": str}``
      ``sample_id``, ``city``, ``sequence_id``, ``lighting``.
  ``{"t": "arr", "dtype": numpy dtype str (e.g. "<f4"), "shape": [ints], "b": raw C-order bytes}``
      ``pose``, ``intrinsics``, ``cam_to_ego``, ``prior``, and the 0-d ``frame_index`` (``<i8``)
      and ``timestamp`` (``<f8``, seconds): bit-exact.
  ``{"t": "png", "shape": [N, H, W, 3], "b": [PNG bytes per camera]}``
      ``images``, lossless (decoded bit-exactly with Pillow): the simulator's codec
      (``image_codec="png"``).
  ``{"t": "jpeg", "shape": [N, H, W, 3], "b": [JPEG bytes per camera], "q": [int per camera]}``
      ``images`` of real data (``image_codec="jpeg"``, the converters' default): baseline JFIF,
      RGB, 4:2:0 chroma, optimized Huffman tables, quality ``q`` (default 95). ``q = 0`` marks a
      camera whose **source JPEG was stored as it is** (pass-through): the producer attached
      the file's bytes (:func:`with_source_jpegs`) and they decode exactly to the sample's
      pixels (checked when encoding; any other camera is re-encoded). Decoding gives
      ``(N, H, W, 3)`` uint8 RGB.
  ``{"t": "lidar16", "n": P, "step": LIDAR_STEP, "b": zlib-compressed payload}``
      ``lidar``, compact: the payload (``7 P`` bytes before zlib) is, for each of x, y, z, the
      low bytes then the high bytes of the ``P`` little-endian int16 values
      ``round(coordinate / step)`` (a byte shuffle: ~12% smaller after zlib than interleaved
      bytes), then ``P`` uint8 intensities ``round(255 intensity)``. Decoding gives ``(P, 4)``
      float32: ``x, y, z = int16 * step``, ``intensity = uint8 / 255``, point order kept. The
      simulator and the converters both store LiDAR this way.

LiDAR error bound (pinned by tests): with ``step = 1/128 m`` every coordinate is stored within
``step / 2 = 1/256 m`` (3.9 mm) of the producer's float32 value (``int16 * step`` is exact in
float32), and intensity within ``1/510``; integer 0-255 intensities divided by 255 (nuScenes,
AV2) come back bit-exactly. Coordinates must be within ``LIDAR_RANGE`` = 256 m (exactly:
``round(coordinate / step)`` must fit int16, -256 m to 255.992 m): a point outside is an error
naming the record, never wrapped or clipped (sensor ranges are 70-200 m). Intensity is clipped to
the schema's ``[0, 1]`` explicitly. A ~30k-point sweep is 210 kB before zlib and ~105 kB after
(simulator and synthetic street sweeps, ``experiments/bench_records.py``), instead of 480 kB of
float32.

Older versions are refused with the remedy (prepare or convert again), both per record
(:func:`decode_sample`) and per dataset (``manifest.read_manifest``): version 1 (float32 LiDAR,
PNG images only), version 2 (no sequence metadata: ``sequence_id``, ``frame_index``,
``timestamp``), version 3 (no ``lighting``).

Shards are written under a temporary name and renamed when complete (:func:`fileio.atomic_path`),
so a shard path that exists is a finished shard. Integrity: :func:`write_shard` returns the
shard's SHA-256 and size, which the manifest records (:mod:`.manifest`), and readers check them
(:func:`verify_shard`, once per process and file version) before reading; riegeli also hashes
every chunk, and record counts are compared with the manifest.
"""

from __future__ import annotations

import hashlib
import io
import os
import threading
import zlib
from collections.abc import Sequence

import msgpack
import numpy as np
from array_record.python.array_record_module import ArrayRecordReader, ArrayRecordWriter
from PIL import Image

from seglocnet_jax import fileio
from seglocnet_jax.data.schema import SAMPLE_KEYS, SchemaError, check_sample

MAGIC = b"SLR1"
# 2: compact LiDAR (int16 fixed point + uint8 intensity), JPEG images; 3: sequence metadata
RECORD_VERSION = 4
RECORD_CHANGES = (
    "version 4 adds each frame's lighting (day, dusk, night or unknown); version 3 added each "
    "frame's sequence metadata (sequence_id, frame_index, timestamp); "
    "version 2 stored LiDAR in 1/128 m fixed point and real-data images as JPEG"
)
EXTRA_KEYS: dict[str, tuple[str, tuple]] = {
    "prior": ("float64", (2,)),  # world (x, y) metres: GT + U[-PRIOR_RANGE, PRIOR_RANGE]
}
IMAGE_CODECS = ("png", "jpeg")
LIDAR_STEP = 1.0 / 128.0  # metres per int16 unit: error <= LIDAR_STEP / 2 (3.9 mm)
LIDAR_RANGE = 32768 * LIDAR_STEP  # 256 m: round(coordinate / LIDAR_STEP) must fit int16
LIDAR_ZLIB_LEVEL = 6
JPEG_SUBSAMPLING = 2  # 4:2:0, as camera JPEGs
# group_size:1 keeps random access (grain shuffles globally) to one chunk per record.
WRITER_OPTIONS = "group_size:1"
SHARD_SUFFIX = ".array_record"


class RecordError(ValueError):
    """A shard or record is unreadable or malformed; the message names the file and index."""


# --------------------------------------------------------------------------- source JPEGs


class CameraImages(np.ndarray):
    """``(N, H, W, 3)`` uint8 camera images carrying each camera's source JPEG file bytes.

    ``source_jpegs[i]`` is the bytes of the file camera ``i`` was decoded from, or None. With
    ``image_codec="jpeg"`` the encoder stores those bytes as they are when they decode exactly
    to ``self[i]`` (the source already has the stored size and was not remapped), so a real
    image is not compressed twice. Views, slices and copies are plain images (no source
    bytes); pickling keeps them (a converter may load samples in worker processes).
    """

    source_jpegs: tuple | None = None

    def __array_finalize__(self, obj):
        self.source_jpegs = None  # a derived array's pixels need not match the bytes

    def __reduce__(self):
        fn, args, state = super().__reduce__()
        return fn, args, (state, self.source_jpegs)

    def __setstate__(self, state):
        base, self.source_jpegs = state
        super().__setstate__(base)


def with_source_jpegs(images: np.ndarray, jpegs: Sequence[bytes | None]) -> CameraImages:
    """``images`` ``(N, H, W, 3)`` uint8 with the source JPEG bytes of each camera attached
    (None where there is none): what a reader returns as ``sample["images"]`` to have the
    source JPEGs passed through (see :class:`CameraImages`)."""
    arr = np.ascontiguousarray(images)  # the dtype is checked with the sample (uint8)
    if arr.ndim != 4 or len(jpegs) != len(arr):
        raise ValueError(f"{len(jpegs)} source JPEGs for images of shape {arr.shape}")
    out = arr.view(CameraImages)
    out.source_jpegs = tuple(None if b is None else bytes(b) for b in jpegs)
    return out


# --------------------------------------------------------------------------- encode / decode


def _png(image: np.ndarray, compress_level: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def _jpeg(image: np.ndarray, quality: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(
        buf, format="JPEG", quality=quality, subsampling=JPEG_SUBSAMPLING, optimize=True
    )
    return buf.getvalue()


def _decodes_to(data: bytes, image: np.ndarray) -> bool:
    """Whether ``data`` is an RGB JPEG that decodes exactly to ``image`` ``(H, W, 3)``."""
    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format != "JPEG" or im.mode != "RGB" or im.size != image.shape[1::-1]:
                return False  # checked from the header, before any decoding
            return bool(np.array_equal(np.asarray(im), image))
    except Exception:  # not an image at all
        return False


def _encode_images(value, codec: str, compress_level: int, jpeg_quality: int) -> dict:
    sources = value.source_jpegs if isinstance(value, CameraImages) else None
    images = np.ascontiguousarray(value)
    if codec == "png":
        return {
            "t": "png",
            "shape": list(images.shape),
            "b": [_png(im, compress_level) for im in images],
        }
    blobs, qualities = [], []
    for i, im in enumerate(images):
        src = sources[i] if sources is not None and len(sources) == len(images) else None
        if src is not None and _decodes_to(src, im):
            blobs.append(src)
            qualities.append(0)
        else:
            blobs.append(_jpeg(im, jpeg_quality))
            qualities.append(jpeg_quality)
    return {"t": "jpeg", "shape": list(images.shape), "b": blobs, "q": qualities}


def _encode_lidar(lidar: np.ndarray, where: str) -> dict:
    """The ``lidar16`` field of ``(P, 4)`` float32 points (see the module docstring)."""
    n = len(lidar)
    q = np.rint(lidar[:, :3].astype(np.float64) / LIDAR_STEP)  # (P, 3), exact for float32
    outside = np.any((q < -32768) | (q > 32767), axis=1)
    if outside.any():
        far = float(np.abs(lidar[outside, :3]).max())
        raise SchemaError(
            f"{where}: key 'lidar': {int(outside.sum())} of {n} points have a coordinate outside "
            f"the stored range [-{LIDAR_RANGE:g}, {LIDAR_RANGE - LIDAR_STEP / 2:g}) m (largest "
            f"|coordinate| {far:.2f} m); records store LiDAR in {LIDAR_STEP:g} m fixed point, so "
            "the producer must drop points beyond the sensor range"
        )
    planes = np.ascontiguousarray(q.T.astype("<i2"))  # (3, P)
    shuffled = planes.view(np.uint8).reshape(3, n, 2).transpose(0, 2, 1)  # (3, lo/hi, P)
    intensity = np.rint(np.clip(lidar[:, 3], 0.0, 1.0) * 255.0).astype(np.uint8)  # (P,)
    payload = shuffled.tobytes() + intensity.tobytes()
    return {
        "t": "lidar16",
        "n": n,
        "step": LIDAR_STEP,
        "b": zlib.compress(payload, LIDAR_ZLIB_LEVEL),
    }


def encode_sample(
    sample: dict,
    *,
    image_codec: str = "png",
    compress_level: int = 1,
    jpeg_quality: int = 95,
    where: str = "sample",
) -> bytes:
    """Serializes a validated sample dict (``SAMPLE_KEYS`` + ``EXTRA_KEYS``) to record bytes.

    Args:
      image_codec: ``"png"`` (lossless; the simulator) or ``"jpeg"`` (real data; source JPEGs
        attached with :func:`with_source_jpegs` are passed through where they decode to the
        stored pixels).
      compress_level: PNG zlib level (0-9; 1 is fast and already lossless).
      jpeg_quality: JPEG quality (1-100) of re-encoded images.
      where: names the sample in errors.

    A LiDAR coordinate outside ``LIDAR_RANGE`` raises :class:`SchemaError` (see the module
    docstring for the stored form and its error bound).
    """
    if image_codec not in IMAGE_CODECS:
        raise ValueError(f"image_codec must be one of {IMAGE_CODECS}, got {image_codec!r}")
    if isinstance(jpeg_quality, bool) or not isinstance(jpeg_quality, int):
        raise ValueError(f"jpeg_quality must be an int in [1, 100], got {jpeg_quality!r}")
    if not 1 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in [1, 100], got {jpeg_quality}")
    base = {k: v for k, v in sample.items() if k not in EXTRA_KEYS}
    check_sample(base, where)
    for key, (dtype, shape) in EXTRA_KEYS.items():
        arr = np.asarray(sample.get(key))
        if key not in sample or arr.dtype != np.dtype(dtype) or arr.shape != shape:
            raise SchemaError(f"{where}: key {key!r} must be {dtype} of shape {shape}")
    fields = {}
    for key, value in sample.items():
        if isinstance(value, str):
            fields[key] = {"t": "str", "v": value}
        elif key == "images":
            fields[key] = _encode_images(value, image_codec, compress_level, jpeg_quality)
        elif key == "lidar":
            fields[key] = _encode_lidar(np.asarray(value), where)
        else:
            fields[key] = array_field(value)
    return MAGIC + msgpack.packb({"v": RECORD_VERSION, "f": fields}, use_bin_type=True)


def array_field(value) -> dict:
    """A raw array field (every array but images and LiDAR): dtype, shape, C-order bytes."""
    arr = np.asarray(value, order="C")  # 0-d stays 0-d (frame_index, timestamp)
    return {"t": "arr", "dtype": arr.dtype.str, "shape": list(arr.shape), "b": arr.tobytes()}


def _decode_images(key: str, enc: dict, fmt: str, where: str) -> np.ndarray:
    shape = tuple(enc["shape"])
    if len(shape) != 4 or len(enc["b"]) != shape[0]:
        raise RecordError(f"{where}: {key} has {len(enc['b'])} images for shape {shape}")
    out = np.empty(shape, np.uint8)  # (N, H, W, 3)
    for i, data in enumerate(enc["b"]):
        with Image.open(io.BytesIO(data)) as im:
            if im.format != fmt or im.mode != "RGB":
                raise RecordError(
                    f"{where}: {key}[{i}] is a {im.mode} {im.format}, expected RGB {fmt}"
                )
            out[i] = np.asarray(im)
    return out


def _decode_lidar(enc: dict) -> np.ndarray:
    n, step = int(enc["n"]), float(enc["step"])
    raw = np.frombuffer(zlib.decompress(enc["b"]), np.uint8)
    if len(raw) != 7 * n or not step > 0:
        raise ValueError(f"lidar16 payload of {len(raw)} bytes for {n} points, step {step}")
    planes = raw[: 6 * n].reshape(3, 2, n)  # (x y z, low / high byte, P)
    q = (planes[:, 1].view(np.int8).astype(np.int16) << 8) | planes[:, 0]  # (3, P) int16
    out = np.empty((4, n), np.float32)
    np.multiply(q, np.float32(step), out=out[:3])  # exact: |int16| * 2^-7 fits float32
    np.divide(raw[6 * n :], np.float32(255.0), out=out[3])
    return out.T.copy()  # (P, 4) C-contiguous


def _decode_field(key: str, enc: dict, where: str):
    kind = enc["t"]
    if kind == "str":
        return str(enc["v"])
    if kind == "arr":
        arr = np.frombuffer(enc["b"], dtype=np.dtype(enc["dtype"]))
        return arr.reshape(tuple(enc["shape"])).copy()  # writable, owns its memory
    if kind == "png":
        return _decode_images(key, enc, "PNG", where)
    if kind == "jpeg":
        return _decode_images(key, enc, "JPEG", where)
    if kind == "lidar16":
        return _decode_lidar(enc)
    raise RecordError(f"{where}: field {key!r} has unknown encoding {kind!r}")


def decode_sample(data: bytes, where: str = "record") -> dict:
    """Record bytes back to the sample dict: bit-exact except JPEG images and the LiDAR's
    fixed-point coordinates (bounds in the module docstring). ``where`` names the file and
    index."""
    if not data.startswith(MAGIC):
        raise RecordError(f"{where}: not a seglocnet record (bad magic {bytes(data[:4])!r})")
    try:
        payload = msgpack.unpackb(data[len(MAGIC) :], raw=False)
        version = payload["v"]
        if version != RECORD_VERSION:
            raise RecordError(
                f"{where}: record version {version}, this code reads version {RECORD_VERSION} "
                f"({RECORD_CHANGES}); re-run the data preparation (or conversion) into a new "
                "directory"
            )
        sample = {k: _decode_field(k, enc, where) for k, enc in payload["f"].items()}
    except RecordError:
        raise
    except Exception as err:  # msgpack, PIL, zlib, reshape: all mean a malformed record
        raise RecordError(f"{where}: malformed record ({type(err).__name__}: {err})") from err
    missing = (set(SAMPLE_KEYS) | set(EXTRA_KEYS)) - set(sample)
    if missing:
        raise RecordError(f"{where}: record lacks keys {sorted(missing)}")
    return sample


# --------------------------------------------------------------------------- shards


def shard_name(split: str, index: int, count: int) -> str:
    """File name of shard ``index`` of ``count`` of a split, e.g. ``train-00003-of-00010``."""
    return f"{split}-{index:05d}-of-{count:05d}{SHARD_SUFFIX}"


_HASH_CHUNK = 1 << 20
_verified: dict[str, tuple[int, int, str]] = {}  # realpath -> (size, mtime_ns, sha256) checked
_verified_lock = threading.Lock()


def file_checksum(path: str | os.PathLike) -> dict:
    """``{"sha256": hex digest, "bytes": size}`` of a file (what the manifest records)."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            h.update(chunk)
            size += len(chunk)
    return {"sha256": h.hexdigest(), "bytes": size}


def write_shard(path: str | os.PathLike, records: list[bytes]) -> dict:
    """Writes encoded ``records`` to an ArrayRecord shard atomically (temp name, then rename);
    returns its :func:`file_checksum` for the manifest."""
    path = os.fspath(path)
    with fileio.atomic_path(path) as tmp:
        writer = ArrayRecordWriter(tmp, WRITER_OPTIONS)
        try:
            for rec in records:
                writer.write(rec)
            ok = writer.ok()
        finally:
            writer.close()
        if not ok:
            raise RecordError(f"{path}: ArrayRecord writer failed")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        checksum = file_checksum(tmp)
    return checksum


def verify_shard(path: str | os.PathLike, entry: dict, manifest: str) -> None:
    """Checks a shard file against its manifest ``entry`` (``sha256``, ``bytes``); raises
    :class:`RecordError` naming the file and ``manifest`` on a difference. A file already
    verified in this process with the same size and mtime is not hashed again."""
    path = os.fspath(path)
    want_sha, want_size = entry.get("sha256"), entry.get("bytes")
    if not isinstance(want_sha, str) or not isinstance(want_size, int):
        raise RecordError(
            f"{path}: {manifest} records no checksum for this shard (preparation did not "
            "finish); prepare the dataset again"
        )
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise RecordError(f"{path}: shard file is missing (listed in {manifest})") from None
    if st.st_size != want_size:
        raise RecordError(
            f"{path}: {st.st_size} bytes, {manifest} records {want_size} (truncated or "
            "replaced shard?); prepare the dataset again into a new directory"
        )
    key = os.path.realpath(path)
    stamp = (st.st_size, st.st_mtime_ns, want_sha)
    with _verified_lock:
        if _verified.get(key) == stamp:
            return
    got = file_checksum(path)["sha256"]
    if got != want_sha:
        raise RecordError(
            f"{path}: SHA-256 {got[:16]}... differs from the {want_sha[:16]}... recorded in "
            f"{manifest}: the shard changed after it was written (disk corruption or an edit); "
            "prepare the dataset again into a new directory"
        )
    with _verified_lock:
        _verified[key] = stamp


def count_records(path: str | os.PathLike) -> int:
    """Number of records in a shard; :class:`RecordError` naming the file if it is unreadable."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise RecordError(f"{path}: shard file is missing")
    try:
        reader = ArrayRecordReader(path)
        try:
            return int(reader.num_records())
        finally:
            reader.close()
    except Exception as err:
        raise RecordError(f"{path}: unreadable ArrayRecord shard ({err})") from err


def read_shard(path: str | os.PathLike, expected: int | None = None) -> list[bytes]:
    """All raw records of a shard. With ``expected``, a different count (e.g. a truncated file)
    raises :class:`RecordError` naming the file."""
    path = os.fspath(path)
    n = count_records(path)
    if expected is not None and n != expected:
        raise RecordError(f"{path}: {n} records, manifest expects {expected} (truncated shard?)")
    try:
        reader = ArrayRecordReader(path)
        try:
            return list(reader.read_all())
        finally:
            reader.close()
    except Exception as err:
        raise RecordError(f"{path}: corrupt ArrayRecord shard ({err})") from err
