"""`bid tables`: the result tables of many `bid evaluate` runs, laid out like the paper's.

Reads every `summary.json` under a folder (one `bid evaluate --out` each) and writes one
Markdown document: the NoCrash table (Town01/Town02: SR, SSR, TL per density), the
leaderboard table (Town05: APA = RC, ADG = DS and the infraction counts) and the paper's
infraction table (DS, SR, IP, PA = RC, ABD, IRL = TL, CWO = CL, CWP = CP, CWV = CV), one row
per run, next to the figures the BID paper reports. A run is named by its folder.
"""

from __future__ import annotations

import json
from pathlib import Path

from bid_sim import metrics as m
from bid_sim.errors import BidError

# What the BID paper reports (the targets of our issue 7), for the rows "paper BID".
PAPER_NOCRASH = {"none": {"SR": 100, "SSR": 100}, "normal": {"SR": 99, "SSR": 97},
                 "crowded": {"SR": 83, "SSR": 77}}
PAPER_TOWN05 = {"RC": 98, "DS": 68}
DENSITY_ORDER = ("none", "normal", "crowded")
INFRACTION_COLUMNS = (("DS", "DS"), ("SR", "SR"), ("IP", "IP"), ("PA", "RC"), ("ABD", "ABD"),
                      ("IRL", "TL"), ("CWO", "CL"), ("CWP", "CP"), ("CWV", "CV"))


def load_runs(folder: str | Path) -> dict[str, dict]:
    """{run name: summary} of every `summary.json` under `folder`, by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BidError(f"{folder} does not exist; run `bid evaluate --out {folder}/NAME` first")
    runs = {}
    for path in sorted(folder.rglob("summary.json")):
        summary = json.loads(path.read_text())
        if "config" in summary and "all" in summary:
            name = path.parent.relative_to(folder).as_posix()
            runs[path.parent.resolve().name if name == "." else name] = summary
    if not runs:
        raise BidError(f"no `bid evaluate` results (summary.json) under {folder}")
    return runs


def _label(name: str, summary: dict) -> str:
    cfg = summary["config"]
    return f"{name} ({cfg['agent']}, {len(cfg['weathers'])} weathers × {cfg['seeds']} seeds)"


def _same_setup(runs: dict[str, dict], town: str) -> dict[tuple, list[str]]:
    """Runs of `town` grouped by agent, checkpoint, weathers and seeds (one per density, say)."""
    groups: dict[tuple, list[str]] = {}
    for name, s in runs.items():
        cfg = s["config"]
        if cfg["town"] == town:
            key = (cfg["agent"], cfg.get("checkpoint"), tuple(cfg["weathers"]), cfg["seeds"])
            groups.setdefault(key, []).append(name)
    return groups


def nocrash_table(runs: dict[str, dict], town: str) -> str:
    """SR, SSR and TL per density, one row per setup (runs of the same agent, checkpoint,
    weathers and seeds share a row, whichever densities each ran)."""
    lines = ["| run | " + " | ".join(f"{d} SR | {d} SSR | {d} TL" for d in DENSITY_ORDER) + " | episodes |",
             "|---|" + "---|" * (3 * len(DENSITY_ORDER) + 1)]
    for names in _same_setup(runs, town).values():
        cells = []
        for d in DENSITY_ORDER:
            st = next((runs[n]["by_density"][d] for n in names if d in runs[n]["by_density"]), None)
            cells += [m.cell(st, k) for k in ("SR", "SSR", "TL")] if st else ["—"] * 3
        episodes = sum(runs[n]["all"]["episodes"] for n in names)
        label = _label(" + ".join(names), runs[names[0]])
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {episodes} |")
    if town == "Town02":
        paper = [f"{PAPER_NOCRASH[d]['SR']} | {PAPER_NOCRASH[d]['SSR']} | —" for d in DENSITY_ORDER]
        lines.append("| paper BID (CARLA Town02) | " + " | ".join(paper) + " | — |")
    return "\n".join(lines)


def leaderboard_table(runs: dict[str, dict], town: str) -> str:
    """APA (= RC), ADG (= DS) and infraction counts, one row per run of `town`."""
    keys = ("RC", "DS", "CV", "CL", "TL", "OL", "RD", "ABD", "episodes")
    lines = ["| run | APA (RC) | ADG (DS) | CV | CL | TL | OL | RD | ABD | episodes |",
             "|---|" + "---|" * len(keys)]
    for name, s in runs.items():
        if s["config"]["town"] == town:
            lines.append(f"| {_label(name, s)} | " + " | ".join(m.cell(s["all"], k) for k in keys) + " |")
    if town == "Town05":
        lines.append(f"| paper BID (CARLA Town05) | {PAPER_TOWN05['RC']} | {PAPER_TOWN05['DS']} | "
                     + " | ".join("—" for _ in keys[2:]) + " |")
    return "\n".join(lines)


def infraction_table(runs: dict[str, dict]) -> str:
    """The paper's infraction table (its ablation layout), one row per run."""
    lines = ["| run | town | " + " | ".join(c for c, _ in INFRACTION_COLUMNS) + " |",
             "|---|---|" + "---|" * len(INFRACTION_COLUMNS)]
    for name, s in runs.items():
        lines.append(f"| {_label(name, s)} | {s['config']['town']} | "
                     + " | ".join(m.cell(s["all"], k) for _, k in INFRACTION_COLUMNS) + " |")
    return "\n".join(lines)


def tables(folder: str | Path) -> str:
    """The whole Markdown document for the runs under `folder`."""
    runs = load_runs(folder)
    towns = sorted({s["config"]["town"] for s in runs.values()})
    parts = ["# Results\n", f"From the `bid evaluate` runs under `{folder}`. Cells are mean ± std over seeds; "
             "SR, SSR, RC, DS in %, TL and the infraction columns are counts.\n"]
    for town in towns:
        if town == "Town05":
            parts += [f"## {town} (leaderboard metrics)\n", leaderboard_table(runs, town), ""]
        else:
            parts += [f"## {town} NoCrash\n", nocrash_table(runs, town), ""]
    parts += ["## Infractions (the paper's ablation table: PA = RC, IRL = TL, CWO/CWP/CWV = "
              "collisions with layout/pedestrians/vehicles)\n", infraction_table(runs), ""]
    return "\n".join(parts)
