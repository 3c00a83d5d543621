"""The findings half of the paper's tables: each of the paper's findings checked against the
rows ``paper_tables.load`` read from the results store, and the provenance rules they follow
(rows of different commits are not compared; rows of different machines are named; gaps are
weighed against the seeds' own range). Imported by ``paper_report.py`` (the tables, figures and
``docs/results.md``) and ``paper_tables.py``; nothing here runs a job or writes a file."""

from __future__ import annotations

import math

# The training's warning threshold for a collapsed NM segmentation term (validation IoU of any
# class, percent): seglocnet_jax.app.train_run.NM_MIN_IOU, pinned equal by the tests.
NM_MIN_IOU = 5.0


def _num(res, split, key, lighting=None):
    """``key`` of a stored row on ``split`` (on the frames of one ``lighting``, from
    ``results.splits[split].lighting``, when given); None where not measured."""
    try:
        v = res["results"]["splits"][split]
        v = (v["lighting"][lighting] if lighting else v)[key]
    except (KeyError, TypeError):
        return None
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)


def _cell(v, digits=1):
    return "–" if v is None else f"{v:.{digits}f}"


SEEDS = ("hd", "hd_seed1", "hd_seed2")
# Each modality's seeds 0, 1, 2 (the fused model is the HD row).
MODALITY_SEEDS = {
    "camera only": ("camera", "camera_seed1", "camera_seed2"),
    "LiDAR only": ("lidar", "lidar_seed1", "lidar_seed2"),
    "fused": SEEDS,
}
# The modality table's columns: (heading, split, lighting or None for every frame).
MODALITY_COLS = (
    ("test", "test", None),
    ("Kouvola", "kouvola", None),
    ("test, night", "test", "night"),
    ("Kouvola, night", "kouvola", "night"),
)


def seed_stats(data, names, split, lighting=None, key="R@1m"):
    """``(values, mean, range)`` of ``key`` over the measured rows among ``names`` (one value
    per seed); None when none is measured or the measured ones ran at different commits (a
    mean over two codes is no seed mean)."""
    if len(_commits(data, names)) > 1:
        return None  # the findings say "rows from different commits"
    vals = [
        _num(data[n], split, key, lighting)
        for n in names
        if n in data and data[n]["results"] is not None
    ]
    vals = [v for v in vals if v is not None]
    if not vals:
        return None
    return vals, sum(vals) / len(vals), max(vals) - min(vals)


def _commits(data, names) -> list[str]:
    """The distinct commits of the measured rows ``names`` (sorted; None where unknown)."""
    found = {data[n].get("commit") for n in names if n in data and data[n]["results"] is not None}
    return sorted(found, key=str)


def _machine(d) -> str:
    """The short name of the machine a stored row ran on."""
    from seglocnet_jax.app.runs import machine_label

    return machine_label(d.get("machine"))


def _machines(data, names) -> list[str]:
    """The distinct machines of the measured rows ``names`` (sorted short names)."""
    return sorted({_machine(data[n]) for n in names if n in data and data[n]["results"]})


def seed_range(data) -> float | None:
    """Max - min R@1m over the HD row's measured seeds, the larger of Helsinki test and
    Kouvola (two held-out splits: three seeds can agree closely on one by chance; None: fewer
    than two seeds, or seeds measured at different commits: their spread would mix code
    changes with seed noise)."""
    if len(_commits(data, SEEDS)) > 1:
        return None
    spans = []
    for split in ("test", "kouvola"):
        seeds = [_num(data[n], split, "R@1m") for n in SEEDS if n in data]
        seeds = [v for v in seeds if v is not None]
        if len(seeds) >= 2:
            spans.append(max(seeds) - min(seeds))
    return max(spans) if spans else None


