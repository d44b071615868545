"""Global planning on the lane graph, benchmark routes and navigation commands.

A route is planned over edges (SUMO's shortest path), then over lanes: on multi-lane roads
the lane at each junction is the one whose connection continues the route, with as few lane
changes as possible. The route's polyline follows lane centres and junction connectors, and
carries the CARLA RoadOption command along its length.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
import shapely
import sumolib

from bid_sim.errors import BidError
from bid_sim.towns import Town

LEFT, RIGHT, STRAIGHT, LANEFOLLOW, CHANGELANELEFT, CHANGELANERIGHT = 1, 2, 3, 4, 5, 6
COMMAND_NAMES = {
    LEFT: "LEFT",
    RIGHT: "RIGHT",
    STRAIGHT: "STRAIGHT",
    LANEFOLLOW: "LANEFOLLOW",
    CHANGELANELEFT: "CHANGELANELEFT",
    CHANGELANERIGHT: "CHANGELANERIGHT",
}
COMMAND_LEAD_M = 20.0  # the junction's command is given this far before entering it
LANE_CHANGE_M = 25.0  # length of a lane change manoeuvre along the route
BEND_DEG = 60.0  # a road bend (Route.road_bends) turns this much or more ...
BEND_WINDOW_M = 40.0  # ... within this distance
BEND_TRIES = 400  # random candidates per route when it must take a bend ...
BEND_WITHIN_M = 250.0  # ... this near its start (a recorded episode is 90 s by default)
_TURN = {"l": LEFT, "L": LEFT, "r": RIGHT, "R": RIGHT, "s": STRAIGHT, "t": LEFT}


@dataclass(frozen=True)
class RouteSpec:
    """A start/goal pair as stored in routes.toml: edge ids and positions along them (m)."""

    start_edge: str
    start_pos_m: float
    goal_edge: str
    goal_pos_m: float


@dataclass(frozen=True)
class Piece:
    """A stretch of the route on one lane, from s0_m to s1_m of the route's length."""

    lane_id: str
    edge: str
    s0_m: float
    s1_m: float
    junction: str  # node id for junction connectors, '' on roads
    command: int  # the turn for a junction piece, LANEFOLLOW on roads, lane changes too


