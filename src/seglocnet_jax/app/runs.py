"""Run directories: identity, lock, results.

A run directory holds ``config.json`` (the resolved typed config that made it), a lock while a
process works in it, checkpoints, logs, figures and ``results.json``. A run resumes only when the
config that defines it is the same as the stored one; otherwise the run stops and names the keys
that differ (``train.restart=true`` moves the old checkpoints aside and starts over instead).
What does not define a run (how often to log, how many devices, where the data root lives, the
final evaluation's options) may change between a run and its resumption.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time

from seglocnet_jax import fileio, metrics
from seglocnet_jax.app import evalset
from seglocnet_jax.app.evalset import RESULTS, RUN_CONFIG
from seglocnet_jax.app.schema import ExperimentConfig
from seglocnet_jax.config_util import ConfigError
from seglocnet_jax.model.config import ModelConfig
from seglocnet_jax.training import checkpoint as ckpt_lib

ARCHIVED_WITH_CHECKPOINTS = (RUN_CONFIG, "metrics.jsonl", "tb", *evalset.TRAIN_ITEMS)

# Flattened keys that do not define a run (prefix match on whole key components).
NOT_DEFINING = (
    "eval",
    "train.log_every",
    "train.eval_every",
    "train.num_devices",
    "train.restart",
    "train.checkpoint.keep_last",
    "loader.num_threads",
    "loader.prefetch",
    "loader.worker_count",
    "data.root",
    "dataset.convert.root",
    "dataset.reader.dataroot",
)


def progress(msg: str) -> None:
    print(f"[seglocnet] {msg}", flush=True)


def config_dict(cfg: ExperimentConfig) -> dict:
    """The typed config as plain JSON types."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def flatten(tree, prefix: str = "") -> dict:
    if isinstance(tree, dict) and tree:
        out = {}
        for k, v in tree.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: tree}


def _defining(flat: dict, skip: tuple[str, ...]) -> dict:
    def keep(key):
        return not any(key == p or key.startswith(p + ".") for p in skip)

    return {k: v for k, v in flat.items() if keep(k)}


_NO_DEFAULT = object()


def _added_model_key_default(key: str):
    """The default of ``model.<field>`` (new network options default to the network as it was
    before them, so a run stored without the key used that value), else a sentinel."""
    field = key.removeprefix("model.")
    if field == key or field not in {f.name for f in dataclasses.fields(ModelConfig)}:
        return _NO_DEFAULT
    value = getattr(ModelConfig(), field)
    return list(value) if isinstance(value, tuple) else value


def config_diff(
    stored: dict, current: dict, only: str | None = None, skip: tuple[str, ...] = NOT_DEFINING
) -> list[str]:
    """``key: stored -> current`` lines for the defining keys that differ (``only``: a prefix
    such as ``"model"``; ``skip``: the key prefixes that define nothing)."""
    a, b = _defining(flatten(stored), skip), _defining(flatten(current), skip)
    lines = []
    for key in sorted(set(a) | set(b)):
        if only and not (key == only or key.startswith(only + ".")):
            continue
        if key not in a and key in b and b[key] == _added_model_key_default(key):
            continue  # a network option added after this run, at its default: the same network
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            lines.append(f"{key}: {a.get(key, '<absent>')!r} -> {b.get(key, '<absent>')!r}")
    return lines


def read_run_config(workdir: str) -> dict | None:
    path = os.path.join(workdir, RUN_CONFIG)
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            return json.load(f)["config"]
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(
            f"{path}: unreadable run config ({err}); delete it only if you know "
            "which config made this run"
        ) from err


def _has_checkpoints(workdir: str) -> bool:
    root = os.path.join(workdir, "checkpoints")
    return (
        any(
            os.path.isdir(os.path.join(root, sub)) and os.listdir(os.path.join(root, sub))
            for sub in ("last", "best")
        )
        if os.path.isdir(root)
        else False
    )


