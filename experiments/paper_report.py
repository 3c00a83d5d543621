"""The collecting half of ``experiments/paper_tables.py``: the paper's quoted numbers, the
tables in the paper's layout, one grouped-bar figure per table and the findings (checked in
``paper_findings.py``), from the rows ``paper_tables.load`` read from the results store
(``collect`` writes ``docs/results.md``). Imported by ``paper_tables.py`` (its sibling: the
scripts' directory is on ``sys.path`` when it runs); nothing here runs a job."""

from __future__ import annotations

import os

from paper_findings import (
    MODALITY_COLS,
    MODALITY_SEEDS,
    NM_MIN_IOU,
    _cell,
    _commits,
    _machine,
    _machines,
    _num,
    findings,
    seed_stats,
)

# The paper's numbers quoted by the project's tracker (nuScenes for Table I; Argoverse Miami ->
# Pittsburgh for III; Argoverse Miami for IV and V). None: not quoted.
PAPER = {
    "I": {
        "hd": {"R@1m": 59.1},
        "sd": {"R@1m": 35.6, "R@5m": 74.6},
        "nm": {"R@1m": 48.2, "R@5m": 61.6},
        "gt_hd": {"R@1m": 89.3},
        "gt_sd": {"R@1m": 91.4},
    },
    "III": {"hd": (55.9, 55.7), "sd": (48.4, 33.0), "nm": (43.7, 9.6)},
    "IV": {"road": {"R@1m": 42.5}, "building": {"R@1m": 37.4}, "hd": {"R@1m": 55.9}},
    "V": {"sd_w2.5": {"R@5m": 75.2}, "sd_w5": {"R@5m": 76.9}, "sd": {"R@5m": 80.3}},
}
COLS = ("R@1m", "R@2m", "R@5m", "R@10m", "R@1deg", "R@2deg", "R@5deg", "R@10deg", "APE", "AOE")
HEAD = {c: c.replace("deg", "°") for c in COLS}
IOU = ("IoU_road", "IoU_building")


def _wall(res) -> str:
    r = res["results"] or {}
    t = (r.get("time") or {}).get("total_s")
    return "–" if t is None else f"{t / 60:.1f} min"


def _row_table(title, rows, data, split, paper=None, paper_label="paper"):
    """A paper-layout table: one row per job on ``split`` (+ IoU, wall time, command)."""
    head = ["Method", *(HEAD[c] for c in COLS), *IOU, "wall", "command"]
    lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, name in rows:
        d = data[name]
        vals = [_cell(_num(d, split, c), 2 if c in ("APE", "AOE") else 1) for c in COLS]
        ious = [_cell(_num(d, split, c)) for c in IOU]
        cmd = f"`{d['command']}`"
        if d.get("commit"):
            cmd += f" @{d['commit'][:7]}{'+dirty' if d['commit'].endswith('+dirty') else ''}"
        if d["results"] is None:
            vals, ious = ["not run"] + ["–"] * (len(COLS) - 1), ["–"] * 2
        else:
            cmd += f" · {_machine(d)}"
        lines.append(f"| {label} | " + " | ".join([*vals, *ious, _wall(d), cmd]) + " |")
        if paper and name in paper:
            p = paper[name]
            pv = [_cell(p.get(c)) if isinstance(p, dict) else "–" for c in COLS]
            lines.append(f"| ↳ {paper_label} | " + " | ".join([*pv, "–", "–", "–", ""]) + " |")
    prior = next((data[n] for _, n in rows if data[n]["results"]), None)
    if prior:
        p = prior["results"]["splits"].get(split, {}).get("prior", {})
        pv = [_cell(p.get(c)) for c in COLS]
        lines.append("| prior alone (tile centre) | " + " | ".join([*pv, "–", "–", "", ""]) + " |")
    return "\n".join(lines)


