"""Authoring aid, run by a developer, never at run time: writes scenarios/townNN/routes.toml.

Town01/02: NoCrash's 25 start/goal pairs (LBC's nocrash_TownNN lists, as the reference gives
them in CARLA's frame) placed on our networks: the start and goal snap to the nearest lane
that runs along the given heading. Town05: 10 long routes, random pairs chosen so that the
planned lengths follow the leaderboard routes' lengths.

    .venv/bin/python tools/author_routes.py ../shared/reference
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from bid_sim.routes import RouteSpec, generate_routes, plan_spec, road_graph
from bid_sim.towns import resolve_town

ROOT = Path(__file__).resolve().parents[1]


def _write(town_dir: Path, specs: list[RouteSpec], lengths: list[float], note: str) -> None:
    lines = [f"# {note}", "# start/goal: edge id and distance along it (m); length_m is informative.", ""]
    for spec, length in zip(specs, lengths, strict=True):
        lines += [
            "[[route]]",
            f'start_edge = "{spec.start_edge}"',
            f"start_pos_m = {spec.start_pos_m:.1f}",
            f'goal_edge = "{spec.goal_edge}"',
            f"goal_pos_m = {spec.goal_pos_m:.1f}",
            f"length_m = {length:.1f}",
            "",
        ]
    (town_dir / "routes.toml").write_text("\n".join(lines))


def nocrash(ref: dict, t: str) -> None:
    town = resolve_town(t)
    graph = road_graph(town.net_file)
    key = next(k for k in ref[f"Town{t}"] if k.startswith("roach_lbc"))
    specs, lengths, carla = [], [], []
    for r in ref[f"Town{t}"][key]:
        ends = []
        for x, y, yaw in (r["start"], r["goal"]):
            edge, _, pos = graph.locate(x, -y, math.radians(-yaw), radius_m=12.0)
            ends.append((edge, pos))
        spec = RouteSpec(ends[0][0], round(ends[0][1], 1), ends[1][0], round(ends[1][1], 1))
        specs.append(spec)
        lengths.append(plan_spec(graph, spec).length_m)
        carla.append(r["route_length_m_est"])
    _write(town.folder, specs, lengths,
           f"Town{t} NoCrash routes: CARLA's 25 start/goal pairs on our network "
           f"(mean {np.mean(lengths):.0f} m here, {np.mean(carla):.0f} m in CARLA)")
    print(f"Town{t}: mean {np.mean(lengths):.0f} m (CARLA {np.mean(carla):.0f} m)")


def town05(ref: dict) -> None:
    town = resolve_town("05")
    graph = road_graph(town.net_file)
    key = next(iter(ref["Town05"]))
    targets = [r["route_length_m_est"] for r in ref["Town05"][key]]
    specs = generate_routes(town, len(targets), seed=5, lengths_m=targets, min_length_m=300.0)
    lengths = [plan_spec(graph, s).length_m for s in specs]
    _write(town.folder, specs, lengths,
           f"Town05 long routes: random pairs matched to the leaderboard routes' lengths "
           f"(mean {np.mean(lengths):.0f} m here, {np.mean(targets):.0f} m in CARLA)")
    print(f"Town05: mean {np.mean(lengths):.0f} m (CARLA {np.mean(targets):.0f} m)")


if __name__ == "__main__":
    ref_dir = Path(sys.argv[1] if len(sys.argv) > 1 else ROOT.parent / "shared" / "reference")
    ref = json.loads((ref_dir / "carla_benchmark_routes.json").read_text())
    nocrash(ref, "01")
    nocrash(ref, "02")
    town05(ref)
