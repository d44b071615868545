"""Rendering benchmark (`bid bench render`): frames per second on one core, cost per stage,
and how cost grows with the number of vehicles in town.

Snapshots come from a real episode (SUMO, the lane follower) in Town01 crowded. For the
700-vs-70 ratio the same snapshots get extra parked vehicles spread over every car lane of
the town, 70 or 700 in all, and the snapshot keeps all of them (not only those near the
ego), so the ratio measures the renderer's own spatial filter. The headline ratio places
them beyond the view range; a second ratio places them anywhere, so more of them are in
view and drawn, which costs what drawing them costs.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import replace

import numpy as np

from bid_sim.render.renderer import STAGES, Renderer
from bid_sim.snapshot import Actors, Snapshot
from bid_sim.town_map import TownMap, load_town_map
from bid_sim.towns import resolve_town

CAR_SIZE = (4.6, 1.9, 1.5)


def collect_snapshots(town: str = "01", density: str = "crowded", route: int = 0, seed: int = 0,
                      frames: int = 240) -> list[Snapshot]:
    """Snapshots of a real episode: the lane follower drives a route with SUMO traffic."""
    from bid_sim.agents import LaneFollower
    from bid_sim.render.view import episode_snapshots

    return episode_snapshots(town, route, density, seed, LaneFollower(6.0), frames)


def with_town_vehicles(snap: Snapshot, town_map: TownMap, n: int, seed: int = 0,
                       beyond_m: float = 0.0) -> Snapshot:
    """The snapshot with n parked vehicles along the town's car lanes, all kept in the
    snapshot; beyond_m > 0 places them only that far or farther from the ego."""
    rng = np.random.default_rng(seed)
    lanes = [ln for ln in town_map.lanes if not ln.internal and ln.length_m() > 8.0]
    lengths = np.array([ln.length_m() for ln in lanes])
    ex, ey = snap.ego.x_m, snap.ego.y_m
    xy, yaw = [], []
    while len(xy) < n:
        ln = lanes[rng.choice(len(lanes), p=lengths / lengths.sum())]
        x, y, a = ln.point_at(rng.uniform(2.5, ln.length_m() - 2.5))
        if math.hypot(x - ex, y - ey) >= beyond_m:
            xy.append((x, y))
            yaw.append(a)
    extra = Actors(tuple(f"parked{i}" for i in range(n)), np.array(xy), np.array(yaw), np.zeros(n),
                   np.tile(np.array(CAR_SIZE), (n, 1)), rng.integers(0, 12, n))
    v = snap.vehicles
    both = Actors(v.ids + extra.ids, np.concatenate([v.xy, extra.xy]), np.concatenate([v.yaw_rad, extra.yaw_rad]),
                  np.concatenate([v.speed_mps, extra.speed_mps]), np.concatenate([v.size, extra.size]),
                  np.concatenate([v.colour, extra.colour]))
    return replace(snap, vehicles=both)


def _cost_ratio(renderer: Renderer, snaps: list[Snapshot], town_map: TownMap, beyond_m: float) -> tuple[float, float]:
    """Median frame cost with 70 and with 700 extra vehicles in town, timed alternately so
    that load from other processes hits both alike."""
    few = [with_town_vehicles(s, town_map, 70, seed=i, beyond_m=beyond_m) for i, s in enumerate(snaps)]
    many = [with_town_vehicles(s, town_map, 700, seed=i, beyond_m=beyond_m) for i, s in enumerate(snaps)]
    t70, t700 = [], []
    for a, b in zip(few, many, strict=True):
        t70 += _time_frames(renderer, [a])
        t700 += _time_frames(renderer, [b])
    return statistics.median(t70), statistics.median(t700)


def _time_frames(renderer: Renderer, snaps: list[Snapshot], timings: dict | None = None) -> list[float]:
    out = []
    for s in snaps:
        t0 = time.process_time()
        renderer.render(s, timings)
        out.append(time.process_time() - t0)
    return out


def bench_render(town: str = "01", density: str = "crowded", weather: str = "HardRainNoon",
                 frames: int = 240, snaps: list[Snapshot] | None = None) -> dict:
    """The benchmark's figures (one process, one core: numpy/OpenCV threads set to 1)."""
    import cv2

    cv2.setNumThreads(1)
    tm = load_town_map(resolve_town(town))
    snaps = snaps if snaps is not None else collect_snapshots(town, density, frames=frames + 40)
    snaps = snaps[40:] if len(snaps) > frames else snaps  # skip the first steps at the spawn point
    r = Renderer(tm, weather=weather)
    for s in snaps[:10]:
        r.render(s)  # warm caches
    timings = dict.fromkeys(STAGES, 0.0)
    secs = _time_frames(r, snaps, timings)
    med = statistics.median(secs)
    n_veh = statistics.median(len(s.vehicles) for s in snaps)
    n_ped = statistics.median(len(s.pedestrians) for s in snaps)
    # Cost against the number of vehicles in the whole town: parked beyond the view range
    # (what the spatial filter is for), and anywhere (more of them are then in view, too).
    sub = snaps[:: max(1, len(snaps) // 120)]
    t70, t700 = _cost_ratio(r, sub, tm, beyond_m=r.view_m + 10.0)
    u70, u700 = _cost_ratio(r, sub, tm, beyond_m=0.0)
    total = sum(timings.values())
    ref = np.random.default_rng(0).random(1000)
    t0 = time.perf_counter()
    for _ in range(5000):
        ref * 2.0
    numpy_us = (time.perf_counter() - t0) / 5000 * 1e6
    return {
        "town": tm.name,
        "density": density,
        "weather": weather,
        "frames": len(snaps),
        "frame_shape": list(r.rig.frame_shape),
        "vehicles_in_snapshot_median": n_veh,
        "pedestrians_in_snapshot_median": n_ped,
        "render_ms_median": round(med * 1e3, 3),
        "render_ms_p95": round(sorted(secs)[int(0.95 * len(secs))] * 1e3, 3),
        "render_fps_per_core": round(1.0 / med, 1),
        "render_fps_target_ratio": round((1.0 / med) / 400.0, 3),
        "stage_ms_per_frame": {k: round(v / len(snaps) * 1e3, 3) for k, v in timings.items()},
        "stage_share": {k: round(v / total, 3) for k, v in timings.items()},
        "render_ms_70_vehicles": round(t70 * 1e3, 3),
        "render_ms_700_vehicles": round(t700 * 1e3, 3),
        "render_cost_ratio_700_vs_70": round(t700 / t70, 3),
        "render_ms_70_vehicles_anywhere": round(u70 * 1e3, 3),
        "render_ms_700_vehicles_anywhere": round(u700 * 1e3, 3),
        "render_cost_ratio_700_vs_70_anywhere": round(u700 / u70, 3),
        # How fast this machine is right now: one numpy multiply of 1,000 floats (about 1 µs on
        # a quiet 2020s core; shared VMs drift to 2–4 µs, and every figure above with it).
        "machine_numpy_mul_1k_us": round(numpy_us, 2),
    }
