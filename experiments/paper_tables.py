"""The paper's tables on the embedded benchmark: run the set, then collect it into
``docs/results.md`` with one figure per table (the tables, figures and findings:
``experiments/paper_report.py``).

    python experiments/paper_tables.py run budget=cpu      # every job; resumable, finished: skipped
    python experiments/paper_tables.py collect budget=cpu  # docs/results.md + docs/results_*.png
    python experiments/paper_tables.py run budget=cpu --only hd,gt_hd   # a subset

Each job is one ``python -m seglocnet_jax.train`` (or ``evaluate`` for the GT rows) with the
overrides listed in :data:`JOBS` plus ``+budget=<budget>`` (``conf/budget/``); its run directory
is the app's default one, so the main job (``python -m seglocnet_jax.train``) is the HD row.
A job whose ``results.json`` exists is not rerun; an interrupted one resumes from its checkpoint;
one whose evaluation set was cut off while moving into place (``INCOMPLETE``) is rerun, and
storing it is refused.
Rows computed on different machines differ in their last digits (XLA's kernels depend on the
CPU's instruction set), so each row names its machine and a finding over rows of several machines
says so.
``--extra`` appends overrides to every job (the tests run the set on a tiny dataset that way;
``--root`` then gives the jobs their own directories).

The results store: when a job finishes (or a finished one is found), ``run`` copies its
``results.json`` with the command, the run directory and the git commit of the code that ran it
into ``experiments/results/<budget>/<job>.json`` (``--store``), which is committed; ``collect``
reads only the store, so the tables survive the run directories (which are not committed) and a
row measured in another checkout (``cd <clone> && python <this repo>/experiments/paper_tables.py
run ...``) lands here with that checkout's commit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import subprocess
import sys
import time
from datetime import UTC, datetime

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:  # loaded by path (the tests): its sibling module is importable too
    sys.path.insert(0, _HERE)

from paper_findings import findings, seed_range  # noqa: E402
from paper_report import PAPER, collect  # noqa: E402

__all__ = ["JOBS", "BY_NAME", "PAPER", "run", "load", "collect", "findings", "seed_range"]


@dataclasses.dataclass(frozen=True)
class Job:
    name: str
    app: str  # "train" | "evaluate"
    overrides: tuple[str, ...] = ()


GT = ("eval.bev_source=gt",)
JOBS = (
    Job("hd", "train"),
    Job("sd", "train", ("map=sd",)),
    # The paper's NM: its neural map reads the multi-class OSM raster (maps.OSM_CLASSES), its
    # segmentation term and the evaluation's priors use the SD map (10 m), like the SD row.
    Job("nm", "train", ("map=sd", "model.variant=nm")),
    Job("gt_hd", "evaluate", GT),
    Job("gt_sd", "evaluate", (*GT, "map=sd")),
    Job("road", "train", ("map.channels=[road]",)),
    Job("building", "train", ("map.channels=[building]",)),
    Job("sd_w2.5", "train", ("map=sd", "map.road_width=2.5")),
    Job("sd_w5", "train", ("map=sd", "map.road_width=5")),
    Job("camera", "train", ("model.modality=camera",)),
    Job("lidar", "train", ("model.modality=lidar",)),
    Job("hd_seed1", "train", ("train.seed=1",)),
    Job("hd_seed2", "train", ("train.seed=2",)),
    # Seeds 1 and 2 of each single modality: the modality findings compare 3-seed means.
    Job("camera_seed1", "train", ("model.modality=camera", "train.seed=1")),
    Job("camera_seed2", "train", ("model.modality=camera", "train.seed=2")),
    Job("lidar_seed1", "train", ("model.modality=lidar", "train.seed=1")),
    Job("lidar_seed2", "train", ("model.modality=lidar", "train.seed=2")),
)
BY_NAME = {j.name: j for j in JOBS}


# --------------------------------------------------------------------------- running


# Only the main job (the HD row) also tracks the drives (eval.mode=both, the default): the
# tables are single-frame, and tracking every drive would add ~20 min to every CPU job.
SINGLE_FRAME = "eval.mode=single"


def job_overrides(
    job: Job, budget: str, extra=(), root: str | None = None, *, single: bool = True
) -> list[str]:
    """The job's command-line overrides; ``single=False`` leaves out :data:`SINGLE_FRAME` (the
    run directory does not depend on it, and a checkout older than ``eval.mode`` lacks it)."""
    out = [*job.overrides, f"+budget={budget}", *extra]
    if single and job.name != "hd" and not any(o.startswith("eval.mode=") for o in out):
        out.append(SINGLE_FRAME)
    if root:
        out.append(f"hydra.run.dir={os.path.join(root, job.name)}")
    return out


def run_dir(job: Job, budget: str, extra=(), root: str | None = None) -> str:
    """The job's run directory (the app's default, or ``<root>/<job>``). An evaluation's
    default directory names ``eval.mode``; a training run's does not."""
    if root:
        return os.path.join(root, job.name)
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from seglocnet_jax.app import hydra_glue

    hydra_glue.register_resolvers()
    name = "config" if job.app == "train" else "evaluate"
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        overrides = job_overrides(job, budget, extra, single=job.app == "evaluate")
        cfg = compose(name, overrides, return_hydra_config=True)
        return str(OmegaConf.select(cfg, "hydra.run.dir"))


