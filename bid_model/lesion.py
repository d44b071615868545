"""`bid lesion`: the closed-loop benchmark with each brain area of a trained BID switched
off in turn (V1 excluded: without it nothing is seen), against the intact model.

Each run is an ordinary `bid evaluate` results folder under OUT (intact/, no_V2/, ...), so
an interrupted study resumes; OUT/lesion.json, lesion.md and lesion.png hold SR, RC, TL, CV
and CP per lesioned area (RC tells areas apart while a model completes few routes).
"""

from __future__ import annotations

import json
from pathlib import Path

from bid_model.checkpoint import load_model
from bid_sim.errors import BidError
from bid_sim.evaluate import evaluate

METRICS = ("SR", "RC", "TL", "CV", "CP")


def lesion_study(checkpoint: str | Path, town: str, density: str, weathers: tuple[str, ...], seeds: int,
                 out: str | Path, workers: int = 1, routes: list[int] | None = None, mode: str = "zero",
                 areas: list[str] | None = None, progress: bool = True, max_steps: int | None = None) -> dict:
    model, _ = load_model(checkpoint)
    present = [a for a in model.areas if a != "V1"]
    chosen = present if areas is None else areas
    bad = [a for a in chosen if a not in present]
    if bad:
        raise BidError(f"cannot lesion {bad[0]!r}; this model's areas (V1 excluded) are {', '.join(present)}")
    out = Path(out)
    runs = {"intact": None, **{a: {"lesions": {a: mode}} for a in chosen}}
    table = {}
    for name, options in runs.items():
        folder = out / ("intact" if options is None else f"no_{name}")
        s = evaluate(town, (density,), weathers, seeds, "bid", folder, checkpoint=str(checkpoint),
                     workers=workers, routes=routes, progress=progress, options=options, max_steps=max_steps)
        table[name] = {k: s["all"][k] for k in (*METRICS, "SR_std", "DS", "episodes")}
    (out / "lesion.json").write_text(json.dumps({"checkpoint": str(checkpoint), "mode": mode, "table": table}, indent=1))
    (out / "lesion.md").write_text(markdown(table, mode))
    plot(table, out / "lesion.png")
    return table


def markdown(table: dict, mode: str) -> str:
    lines = [f"Lesions ({mode}): the closed-loop benchmark with one area switched off", "",
             "| lesioned | SR | RC | TL | CV | CP | DS | episodes |", "|---|---|---|---|---|---|---|---|"]
    for name, r in table.items():
        lines.append(f"| {name} | {r['SR']:.1f} ± {r['SR_std']:.1f} | {r['RC']:.1f} | {r['TL']} | {r['CV']} | {r['CP']} | "
                     f"{r['DS']:.1f} | {r['episodes']} |")
    return "\n".join(lines) + "\n"


def plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(table)
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.2 * len(METRICS), 3.2))
    for ax, key in zip(axes, METRICS, strict=True):
        ax.bar(names, [table[n][key] for n in names], color=["#555555"] + ["#c0504d"] * (len(names) - 1))
        ax.set_title(key)
        ax.tick_params(axis="x", rotation=60)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