@dataclass(frozen=True)
class Route:
    """A planned route: SUMO edges for the ego's SUMO route, and lane-level geometry."""

    edges: tuple[str, ...]
    pieces: tuple[Piece, ...]
    polyline: np.ndarray  # (N, 2) m, from start to goal
    cum_s: np.ndarray  # (N,) m
    length_m: float

    def point_at(self, s_m: float) -> tuple[float, float, float]:
        """x, y, heading_rad at distance s_m along the route."""
        s = min(max(s_m, 0.0), self.length_m)
        i = int(np.clip(np.searchsorted(self.cum_s, s, side="right") - 1, 0, len(self.cum_s) - 2))
        p0, p1 = self.polyline[i], self.polyline[i + 1]
        seg = self.cum_s[i + 1] - self.cum_s[i]
        t = 0.0 if seg <= 0 else (s - self.cum_s[i]) / seg
        p = p0 + t * (p1 - p0)
        return float(p[0]), float(p[1]), math.atan2(p1[1] - p0[1], p1[0] - p0[0])

    def piece_at(self, s_m: float) -> Piece:
        for piece in self.pieces:
            if s_m < piece.s1_m:
                return piece
        return self.pieces[-1]

    def project(self, x: float, y: float, s_hint_m: float = 0.0, window_m: float = 40.0):
        """(s_m, signed lateral_m (+ left), heading_rad) of the nearest point near s_hint_m.

        The search stays within window_m of the hint so a route that passes the same place
        twice is followed in order.
        """
        lo = np.searchsorted(self.cum_s, s_hint_m - window_m / 4) - 1
        hi = np.searchsorted(self.cum_s, s_hint_m + window_m) + 1
        lo, hi = max(int(lo), 0), min(int(hi), len(self.cum_s) - 1)
        return project_polyline(self.polyline[lo : hi + 1], self.cum_s[lo : hi + 1], x, y)

    def command_at(self, s_m: float) -> int:
        """The navigation command at s_m: the next junction's turn within 20 m of it."""
        for piece in self.pieces:
            if piece.s1_m <= s_m:
                continue
            if piece.command != LANEFOLLOW and piece.s0_m - COMMAND_LEAD_M <= s_m:
                return piece.command
            if piece.s0_m > s_m + COMMAND_LEAD_M:
                break
        return LANEFOLLOW

    def road_bends(self, min_turn_deg: float = BEND_DEG, window_m: float = BEND_WINDOW_M
                   ) -> list[tuple[float, float]]:
        """Bends of the road outside junctions, the ring's corners: (s_m, turn in degrees,
        + left) for each stretch of one road piece that turns by min_turn_deg or more within
        window_m, s_m where the first such window starts (up to window_m before the bend's
        middle). A junction's turn is not a bend (it has its own command); a bend is driven
        under LANEFOLLOW."""
        seg = np.diff(self.polyline, axis=0)
        length = np.hypot(seg[:, 0], seg[:, 1])
        keep = length > 0.05
        heading = np.unwrap(np.arctan2(seg[keep, 1], seg[keep, 0]))
        mid = (self.cum_s[:-1] + 0.5 * length)[keep]
        road = np.full(len(mid), -1)  # the road piece each segment lies on, -1 in a junction
        for k, piece in enumerate(self.pieces):
            if not piece.junction:
                road[(mid >= piece.s0_m) & (mid < piece.s1_m)] = k
        bends: list[tuple[float, float]] = []
        i = 0
        while i < len(mid):
            if road[i] >= 0:
                j = int(np.searchsorted(mid, mid[i] + window_m, side="right"))
                same = np.nonzero(road[i:j] == road[i])[0] + i
                turn = math.degrees(heading[same[-1]] - heading[i])
                if abs(turn) >= min_turn_deg:
                    bends.append((round(float(mid[i]), 1), round(turn, 1)))
                    i = j
                    continue
            i += 1
        return bends

    def lanes_at(self, s_m: float) -> tuple[str, ...]:
        """Lane ids of the route around s_m (the lane there and its neighbours on the route)."""
        return tuple(p.lane_id for p in self.pieces if p.s0_m - 5.0 <= s_m <= p.s1_m + 5.0)


def project_polyline(poly: np.ndarray, cum: np.ndarray, x: float, y: float):
    a, b = poly[:-1], poly[1:]
    d = b - a
    seg2 = np.maximum((d * d).sum(1), 1e-12)
    t = np.clip(((x - a[:, 0]) * d[:, 0] + (y - a[:, 1]) * d[:, 1]) / seg2, 0.0, 1.0)
    px, py = a[:, 0] + t * d[:, 0], a[:, 1] + t * d[:, 1]
    dist2 = (x - px) ** 2 + (y - py) ** 2
    i = int(np.argmin(dist2))
    s = float(cum[i] + t[i] * math.sqrt(seg2[i]))
    cross = d[i, 0] * (y - a[i, 1]) - d[i, 1] * (x - a[i, 0])
    lateral = math.copysign(math.sqrt(dist2[i]), cross)
    return s, lateral, math.atan2(d[i, 1], d[i, 0])


