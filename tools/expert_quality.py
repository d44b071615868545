"""How well the expert drives: its benchmark table on a town's routes (DESIGN.md section 7).

Runs the expert over the town's benchmark routes × seeds × densities in worker processes
(libsumo runs one simulation per process) and prints, per density, route completion,
success, driving score, collisions split by who was at fault, and red-light runs.

    .venv/bin/python tools/expert_quality.py                      # Town02, 25 routes × 3 seeds
    .venv/bin/python tools/expert_quality.py --routes 5 --seeds 1 # a quick subset
    .venv/bin/python tools/expert_quality.py --json > expert.json

At fault: at the first contact with an actor the ego was moving (> 0.3 m/s) and closing on
it by its own motion at least as fast as the actor closed on the ego (a car that runs into
a stopped or slower ego, from behind or from the side, is not the ego's fault).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bid_sim import metrics as m
from bid_sim.errors import BidError

CONTACT_M = 9.0  # actors this close to the ego are logged each step, for the fault check
MOVING_MPS = 0.3


def _recording_expert():
    from bid_sim.expert import Expert

    class Recording(Expert):
        """The expert, logging the ego and the actors around it at every step."""

        def reset(self, info):
            super().reset(info)
            self.log: dict[float, tuple] = {}
            self.held: dict[str, int] = {}

        def act(self, obs):
            snap = obs.snapshot
            e = snap.ego
            near = {}
            for actors in (snap.vehicles, snap.pedestrians):
                for i, aid in enumerate(actors.ids):
                    x, y = actors.xy[i]
                    if math.hypot(x - e.x_m, y - e.y_m) < CONTACT_M:
                        near[aid] = (float(x), float(y), float(actors.yaw_rad[i]), float(actors.speed_mps[i]))
            self.log[round(snap.time_s, 2)] = ((e.x_m, e.y_m, e.yaw_rad, e.speed_mps), near)
            control = super().act(obs)
            if e.speed_mps < 0.1:  # what held the expert at a standstill, by kind
                kind = self.reason.split(" ")[0]
                self.held[kind] = self.held.get(kind, 0) + 1
            return control

    return Recording()


def at_fault(ego: tuple, other: tuple | None) -> bool:
    """Whether the ego caused a contact: ego and other are (x, y, yaw, speed)."""
    if other is None:
        return True  # not logged (the episode's last step): count it against the ego
    ex, ey, eyaw, ev = ego
    ox, oy, oyaw, ov = other
    d = math.hypot(ox - ex, oy - ey)
    if d < 1e-6:
        return ev > MOVING_MPS
    ux, uy = (ox - ex) / d, (oy - ey) / d
    ego_closing = ev * (math.cos(eyaw) * ux + math.sin(eyaw) * uy)
    other_closing = -ov * (math.cos(oyaw) * ux + math.sin(oyaw) * uy)
    return ev > MOVING_MPS and ego_closing > 0.1 and ego_closing >= other_closing


def run_one(task: tuple) -> dict:
    """One episode in this worker process: the result row with the fault split."""
    from bid_sim.episode import run_episode

    town, route, density, seed, weather = task
    agent = _recording_expert()
    t0 = time.perf_counter()
    result = run_episode(town, route, weather, density, seed, agent)
    wall = time.perf_counter() - t0
    faults = []
    for inf in result.infractions:
        if inf.kind not in m.COLLISION_KINDS:
            continue
        entry = agent.log.get(round(inf.time_s, 2))
        other = entry[1].get(inf.actor) if entry else None
        faults.append({"kind": inf.kind, "actor": inf.actor, "time_s": inf.time_s,
                       "at_fault": at_fault(entry[0], other) if entry else True})
    return {
        "route": route, "density": density, "seed": seed, "weather": weather,
        "status": result.status, "time_s": result.time_s, "steps": result.steps,
        "wall_s": round(wall, 2), "route_length_m": result.route_length_m,
        "completed_m": result.completed_m,
        "infractions": [i.to_dict() for i in result.infractions],
        "collisions": faults,
        "held_s": {k: round(v * 0.1, 1) for k, v in sorted(agent.held.items(), key=lambda kv: -kv[1])},
        **result.metrics,
    }


def summarise(rows: list[dict]) -> dict:
    """Per density: completion, SR, RC, DS (mean ± std over seeds), infraction counts."""
    out = {}
    for density in sorted({r["density"] for r in rows}, key=["none", "normal", "crowded"].index):
        group = [r for r in rows if r["density"] == density]
        st = m.stats([{**r, "seed": r["seed"]} for r in group])
        coll = [c for r in group for c in r["collisions"]]
        out[density] = {
            "episodes": len(group),
            "completed_pct": 100.0 * sum(r["status"] == "completed" for r in group) / len(group),
            "SR": st["SR"], "SR_std": st["SR_std"],
            "RC": st["RC"], "RC_std": st["RC_std"],
            "DS": st["DS"], "DS_std": st["DS_std"],
            "collisions": len(coll),
            "at_fault": sum(c["at_fault"] for c in coll),
            "not_at_fault": sum(not c["at_fault"] for c in coll),
            "at_fault_vehicle": sum(c["at_fault"] and c["kind"] == m.COLLISION_VEHICLE for c in coll),
            "at_fault_pedestrian": sum(c["at_fault"] and c["kind"] == m.COLLISION_PEDESTRIAN for c in coll),
            "layout": sum(c["kind"] == m.COLLISION_LAYOUT for c in coll),
            "red_lights": int(st["TL"]),
            "outside_lane": int(st["OL"]),
            "blocked": int(st["ABD"]),
            "timeouts": int(st["TO"]),
            "route_deviations": int(st["RD"]),
            "km": round(st["km"], 3),
            "mean_wall_s": round(statistics.fmean(r["wall_s"] for r in group), 2),
        }
    return out


def format_summary(summary: dict) -> str:
    head = (f"{'density':<9}{'eps':>5}{'done %':>8}{'SR':>14}{'RC':>14}{'DS':>14}"
            f"{'coll':>6}{'fault':>7}{'not':>5}{'TL':>4}{'OL':>4}{'ABD':>5}{'TO':>4}{'RD':>4}")
    lines = [head]
    for density, s in summary.items():
        lines.append(
            f"{density:<9}{s['episodes']:>5}{s['completed_pct']:>8.1f}"
            f"{s['SR']:>8.1f} ±{s['SR_std']:>4.1f}{s['RC']:>8.1f} ±{s['RC_std']:>4.1f}"
            f"{s['DS']:>8.1f} ±{s['DS_std']:>4.1f}{s['collisions']:>6}{s['at_fault']:>7}"
            f"{s['not_at_fault']:>5}{s['red_lights']:>4}{s['outside_lane']:>4}{s['blocked']:>5}"
            f"{s['timeouts']:>4}{s['route_deviations']:>4}"
        )
    return "\n".join(lines)


def problems(rows: list[dict]) -> list[str]:
    """One line per episode that did not complete or had a collision or red light."""
    out = []
    for r in sorted(rows, key=lambda r: (r["density"], r["route"], r["seed"])):
        bad = [i for i in r["infractions"] if i["kind"] != m.OUTSIDE_LANE]
        if r["status"] == "completed" and not bad:
            continue
        faults = {(c["actor"], c["time_s"]): c["at_fault"] for c in r["collisions"]}
        what = ", ".join(
            f"{i['kind']}@{i['time_s']:.1f}s"
            + (f" {i['actor']}" if i["actor"] else "")
            + (" (at fault)" if faults.get((i["actor"], i["time_s"])) else "")
            for i in bad
        )
        held = ", ".join(f"{k} {v:.0f}s" for k, v in list(r["held_s"].items())[:3])
        out.append(f"{r['density']:<8} route {r['route']:>2} seed {r['seed']}: {r['status']}; {what}"
                   + (f"; stood for {held}" if r["status"] != "completed" else ""))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--town", default="02")
    p.add_argument("--routes", type=int, default=None, help="the first N routes (default: all)")
    p.add_argument("--route", type=int, action="append", help="only these route indices")
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..K-1")
    p.add_argument("--densities", default="none,normal,crowded")
    p.add_argument("--weather", default="ClearNoon", help="weather changes only the rendering")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--out", type=Path, default=None, help="write every episode's row to this JSON file")
    args = p.parse_args(argv)

    from bid_sim.routes import load_routes
    from bid_sim.towns import resolve_town

    try:
        town = resolve_town(args.town)
        n_routes = len(load_routes(town))
        densities = [d.strip() for d in args.densities.split(",") if d.strip()]
        for d in densities:
            town.density(d)
    except BidError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    routes = args.route or list(range(min(args.routes or n_routes, n_routes)))
    tasks = [(args.town, r, d, s, args.weather) for d in densities for r in routes for s in range(args.seeds)]
    town.net_file  # noqa: B018 -- build the network once, before the workers race to it
    rows: list[dict] = []
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        def tqdm(it, **_):
            return it
    with ctx.Pool(args.workers) as pool:
        for row in tqdm(pool.imap_unordered(run_one, tasks), total=len(tasks), desc="episodes",
                        file=sys.stderr, disable=None):
            rows.append(row)
    rows.sort(key=lambda r: (r["density"], r["route"], r["seed"]))
    summary = summarise(rows)
    wall = time.perf_counter() - t0
    if args.out is not None:
        args.out.write_text(json.dumps({"summary": summary, "episodes": rows}, indent=1))
    if args.json:
        print(json.dumps({"town": town.name, "routes": routes, "seeds": args.seeds,
                          "wall_s": round(wall, 1), "summary": summary}, indent=1))
    else:
        print(f"{town.name}: expert, {len(routes)} routes × {args.seeds} seeds, {len(tasks)} episodes "
              f"in {wall:.0f} s ({args.workers} workers)")
        print(format_summary(summary))
        for line in problems(rows):
            print("  " + line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