def command(job: Job, budget: str, extra=(), root=None, *, single: bool = True) -> list[str]:
    return [
        sys.executable,
        "-m",
        f"seglocnet_jax.{job.app}",
        *job_overrides(job, budget, extra, root, single=single),
    ]


def ran_command(job: Job, budget: str, res: dict) -> str:
    """The command that made ``res`` (a run's results.json): without :data:`SINGLE_FRAME`
    when its config has no ``eval.mode`` (a checkout older than that key, where single-frame
    evaluation was all there was, ran the job without it)."""
    has_mode = "mode" in ((res.get("config") or {}).get("eval") or {})
    return shown(command(job, budget, single=has_mode))


def shown(cmd: list[str]) -> str:
    return " ".join(["python", *[shlex.quote(c) for c in cmd[1:]]])


def store_dir(budget: str) -> str:
    """The committed results store of a budget."""
    return os.path.join(REPO, "experiments", "results", budget)


def _commit(cwd: str, store: str | None = None) -> str:
    """``git rev-parse HEAD`` of the checkout the jobs run in, ``+dirty`` if tracked files
    differ from it, not counting the results store ``store`` (its entries are this script's
    output: a set run from a checkout that holds its own store would otherwise mark every row
    after the first dirty); ``unknown`` outside a git checkout."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, check=True
        ).stdout.strip()
        top = os.path.realpath(
            subprocess.run(
                ["git", "rev-parse", "--show-toplevel"],
                cwd=cwd,
                capture_output=True,
                text=True,
                check=True,
            ).stdout.strip()
        )
        spec = []
        if store is not None and os.path.commonpath([os.path.realpath(store), top]) == top:
            spec = ["--", ":/", f":(top,exclude){os.path.relpath(os.path.realpath(store), top)}"]
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", *spec],
            cwd=cwd,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def store_result(job: Job, budget: str, rdir: str, store: str) -> str:
    """Copies ``<rdir>/results.json`` into ``<store>/<job>.json`` (atomic) with the command
    that ran it (:func:`ran_command`), run directory and commit; an entry holding the same
    results keeps its commit and run directory (only a command stored wrongly by an older
    version of this script is corrected). An incomplete evaluation set is refused."""
    reason = incomplete_set(rdir)
    if reason is not None:
        raise ValueError(reason)
    with open(os.path.join(rdir, "results.json")) as f:
        res = json.load(f)
    path = os.path.join(store, f"{job.name}.json")
    from seglocnet_jax import fileio

    cmd = ran_command(job, budget, res)
    if os.path.exists(path):
        with open(path) as f:
            old = json.load(f)
        if old.get("results") == res:  # the same row: its commit and run directory stay
            if old.get("command") != cmd:  # stored by an older version of this script
                fileio.write_json_atomic(path, {**old, "command": cmd}, indent=1)
            return path
    entry = {
        "job": job.name,
        "budget": budget,
        "command": cmd,
        "run_dir": os.path.abspath(rdir),
        "commit": _commit(os.getcwd(), store),
        "stored_at": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "results": res,
    }
    os.makedirs(store, exist_ok=True)
    fileio.write_json_atomic(path, entry, indent=1)
    return path


def incomplete_set(rdir: str) -> str | None:
    """Why ``rdir``'s results cannot be stored (None: they can): its evaluation set was cut
    off while moving into place (``INCOMPLETE``), so its files may mix two evaluations."""
    from seglocnet_jax.app import evalset

    marker = evalset.incomplete(rdir)
    if marker is None:
        return None
    return (
        f"{marker}: the evaluation set of {rdir} is incomplete (cut off while moving into "
        "place; its files may mix two evaluations); rerun the job"
    )


def run(jobs, budget: str, extra=(), root=None, store: str | None = None) -> int:
    """Runs the jobs in order (each its own process, log in ``<run dir>/paper_job.log``) and
    stores each finished one (:func:`store_result`); returns the number that failed. Finished
    jobs are skipped (and stored)."""
    store = store or store_dir(budget)
    failed = 0
    for i, job in enumerate(jobs):
        rdir = run_dir(job, budget, extra, root)
        cut = incomplete_set(rdir)
        if cut is not None:
            print(f"[paper] {i + 1}/{len(jobs)} {job.name}: {cut}", flush=True)
        elif os.path.exists(os.path.join(rdir, "results.json")):
            print(f"[paper] {i + 1}/{len(jobs)} {job.name}: done ({rdir})", flush=True)
            print(f"[paper] stored {store_result(job, budget, rdir, store)}", flush=True)
            continue
        cmd = command(job, budget, extra, root)
        print(f"[paper] {i + 1}/{len(jobs)} {job.name}: {shown(cmd)}", flush=True)
        os.makedirs(rdir, exist_ok=True)
        t0 = time.time()
        with open(os.path.join(rdir, "paper_job.log"), "a") as log:
            rc = subprocess.call(cmd, cwd=os.getcwd(), stdout=log, stderr=subprocess.STDOUT)
        status = "ok" if rc == 0 else f"FAILED (exit {rc}, log {rdir}/paper_job.log)"
        print(f"[paper] {job.name}: {status} in {time.time() - t0:.0f} s", flush=True)
        if rc == 0:
            print(f"[paper] stored {store_result(job, budget, rdir, store)}", flush=True)
        failed += rc != 0
    return failed


def load(jobs, budget: str, store: str | None = None) -> dict:
    """``{job name: {"results", "dir", "command", "commit", "machine", "stale"}}`` from the store
    (results None when the job has no entry; ``machine``: the record of
    ``seglocnet_jax.app.runs.machine`` in the results, or, for a row run before results
    recorded it, the entry's own ``machine``, written by hand from ``docs/log.md``; None if
    neither). An entry of another job or budget is an error naming it.
    An entry whose command is not the job's as defined now (the job was redefined since, e.g.
    NM moved to the SD map and the OSM class raster) is stale: its results are left out (None)
    and ``stale`` holds the command it ran."""
    store = store or store_dir(budget)
    out = {}
    for job in jobs:
        path = os.path.join(store, f"{job.name}.json")
        entry = {}
        if os.path.exists(path):
            with open(path) as f:
                entry = json.load(f)
            if entry.get("job") != job.name or entry.get("budget") != budget:
                raise ValueError(
                    f"{path}: holds job {entry.get('job')!r} budget {entry.get('budget')!r}, "
                    f"expected job {job.name!r} budget {budget!r}"
                )
        results, stale = entry.get("results"), None
        if results is not None and entry.get("command") != ran_command(job, budget, results):
            results, stale = None, entry.get("command")
        out[job.name] = {
            "results": results,
            "dir": entry.get("run_dir") if stale is None else None,
            "command": entry.get("command") if results else shown(command(job, budget)),
            "commit": entry.get("commit") if stale is None else None,
            "machine": (results or {}).get("machine") or entry.get("machine"),
            "stale": stale,
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("action", choices=("run", "collect"))
    ap.add_argument("budget", help="budget=cpu | budget=paper")
    ap.add_argument("--only", default="", help="comma-separated job names (default: all)")
    ap.add_argument("--extra", nargs="*", default=[], help="overrides added to every job")
    ap.add_argument(
        "--root",
        default=None,
        help="run directories <root>/<job> (default: the app's own run directories)",
    )
    ap.add_argument(
        "--store",
        default=None,
        help="results store (default: experiments/results/<budget>, committed)",
    )
    ap.add_argument("--out", default=os.path.join(REPO, "docs", "results.md"))
    ap.add_argument("--figures", default=os.path.join(REPO, "docs"))
    ap.add_argument("--note", default="", help="a paragraph put under the header (collect)")
    args = ap.parse_args(argv)
    if not args.budget.startswith("budget="):
        ap.error(f"expected budget=cpu or budget=paper, got {args.budget!r}")
    budget = args.budget.split("=", 1)[1]
    if budget not in ("cpu", "paper"):
        ap.error(f"unknown budget {budget!r}; conf/budget has cpu, paper")
    names = [n for n in args.only.split(",") if n] or [j.name for j in JOBS]
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        ap.error(f"unknown job(s) {unknown}; jobs: {list(BY_NAME)}")
    jobs = [BY_NAME[n] for n in names]
    if args.action == "run":
        failed = run(jobs, budget, args.extra, args.root, args.store)
        print(f"[paper] {len(jobs) - failed}/{len(jobs)} jobs finished", flush=True)
        return 1 if failed else 0
    data = load(JOBS, budget, args.store)
    print(collect(data, budget, args.out, args.figures, args.note))
    return 0


if __name__ == "__main__":
    sys.exit(main())
