"""Sample serialization and ArrayRecord shards: the one seam to array_record.

Record format, version ``RECORD_VERSION`` (a record is one frame, bytes):

* ``MAGIC`` (4 bytes, ``b"SLR1"``) then a msgpack map (``use_bin_type``) with
  ``"v"`` (int, the record version) and ``"f"`` (a map field name -> encoded field).
* An encoded field is one of
  ``{"t": "str", "v": str}``,
  ``{"t": "arr", "dtype": numpy dtype str (e.g. "<f4"), "shape": [ints], "b": raw C-order bytes}``,
  ``{"t": "png", "shape": [N, H, W, 3], "b": [PNG bytes per camera]}`` (the ``images`` key:
  lossless, decoded bit-exactly with Pillow).
* Fields: the producer's sample (``schema.SAMPLE_KEYS``) plus ``EXTRA_KEYS`` (``prior``: the
  seeded world (x, y) prior in metres that evaluation uses).

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

import msgpack
import numpy as np
from array_record.python.array_record_module import ArrayRecordReader, ArrayRecordWriter
from PIL import Image

from seglocnet_jax import fileio
from seglocnet_jax.data.schema import SAMPLE_KEYS, SchemaError, check_sample

MAGIC = b"SLR1"
RECORD_VERSION = 1
EXTRA_KEYS: dict[str, tuple[str, tuple]] = {
    "prior": ("float64", (2,)),  # world (x, y) metres: GT + U[-PRIOR_RANGE, PRIOR_RANGE]
}
# group_size:1 keeps random access (grain shuffles globally) to one chunk per record.
WRITER_OPTIONS = "group_size:1"
SHARD_SUFFIX = ".array_record"


class RecordError(ValueError):
    """A shard or record is unreadable or malformed; the message names the file and index."""


# --------------------------------------------------------------------------- encode / decode


def _png(image: np.ndarray, compress_level: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def encode_sample(sample: dict, *, compress_level: int = 1, where: str = "sample") -> bytes:
    """Serializes a validated sample dict (``SAMPLE_KEYS`` + ``EXTRA_KEYS``) to record bytes.

    ``compress_level`` is the PNG zlib level (0-9; 1 is fast and already lossless).
    """
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
            images = np.ascontiguousarray(value)
            fields[key] = {
                "t": "png",
                "shape": list(images.shape),
                "b": [_png(im, compress_level) for im in images],
            }
        else:
            arr = np.ascontiguousarray(value)
            fields[key] = {
                "t": "arr",
                "dtype": arr.dtype.str,
                "shape": list(arr.shape),
                "b": arr.tobytes(),
            }
    return MAGIC + msgpack.packb({"v": RECORD_VERSION, "f": fields}, use_bin_type=True)


def _decode_field(key: str, enc: dict, where: str):
    kind = enc["t"]
    if kind == "str":
        return str(enc["v"])
    shape = tuple(enc["shape"])
    if kind == "arr":
        arr = np.frombuffer(enc["b"], dtype=np.dtype(enc["dtype"]))
        return arr.reshape(shape).copy()  # writable, owns its memory
    if kind == "png":
        out = np.empty(shape, np.uint8)  # (N, H, W, 3)
        for i, data in enumerate(enc["b"]):
            with Image.open(io.BytesIO(data)) as im:
                if im.mode != "RGB":
                    raise RecordError(f"{where}: {key}[{i}] is a {im.mode} PNG, expected RGB")
                out[i] = np.asarray(im)
        return out
    raise RecordError(f"{where}: field {key!r} has unknown encoding {kind!r}")


def decode_sample(data: bytes, where: str = "record") -> dict:
    """Record bytes back to the sample dict (bit-exact). ``where`` names the file and index."""
    if not data.startswith(MAGIC):
        raise RecordError(f"{where}: not a seglocnet record (bad magic {bytes(data[:4])!r})")
    try:
        payload = msgpack.unpackb(data[len(MAGIC) :], raw=False)
        version = payload["v"]
        if version != RECORD_VERSION:
            raise RecordError(
                f"{where}: record version {version}, this code reads version {RECORD_VERSION}; "
                "re-run the data preparation"
            )
        sample = {k: _decode_field(k, enc, where) for k, enc in payload["f"].items()}
    except RecordError:
        raise
    except Exception as err:  # msgpack, PIL, reshape: all mean a malformed record
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
