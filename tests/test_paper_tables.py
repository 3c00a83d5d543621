"""experiments/paper_tables.py on a tiny set (2 jobs, a few steps): runs each job through the
apps, skips finished jobs on a rerun, and collects docs-style tables with figures."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys

import pytest

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "experiments", "paper_tables.py")


def _module():
    """The script as a module (dataclasses look their module up in ``sys.modules``)."""
    spec = importlib.util.spec_from_file_location("paper_tables", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("paper_tables", mod)
    spec.loader.exec_module(mod)
    return mod


def _tiny(data_root):
    return [
        f"data.root={data_root}",
        "data.name=tiny",
        "data.test_city=null",
        "data.num_val_drives=0",  # no drive splits: not rendered
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
        "eval.mode=single",  # no drive splits: not tracked
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
    store = tmp_path / "store"
    common = [
        "budget=cpu",
        "--root",
        str(root),
        "--store",
        str(store),
        "--extra",
        *_tiny(tmp_path / "data"),
    ]
    proc = _script("run", *common[:5], "--only", "hd,gt_hd", *common[5:], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (root / "hd" / "results.json").exists() and (root / "gt_hd" / "results.json").exists()
    again = _script("run", *common[:5], "--only", "hd", *common[5:], cwd=tmp_path)
    assert again.returncode == 0 and "hd: done" in again.stdout  # finished: not rerun
    entry = json.loads((store / "hd.json").read_text())
    assert entry["results"] == json.loads((root / "hd" / "results.json").read_text())
    assert entry["job"] == "hd" and entry["budget"] == "cpu" and entry["commit"] == "unknown"
    assert entry["command"] == "python -m seglocnet_jax.train +budget=cpu"
    shutil.rmtree(root)  # collect reads the committed store only, not the run directories

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
    assert "@unknown" in rows["SegLocNet-HD"]  # the commit of the code that ran the row
    from seglocnet_jax.app.runs import machine, machine_label

    assert entry["results"]["machine"]["cpu"] == machine()["cpu"]  # what computed the row
    assert f"@unknown · {machine_label(machine())}" in rows["SegLocNet-HD"]
    assert "| I: HD > NM > SD at R@1m (test) | – | not all rows measured |" in text
    for key in ("i", "iii", "iv", "v", "modality", "seeds"):
        assert (figs / f"results_{key}.png").stat().st_size > 1000


def test_store_entry_of_another_job_is_refused(tmp_path):
    mod = _module()
    (tmp_path / "sd.json").write_text(json.dumps({"job": "hd", "budget": "cpu", "results": {}}))
    with pytest.raises(
        ValueError, match=r"sd\.json: holds job 'hd' budget 'cpu', expected job 'sd'"
    ):
        mod.load(mod.JOBS, "cpu", str(tmp_path))
    assert mod.load(mod.JOBS[:1], "cpu", str(tmp_path))["hd"]["results"] is None


def test_stored_command_is_the_one_that_ran(tmp_path):
    # A row run at a checkout older than eval.mode (its config has no such key) ran without
    # eval.mode=single: the store says so, and re-storing corrects an entry that claimed it,
    # keeping the entry's commit and run directory.
    mod = _module()
    job, rdir, store = mod.BY_NAME["sd"], tmp_path / "run", tmp_path / "store"
    rdir.mkdir()
    old = {"splits": {}, "config": {"eval": {"splits": ["test"]}}}
    (rdir / "results.json").write_text(json.dumps(old))
    store.mkdir()
    wrong = "python -m seglocnet_jax.train map=sd +budget=cpu eval.mode=single"
    (store / "sd.json").write_text(
        json.dumps(
            {
                "job": "sd",
                "budget": "cpu",
                "command": wrong,
                "commit": "abc",
                "run_dir": "/elsewhere",
                "results": old,
            }
        )
    )
    mod.store_result(job, "cpu", str(rdir), str(store))
    entry = json.loads((store / "sd.json").read_text())
    assert entry["command"] == "python -m seglocnet_jax.train map=sd +budget=cpu"
    assert entry["commit"] == "abc" and entry["run_dir"] == "/elsewhere"
    new = {"splits": {}, "config": {"eval": {"mode": "single"}}}
    (rdir / "results.json").write_text(json.dumps(new))
    mod.store_result(job, "cpu", str(rdir), str(store))
    assert json.loads((store / "sd.json").read_text())["command"] == wrong


def test_findings_weigh_the_deciding_gap_against_the_seed_range():
    mod = _module()

    def row(r1):
        return {"results": {"splits": {"test": {"R@1m": r1}}}}

    data = {n: {"results": None} for n in mod.BY_NAME}
    data.update(hd=row(54.0), road=row(47.0), building=row(44.0))
    by_text = {f[0]: f for f in mod.findings(data)}
    road = by_text["IV: drivable area alone beats buildings alone (R@1m)"]
    assert road[1] is True and road[3] == "–"  # one seed: no spread to compare with
    data["hd_seed1"] = row(59.0)  # seed range 5.0
    by_text = {f[0]: f for f in mod.findings(data)}
    road = by_text["IV: drivable area alone beats buildings alone (R@1m)"]
    both = by_text["IV: both together best (R@1m: both, road, building)"]
    assert road[1] is True and road[3] == "gap 3.0 ≤ seed range 5.0"
    assert both[1] is True and both[3] == "gap 7.0 > seed range 5.0"
    assert by_text["I: HD > NM > SD at R@1m (test)"][1] is None

    def modality(data):
        return {f[0]: f[1:] for f in mod.findings(data) if f[0].startswith("Modality")}

    data.update(camera=row(8.0), lidar=row(60.0))  # the fused row at seed 0 is hd
    test = "Modality (not in the paper): fused beats camera only and LiDAR only (R@1m test, mean"
    # fused: the mean of its 2 seeds; one LiDAR seed: no range of its own to weigh the gap
    assert modality(data)[f"{test} of 2 / 1 / 1 seeds: fused, camera, LiDAR)"] == (
        False,
        "56.5 / 8.0 / 60.0",
        "–",
    )
    data.update(lidar_seed1=row(52.0), hd_seed2=row(58.0))  # LiDAR range 8.0, fused 5.0
    assert modality(data)[f"{test} of 3 / 1 / 2 seeds: fused, camera, LiDAR)"] == (
        True,
        "57.0 / 8.0 / 56.0",
        "gap 1.0 ≤ their seed range 8.0",
    )


def test_rows_from_different_commits_are_not_compared():
    # A partial rerun leaves rows of older code in the store: a finding over rows of two
    # commits (or a seed range over seeds of two commits) would compare code, not settings.
    mod = _module()

    def row(r1, commit):
        return {"results": {"splits": {"test": {"R@1m": r1}}}, "commit": commit}

    data = {n: {"results": None} for n in mod.BY_NAME}
    data.update(hd=row(63.0, "new"), road=row(47.0, "old"), building=row(44.0, "old"))
    by_text = {f[0]: f for f in mod.findings(data)}
    both = by_text["IV: both together best (R@1m: both, road, building)"]
    assert both[1:] == (None, "63.0 / 47.0 / 44.0, rows from different commits (new, old)", "–")
    road = by_text["IV: drivable area alone beats buildings alone (R@1m)"]
    assert road[1] is True  # one commit: compared
    data.update(hd_seed1=row(59.0, "new"), hd_seed2=row(54.0, "old"))
    assert mod.seed_range(data) is None
    assert not [f for f in mod.findings(data) if f[0].startswith("seed spread")]
    data["hd_seed2"]["commit"] = "new"
    assert mod.seed_range(data) == 9.0
    # the unseen city's spread counts too: three seeds can agree on one split by chance
    for name, unseen in (("hd", 50.0), ("hd_seed1", 61.0)):
        data[name]["results"]["splits"]["kouvola"] = {"R@1m": unseen}
    assert mod.seed_range(data) == 11.0
    for name in ("hd", "hd_seed1"):
        del data[name]["results"]["splits"]["kouvola"]
    by_text = {f[0]: f for f in mod.findings(data)}
    road = by_text["IV: drivable area alone beats buildings alone (R@1m)"]
    assert road[1:] == (True, "47.0 / 44.0", "–")  # the seeds' range is the new code's
    data.update(road=row(47.0, "new"), building=row(44.0, "new"))
    road = {f[0]: f for f in mod.findings(data)}[road[0]]
    assert road[3] == "gap 3.0 ≤ seed range 9.0"


def test_rows_from_different_machines_are_compared_and_named(tmp_path):
    # The same code gives other last digits on another CPU (XLA's kernels follow the
    # instruction set): a finding over rows of two machines says which.
    mod = _module()
    import paper_report

    zen = {"backend": "cpu", "cpu": "AMD EPYC", "isa": ["avx2", "fma"]}
    xeon = {"backend": "cpu", "cpu": "Intel Xeon", "isa": ["avx2", "fma", "avx512f"]}

    def row(r1, machine):
        split = {"test": {"R@1m": r1}}
        return {"results": {"splits": split}, "commit": "c", "machine": machine, "command": "x"}

    data = {n: {"results": None} for n in mod.BY_NAME}
    data.update(hd=row(63.0, zen), road=row(47.0, zen), building=row(44.0, xeon))
    by_text = {f[0]: f for f in mod.findings(data)}
    road = by_text["IV: drivable area alone beats buildings alone (R@1m)"]
    assert road[1:3] == (
        True,
        "47.0 / 44.0; rows from 2 machines (AMD EPYC (no AVX-512), Intel Xeon (AVX-512))",
    )
    assert by_text["IV: both together best (R@1m: both, road, building)"][2].startswith(
        "63.0 / 47.0 / 44.0; rows from 2 machines"
    )
    data.update(road=row(47.0, xeon))
    road = {f[0]: f for f in mod.findings(data)}[road[0]]
    assert road[1:3] == (True, "47.0 / 44.0")  # one machine: nothing to say
    data.update(lidar=row(55.0, zen), lidar_seed1=row(57.0, xeon))
    assert "| LiDAR only | 0, 1 (2 machines) | 56.0 (55.0–57.0) |" in (
        paper_report._modality_table(data)
    )
    table = paper_report._row_table("IV", [("r", "road")], data, "test")
    assert "· Intel Xeon (AVX-512) |" in table
    # A row stored before results recorded the machine: the entry's hand-written record.
    res = {"splits": {"test": {"R@1m": 50.0}}, "config": {"eval": {}}}
    entry = {"job": "road", "budget": "cpu", "results": res, "machine": zen}
    entry["command"] = "python -m seglocnet_jax.train map.channels=[road] +budget=cpu"
    (tmp_path / "road.json").write_text(json.dumps(entry))
    assert mod.load([mod.BY_NAME["road"]], "cpu", str(tmp_path))["road"]["machine"] == zen


def test_nm_job_is_the_papers_nm_measured_beside_hd_and_sd():
    """The NM row trains on the SD map (paper: road width 10) with the neural map over the OSM
    class raster, and is evaluated on the same splits as HD and SD (test and the unseen
    city), single-frame like every row but HD."""
    from hydra import compose, initialize_config_dir

    from seglocnet_jax.app import hydra_glue
    from seglocnet_jax.app.datasets import reads_osm_classes
    from seglocnet_jax.app.schema import build_experiment

    mod = _module()
    overrides = {n: mod.job_overrides(mod.BY_NAME[n], "cpu") for n in ("hd", "sd", "nm")}
    assert overrides["nm"] == ["map=sd", "model.variant=nm", "+budget=cpu", "eval.mode=single"]
    hydra_glue.register_resolvers()
    exps = {}
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        for name, ovr in overrides.items():
            exps[name] = build_experiment(hydra_glue.to_tree(compose("config", ovr)))
    nm, sd = exps["nm"], exps["sd"]
    assert (nm.map.kind, nm.map.road_width, nm.model.variant) == ("sd", 10.0, "nm")
    assert nm.map == sd.map and reads_osm_classes(nm) and not reads_osm_classes(sd)
    assert "kouvola" in nm.eval.splits and nm.eval.splits == sd.eval.splits
    assert nm.eval.splits == exps["hd"].eval.splits


def test_nm_row_shows_its_iou_and_a_redefined_job_is_not_reported(tmp_path):
    mod = _module()
    import paper_findings  # the sibling modules paper_tables put on the path
    import paper_report

    from seglocnet_jax.app import train_run

    assert paper_findings.NM_MIN_IOU == train_run.NM_MIN_IOU  # one threshold
    old = "python -m seglocnet_jax.train model.variant=nm +budget=cpu"  # the HD-map NM
    res = {"splits": {"test": {"R@1m": 82.3, "IoU_road": 0.1}}, "config": {"eval": {}}}
    (tmp_path / "nm.json").write_text(
        json.dumps({"job": "nm", "budget": "cpu", "command": old, "results": res})
    )
    data = mod.load(mod.JOBS, "cpu", str(tmp_path))
    assert data["nm"]["results"] is None and data["nm"]["stale"] == old
    assert data["nm"]["command"] == (
        "python -m seglocnet_jax.train map=sd model.variant=nm +budget=cpu eval.mode=single"
    )
    text = paper_report._row_table("I", [("NM", "nm")], data, "test")
    assert "| NM | not run |" in text

    res["config"]["eval"]["mode"] = "single"
    data["nm"] = {"results": res, "command": data["nm"]["command"], "commit": None}
    row = paper_report._row_table("I", [("NM", "nm")], data, "test").splitlines()[4]
    cells = [c.strip() for c in row.split("|")]
    assert cells[2] == "82.3" and cells[12] == "0.1"  # R@1m ... IoU_road beside the recalls
    collapse = [f for f in mod.findings(data) if f[0].startswith("NM: its segmentation")]
    assert collapse == [(collapse[0][0], None, "not all rows measured", "–")]  # no Kouvola
    res["splits"]["kouvola"] = {"R@1m": 70.0, "IoU_road": 12.0}
    collapse = [f for f in mod.findings(data) if f[0].startswith("NM: its segmentation")]
    assert collapse[0][1:3] == (None, "not all rows measured")  # no building IoU
    # Every class counts: healthy roads do not hide collapsed buildings (road test, Kouvola,
    # then building test, Kouvola).
    res["splits"]["test"].update(IoU_road=20.3, IoU_building=0.6)
    res["splits"]["kouvola"]["IoU_building"] = 0.7
    collapse = [f for f in mod.findings(data) if f[0].startswith("NM: its segmentation")]
    assert collapse[0][1:3] == (False, "20.3 / 12.0 / 0.6 / 0.7")
    res["splits"]["test"]["IoU_building"] = res["splits"]["kouvola"]["IoU_building"] = 5.0
    collapse = [f for f in mod.findings(data) if f[0].startswith("NM: its segmentation")]
    assert collapse[0][1:3] == (True, "20.3 / 12.0 / 5.0 / 5.0")


def test_modality_table_shows_seed_means_and_night_frames():
    mod = _module()
    import paper_report

    def row(r1, night, commit="c"):
        split = {"R@1m": r1, "lighting": {"night": {"R@1m": night}}}
        return {"results": {"splits": {"test": split}}, "commit": commit}

    data = {n: {"results": None} for n in mod.BY_NAME}
    data.update(hd=row(60.0, 50.0), hd_seed1=row(64.0, 40.0), lidar=row(55.0, 45.0))
    table = paper_report._modality_table(data)
    assert "| fused | 0, 1 | 62.0 (60.0–64.0) | – | 45.0 (40.0–50.0) | – |" in table
    assert "| LiDAR only | 0 | 55.0 (55.0–55.0) | – | 45.0 (45.0–45.0) | – |" in table
    assert "| camera only | none | – | – | – | – |" in table
    data["lidar_seed2"] = row(57.0, 45.0, commit="other")
    assert "| LiDAR only | 0, 2 (different commits: no mean) | – | – | – | – |" in (
        paper_report._modality_table(data)
    )


def test_the_results_store_does_not_make_the_checkout_dirty(tmp_path, monkeypatch):
    """A set run from a checkout that holds its own store (``run`` -> ``store_result``): the
    rows stored after the first still name the clean commit; a change to the code, or to a
    store outside the checkout, still shows as ``+dirty``."""
    mod = _module()
    repo = tmp_path / "repo"
    store = repo / "experiments" / "results" / "cpu"
    store.mkdir(parents=True)
    (store / "hd.json").write_text("{}")
    (repo / "code.py").write_text("x = 1\n")

    def git(*args):
        return subprocess.run(
            ["git", *args], cwd=repo, check=True, capture_output=True, text=True
        ).stdout.strip()

    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
    head = git("rev-parse", "HEAD")
    monkeypatch.chdir(repo)  # the jobs run in the checkout
    rdir = tmp_path / "run"
    rdir.mkdir()

    def stored(job, splits, where=store):
        (rdir / "results.json").write_text(json.dumps({"splits": splits, "config": {}}))
        return json.loads(
            open(mod.store_result(mod.BY_NAME[job], "cpu", str(rdir), str(where))).read()
        )["commit"]

    assert stored("hd", {"test": 1}) == head  # rewrites the tracked hd.json
    assert stored("sd", {"test": 2}) == head  # the store's own write is not a change
    (repo / "code.py").write_text("x = 2\n")
    assert stored("road", {"test": 3}) == head + "+dirty"
    (repo / "code.py").write_text("x = 1\n")
    (store / "hd.json").write_text("[]")  # tracked, changed, but not the store named
    assert stored("building", {"test": 4}, where=tmp_path / "elsewhere") == head + "+dirty"