class RoadGraph:
    """Lane connectivity and shapes of a SUMO network, for planning."""

    def __init__(self, net_file: Path):
        self.net = sumolib.net.readNet(str(net_file), withInternal=True)
        self.car_edges = {
            e.getID(): [lane for lane in e.getLanes() if lane.allows("passenger")]
            for e in self.net.getEdges()
            if e.getFunction() == "" and any(lane.allows("passenger") for lane in e.getLanes())
        }

    def edge(self, edge_id: str):
        if edge_id not in self.car_edges:
            raise BidError(f"edge {edge_id!r} is not a driving edge of this town; check routes.toml")
        return self.net.getEdge(edge_id)

    def shortest_edges(self, start: str, goal: str, loop: bool = False) -> tuple[str, ...]:
        """Edges of the shortest drive; loop=True when the goal lies behind the start on
        the same edge, so the route has to come round again."""
        if start == goal and not loop:
            return (start,)
        best = None
        firsts = [self.edge(start)] if start != goal else sorted(
            self.edge(start).getOutgoing(), key=lambda e: e.getID())
        for first in firsts:
            if first.getID() not in self.car_edges:
                continue
            path, cost = self.net.getShortestPath(first, self.edge(goal), vClass="passenger")
            if path and (best is None or cost < best[1]):
                best = (path, cost)
        if best is None:
            raise BidError(f"no drivable path from edge {start} to {goal}; pick another route")
        path = tuple(e.getID() for e in best[0])
        return path if start != goal else (start, *path)

    def connections(self, from_edge: str, to_edge: str):
        """(from lane index, to lane index, [via lanes], direction) of the links between edges."""
        out = []
        for conns in self.edge(from_edge).getOutgoing().values():
            for c in conns:
                if c.getTo().getID() != to_edge or not c.getToLane().allows("passenger"):
                    continue
                out.append((c.getFromLane().getIndex(), c.getToLane().getIndex(), self._vias(c), c.getDirection()))
        return sorted(out, key=lambda t: (t[0], t[1]))

    @cached_property
    def overpasses(self) -> dict[str, tuple[tuple[str, float, float], ...]]:
        """Where two streets cross with no junction between them, one over the other (Town05's
        bridges; our towns are flat): edge -> ((the other edge, x, y), ...)."""
        edges = [self.net.getEdge(e) for e in sorted(self.car_edges)]
        lines = {e.getID(): shapely.LineString([p[:2] for p in e.getShape()]) for e in edges}
        tree = shapely.STRtree([lines[e.getID()] for e in edges])
        out: dict[str, list[tuple[str, float, float]]] = {}
        for i, a in enumerate(edges):
            for j in sorted(int(k) for k in tree.query(lines[a.getID()], predicate="crosses")):
                b = edges[j]
                if j <= i or {a.getFromNode(), a.getToNode()} & {b.getFromNode(), b.getToNode()}:
                    continue
                for point in shapely.get_parts(lines[a.getID()].intersection(lines[b.getID()])):
                    out.setdefault(a.getID(), []).append((b.getID(), point.x, point.y))
                    out.setdefault(b.getID(), []).append((a.getID(), point.x, point.y))
        return {e: tuple(v) for e, v in out.items()}

    @cached_property
    def tls_links(self) -> dict[tuple[str, str], tuple[str, int]]:
        """(incoming lane, first junction connector lane) -> (signal id, link index)."""
        out = {}
        for edge_id in self.car_edges:
            for conns in self.net.getEdge(edge_id).getOutgoing().values():
                for c in conns:
                    if c.getTLSID() and c.getViaLaneID():
                        out[(c.getFromLane().getID(), c.getViaLaneID())] = (c.getTLSID(), c.getTLLinkIndex())
        return out

    def _vias(self, conn) -> list[str]:
        vias = []
        via = conn.getViaLaneID()
        while via:
            vias.append(via)
            nxt = ""
            for c in self.net.getLane(via).getOutgoing():
                nxt = c.getViaLaneID()
                break
            via = nxt
        return vias

    def lane_shape(self, lane_id: str) -> np.ndarray:
        return np.asarray(self.net.getLane(lane_id).getShape(), dtype=float)

    def locate(self, x: float, y: float, yaw_rad: float | None = None, radius_m: float = 8.0):
        """(edge, lane index, pos_m) of the nearest car lane, preferring lanes along yaw."""
        best = None
        for lane, dist in self.net.getNeighboringLanes(x, y, radius_m, includeJunctions=False):
            if not lane.allows("passenger") or lane.getEdge().getFunction() != "":
                continue
            shape = np.asarray(lane.getShape(), dtype=float)
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(shape, axis=0), axis=1))])
            s, _, heading = project_polyline(shape, cum, x, y)
            cost = dist
            if yaw_rad is not None:
                dyaw = abs(math.atan2(math.sin(yaw_rad - heading), math.cos(yaw_rad - heading)))
                cost += 20.0 * (dyaw > math.pi / 2)
            if best is None or cost < best[0]:
                best = (cost, lane.getEdge().getID(), lane.getIndex(), s)
        if best is None:
            raise BidError(f"no driving lane within {radius_m} m of ({x:.1f}, {y:.1f})")
        return best[1], best[2], best[3]


