"""The infraction monitor: collisions, red lights, outside-lane driving, deviation, blocking.

SUMO does not see an ego that left the network and misses some collisions (DESIGN.md
section 6), so everything here is our own geometry on the snapshot and the static map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bid_sim import metrics as m
from bid_sim.ego import EgoParams, EgoState, box_corners
from bid_sim.metrics import Infraction
from bid_sim.routes import RoadGraph, Route
from bid_sim.snapshot import RED, Snapshot, light_code
from bid_sim.town_map import TownMap

OUTSIDE_MARGIN_M = 1.3
OUTSIDE_HEADING_RAD = math.radians(120.0)
DEVIATION_M = 30.0
BLOCKED_SPEED_MPS = 0.1
BLOCKED_S = 90.0
DEDUP_S = 5.0


def boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test for two convex quadrilaterals given as (4, 2) corners."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.column_stack([-edges[:, 1], edges[:, 0]])
        pa = a @ normals.T
        pb = b @ normals.T
        if np.any((pa.max(0) < pb.min(0)) | (pb.max(0) < pa.min(0))):
            return False
    return True


def contact_side(ego: EgoState, params: EgoParams, x_m: float, y_m: float) -> str:
    """The face of the ego's box nearest the point (an actor's centre): "front", "rear",
    "left" or "right". With the ego's speed it tells a rear-ending from being rear-ended."""
    dx, dy = x_m - ego.x_m, y_m - ego.y_m
    c, s = math.cos(ego.yaw_rad), math.sin(ego.yaw_rad)
    ahead, left = c * dx + s * dy, -s * dx + c * dy
    if abs(ahead) / params.length_m >= abs(left) / params.width_m:
        return "front" if ahead >= 0 else "rear"
    return "left" if left >= 0 else "right"