class RunDir:
    """The run directory of one process: locked for its lifetime, identity checked."""

    def __init__(self, workdir: str, cfg: ExperimentConfig, what: str):
        self.workdir = os.path.abspath(workdir)
        self.cfg = cfg
        self.what = what
        os.makedirs(self.workdir, exist_ok=True)
        self.lock = fileio.DirLock(self.workdir, what)

    def __enter__(self) -> RunDir:
        self.lock.acquire()
        if self.lock.previous:
            progress(
                f"took over the lock of {self.workdir} from pid {self.lock.previous.get('pid')} "
                "(no longer running)"
            )
        removed = fileio.clean_stale_tmp(self.workdir)
        if removed:
            progress(f"removed {len(removed)} temporary file(s) left by a killed run")
        return self

    def __exit__(self, *exc) -> None:
        self.lock.release()

    def check_identity(self, restart: bool) -> None:
        """Refuses to resume checkpoints made with another defining config (or with an unknown
        one); with ``restart`` moves them aside instead. Then stores this config."""
        current = config_dict(self.cfg)
        stored = read_run_config(self.workdir)
        if _has_checkpoints(self.workdir):
            if stored is None:
                problem = (
                    f"{self.workdir} holds checkpoints but no {RUN_CONFIG}, so the config "
                    "that made them is unknown"
                )
            else:
                diff = config_diff(stored, current)
                problem = (
                    (
                        f"{self.workdir} holds a run made with another config; it would resume "
                        "with these keys changed (stored -> now):\n  " + "\n  ".join(diff)
                    )
                    if diff
                    else None
                )
            if problem and not restart:
                raise ConfigError(
                    f"{problem}\nStart a new run in another directory (hydra.run.dir=PATH, or "
                    "change the settings that name the run directory) or rerun with "
                    "train.restart=true to move the old checkpoints aside and start over"
                )
            if problem:
                self.archive("the old run")
        self.write_config()

    def archive(self, what: str) -> str | None:
        """Moves the checkpoints aside (``checkpoints.discarded-<time>``) and with them the
        old run's logs and its evaluation sets, the current one and those moved aside
        (``.../run_files``): nothing is lost, nothing is relabelled by the new run."""
        moved = ckpt_lib.archive_checkpoints(self.workdir)
        if moved is None:
            return None
        keep = os.path.join(moved, "run_files")
        names = [*ARCHIVED_WITH_CHECKPOINTS, evalset.INCOMPLETE]
        names += [n for n in os.listdir(self.workdir) if n.startswith(evalset.DISCARDED + ".")]
        for name in names:
            src = os.path.join(self.workdir, name)
            if os.path.lexists(src):
                os.makedirs(keep, exist_ok=True)
                os.rename(src, os.path.join(keep, name))
        progress(f"train.restart=true: moved {what} (checkpoints, logs, results) to {moved}")
        return moved

    def write_config(self) -> None:
        fileio.write_json_atomic(
            os.path.join(self.workdir, RUN_CONFIG),
            {"config": config_dict(self.cfg), "written": time.strftime("%Y-%m-%dT%H:%M:%S")},
        )


def find_run_config(checkpoint: str) -> tuple[str, dict] | None:
    """The ``config.json`` of the run a checkpoint path belongs to (searching upwards)."""
    path = os.path.abspath(checkpoint)
    for _ in range(5):
        cand = os.path.join(path, RUN_CONFIG)
        if os.path.isfile(cand):
            return cand, read_run_config(path)
        path = os.path.dirname(path)
    return None


def check_checkpoint_compatible(checkpoint: str, cfg: ExperimentConfig) -> None:
    """The checkpoint's run must have the same network (``model.*``) and map channels: a
    clear error naming the differing keys instead of a failed restore."""
    found = find_run_config(checkpoint)
    if found is None:
        return  # a bare checkpoint: the restore itself checks the parameter tree
    path, stored = found
    current = config_dict(cfg)
    diff = config_diff(stored, current, only="model") + config_diff(
        stored, current, only="map.channels"
    )
    if diff:
        raise ConfigError(
            f"checkpoint={checkpoint!r} was trained with another network config ({path}); "
            "stored -> now:\n  " + "\n  ".join(diff) + "\nPass the same overrides as the "
            "training run (e.g. the same +exp=, model.*, map.channels)"
        )


# CPU features that change which kernels XLA emits, and so the last digits of a training run
# (the same run differed by up to 1.7 R@1m points between an AMD EPYC and an Intel Xeon).
ISA_FLAGS = ("avx2", "fma", "avx512f", "avx512_bf16", "amx_tile")


def machine() -> dict:
    """What computed the numbers: the JAX backend and its devices, and the CPU (``/proc/cpuinfo``
    on Linux: model name, family, model and the :data:`ISA_FLAGS` it has; elsewhere
    ``platform.processor()`` and no flags) with the cores this process may use."""
    import jax

    devices = jax.devices()
    try:
        with open("/proc/cpuinfo") as f:
            block = f.read().split("\n\n")[0]  # the first processor's fields
    except OSError:
        block = ""
    fields = {k.strip(): v.strip() for k, _, v in (ln.partition(":") for ln in block.splitlines())}
    known = "model name" in fields
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "backend": jax.default_backend(),
        "devices": f"{len(devices)} x {devices[0].device_kind}",
        "cpu": fields["model name"] if known else platform.processor() or platform.machine(),
        "cpu_family": fields.get("cpu family"),
        "cpu_model": fields.get("model"),
        "isa": [f for f in ISA_FLAGS if f in fields.get("flags", "").split()] if known else None,
        "cores": cores,
        "jax": jax.__version__,
    }