@lru_cache(maxsize=8)
def road_graph(net_file: Path) -> RoadGraph:
    return RoadGraph(net_file)


def plan(graph: RoadGraph, start_edge: str, start_pos_m: float, goal_edge: str, goal_pos_m: float,
         start_lane: int | None = None) -> Route:
    """Plans the lane-level route from a position on start_edge to one on goal_edge."""
    edges = graph.shortest_edges(start_edge, goal_edge, loop=goal_pos_m <= start_pos_m + 5.0)
    # Lane choice by dynamic programming backwards: fewest lane changes over the route.
    n = len(edges)
    links = [graph.connections(edges[i], edges[i + 1]) for i in range(n - 1)]
    lanes_of = [[lane.getIndex() for lane in graph.car_edges[e]] for e in edges]
    cost: list[dict[int, float]] = [{} for _ in range(n)]
    choice: list[dict[int, tuple]] = [{} for _ in range(n)]
    for lane in lanes_of[-1]:
        cost[-1][lane] = 0.0
    for i in range(n - 2, -1, -1):
        for entry in lanes_of[i]:
            best = None
            for frm, to, vias, direction in links[i]:
                c = abs(frm - entry) + cost[i + 1][to]
                if best is None or c < best[0]:
                    best = (c, frm, to, vias, direction)
            if best is not None:
                cost[i][entry] = best[0]
                choice[i][entry] = best[1:]
    if start_lane is None or start_lane not in cost[0]:
        start_lane = min(cost[0], key=lambda k: (cost[0][k], -k))
    # Walk forward, collecting lane stretches and connectors.
    stretches = []  # (lane_id, edge, from_s, to_s, junction, command, lateral shift to next)
    entry = start_lane
    for i, edge in enumerate(edges):
        e = graph.net.getEdge(edge)
        s_from = start_pos_m if i == 0 else 0.0
        s_to = goal_pos_m if i == n - 1 else None
        if i < n - 1:
            frm, to, vias, direction = choice[i][entry]
            stretches.append((edge, entry, frm, s_from, s_to))
            junction = e.getToNode().getID()
            for via in vias:
                stretches.append((via, junction, _TURN.get(direction, STRAIGHT) if _is_junction(e.getToNode()) else LANEFOLLOW))
            entry = to
        else:
            stretches.append((edge, entry, entry, s_from, s_to))
    return _build(graph, edges, stretches)


def _is_junction(node) -> bool:
    """Three or more streets meet here (a bend between two streets gives no command)."""
    others = {e.getFromNode().getID() for e in node.getIncoming()} | {
        e.getToNode().getID() for e in node.getOutgoing()
    }
    return len(others) >= 3


def _build(graph: RoadGraph, edges, stretches) -> Route:
    pts: list[np.ndarray] = []
    pieces: list[Piece] = []
    s = 0.0

    def add(points: np.ndarray, lane_id: str, edge: str, junction: str, command: int):
        nonlocal s
        if len(points) < 2:
            return
        if pts and np.linalg.norm(pts[-1][-1] - points[0]) < 1e-6:
            points = points[1:]
        seg = np.concatenate([pts[-1][-1:], points]) if pts else points
        length = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        if length <= 0:
            return
        pieces.append(Piece(lane_id, edge, s, s + length, junction, command))
        s += length
        pts.append(points)

    for st in stretches:
        if len(st) == 3:  # connector
            via, junction, command = st
            add(graph.lane_shape(via), via, via.rsplit("_", 1)[0], junction, command)
            continue
        edge, entry, exit_, s_from, s_to = st
        a = _cut(graph.lane_shape(f"{edge}_{entry}"), s_from, s_to)
        if entry == exit_:
            add(a, f"{edge}_{entry}", edge, "", LANEFOLLOW)
            continue
        # Lane change(s) in the middle of the edge: follow the entry lane, blend across.
        b = _cut(graph.lane_shape(f"{edge}_{exit_}"), s_from, s_to)
        total = _length(a)
        mid0 = max(0.0, total / 2 - LANE_CHANGE_M / 2)
        mid1 = min(total, mid0 + LANE_CHANGE_M)
        add(_cut(a, 0, mid0), f"{edge}_{entry}", edge, "", LANEFOLLOW)
        blend = []
        for t in np.linspace(0, 1, 6):
            pa = _at(a, mid0 + t * (mid1 - mid0))
            pb = _at(b, mid0 + t * (mid1 - mid0))
            blend.append(pa + (3 * t * t - 2 * t**3) * (pb - pa))
        command = CHANGELANELEFT if exit_ > entry else CHANGELANERIGHT
        add(np.array(blend), f"{edge}_{exit_}", edge, "", command)
        add(_cut(b, mid1, None), f"{edge}_{exit_}", edge, "", LANEFOLLOW)
    poly = np.concatenate(pts)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    return Route(tuple(edges), tuple(pieces), poly, cum, float(cum[-1]))