def findings(data) -> list[tuple[str, bool | None, str, str]]:
    """``(finding, holds (None: not measurable yet), measured, against the spread)`` per paper
    finding. The last: whether the gap that decides the finding (the smallest difference its
    comparison rests on) exceeds the HD row's seed range (:func:`seed_range`;
    "–" with fewer than two seeds or for a finding that is not a plain ordering)."""

    def r(name, key="R@1m", split="test"):
        return _num(data[name], split, key) if name in data else None

    out = []
    spread = seed_range(data)

    def add(text, names, values, check, gap=None, own_range=None):
        """``names``: the rows ``values`` come from; rows measured at different commits are
        not compared (the difference could be the code's, not the finding's). ``own_range``:
        the seed range of the compared rows themselves, weighed instead of the HD row's."""
        commits = _commits(data, names)
        if len(commits) > 1:
            shown = ", ".join(str(c)[:7] for c in commits)
            measured = " / ".join(_cell(v) for v in values)
            out.append((text, None, f"{measured}, rows from different commits ({shown})", "–"))
            return
        if any(v is None for v in values):
            out.append((text, None, "not all rows measured", "–"))
            return
        measured = " / ".join(f"{v:.1f}" for v in values)
        machines = _machines(data, names)
        if len(machines) > 1:  # same code, other kernels: differences of a few points
            measured += f"; rows from {len(machines)} machines ({', '.join(machines)})"
        margin = "–"  # the seed range weighs a gap of the seeds' own code only
        if gap is not None and own_range is not None:
            g = abs(gap(*values))
            margin = f"gap {g:.1f} {'>' if g > own_range else '≤'} their seed range {own_range:.1f}"
        elif gap is not None and spread is not None and commits == _commits(data, SEEDS):
            g = abs(gap(*values))
            margin = f"gap {g:.1f} {'>' if g > spread else '≤'} seed range {spread:.1f}"
        out.append((text, bool(check(*values)), measured, margin))

    seeds = [r(n) for n in SEEDS]
    add(
        "I: HD > NM > SD at R@1m (test)",
        ("hd", "nm", "sd"),
        [r("hd"), r("nm"), r("sd")],
        lambda a, b, c: a > b > c,
        lambda a, b, c: min(a - b, b - c, key=abs),
    )
    add(
        "I: NM behind SD at R@5m (test)",
        ("nm", "sd"),
        [r("nm", "R@5m"), r("sd", "R@5m")],
        lambda a, b: a < b,
    )
    add(
        "I: GT rows far above every trained one (R@1m test: GT-HD, GT-SD, best trained)",
        ("gt_hd", "gt_sd", "hd", "sd", "nm"),
        [
            r("gt_hd"),
            r("gt_sd"),
            max([v for v in (r("hd"), r("sd"), r("nm")) if v is not None], default=None),
        ],
        lambda a, b, c: min(a, b) > c + 10,
    )
    add(
        f"NM: its segmentation term did not collapse (road, building IoU ≥ {NM_MIN_IOU:g} %: "
        "test, Kouvola)",
        ("nm",),
        [r("nm", f"IoU_{c}", s) for c in ("road", "building") for s in ("test", "kouvola")],
        lambda *iou: min(iou) >= NM_MIN_IOU,
    )
    add(
        "III: HD and SD keep most accuracy on the unseen city (R@1m Kouvola / test)",
        ("hd", "sd"),
        [r("hd", split="kouvola"), r("hd"), r("sd", split="kouvola"), r("sd")],
        lambda a, b, c, d: a > 0.5 * b and c > 0.5 * d,
    )
    add(
        "III: NM collapses on the unseen city (R@1m Kouvola / test)",
        ("nm",),
        [r("nm", split="kouvola"), r("nm")],
        lambda a, b: a < 0.5 * b,
    )
    add(
        "IV: drivable area alone beats buildings alone (R@1m)",
        ("road", "building"),
        [r("road"), r("building")],
        lambda a, b: a > b,
        lambda a, b: a - b,
    )
    add(
        "IV: both together best (R@1m: both, road, building)",
        ("hd", "road", "building"),
        [r("hd"), r("road"), r("building")],
        lambda a, b, c: a > max(b, c),
        lambda a, b, c: a - max(b, c),
    )
    add(
        "V: 2.5 m best at R@1m (2.5 / 5 / 10 m)",
        ("sd_w2.5", "sd_w5", "sd"),
        [r("sd_w2.5"), r("sd_w5"), r("sd")],
        lambda a, b, c: a >= max(b, c),
        lambda a, b, c: a - max(b, c),
    )
    add(
        "V: 10 m best at R@5m (2.5 / 5 / 10 m)",
        ("sd_w2.5", "sd_w5", "sd"),
        [r("sd_w2.5", "R@5m"), r("sd_w5", "R@5m"), r("sd", "R@5m")],
        lambda a, b, c: c >= max(a, b),
    )
    # Modality: the means over each modality's measured seeds; the gap that decides is weighed
    # against the larger seed range of the two rows it lies between, once both have 2+ seeds
    # (not against the HD row's test range: these rows have their own spread).
    rows = [MODALITY_SEEDS[m] for m in ("fused", "camera only", "LiDAR only")]
    for where, split, lighting in MODALITY_COLS[:3]:
        stats = [seed_stats(data, names, split, lighting) for names in rows]
        counts = " / ".join(str(len(st[0])) if st else "0" for st in stats)
        values = [st[1] if st else None for st in stats]
        own = None
        if all(stats) and len(stats[0][0]) > 1:
            rival = 1 if values[1] > values[2] else 2
            if len(stats[rival][0]) > 1:
                own = max(stats[0][2], stats[rival][2])
        add(
            "Modality (not in the paper): fused beats camera only and LiDAR only (R@1m "
            f"{where}, mean of {counts} seeds: fused, camera, LiDAR)",
            sum(rows, ()),
            values,
            lambda a, b, c: a > max(b, c),
            (lambda a, b, c: a - max(b, c)) if own is not None else None,
            own_range=own,
        )
    if all(v is not None for v in seeds) and len(_commits(data, SEEDS)) <= 1:
        import numpy as np

        shown = f"test {np.mean(seeds):.1f} ± {np.std(seeds, ddof=1):.1f}"
        unseen = [r(n, split="kouvola") for n in SEEDS]
        if all(v is not None for v in unseen):
            shown += f", Kouvola {np.mean(unseen):.1f} ± {np.std(unseen, ddof=1):.1f}"
        out.append(
            (
                "seed spread of the HD row (R@1m, 3 seeds: mean ± std)",
                None,
                shown,
                f"range {spread:.1f} (the larger of test and Kouvola)",
            )
        )
    return out
