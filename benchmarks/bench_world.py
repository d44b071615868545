"""World speed: SUMO step and snapshot extraction in Town02 crowded (targets 2 ms / 1 ms median),
and the town map's nearest-lane query that the expert and the infraction monitor use every step.

    .venv/bin/python benchmarks/bench_world.py [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import libsumo as traci
import numpy as np

from bid_sim.agents import LaneFollower
from bid_sim.ego import EgoState
from bid_sim.episode import Progress, _view, run_episode
from bid_sim.routes import plan_spec, road_graph, route_by_index
from bid_sim.town_map import load_town_map
from bid_sim.towns import resolve_town
from bid_sim.world import World


def bench_world(town_name: str = "02", density: str = "crowded", steps: int = 1000) -> dict:
    town = resolve_town(town_name)
    route = plan_spec(road_graph(town.net_file), route_by_index(town, 0))
    sumo_ms, snap_ms = [], []
    with World(town, density, 0, route) as w:
        w.step_idle(200)  # warm up: traffic spread out
        progress = Progress(route)
        for _ in range(steps):
            ego = EgoState(w.ego.x_m, w.ego.y_m, w.ego.yaw_rad, 0.0)
            t0 = time.perf_counter()
            w.advance(ego)
            t1 = time.perf_counter()
            w.snapshot(_view(ego, progress, w.params))
            t2 = time.perf_counter()
            sumo_ms.append((t1 - t0) * 1e3)
            snap_ms.append((t2 - t1) * 1e3)
        n_veh = len(traci.vehicle.getIDList()) - 1
        n_ped = len(traci.person.getIDList())
    nearest_us = _nearest_lanes_us(town)
    t0 = time.perf_counter()
    r = run_episode(town, 0, "ClearNoon", density, 0, LaneFollower(6.0), max_steps=1000)
    episode_s = time.perf_counter() - t0
    return {
        "town": town.name,
        "density": density,
        "vehicles": n_veh,
        "pedestrians": n_ped,
        "sumo_step_ms_median": round(statistics.median(sumo_ms), 3),
        "sumo_step_ms_p95": round(sorted(sumo_ms)[int(0.95 * len(sumo_ms))], 3),
        "snapshot_ms_median": round(statistics.median(snap_ms), 3),
        "episode_steps_per_s": round(r.steps / episode_s, 1),
        "nearest_lanes_us_per_query": round(nearest_us, 1),
        "sumo_step_target_ratio": round(statistics.median(sumo_ms) / 2.0, 3),
        "snapshot_target_ratio": round(statistics.median(snap_ms) / 1.0, 3),
    }


def _nearest_lanes_us(town, queries: int = 2000) -> float:
    """Mean time of TownMap.nearest_lanes at points within about a metre of random lanes."""
    town_map = load_town_map(town)
    rng = np.random.default_rng(0)
    points = []
    for _ in range(queries):
        ln = town_map.lanes[rng.integers(len(town_map.lanes))]
        x, y, _ = ln.point_at(rng.uniform(0, ln.length_m()))
        points.append((x + rng.normal(0, 1.0), y + rng.normal(0, 1.0)))
    t0 = time.perf_counter()
    for p in points:
        town_map.nearest_lanes(*p)
    return (time.perf_counter() - t0) / queries * 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--json", action="store_true")
    p.add_argument("--steps", type=int, default=1000)
    args = p.parse_args()
    res = bench_world(steps=args.steps)
    if args.json:
        print(json.dumps(res))
        return
    print(f"{res['town']} {res['density']}: {res['vehicles']} vehicles, {res['pedestrians']} pedestrians")
    print(f"  SUMO step     median {res['sumo_step_ms_median']:.3f} ms (p95 {res['sumo_step_ms_p95']:.3f}), "
          f"target 2 ms, ratio {res['sumo_step_target_ratio']:.2f}")
    print(f"  snapshot      median {res['snapshot_ms_median']:.3f} ms, target 1 ms, ratio {res['snapshot_target_ratio']:.2f}")
    print(f"  whole episode loop (lane follower, no rendering): {res['episode_steps_per_s']:.0f} steps/s")
    print(f"  nearest-lane query: {res['nearest_lanes_us_per_query']:.1f} µs")


if __name__ == "__main__":
    main()
