"""Collects the result directories of a Hydra sweep into a markdown table shaped like the paper's
ablations (one row per job: its overrides, then the localization metrics of each split).

    python experiments/collect_results.py multirun/2026-11-22/10-00-00 [--split test]

Each job directory holds ``results.json`` (written by ``seglocnet_jax.train`` / ``evaluate``)
and ``.hydra/overrides.yaml``.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys

from seglocnet_jax import metrics


def _overrides(job_dir: str) -> list[str]:
    path = os.path.join(job_dir, ".hydra", "overrides.yaml")
    if not os.path.exists(path):
        return [os.path.basename(job_dir)]
    with open(path) as f:
        return [ln.strip()[2:] for ln in f if ln.strip().startswith("- ")]


def collect(root: str, split: str) -> str:
    """The markdown table; overrides shared by every job go to a line above it, so each row is
    named by what the sweep varied (e.g. ``map.road_width=5``)."""
    paths = sorted(glob.glob(os.path.join(root, "**", "results.json"), recursive=True))
    if not paths:
        raise FileNotFoundError(f"no results.json under {root!r}: is it a sweep output directory?")
    jobs = []
    for path in paths:
        with open(path) as f:
            res = json.load(f)
        splits = res.get("splits", {})
        if split not in splits:
            print(f"skipping {path}: no split {split!r} (has {sorted(splits)})", file=sys.stderr)
            continue
        jobs.append((_overrides(os.path.dirname(path)), splits[split]))
    if not jobs:
        raise FileNotFoundError(f"no job under {root!r} has results for split {split!r}")
    common = set.intersection(*(set(o) for o, _ in jobs)) if len(jobs) > 1 else set()
    rows = [
        (", ".join(o for o in ovr if o not in common) or "(defaults)", res) for ovr, res in jobs
    ]
    caption = f"Split {split}; every job: {', '.join(sorted(common)) or '(no common overrides)'}"
    return caption + "\n\n" + metrics.markdown_table(rows, name="setting")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", help="a sweep's output directory (multirun/...)")
    p.add_argument("--split", default="test")
    args = p.parse_args(argv)
    print(collect(args.root, args.split))


if __name__ == "__main__":
    main()