def _length(line: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


def _at(line: np.ndarray, s: float) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    return np.array([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])])


def _cut(line: np.ndarray, s0: float, s1: float | None) -> np.ndarray:
    """The part of a polyline between arc lengths s0 and s1 (None = the end)."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    s1 = cum[-1] if s1 is None else min(s1, cum[-1])
    s0 = min(max(s0, 0.0), s1)
    inner = line[(cum > s0) & (cum < s1)]
    return np.concatenate([_at(line, s0)[None], inner, _at(line, s1)[None]])


def plan_spec(graph: RoadGraph, spec: RouteSpec) -> Route:
    return plan(graph, spec.start_edge, spec.start_pos_m, spec.goal_edge, spec.goal_pos_m)


def load_routes(town: Town) -> list[RouteSpec]:
    """The town's benchmark routes from routes.toml, or generated ones if it has none."""
    if not town.routes_file.exists():
        return generate_routes(town, count=25, seed=0)
    try:
        data = tomllib.loads(town.routes_file.read_text())
        return [
            RouteSpec(r["start_edge"], float(r["start_pos_m"]), r["goal_edge"], float(r["goal_pos_m"]))
            for r in data["route"]
        ]
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as e:
        raise BidError(f"{town.routes_file} is malformed ({e}); fix it or delete it to use generated routes") from e


def route_by_index(town: Town, index: int) -> RouteSpec:
    routes = load_routes(town)
    if not 0 <= index < len(routes):
        raise BidError(f"route {index} out of range; {town.name} has routes 0..{len(routes) - 1}")
    return routes[index]


def generate_routes(town: Town, count: int, seed: int, lengths_m: list[float] | None = None,
                    min_length_m: float = 150.0, bends: bool = False) -> list[RouteSpec]:
    """Random start/goal pairs, deterministic per seed; with lengths_m, one route per target
    length, picking the candidate whose planned length is closest. With bends, only routes
    that take a bend of the road (Route.road_bends) in their first BEND_WITHIN_M: a third of
    random routes pass one of Town01's four corners at all, and few of them early."""
    graph = road_graph(town.net_file)
    rng = np.random.default_rng(seed)
    edges = sorted(graph.car_edges)
    long_edges = [e for e in edges if graph.net.getEdge(e).getLength() > 30.0] or edges
    targets = lengths_m if lengths_m is not None else [None] * count
    out: list[RouteSpec] = []
    for target in targets:
        best = None
        for _ in range(BEND_TRIES if bends else 60 if target else 20):
            a, b = rng.choice(long_edges, 2, replace=True)
            la, lb = graph.net.getEdge(a).getLength(), graph.net.getEdge(b).getLength()
            pa = float(np.round(rng.uniform(0.2, 0.6) * la, 1))
            pb = float(np.round(rng.uniform(0.4, 0.8) * lb, 1))
            spec = RouteSpec(str(a), pa, str(b), pb)
            try:
                route = plan_spec(graph, spec)
            except BidError:
                continue
            length = route.length_m
            if length < min_length_m or (bends and not any(at <= BEND_WITHIN_M for at, _ in route.road_bends())):
                continue
            err = 0.0 if target is None else abs(length - target)
            if best is None or err < best[0]:
                best = (err, spec)
            if target is None:
                break
        if best is not None:
            out.append(best[1])
    return out
