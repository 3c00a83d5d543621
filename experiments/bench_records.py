"""Record format benchmark: bytes and decode time per record; the last line of the output is JSON.

    python experiments/bench_records.py                      # simulator presets + converted record
    python experiments/bench_records.py --records 8 --skip-sim  # the converted record only

Bytes per record (this record version, and what record version 1
stored: PNG images and float32 LiDAR) and decode time per record (``records.decode_sample``:
one thread, and records/s over ``--threads`` threads) for

* ``sim_cpu``, ``sim_paper``: frames rendered by the simulator with the ``sim=cpu`` / ``sim=paper``
  presets (``conf/sim``), stored as the simulator pipeline stores them (lossless PNG images,
  compact LiDAR);
* ``converted_320x800``: a synthesized converted real-data record (6 x 320 x 800 images of
  natural-looking content -- a 1/f-spectrum texture, sky / ground, sharp-edged objects with
  window grids, lane markings, sensor noise -- stored as JPEG at ``--jpeg-quality``; a 32-beam
  sweep of ~30k points of a street canyon with 2 cm range noise and integer 0-255 intensity).

For realism, the JPEG bits per pixel of the synthetic images are printed beside those of a real
photograph resized to 320 x 800 at the same quality (``--reference-photo``; default matplotlib's
``grace_hopper.jpg`` sample photo). Targets (issue): <= 1 MB per 6 x 320 x 800 record, decoding
>= 100 records/s on 2 cores. The cores here are shared: the load average is printed too.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor

import msgpack
import numpy as np
import yaml
from PIL import Image

from seglocnet_jax.data import records

CONF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "conf")
QUICK_FRAMES = 2000 + 300 + 300 + 300  # data=quick: train + val + test + kouvola
NUSCENES_TRAINVAL = 34149  # keyframes (samples) of nuScenes v1.0-trainval


# --------------------------------------------------------------------------- synthetic content


def _field(rng: np.random.Generator, h: int, w: int, slope: float) -> np.ndarray:
    """``(h, w)`` Gaussian noise with a ``1 / f^slope`` amplitude spectrum, unit std."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    spec = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) * f**-slope
    spec[0, 0] = 0.0
    out = np.fft.irfft2(spec, s=(h, w))
    return out / out.std()