def _save(fig, path):
    """Writes a figure to ``path`` through a temporary name, then closes it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)


def _figure(path, title, groups, data, split):
    """Grouped bars of R@1m / R@5m / R@1° per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    metrics = ("R@1m", "R@5m", "R@1deg")
    labels = [label.replace(", ", ",\n").replace(" (", "\n(") for label, _ in groups]
    fig, ax = plt.subplots(figsize=(1.6 + 1.2 * len(groups), 3.4), dpi=100)
    x = np.arange(len(groups))
    for g, (_, name) in enumerate(groups):
        if data[name]["results"] is None:  # not measured: say so, never draw a zero
            ax.text(x[g], 4, "not run", ha="center", fontsize=8, color="0.4")
    for i, m in enumerate(metrics):
        vals = [_num(data[n], split, m) for _, n in groups]
        xs = [x[g] + (i - 1) * 0.27 for g, v in enumerate(vals) if v is not None]
        bars = ax.bar(xs, [v for v in vals if v is not None], 0.27, label=HEAD[m])
        ax.bar_label(bars, fmt="%.0f", fontsize=7)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylim(0, 112)
    ax.set_ylabel("recall (%)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.28), frameon=False)
    _save(fig, path)


def _modality_table(data) -> str:
    """R@1m per modality as the mean over its measured seeds (min–max), on every frame and on
    the night frames of each split."""
    head = ["Modality", "seeds", *(c[0] for c in MODALITY_COLS)]
    lines = [
        "**Modality over seeds: R@1m, mean (min–max) over the seeds measured**",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for label, names in MODALITY_SEEDS.items():
        cells = []
        for _, split, lighting in MODALITY_COLS:
            st = seed_stats(data, names, split, lighting)
            cells.append("–" if st is None else f"{st[1]:.1f} ({min(st[0]):.1f}–{max(st[0]):.1f})")
        measured = [n for n in names if n in data and data[n]["results"] is not None]
        seeds = ", ".join(str(names.index(n)) for n in measured) or "none"
        if len(_commits(data, names)) > 1:
            seeds += " (different commits: no mean)"
        machines = len(_machines(data, names))
        if machines > 1:
            seeds += f" ({machines} machines)"
        lines.append(f"| {label} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _modality_figure(path, data):
    """Bars of each modality's seed-mean R@1m per column of the modality table, whiskers from
    the lowest to the highest seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 3.4), dpi=100)
    x = np.arange(len(MODALITY_COLS))
    width = 0.8 / len(MODALITY_SEEDS)
    for i, (label, names) in enumerate(MODALITY_SEEDS.items()):
        stats = [seed_stats(data, names, split, lt) for _, split, lt in MODALITY_COLS]
        xs = [x[j] + (i - 1) * width for j, st in enumerate(stats) if st]
        shown = [st for st in stats if st]
        err = [[st[1] - min(st[0]) for st in shown], [max(st[0]) - st[1] for st in shown]]
        bars = ax.bar(xs, [st[1] for st in shown], width, yerr=err, capsize=3, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=7, padding=2)
    ax.set_xticks(x, [c[0] for c in MODALITY_COLS], fontsize=8)
    ax.set_ylim(0, 100)
    ax.set_ylabel("R@1m (%)")
    ax.set_title("Modality (HD map): the mean over seeds, whiskers from min to max", fontsize=9)
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.12), frameon=False)
    _save(fig, path)


def collect(data, budget: str, out_md: str, fig_dir: str, note: str = "") -> str:
    os.makedirs(fig_dir, exist_ok=True)
    rel = os.path.relpath(fig_dir, os.path.dirname(os.path.abspath(out_md)))
    parts = [
        f"# Results: the paper's tables on the embedded benchmark (budget `{budget}`)",
        "",
        "Measured by `python experiments/paper_tables.py run budget="
        f"{budget}` and collected by `python experiments/paper_tables.py collect budget={budget}`"
        " (each row's own command is in its last column). Data: the simulator over real OSM "
        "Helsinki (train / val / test, spatially disjoint) and Kouvola (never trained on: the "
        "generalization test, the paper's Miami → Pittsburgh). Recalls in %, APE in m, AOE in °, "
        "IoU of the predicted BEV in %. The paper's numbers (↳ rows) are on nuScenes (Table I) "
        "and Argoverse (III–V), quoted where the project tracks them. Each command ends with the "
        "commit it ran at (`@abc1234`) and the machine that computed it (the same run differs "
        "between CPUs in its last digits: XLA's kernels depend on the instruction set). "
        "Every row but HD runs with `eval.mode=single` "
        "(single-frame evaluation only; at commits before that key existed, single-frame was "
        "all there was); the HD row is the main job and also tracks the drives "
        "(README, sequential localization). The NM row is the paper's SegLocNet-NM: its neural "
        "map reads the multi-class OSM raster (road classes, paths, buildings, parking, green, "
        "water), its segmentation term and priors use the SD map (10 m); its IoU columns show "
        "whether that segmentation term survived training (the training warns below "
        f"{NM_MIN_IOU:g} % IoU of any class on validation).",
        "",
        *([note, ""] if note else []),
    ]
    tables = [
        (
            "I",
            "Table I — map kinds and the GT-segmentation upper bound (Helsinki test)",
            [
                ("SegLocNet-HD", "hd"),
                ("SegLocNet-SD (10 m)", "sd"),
                ("SegLocNet-NM (OSM classes)", "nm"),
                ("GT segmentation, HD", "gt_hd"),
                ("GT segmentation, SD", "gt_sd"),
            ],
            "test",
        ),
        (
            "III",
            "Table III — generalization: trained on Helsinki, tested on Kouvola",
            [
                ("SegLocNet-HD", "hd"),
                ("SegLocNet-SD (10 m)", "sd"),
                ("SegLocNet-NM (OSM classes)", "nm"),
                ("GT segmentation, HD", "gt_hd"),
                ("GT segmentation, SD", "gt_sd"),
            ],
            "kouvola",
        ),
        (
            "IV",
            "Table IV — map channels (HD map, Helsinki test)",
            [("drivable area only", "road"), ("buildings only", "building"), ("both", "hd")],
            "test",
        ),
        (
            "V",
            "Table V — SD road width (Helsinki test)",
            [("2.5 m", "sd_w2.5"), ("5 m", "sd_w5"), ("10 m", "sd")],
            "test",
        ),
        (
            "modality",
            "Modality (HD map, same budget; not in the paper), Helsinki test, seed 0",
            [("camera only", "camera"), ("LiDAR only", "lidar"), ("fused", "hd")],
            "test",
        ),
        (
            "seeds",
            "Seed spread (HD row, three seeds), Helsinki test",
            [("seed 0", "hd"), ("seed 1", "hd_seed1"), ("seed 2", "hd_seed2")],
            "test",
        ),
    ]
    for key, title, rows, split in tables:
        paper = PAPER.get(key)
        if key == "III":
            paper = {n: {"R@1m": v[1]} for n, v in PAPER["III"].items()}
        parts.append(_row_table(title, rows, data, split, paper))
        if key == "III":
            parts.append("")
            parts.append(
                "Paper, Argoverse R@1m Miami → Pittsburgh: "
                + ", ".join(f"{n.upper()} {a} → {b}" for n, (a, b) in PAPER["III"].items())
            )
        fig = os.path.join(fig_dir, f"results_{key.lower()}.png")
        if key == "modality":  # seed 0's full row above, every seed's R@1m below
            parts += ["", _modality_table(data)]
            _modality_figure(fig, data)
            title = "Modality over seeds, R@1m"
        else:
            _figure(fig, title, rows, data, split)
        parts += ["", f"![{title}]({os.path.join(rel, os.path.basename(fig))})", ""]
        if key == "III":  # the same rows on both cities side by side
            parts.append("")
    parts += [
        "## Findings",
        "",
        "The last column compares the gap that decides a finding with the HD row's seed range "
        "(max − min R@1m over its seeds, the larger of Helsinki test and Kouvola): a gap within "
        "it may be run-to-run noise. The modality findings compare means over seeds and weigh "
        "the gap against the compared rows' own seed range.",
        "",
        "| finding | holds here | measured | against the seed spread |",
        "|---|---|---|---|",
    ]
    for text, holds, measured, margin in findings(data):
        verdict = "–" if holds is None else ("yes" if holds else "no")
        parts.append(f"| {text} | {verdict} | {measured} | {margin} |")
    missing = [
        n
        + (
            f" (its stored row ran `{d['stale']}`, before the job was redefined)"
            if d.get("stale")
            else ""
        )
        for n, d in data.items()
        if d["results"] is None
    ]
    if missing:
        parts += ["", f"Not yet measured: {', '.join(missing)} (run the set again to fill them)."]
    text = "\n".join(parts) + "\n"
    from seglocnet_jax import fileio

    fileio.write_text_atomic(out_md, text)
    return text