@dataclass
class Monitor:
    """Watches one episode and collects its infractions."""

    town_map: TownMap
    graph: RoadGraph
    params: EgoParams = field(default_factory=EgoParams)
    infractions: list[Infraction] = field(default_factory=list)
    outside_lane_m: float = 0.0
    _outside: bool = False
    _last_hit: dict[str, float] = field(default_factory=dict)
    _still_since: float = 0.0

    def __post_init__(self) -> None:
        self._links = self.graph.tls_links
        self._stop_by_lane = {s.lane_id: s for s in self.town_map.stop_lines}

    def _add(self, kind: str, t: float, x: float, y: float, actor: str = "", detail: str = "") -> None:
        self.infractions.append(Infraction(kind, round(t, 2), round(x, 2), round(y, 2), actor, detail))

    def _collision(self, kind: str, t: float, ego: EgoState, actor: str, detail: str = "") -> None:
        last = self._last_hit.get(actor)
        if last is not None and t - last <= DEDUP_S:
            return  # the same actor again within 5 s counts once
        self._last_hit[actor] = t
        self._add(kind, t, ego.x_m, ego.y_m, actor, detail)

    def check(self, snap: Snapshot, prev: EgoState, ego: EgoState, route: Route,
              route_s_m: float, ds_m: float) -> None:
        """Checks the step that moved the ego from prev to ego (route progress ds_m)."""
        t = snap.time_s
        corners = ego.corners(self.params)
        self._check_actors(snap, ego, corners, t)
        self._check_layout(ego, corners, t)
        self._check_red_light(snap, prev, ego, route, t)
        self._check_outside(ego, ds_m, t)
        if ego.speed_mps < BLOCKED_SPEED_MPS:
            self._still_since += 0.1
        else:
            self._still_since = 0.0

    @property
    def blocked(self) -> bool:
        return self._still_since >= BLOCKED_S - 1e-9

    def _check_actors(self, snap: Snapshot, ego: EgoState, corners: np.ndarray, t: float) -> None:
        reach = 0.5 * math.hypot(self.params.length_m, self.params.width_m)
        for actors, kind in ((snap.vehicles, m.COLLISION_VEHICLE), (snap.pedestrians, m.COLLISION_PEDESTRIAN)):
            if not len(actors):
                continue
            d = np.hypot(actors.xy[:, 0] - ego.x_m, actors.xy[:, 1] - ego.y_m)
            near = np.nonzero(d < reach + 0.5 * np.hypot(actors.size[:, 0], actors.size[:, 1]))[0]
            for i in near:
                other = box_corners(actors.xy[i, 0], actors.xy[i, 1], actors.yaw_rad[i],
                                    actors.size[i, 0], actors.size[i, 1])
                if boxes_overlap(corners, other):
                    side = contact_side(ego, self.params, actors.xy[i, 0], actors.xy[i, 1])
                    x, y, v = actors.xy[i, 0], actors.xy[i, 1], actors.speed_mps[i]
                    self._collision(kind, t, ego, actors.ids[i],
                                    f"{side}, ego {ego.speed_mps:.1f} m/s; it at ({x:.1f}, {y:.1f}), {v:.1f} m/s")

    def _check_layout(self, ego: EgoState, corners: np.ndarray, t: float) -> None:
        b = self.town_map.building_hit(corners)
        if b >= 0:
            self._collision(m.COLLISION_LAYOUT, t, ego, f"building:{b}")
        p = self.town_map.pole_hit(corners)
        if p >= 0:
            self._collision(m.COLLISION_LAYOUT, t, ego, f"pole:{p}")
        if self.town_map.off_paved(corners):
            self._collision(m.COLLISION_LAYOUT, t, ego, "unpaved")

    def _check_red_light(self, snap: Snapshot, prev: EgoState, ego: EgoState, route: Route,
                         t: float) -> None:
        """A red-light run: the front bumper crosses a stop line while its link is red."""
        a = np.array(prev.front_bumper(self.params))
        b = np.array(ego.front_bumper(self.params))
        if np.allclose(a, b):
            return
        for lane_id, _, _, _ in self.town_map.nearest_lanes(b[0], b[1], 6.0):
            stop = self._stop_by_lane.get(lane_id)
            if stop is None or not _segments_cross(a, b, stop.p0, stop.p1):
                continue
            fwd = np.array([math.cos(stop.heading_rad), math.sin(stop.heading_rad)])
            if np.dot(b - a, fwd) <= 0:
                continue
            states = snap.tls_states.get(stop.tls_id, "")
            via = _next_via(route, lane_id)
            link = self._links.get((lane_id, via)) if via else None
            if link is not None:
                red = link[1] < len(states) and light_code(states[link[1]]) == RED
            else:
                red = bool(stop.link_indices) and all(
                    i < len(states) and light_code(states[i]) == RED for i in stop.link_indices
                )
            if red:
                self._add(m.RED_LIGHT, t, ego.x_m, ego.y_m, stop.tls_id, lane_id)

    def _check_outside(self, ego: EgoState, ds_m: float, t: float) -> None:
        outside = not self.in_lane(ego)
        if outside:
            self.outside_lane_m += max(ds_m, 0.0)
            if not self._outside:
                self._add(m.OUTSIDE_LANE, t, ego.x_m, ego.y_m)
        self._outside = outside

    def in_lane(self, ego: EgoState) -> bool:
        """Within lane_width/2 + 1.3 m of a driving-lane centre, heading within 120° of it."""
        for lane_id, dist, _, heading in self.town_map.nearest_lanes(ego.x_m, ego.y_m, 4.0 + OUTSIDE_MARGIN_M):
            dyaw = abs(math.atan2(math.sin(ego.yaw_rad - heading), math.cos(ego.yaw_rad - heading)))
            if dyaw <= OUTSIDE_HEADING_RAD and dist <= self._lane_width(lane_id) / 2 + OUTSIDE_MARGIN_M:
                return True
        return False

    def _lane_width(self, lane_id: str) -> float:
        i = self.town_map.lane_index.get(lane_id)
        return self.town_map.lanes[i].width_m if i is not None else 3.5


def _segments_cross(a, b, c, d) -> bool:
    def orient(p, q, r):
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    return (orient(a, b, c) * orient(a, b, d) <= 0) and (orient(c, d, a) * orient(c, d, b) <= 0)


def _next_via(route: Route, lane_id: str) -> str:
    """The junction connector the route takes after lane_id ('' if lane_id is off-route)."""
    pieces = route.pieces
    for i, p in enumerate(pieces[:-1]):
        if p.lane_id == lane_id and pieces[i + 1].junction:
            return pieces[i + 1].lane_id
    return ""