def natural_image(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """``(h, w, 3)`` uint8 street-like image: smooth sky over textured ground (a 1/f spectrum,
    like natural images), 12-20 flat-coloured textured objects with sharp edges (half with a
    window grid), lane markings and sensor noise (std 1.5)."""
    y = np.arange(h)[:, None] / h
    horizon = rng.uniform(0.35, 0.55)
    sky = y < horizon
    base = np.where(sky, 170 + 40 * (horizon - y), 95 + 30 * (y - horizon))  # (h, 1)
    lum = 20.0 * _field(rng, h, w, 1.0) * np.where(sky, 0.3, 1.0)  # (h, w)
    img = np.repeat((base + lum)[..., None], 3, axis=-1)
    img += 8.0 * np.stack([_field(rng, h, w, 1.5) for _ in range(3)], axis=-1)  # colour
    for _ in range(int(rng.integers(12, 20))):
        bw, bh = rng.uniform(0.03, 0.25) * w, rng.uniform(0.05, 0.4) * h
        x0, y1 = rng.uniform(-0.1, 1.0) * w, (horizon + rng.uniform(-0.05, 0.25)) * h
        r0, r1 = int(max(0, y1 - bh)), int(min(h, y1))
        c0, c1 = int(max(0, x0)), int(min(w, x0 + bw))
        if r1 <= r0 or c1 <= c0:
            continue
        img[r0:r1, c0:c1] = (
            rng.uniform(30, 220, 3) + 12.0 * _field(rng, r1 - r0, c1 - c0, 0.8)[..., None]
        )
        if rng.random() < 0.5:  # windows / panels
            step = int(rng.integers(6, 14))
            img[r0:r1:step, c0:c1] *= 0.6
            img[r0:r1, c0:c1:step] *= 0.6
    for _ in range(int(rng.integers(2, 6))):  # lane markings
        c = int(rng.uniform(0.1, 0.9) * w)
        img[int(horizon * h) :, max(0, c - 1) : c + 2] = 230
    img += rng.normal(0.0, 1.5, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def street_sweep(
    rng: np.random.Generator, beams: int = 32, azimuths: int = 1084, max_range: float = 100.0
) -> np.ndarray:
    """``(P, 4)`` float32 ego ``x, y, z, intensity`` of a spinning 32-beam LiDAR 1.8 m up in a
    street canyon (ground, building walls 6-30 m either side with gaps, 2 cm range noise, 2%
    dropout), in firing order (azimuth-major); intensity is an integer 0-255 divided by 255,
    like nuScenes / AV2. ~30k points for the defaults."""
    elev = np.radians(np.linspace(-30.0, 10.0, beams))  # (beams,)
    az = np.linspace(-np.pi, np.pi, azimuths, endpoint=False)  # (A,)
    d = np.stack(
        [
            np.cos(elev)[None, :] * np.cos(az)[:, None],
            np.cos(elev)[None, :] * np.sin(az)[:, None],
            np.broadcast_to(np.sin(elev)[None, :], (azimuths, beams)),
        ],
        axis=-1,
    )  # (A, beams, 3)
    height = 1.8
    t = np.full((azimuths, beams), np.inf)
    down = d[..., 2] < 0
    t[down] = height / -d[..., 2][down]  # the ground
    # Walls: one facade per side and 10 m block along x, set back 6-30 m, 5-40 m tall.
    blocks = np.arange(-12, 12)
    setback = {s: rng.uniform(6.0, 30.0, len(blocks)) for s in (-1, 1)}
    tall = {
        s: rng.uniform(5.0, 40.0, len(blocks)) * (rng.random(len(blocks)) > 0.15) for s in (-1, 1)
    }
    for side in (-1, 1):
        dy = d[..., 1] * side
        for k, x0 in enumerate(blocks * 10.0):
            with np.errstate(divide="ignore", invalid="ignore"):
                tw = setback[side][k] / dy
            x = tw * d[..., 0]
            z = height + tw * d[..., 2]
            hit = (dy > 0) & (x >= x0) & (x < x0 + 10.0) & (z >= 0) & (z < tall[side][k])
            t = np.where(hit & (tw < t), tw, t)
    t = t + rng.normal(0.0, 0.02, t.shape)
    keep = (t < max_range) & (rng.random(t.shape) > 0.02)
    pts = d[keep] * t[keep][:, None] + np.array([0.0, 0.0, height])  # (P, 3)
    wall = pts[:, 2] > 0.05
    inten = np.where(wall, rng.normal(60, 25, len(pts)), rng.normal(15, 6, len(pts)))
    inten = np.clip(np.rint(inten), 0, 255) / 255.0
    return np.concatenate([pts, inten[:, None]], axis=1).astype(np.float32)


def converted_sample(rng: np.random.Generator, i: int, cams: int, hw: tuple[int, int]) -> dict:
    """A synthesized converted real-data sample (``schema.SAMPLE_KEYS`` + ``prior``)."""
    pose = np.array([100.0 + i, 200.0, 0.3], np.float64)
    return {
        "sample_id": f"conv-{i:04d}",
        "city": "boston-seaport",
        "sequence_id": "scene-0001",
        "frame_index": np.int64(i),
        "timestamp": np.float64(1.5e9 + 0.5 * i),  # seconds
        "lighting": "day",
        "pose": pose,
        "images": np.stack([natural_image(rng, *hw) for _ in range(cams)]),
        "intrinsics": np.tile(np.eye(3, dtype=np.float32), (cams, 1, 1)),
        "cam_to_ego": np.tile(np.eye(4, dtype=np.float32), (cams, 1, 1)),
        "lidar": street_sweep(rng),
        "prior": pose[:2] + 5.0,
    }


def sim_preset(name: str) -> dict:
    """The ``sim`` section of a ``conf/sim/<name>.yaml`` preset (its ``defaults`` merged)."""
    with open(os.path.join(CONF, "sim", f"{name}.yaml")) as f:
        tree = yaml.safe_load(f)
    out: dict = {}
    for parent in tree.pop("defaults", []):
        if parent != "_self_":
            out = sim_preset(parent)
    tree.pop("name", None)
    for key, value in tree.items():
        out[key] = {**out.get(key, {}), **value} if isinstance(value, dict) else value
    return out


def sim_samples(preset: str, n: int) -> list[dict]:
    """``n`` frames of Helsinki rendered with a simulator preset, with priors."""
    from seglocnet_jax.data.simulated.source import SimSource

    source = SimSource("helsinki", sim_preset(preset), 0)
    poses = source.drive(np.random.default_rng(0), n)
    out = source.render(poses, 1)
    return [dict(s, prior=np.asarray(s["pose"][:2] + 5.0, np.float64)) for s in out]


# --------------------------------------------------------------------------- record benchmark


def v1_record(sample: dict, png_level: int = 1) -> bytes:
    """What record version 1 stored for ``sample``: PNG images, every array raw (float32
    LiDAR); for the before/after sizes."""
    fields = {}
    for key, value in sample.items():
        if isinstance(value, str):
            fields[key] = {"t": "str", "v": value}
        elif key == "images":  # the PNG field is the same in both versions
            fields[key] = records._encode_images(value, "png", png_level, 95)
        else:  # float32 LiDAR included: version 1 stored it raw
            fields[key] = records.array_field(value)
    return records.MAGIC + msgpack.packb({"v": 1, "f": fields}, use_bin_type=True)


def _jpeg_bpp(images: np.ndarray, quality: int) -> float:
    bits = sum(8 * len(records._jpeg(im, quality)) for im in images)  # as the records store
    return bits / (images.shape[0] * images.shape[1] * images.shape[2])


def reference_bpp(path: str | None, hw: tuple[int, int], quality: int) -> float:
    """JPEG bits per pixel of a real photograph resized to ``hw`` at ``quality``; ``path`` None:
    matplotlib's sample photo (matplotlib is a dependency, and it ships the photo)."""
    if path is None:
        import matplotlib

        path = os.path.join(matplotlib.get_data_path(), "sample_data", "grace_hopper.jpg")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"reference photo {path} not found (--reference-photo PATH)")
    with Image.open(path) as im:
        photo = np.asarray(im.convert("RGB").resize(hw[::-1], Image.Resampling.BILINEAR))
    return _jpeg_bpp(photo[None], quality)


def measure(name: str, samples: list[dict], encode: dict, threads: int, repeat: int) -> dict:
    """Bytes and decode time per record of ``samples`` encoded with ``encode`` options."""
    t0 = time.perf_counter()
    recs = [records.encode_sample(s, **encode, where=f"{name} {i}") for i, s in enumerate(samples)]
    encode_ms = (time.perf_counter() - t0) / len(recs) * 1e3
    before = [len(v1_record(s)) for s in samples]
    lidar_bytes, lidar_err, image_err = [], 0.0, 0.0
    for rec, s in zip(recs, samples, strict=True):
        fields = msgpack.unpackb(rec[len(records.MAGIC) :], raw=False)["f"]
        lidar_bytes.append(len(fields["lidar"]["b"]))
        back = records.decode_sample(rec)
        lidar_err = max(lidar_err, float(np.abs(back["lidar"][:, :3] - s["lidar"][:, :3]).max()))
        image_err = max(image_err, float(np.abs(back["images"].astype(int) - s["images"]).mean()))
    for rec in recs:  # warm-up
        records.decode_sample(rec)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        for rec in recs:
            records.decode_sample(rec)
    decode_ms = (time.perf_counter() - t0) / (repeat * len(recs)) * 1e3
    decode_cpu_ms = (time.process_time() - c0) / (repeat * len(recs)) * 1e3
    work = recs * (repeat * threads)
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(records.decode_sample, recs))
        t0 = time.perf_counter()
        list(pool.map(records.decode_sample, work))
        rate = len(work) / (time.perf_counter() - t0)
    s0 = samples[0]
    n_cams, h, w = s0["images"].shape[:3]
    return {
        "records": len(recs),
        "images": [int(n_cams), int(h), int(w)],
        "image_codec": encode.get("image_codec", "png"),
        "points_mean": float(np.mean([len(s["lidar"]) for s in samples])),
        "bytes_per_record": float(np.mean([len(r) for r in recs])),
        "bytes_per_record_v1": float(np.mean(before)),
        "lidar_bytes_per_record": float(np.mean(lidar_bytes)),
        "lidar_bytes_per_record_v1": float(np.mean([16 * len(s["lidar"]) for s in samples])),
        "lidar_max_abs_error_m": lidar_err,
        "image_mean_abs_error": image_err,
        "encode_ms_per_record": encode_ms,
        "decode_ms_per_record": decode_ms,
        "decode_cpu_ms_per_record": decode_cpu_ms,  # CPU time: less sensitive to shared cores
        "decode_records_per_s_2_cores_from_cpu_time": 2e3 / decode_cpu_ms,
        "decode_records_per_s": rate,
        "decode_threads": threads,
    }


