"""Hand-built snapshots for the renderer's tests (no SUMO): an ego on a straight street of
Town02 with actors placed where a test wants them."""

from __future__ import annotations

import math

import numpy as np

from bid_sim.snapshot import GREEN, Actors, EgoView, Snapshot
from bid_sim.town_map import TownMap

# A straight eastbound stretch of Town02's lane -S10_1 (y = -306.5, heading +x); the
# westbound lane is 4 m to its left.
STREET_XY = (70.0, -306.5)
STREET_YAW = 0.0
CAR = (4.6, 1.9, 1.5)
PERSON = (0.5, 0.5, 1.8)


def ego_view(x: float, y: float, yaw: float) -> EgoView:
    return EgoView(x, y, yaw, 0.0, 4.6, 1.9, 1.5, "", 0.0, 0.0, 0.0, 100.0, 4)


def polar(x: float, y: float, yaw: float, dist: float, angle_deg: float = 0.0) -> tuple[float, float]:
    """The point `dist` m from (x, y) at `angle_deg` left of heading `yaw`."""
    a = yaw + math.radians(angle_deg)
    return x + dist * math.cos(a), y + dist * math.sin(a)


def actors(items, size) -> Actors:
    """Actors from (x, y, yaw, colour) tuples."""
    if not items:
        return Actors.empty()
    n = len(items)
    arr = np.array([it[:3] for it in items], dtype=np.float64)
    return Actors(tuple(f"a{i}" for i in range(n)), arr[:, :2].copy(), arr[:, 2].copy(), np.zeros(n),
                  np.tile(np.array(size, dtype=np.float64), (n, 1)), np.array([it[3] for it in items]))


def local(x: float, y: float, yaw: float, ahead: float, left: float = 0.0) -> tuple[float, float]:
    """The point `ahead` m forward and `left` m to the left of (x, y) heading `yaw`."""
    c, s = math.cos(yaw), math.sin(yaw)
    return x + ahead * c - left * s, y + ahead * s + left * c


def snapshot(town_map: TownMap, x: float, y: float, yaw: float, vehicles=(), pedestrians=(),
             light: int = GREEN, step: int = 0) -> Snapshot:
    lights = np.full(len(town_map.signal_heads), light, dtype=np.uint8)
    return Snapshot(time_s=step * 0.1, step=step, ego=ego_view(x, y, yaw),
                    vehicles=actors(list(vehicles), CAR), pedestrians=actors(list(pedestrians), PERSON),
                    light_states=lights)


def facing_head(town_map: TownMap, index: int, dist: float) -> tuple[float, float, float]:
    """An ego pose `dist` m in front of signal head `index`, looking at it."""
    head = town_map.signal_heads[index]
    x, y = polar(float(head.position[0]), float(head.position[1]), head.facing_rad, dist)
    return x, y, head.facing_rad + math.pi


def street_scene(town_map: TownMap, light: int = GREEN, step: int = 0) -> Snapshot:
    """The golden street: cars ahead in both lanes, pedestrians on the sidewalks."""
    x, y = STREET_XY
    cars = [(*local(x, y, 0.0, 14.0), 0.0, 0), (*local(x, y, 0.0, 30.0), 0.0, 1),
            (*local(x, y, 0.0, 22.0, 4.0), math.pi, 2), (*local(x, y, 0.0, 45.0, 4.0), math.pi, 5)]
    people = [(*local(x, y, 0.0, 12.0, -4.5), 0.0, 3), (*local(x, y, 0.0, 18.0, 8.0), 0.0, 40)]
    return snapshot(town_map, x, y, STREET_YAW, cars, people, light, step)