def machine_label(info: dict | None) -> str:
    """A short name of :func:`machine`'s record: the accelerator, or the CPU with its widest
    vector unit (``"unknown machine"`` for a row stored without one)."""
    if not info:
        return "unknown machine"
    if info.get("backend") not in (None, "cpu"):
        return str(info.get("devices"))
    isa = info.get("isa")
    width = "ISA unknown" if isa is None else ("AVX-512" if "avx512f" in isa else "no AVX-512")
    return f"{info.get('cpu')} ({width})"


def write_results(workdir: str, cfg: ExperimentConfig, results: dict, extra: dict) -> str:
    """``<workdir>/results.json`` (atomic), with the config that produced the numbers and the
    :func:`machine` that computed them (``workdir``: the staging directory of an
    :class:`evalset.OutputSet`)."""
    path = os.path.join(workdir, RESULTS)
    payload = {
        "experiment": cfg.name,
        "variant": cfg.map.name,
        "model_variant": cfg.model.variant,
        "bev_source": cfg.eval.bev_source,
        "splits": results,
        **extra,
        "machine": machine(),
        "config": config_dict(cfg),
    }
    fileio.write_json_atomic(path, payload, indent=2, sort_keys=False)
    return path


def _source(cfg: ExperimentConfig) -> str:
    return "gt" if cfg.eval.bev_source == "gt" else f"{cfg.model.name}-{cfg.model.variant}"


def format_table(cfg: ExperimentConfig, results: dict, sequential: dict | None = None) -> str:
    """The paper-style table of the single-frame splits (``results``; a split whose frames have
    more than one known lighting also per lighting) and, with ``sequential``
    (``{split: summary}`` of :func:`seglocnet_jax.sequential.summarize`), the filtered and
    single-frame rows of the tracked splits (same frames) and a table of the tracking numbers."""
    parts = []
    rows = []
    for split, res in results.items():
        rows.append((f"{cfg.name} [{cfg.map.name}, {_source(cfg)}] {split}", res))
        for lighting, sub in res.get("lighting", {}).items():
            if len(res["lighting"]) > 1:  # the split's frames by lighting
                rows.append((f"  {split}, {lighting} frames only ({sub['count']})", sub))
        if "prior" in res:
            rows.append((f"prior alone (tile centre, no heading) {split}", res["prior"]))
    if rows:
        parts.append(metrics.markdown_table(rows))
    if sequential:
        parts.append(_sequential_tables(cfg, sequential))
    return "\n\n".join(parts)


SEQUENTIAL_COLUMNS = (
    ("drives", "drives", "{:d}"),
    ("frames", "frames", "{:d}"),
    ("tracked_pct", "tracked ≤5 m (%)", "{:.1f}"),
    ("frames_to_converge", "frames to ≤2 m (median)", "{:.0f}"),
    ("drives_not_converged", "not converged", "{:d}"),
    ("drives_never_lost_pct", "never lost >10 frames (%)", "{:.1f}"),
    ("losses_detected", "losses detected", "{:d}"),
    ("losses_recovered", "recovered", "{:d}"),
    ("coverage_90", "GT in 90% region (%)", "{:.1f}"),
    ("narrowed_pct", "in tracking window (%)", "{:.1f}"),
    ("hypotheses_mean", "windows per frame", "{:.2f}"),
    ("mean_log_p_gt", "log p(GT) (nats)", "{:.2f}"),
    ("temperature", "T", "{:.3g}"),
    ("filter_ms_per_frame", "filter ms/frame", "{:.1f}"),
    ("score_ms_per_frame", "GT read-out ms/frame", "{:.1f}"),
    ("compile_ms_per_frame", "compile ms/frame", "{:.1f}"),
    ("localize_ms_per_frame", "localize ms/frame", "{:.1f}"),
)


def _sequential_tables(cfg: ExperimentConfig, sequential: dict) -> str:
    rows = []
    for split, res in sequential.items():
        head = f"{cfg.name} [{cfg.map.name}, {_source(cfg)}] {split}"
        rows.append((f"{head} filtered", res["filtered"]))
        rows.append((f"{head} single-frame", res["single"]))
    lines = [metrics.markdown_table(rows, name="Sequential (same frames)"), ""]
    lines.append("| split | " + " | ".join(c[1] for c in SEQUENTIAL_COLUMNS) + " |")
    lines.append("|---|" + "|".join("---:" for _ in SEQUENTIAL_COLUMNS) + "|")
    for split, res in sequential.items():
        cells = [
            "–" if res.get(k) is None else fmt.format(res[k]) for k, _, fmt in SEQUENTIAL_COLUMNS
        ]
        lines.append(f"| {split} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