def record_benchmark(args) -> dict:
    out: dict = {}
    if not args.skip_sim:
        for preset in ("cpu", "paper"):
            samples = sim_samples(preset, args.sim_frames)
            out[f"sim_{preset}"] = measure(f"sim_{preset}", samples, {}, args.threads, args.repeat)
    rng = np.random.default_rng(0)
    hw = (args.height, args.width)
    conv = [converted_sample(rng, i, args.cams, hw) for i in range(args.records)]
    enc = {"image_codec": "jpeg", "jpeg_quality": args.jpeg_quality}
    key = f"converted_{args.height}x{args.width}"
    out[key] = measure(key, conv, enc, args.threads, args.repeat)
    out[key]["jpeg_quality"] = args.jpeg_quality
    out[key]["synthetic_bpp"] = _jpeg_bpp(conv[0]["images"], args.jpeg_quality)
    out[key]["reference_photo_bpp"] = reference_bpp(args.reference_photo, hw, args.jpeg_quality)
    summary = {
        "converted_mb_per_record": out[key]["bytes_per_record"] / 1e6,
        "converted_decode_records_per_s": out[key]["decode_records_per_s"],
        "converted_decode_records_per_s_2_cores_from_cpu_time": out[key][
            "decode_records_per_s_2_cores_from_cpu_time"
        ],
        "targets": {"mb_per_record": 1.0, "decode_records_per_s": 100.0},
        "nuscenes_trainval_gb": out[key]["bytes_per_record"] * NUSCENES_TRAINVAL / 1e9,
        "nuscenes_trainval_gb_v1": out[key]["bytes_per_record_v1"] * NUSCENES_TRAINVAL / 1e9,
    }
    if "sim_cpu" in out:
        summary["quick_preset_gb"] = out["sim_cpu"]["bytes_per_record"] * QUICK_FRAMES / 1e9
        summary["quick_preset_gb_v1"] = out["sim_cpu"]["bytes_per_record_v1"] * QUICK_FRAMES / 1e9
    for name, m in out.items():
        print(
            f"{name:>18}: {m['bytes_per_record'] / 1e3:8.1f} kB/record "
            f"(v1 {m['bytes_per_record_v1'] / 1e3:8.1f} kB; "
            f"LiDAR {m['lidar_bytes_per_record'] / 1e3:.1f} kB, "
            f"v1 {m['lidar_bytes_per_record_v1'] / 1e3:.1f} kB, {m['points_mean']:.0f} pts), "
            f"decode {m['decode_ms_per_record']:.2f} ms/record "
            f"({m['decode_cpu_ms_per_record']:.2f} ms CPU), "
            f"{m['decode_records_per_s']:.0f} records/s on {m['decode_threads']} threads",
            flush=True,
        )
    return {
        "benchmark": "records",
        "record_version": records.RECORD_VERSION,
        "loadavg": list(os.getloadavg()),
        "cpus": os.cpu_count(),
        "presets": out,
        "summary": summary,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", type=int, default=8, help="converted records to synthesize")
    ap.add_argument("--sim-frames", type=int, default=4, help="frames per simulator preset")
    ap.add_argument("--skip-sim", action="store_true", help="no simulator presets")
    ap.add_argument("--jpeg-quality", type=int, default=95)
    ap.add_argument("--repeat", type=int, default=5, help="decode passes over the records")
    ap.add_argument("--reference-photo", default=None, help="a real photo for the JPEG bpp")
    ap.add_argument("--cams", type=int, default=6)
    ap.add_argument("--height", type=int, default=320)
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--threads", type=int, default=2)
    print(json.dumps(record_benchmark(ap.parse_args())))


if __name__ == "__main__":
    main()
