"""experiments/paper_tables.py on a tiny set (2 jobs, a few steps): runs each job through the
apps, skips finished jobs on a rerun, and collects docs-style tables with figures."""

import os
import subprocess
import sys

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "experiments", "paper_tables.py")


def _tiny(data_root):
    return [
        f"data.root={data_root}",
        "data.name=tiny",
        "data.test_city=null",
        "data.num_train=16",
        "data.num_val=8",
        "data.num_test=8",
        "data.shard_size=8",
        "data.render_batch=8",
        "loader.max_points=4096",
        "loader.num_threads=0",
        "model.modality=lidar",
        "solver.num_rotations=64",
        "train.batch_size=2",
        "train.num_steps=2",
        "train.num_devices=1",
        "train.eval_every=0",
        "train.val_batches=1",
        "train.log_every=1",
        "train.optim.warmup_steps=1",
        "train.checkpoint.every_steps=2",
        "eval.splits=[test]",
        "eval.num_figures=0",
        "eval.batch_size=4",
        "eval.max_batches=1",
    ]


def _script(*args, cwd):
    return subprocess.run(
        [sys.executable, SCRIPT, *args], cwd=cwd, capture_output=True, text=True, timeout=900
    )


def test_run_skip_and_collect(tmp_path):
    root, out, figs = tmp_path / "runs", tmp_path / "results.md", tmp_path / "figs"
    common = ["budget=cpu", "--root", str(root), "--extra", *_tiny(tmp_path / "data")]
    proc = _script("run", *common[:3], "--only", "hd,gt_hd", *common[3:], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (root / "hd" / "results.json").exists() and (root / "gt_hd" / "results.json").exists()
    again = _script("run", *common[:3], "--only", "hd", *common[3:], cwd=tmp_path)
    assert again.returncode == 0 and "hd: done" in again.stdout  # finished: not rerun

    proc = _script("collect", *common, "--out", str(out), "--figures", str(figs), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    rows = {}  # first occurrence: Table I (Helsinki test)
    for line in text.splitlines():
        if line.startswith("| "):
            rows.setdefault(line.split("|")[1].strip(), line)
    assert "not run" not in rows["SegLocNet-HD"] and "not run" in rows["SegLocNet-SD (10 m)"]
    assert (
        "python -m seglocnet_jax.evaluate eval.bev_source=gt +budget=cpu"
        in rows["GT segmentation, HD"]
    )
    gt = rows["GT segmentation, HD"].split("|")
    assert float(gt[2]) >= 50.0 and float(gt[6]) >= 50.0  # R@1m, R@1° of GT labels (K = 64)
    assert "| I: HD > SD > NM at R@1m (test) | – | not all rows measured |" in text
    for key in ("i", "iii", "iv", "v", "modality", "seeds"):
        assert (figs / f"results_{key}.png").stat().st_size > 1000
