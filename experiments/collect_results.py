"""Collects the result directories of a Hydra sweep into a markdown table shaped like the paper's
ablations (one row per job: its overrides, then the localization metrics of each split).

    python experiments/collect_results.py multirun/sim_helsinki_sd [--split test] [--allow-failed]

Each job directory holds ``.hydra/overrides.yaml`` and, once it finished, ``results.json``
(written by ``seglocnet_jax.train`` / ``evaluate``; an evaluation's ``config.json`` records its
own overrides, which name its row). A job without ``results.json`` (it crashed or has not
finished), or whose evaluation set is incomplete (``INCOMPLETE``: cut off while moving into
place, its files may mix two evaluations), gets a FAILED row and, below the table, its directory
and the reason and the last lines of its log; the script then exits with status 1 unless
``--allow-failed`` is given. Sets moved aside (``*.discarded-*``) are not read.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys

from seglocnet_jax import metrics
from seglocnet_jax.app import evalset

RESULTS = "results.json"
LOG_LINES = 5


def _overrides(job_dir: str) -> list[str]:
    """The overrides that made the job: an evaluation's own record (``config.json``; Hydra's
    ``.hydra/`` is rewritten by any later command in the directory), else Hydra's."""
    config = os.path.join(job_dir, evalset.RUN_CONFIG)
    try:
        with open(config) as f:
            recorded = (json.load(f).get("evaluation") or {}).get("overrides")
    except (OSError, ValueError, AttributeError):  # none, or not an evaluation's
        recorded = None
    if recorded is not None:
        return list(recorded)
    path = os.path.join(job_dir, ".hydra", "overrides.yaml")
    if not os.path.exists(path):
        return [os.path.basename(job_dir)]
    with open(path) as f:
        return [ln.strip()[2:] for ln in f if ln.strip().startswith("- ")]


def find_jobs(root: str) -> list[str]:
    """Job directories under ``root``: those with a ``.hydra`` directory, a ``results.json`` or
    an ``INCOMPLETE`` set (their own subdirectories, and sets moved aside, are not searched)."""
    jobs = []
    for dirpath, dirnames, files in os.walk(root):
        if ".hydra" in dirnames or RESULTS in files or evalset.INCOMPLETE in files:
            jobs.append(dirpath)
            dirnames[:] = []
        else:
            dirnames[:] = sorted(d for d in dirnames if not evalset.is_aside(d))
    return sorted(jobs)


def log_tail(job_dir: str, n: int = LOG_LINES) -> list[str]:
    """The last ``n`` non-empty lines of the job's newest ``*.log`` (Hydra's ``<job>.log``)."""
    logs = sorted(glob.glob(os.path.join(job_dir, "*.log")), key=os.path.getmtime)
    if not logs:
        return []
    with open(logs[-1], errors="replace") as f:
        lines = [ln.rstrip() for ln in f if ln.strip()]
    return [f"{os.path.basename(logs[-1])}: {ln[:200]}" for ln in lines[-n:]]


def _failure(job_dir: str) -> str | None:
    """Why a job has no usable results (None: it has)."""
    path = os.path.join(job_dir, RESULTS)
    marker = evalset.incomplete(job_dir)
    if marker is not None:
        return (
            f"incomplete evaluation set ({marker}): it was cut off while moving into place and "
            "its files may mix two evaluations; rerun the job"
        )
    if not os.path.exists(path):
        return f"no {RESULTS} (the job crashed or has not finished)"
    try:
        with open(path) as f:
            json.load(f)
    except (OSError, ValueError) as err:
        return f"unreadable {RESULTS} ({err})"
    return None


def collect_jobs(root: str, split: str) -> tuple[str, list[tuple[str, str]]]:
    """``(markdown, failed)``: the table (failed jobs as FAILED rows, their details below it)
    and ``[(job dir, reason)]`` of the failed jobs."""
    job_dirs = find_jobs(root)
    if not job_dirs:
        raise FileNotFoundError(f"no {RESULTS} under {root!r}: is it a sweep output directory?")
    jobs, failed = [], []
    for job in job_dirs:
        reason = _failure(job)
        if reason is not None:
            failed.append((job, reason))
            jobs.append((_overrides(job), None))
            continue
        with open(os.path.join(job, RESULTS)) as f:
            splits = json.load(f).get("splits", {})
        if split not in splits:
            print(f"skipping {job}: no split {split!r} (has {sorted(splits)})", file=sys.stderr)
            continue
        jobs.append((_overrides(job), splits[split]))
    if not failed and not jobs:
        raise FileNotFoundError(f"no job under {root!r} has results for split {split!r}")
    common = set.intersection(*(set(o) for o, _ in jobs)) if len(jobs) > 1 else set()
    empty = {k: None for k in _metric_keys()}
    rows = []
    for ovr, res in jobs:
        name = ", ".join(o for o in ovr if o not in common) or "(defaults)"
        rows.append((f"{name} (FAILED)" if res is None else name, empty if res is None else res))
    caption = f"Split {split}; every job: {', '.join(sorted(common)) or '(no common overrides)'}"
    text = caption + "\n\n" + metrics.markdown_table(rows, name="setting")
    if failed:
        lines = ["", f"Failed jobs ({len(failed)} of {len(job_dirs)}):"]
        for job, reason in failed:
            lines.append(f"- {job}: {reason}")
            tail = log_tail(job)
            lines += [f"    {ln}" for ln in tail] if tail else ["    (no log file)"]
        text += "\n" + "\n".join(lines)
    return text, failed


def _metric_keys() -> list[str]:
    cfg = metrics.MetricsConfig()
    keys = [metrics.position_key(t) for t in cfg.position_thresholds]
    return keys + [metrics.yaw_key(t) for t in cfg.yaw_thresholds] + ["APE", "AOE"]


def collect(root: str, split: str) -> str:
    """The markdown table; overrides shared by every job go to a line above it, so each row is
    named by what the sweep varied (e.g. ``map.road_width=5``)."""
    return collect_jobs(root, split)[0]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", help="a sweep's output directory (multirun/...)")
    p.add_argument("--split", default="test")
    p.add_argument(
        "--allow-failed",
        action="store_true",
        help="exit 0 even if some jobs have no results (they are listed as FAILED)",
    )
    args = p.parse_args(argv)
    text, failed = collect_jobs(args.root, args.split)
    print(text)
    if failed and not args.allow_failed:
        print(
            f"{len(failed)} job(s) failed (listed above); rerun them, or pass --allow-failed to "
            "accept the table without them",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
