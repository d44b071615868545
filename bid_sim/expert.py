"""The expert: a rule-based driver with privileged state (the snapshot), never the pixels.

Lateral: pure pursuit on the planned route with a speed-dependent look-ahead. Longitudinal:
the Intelligent Driver Model (Treiber, Hennecke and Helbing 2000) taken over every
constraint ahead at once — the lead vehicle in the path corridor, the stop line of a red or
amber signal, pedestrians on or about to enter the path, the entry of a junction whose
crossing traffic has priority or whose exit is blocked, the end of the route — under a speed
profile from the lanes' limits and the route's curvature. On multi-lane roads the route's lane
changes wait for a gap on the target lane.

All geometry is in the world frame (m, rad); route positions ``s`` are metres along the
route. Outputs use DESIGN.md's control convention. Nothing here is random.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

from bid_sim.agents import EpisodeInfo, Observation
from bid_sim.ego import Control, EgoParams
from bid_sim.errors import BidError
from bid_sim.routes import (
    CHANGELANELEFT,
    CHANGELANERIGHT,
    LANEFOLLOW,
    RoadGraph,
    Route,
    plan,
    project_polyline,
    road_graph,
)
from bid_sim.snapshot import RED, YELLOW, Actors, Snapshot
from bid_sim.town_map import TownMap, load_town_map
from bid_sim.towns import Town, resolve_town

log = logging.getLogger(__name__)

GRID_M = 1.0  # resolution of the route's speed profile and corridor
DT_S = 0.1  # the episode step
PRIORITY, MINOR, STOP = "G", "g", "r"


@dataclass(frozen=True)
class ExpertConfig:
    """Tuning of the expert; speeds m/s, accelerations m/s², distances m, times s."""

    max_speed_mps: float = 13.9  # never faster, whatever the lane allows
    lateral_accel_mps2: float = 2.5  # in turns
    wide_right_gain_m2: float = 3.0  # right turns shifted out by this times the curvature
    wide_right_max_m: float = 0.5
    accel_mps2: float = 2.0  # IDM maximum acceleration
    comfort_decel_mps2: float = 3.0  # IDM comfortable deceleration, and for the speed profile
    headway_s: float = 1.3  # IDM time gap to a moving lead
    min_gap_m: float = 3.0  # standstill gap to a vehicle
    ped_gap_m: float = 3.0  # standstill gap to a pedestrian
    stop_line_gap_m: float = 1.0  # the front bumper stops this far before a stop line
    crossing_gap_m: float = 2.0  # and this far before a crossing (a turning car's corner leads)
    amber_decel_mps2: float = 3.5  # stop at amber if this deceleration suffices
    amber_s: float = 3.0  # amber phase length (our towns' signal programs)
    lookahead_m: float = 2.0  # pure pursuit look-ahead at standstill
    lookahead_s: float = 0.35  # look-ahead grows by speed times this
    lookahead_max_m: float = 9.0
    ff_preview_m: float = -1.0  # the curvature fed forward is read this far ahead (measured best)
    ff_preview_s: float = -0.1  # plus speed times this
    horizon_m: float = 70.0  # how far along the route actors are considered
    corridor_margin_m: float = 0.35  # beyond both half-widths, vehicles
    ped_margin_m: float = 1.0  # beyond both half-widths, pedestrians
    ped_predict_s: float = 3.0  # pedestrians are extrapolated this far
    ped_clearance_m: float = 0.4  # between the car's side and a standing pedestrian
    max_nudge_m: float = 0.7  # sideways shift to pass a standing pedestrian at the kerb
    ped_patience_s: float = 4.0  # on a yielding link, wait this long for one standing at a crossing
    conflict_half_width_m: float = 2.3  # two paths closer than this conflict
    conflict_buffer_s: float = 1.5  # clearance before and after the ego in a conflict zone
    junction_look_m: float = 45.0  # conflicts are checked from this far before a junction
    deadlock_patience_s: float = 3.0  # after waiting this long for a standing car, go
    lane_change_gap_s: float = 1.0  # time gap wanted ahead and behind on the target lane
    lane_change_min_gap_m: float = 4.0


CROSSING_STEP_M = 0.1  # the route is sampled this finely to find where it crosses crossings


# ----------------------------------------------------------------------------- town facts


@dataclass(frozen=True, eq=False)
class _Link:
    """One way through a junction: incoming lane, connector lanes, outgoing lane, signal."""

    incoming: str
    vias: tuple[str, ...]
    outgoing: str
    junction: str
    tls_id: str  # '' when unsignalised
    link_index: int
    static: str  # PRIORITY or MINOR where unsignalised
    line: np.ndarray  # (N, 2) connector centre line
    offsets: tuple[float, ...]  # where each via starts along line


class _TownFacts:
    """Junction links and pedestrian areas of a town, built once per town."""

    def __init__(self, town_map: TownMap, graph: RoadGraph):
        self.map = town_map
        self.graph = graph
        self.links: list[_Link] = []
        self.by_via: dict[str, list[tuple[_Link, float]]] = {}
        self.by_incoming: dict[str, list[_Link]] = {}
        net = graph.net
        for edge_id in sorted(graph.car_edges):
            edge = net.getEdge(edge_id)
            for conns in edge.getOutgoing().values():
                for c in conns:
                    if not c.getToLane().allows("passenger") or not c.getViaLaneID():
                        continue
                    vias = _via_chain(net, c.getViaLaneID())
                    shapes = [np.asarray(net.getLane(v).getShape(), float)[:, :2] for v in vias]
                    offsets, total, pts = [], 0.0, []
                    for shp in shapes:
                        offsets.append(total)
                        total += float(np.linalg.norm(np.diff(shp, axis=0), axis=1).sum())
                        pts.append(shp if not pts else shp[1:])
                    link = _Link(c.getFromLane().getID(), vias, c.getToLane().getID(),
                                 edge.getToNode().getID(), c.getTLSID() or "",
                                 int(c.getTLLinkIndex()) if c.getTLSID() else -1,
                                 PRIORITY if c.getState() == "M" else MINOR,
                                 np.concatenate(pts), tuple(offsets))
                    self.links.append(link)
                    self.by_incoming.setdefault(link.incoming, []).append(link)
                    for via, off in zip(vias, offsets, strict=True):
                        self.by_via.setdefault(via, []).append((link, off))
        self.lane_length = {lane.id: lane.length_m() for lane in town_map.lanes}
        walk = shapely.union_all([Polygon(r) for r in town_map.sidewalks]) if town_map.sidewalks \
            else Polygon()
        cross = shapely.union_all([Polygon(r) for r in town_map.crossings]) if town_map.crossings \
            else Polygon()
        # Where a pedestrian is out of the cars' way: sidewalks and walking areas, not crossings,
        # and not where a walking area reaches over a driving lane (Town05 has 350 m² of such).
        lanes = shapely.union_all([LineString(lane.centre).buffer(lane.width_m / 2 - 0.3, cap_style="flat")
                                   for lane in town_map.lanes if not lane.internal])
        self.kerb = walk.difference(cross).difference(lanes)
        shapely.prepare(self.kerb)
        self.walk_on_road = walk.intersection(lanes)  # pedestrians walk there, across the lanes
        shapely.prepare(self.walk_on_road)

    def link_of(self, incoming: str, first_via: str) -> _Link | None:
        """The link that leaves the incoming lane through the given first connector lane."""
        for link in self.by_incoming.get(incoming, ()):
            if link.vias[0] == first_via:
                return link
        return None


def _via_chain(net, first: str) -> tuple[str, ...]:
    """The connector lanes of one connection, in order (SUMO splits a turn that waits
    inside the junction into two)."""
    chain = []
    via = first
    while via:
        chain.append(via)
        outgoing = net.getLane(via).getOutgoing()
        via = outgoing[0].getViaLaneID() if outgoing else ""
    return tuple(chain)


# ----------------------------------------------------------------------------- route plan


@dataclass(frozen=True, eq=False)
class _Conflict:
    """Where another junction link crosses or merges with the ego's path."""

    other: _Link
    s_in: float  # route s where the ego's path enters the conflict zone
    s_out: float
    a_in: float  # distance along the other link where it enters the zone
    a_out: float


@dataclass(frozen=True, eq=False)
class _Junction:
    """One junction on the route: where the ego is inside it and how it goes through."""

    node: str
    s_in: float
    s_out: float
    link: _Link | None
    conflicts: tuple[_Conflict, ...]


@dataclass(frozen=True, eq=False)
class _LaneChange:
    s0: float  # the route's blend across starts here
    s1: float
    entry_lane: str
    target_lane: str
    s_limit: float  # the change must be done by here (end of the road)


@dataclass
class _LaneChangeState:
    waiting: bool = False  # no gap yet: keeping to the entry lane
    began: float | None = None  # route s where the ego's own change across began
    span_m: float = 12.0
    done: bool = False


@dataclass(eq=False)
class _Plan:
    """The route, resampled with its speed profile, junctions and lane changes."""

    polyline: np.ndarray  # the snapshot's route polyline (identity marks a re-plan)
    s: np.ndarray  # (M,) grid, m
    xy: np.ndarray  # (M, 2)
    heading: np.ndarray  # (M,)
    curvature: np.ndarray  # (M,) signed, 1/m, + left
    v_limit: np.ndarray  # (M,) lane limit and curvature
    v_profile: np.ndarray  # (M,) v_limit with comfortable braking towards what comes
    length_m: float
    junctions: tuple[_Junction, ...] = ()
    lane_changes: tuple[_LaneChange, ...] = ()
    crossings: tuple[tuple[float, float], ...] = ()  # (s_in, s_out) of pedestrian crossings

    def index(self, s_m: float) -> int:
        return int(min(max(round(s_m / GRID_M), 0), len(self.s) - 1))

    def point(self, s_m: float) -> tuple[float, float]:
        s = min(max(s_m, 0.0), self.length_m)
        return float(np.interp(s, self.s, self.xy[:, 0])), float(np.interp(s, self.s, self.xy[:, 1]))


def _build_plan(polyline: np.ndarray, route: Route | None, facts: _TownFacts, cfg: ExpertConfig,
                default_limit: float) -> _Plan:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0), axis=1))])
    length = float(cum[-1])
    s = np.arange(0.0, length + GRID_M, GRID_M)
    s[-1] = min(s[-1], length)
    xy = np.column_stack([np.interp(s, cum, polyline[:, 0]), np.interp(s, cum, polyline[:, 1])])
    d = np.gradient(xy, axis=0) if len(s) > 1 else np.array([[1.0, 0.0]])
    heading = np.arctan2(d[:, 1], d[:, 0])
    curv = _curvature(heading)
    # Right turns a little wide: their inner corner is where pedestrians wait to cross.
    wide = np.convolve(np.clip(-curv * cfg.wide_right_gain_m2, 0.0, cfg.wide_right_max_m),
                       np.ones(7) / 7, mode="same")
    if wide.any():
        xy = xy + wide[:, None] * np.column_stack([-np.sin(heading), np.cos(heading)])
        d = np.gradient(xy, axis=0)
        heading = np.arctan2(d[:, 1], d[:, 0])
        curv = _curvature(heading)
    v_curve = np.sqrt(cfg.lateral_accel_mps2 / np.maximum(np.abs(curv), 1e-4))
    lane_limit = np.full(len(s), default_limit)
    junctions: list[_Junction] = []
    lane_changes: list[_LaneChange] = []
    if route is not None:
        for p in route.pieces:
            i0, i1 = int(p.s0_m // GRID_M), math.ceil(p.s1_m / GRID_M) + 1
            idx = facts.map.lane_index.get(p.lane_id)
            if idx is not None and not facts.map.lanes[idx].internal:
                lane_limit[i0:i1] = facts.map.lanes[idx].speed_mps
        junctions = _route_junctions(route, facts, cfg)
        lane_changes = _route_lane_changes(route, facts)
    v_limit = np.minimum(np.minimum(lane_limit, v_curve), cfg.max_speed_mps)
    v_profile = v_limit.copy()
    for i in range(len(s) - 2, -1, -1):  # brake comfortably towards every slower stretch
        reach = math.sqrt(v_profile[i + 1] ** 2 + 2.0 * 0.7 * cfg.comfort_decel_mps2 * GRID_M)
        v_profile[i] = min(v_profile[i], reach)
    return _Plan(polyline, s, xy, heading, curv, v_limit, v_profile, length, tuple(junctions),
                 tuple(lane_changes), _route_crossings(polyline, facts))


def _curvature(heading: np.ndarray) -> np.ndarray:
    """Signed curvature (1/m, + left) on the 1 m grid, from the heading change over ±2 m,
    smoothed: the route polyline's corners are sharp."""
    unwrapped = np.unwrap(heading)
    k = 2
    curv = np.zeros(len(heading))
    if len(heading) > 2 * k:
        curv[k:-k] = (unwrapped[2 * k:] - unwrapped[: -2 * k]) / (2 * k * GRID_M)
        curv = np.convolve(curv, np.ones(3) / 3, mode="same")
    return curv


def _route_crossings(polyline: np.ndarray, facts: _TownFacts) -> tuple[tuple[float, float], ...]:
    """Route s intervals where the route runs over a pedestrian crossing, one per pass: a
    route that comes by the same crossing twice (round a block) has two intervals."""
    line = LineString(polyline)
    s_vertex = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(polyline, axis=0).T))])
    s = np.arange(0.0, s_vertex[-1] + CROSSING_STEP_M, CROSSING_STEP_M)
    x, y = np.interp(s, s_vertex, polyline[:, 0]), np.interp(s, s_vertex, polyline[:, 1])
    out = []
    for ring in facts.map.crossings:
        polygon = Polygon(ring)
        if not line.intersects(polygon):
            continue
        inside = np.concatenate([[False], shapely.contains_xy(polygon, x, y), [False]])
        edges = np.flatnonzero(np.diff(inside.astype(np.int8)))
        out += [(float(s[a]), float(s[b - 1])) for a, b in zip(edges[::2], edges[1::2], strict=True)]
    return tuple(sorted(out))


def _route_junctions(route: Route, facts: _TownFacts, cfg: ExpertConfig) -> list[_Junction]:
    out = []
    pieces = route.pieces
    i = 0
    while i < len(pieces):
        p = pieces[i]
        if not p.junction:
            i += 1
            continue
        j = i
        while j + 1 < len(pieces) and pieces[j + 1].junction == p.junction:
            j += 1
        s_in, s_out = p.s0_m, pieces[j].s1_m
        link = facts.link_of(pieces[i - 1].lane_id, p.lane_id) if i > 0 else None
        conflicts = _conflicts(route, s_in, s_out, link, facts, cfg) if link is not None else ()
        out.append(_Junction(p.junction, s_in, s_out, link, conflicts))
        i = j + 1
    return out


def _conflicts(route: Route, s_in: float, s_out: float, link: _Link, facts: _TownFacts,
               cfg: ExpertConfig) -> tuple[_Conflict, ...]:
    mask = (route.cum_s > s_in) & (route.cum_s < s_out)
    pts = [route.point_at(s_in)[:2], *map(tuple, route.polyline[mask]), route.point_at(s_out)[:2]]
    ours = LineString(pts)
    ours_zone = ours.buffer(cfg.conflict_half_width_m, cap_style="flat")
    out = []
    for other in facts.links:
        if other.junction != link.junction or other.incoming == link.incoming:
            continue
        theirs = LineString(other.line)
        hit = theirs.intersection(ours_zone)
        if hit.is_empty:
            continue
        a = [theirs.project(shapely.Point(c)) for g in shapely.get_parts(hit) for c in g.coords]
        back = ours.intersection(theirs.buffer(cfg.conflict_half_width_m, cap_style="flat"))
        b = [ours.project(shapely.Point(c)) for g in shapely.get_parts(back) for c in g.coords]
        if not a or not b:
            continue
        out.append(_Conflict(other, s_in + min(b), s_in + max(b), min(a), max(a)))
    return tuple(out)


def _route_lane_changes(route: Route, facts: _TownFacts) -> list[_LaneChange]:
    out = []
    pieces = route.pieces
    for i, p in enumerate(pieces):
        if p.command not in (CHANGELANELEFT, CHANGELANERIGHT) or i == 0:
            continue
        end = p.s1_m
        for q in pieces[i + 1:]:
            if q.junction or q.edge != p.edge:
                break
            end = q.s1_m
        entry = pieces[i - 1].lane_id
        if entry in facts.by_via:  # a change right after a junction: from the lane it leads onto
            entry = facts.by_via[entry][0][0].outgoing
        out.append(_LaneChange(p.s0_m, p.s1_m, entry, p.lane_id, end))
    return out


# ----------------------------------------------------------------------------- helpers


def _idm(v: float, v0: float, gap: float, lead_v: float, cfg: ExpertConfig, s0: float,
         headway: float) -> float:
    """IDM acceleration behind an obstacle gap metres ahead moving at lead_v along the path."""
    free = 1.0 - (v / max(v0, 0.1)) ** 4
    if gap <= 0.05:
        return -1e3
    dyn = s0 + max(0.0, v * headway + v * (v - lead_v) / (2.0 * math.sqrt(cfg.accel_mps2 * cfg.comfort_decel_mps2)))
    return cfg.accel_mps2 * (free - (dyn / gap) ** 2)


def _travel_time(d: float, v: float, a: float, vmax: float) -> float:
    """Seconds to cover d metres from speed v accelerating at a up to vmax."""
    if d <= 0.0:
        return 0.0
    v = max(v, 0.0)
    vmax = max(vmax, v, 0.5)
    if a <= 1e-6:
        return d / max(v, 0.5)
    t_acc = (vmax - v) / a
    d_acc = v * t_acc + 0.5 * a * t_acc * t_acc
    if d <= d_acc:
        return (-v + math.sqrt(v * v + 2.0 * a * d)) / a
    return t_acc + (d - d_acc) / vmax


def _pursuit_angle(x: float, y: float, yaw: float, tx: float, ty: float, wheelbase: float) -> float:
    """Pure-pursuit wheel angle (rad, + left) from a pose towards a target point."""
    alpha = math.atan2(ty - y, tx - x) - yaw
    ld = max(math.hypot(tx - x, ty - y), 1e-3)
    return math.atan2(2.0 * wheelbase * math.sin(alpha), ld)


def _wrap(a: np.ndarray | float):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass
class _Constraint:
    gap_m: float  # front bumper to the obstacle (or the stop point), m
    speed_mps: float  # obstacle speed along the path
    s0_m: float
    headway_s: float
    reason: str


# ----------------------------------------------------------------------------- the expert


class Expert:
    """Rule-based driver with privileged state; implements the Agent protocol.

    town: the town (or its name) when EpisodeInfo.town alone does not resolve it.
    After each act(), ``command`` holds the navigation command (CARLA RoadOption 1..6),
    ``reason`` what limited the speed, ``gap_m`` how far ahead of the front bumper that was (inf
    for the speed itself) and ``lane_change`` the state of a lane change (for inspection, tests
    and bid_sim.perturb.Dagger's late braking).
    """

    def __init__(self, config: ExpertConfig = ExpertConfig(), town: Town | str | None = None):
        self.cfg = config
        self._town_override = town
        self.params = EgoParams()
        self.facts: _TownFacts | None = None
        self._facts_key: str | None = None
        self.info: EpisodeInfo | None = None
        self.plan: _Plan | None = None
        self.command = LANEFOLLOW
        self.reason = ""
        self.gap_m = math.inf
        self.speed_limit_mps = 11.18
        self.nudge_m = 0.0  # sideways shift of the path (+ left) to pass a standing pedestrian
        self.lane_change = ""  # '' | 'waiting' (for a gap) | 'changing' (its own change across)
        self._amber: dict[int, tuple[float, bool | None]] = {}  # stop line route m -> (amber seen, go)
        self._lc: dict[int, _LaneChangeState] = {}
        self._stalled: dict[str, float] = {}  # standing vehicle -> seconds the ego stood for it
        self._ped_wait: dict[str, float] = {}  # standing pedestrian -> seconds the ego waited

    # -- Agent protocol -----------------------------------------------------------------
    def reset(self, info: EpisodeInfo) -> None:
        self.info = info
        self.params = info.params
        town = self._town_override if self._town_override is not None else info.town
        town = town if isinstance(town, Town) else resolve_town(town)
        key = str(town.net_file)
        if self._facts_key != key:
            self.facts = _TownFacts(load_town_map(town), road_graph(town.net_file))
            self._facts_key = key
        self.speed_limit_mps = town.speed_limit_mps
        self.plan = _build_plan(info.route.polyline, info.route, self.facts, self.cfg, self.speed_limit_mps)
        self.command = LANEFOLLOW
        self.reason = ""
        self.gap_m = math.inf
        self._amber = {}
        self._lc = {}
        self._stalled = {}
        self._ped_wait = {}

    def act(self, obs: Observation) -> Control:
        if self.plan is None or self.facts is None:
            raise BidError("Expert.act before reset; call reset(episode_info) first")
        snap = obs.snapshot
        if snap.route_polyline is not self.plan.polyline and len(snap.route_polyline) >= 2:
            self._replan(snap.route_polyline)
        self.command = int(obs.command)
        ego = snap.ego
        plan = self.plan
        s_c = ego.route_s_m
        s_f = s_c + self.params.length_m / 2
        v = ego.speed_mps
        cons = self._update_lane_changes(snap, s_c, s_f)
        ped_cons, self.nudge_m = self._pedestrians(snap, s_c, s_f, self._minor_link_ahead(snap, s_f))
        steer = self._steer(snap, s_c, v)

        v0 = float(plan.v_profile[plan.index(s_c + 1.0)])
        active = self._active_lane_change()
        self.lane_change = "" if active is None else "waiting" if active[1].waiting else "changing"
        if active is not None and active[1].waiting:
            v0 *= 0.8  # let the car alongside pass
        if self.nudge_m:
            v0 = min(v0, 3.0)  # edging past a pedestrian
        cons += self._vehicles(snap, s_c, s_f)
        cons += ped_cons
        cons += self._light(snap, s_f, v)
        cons += self._junction(snap, s_c, s_f, v, cons)
        cons.append(_Constraint(plan.length_m + 2.0 - s_f, 0.0, 0.0, 0.0, "route end"))
        free = self.cfg.accel_mps2 * (1.0 - (v / max(v0, 0.1)) ** 4)
        a, self.reason, self.gap_m = free, "speed", math.inf
        for c in cons:
            ac = _idm(v, v0, c.gap_m, c.speed_mps, self.cfg, c.s0_m, c.headway_s)
            if ac < a:
                a = ac
                if ac < free - 0.1:
                    self.reason, self.gap_m = c.reason, c.gap_m
        a = min(max(a, -self.params.max_brake_mps2), self.cfg.accel_mps2)
        if v < 0.05 and a < 0.1:
            a = min(a, -1.0)  # hold the brake at a standstill
        accel = a / self.params.max_accel_mps2 if a > 0 else a / self.params.max_brake_mps2
        return Control(float(np.clip(steer, -1.0, 1.0)), float(np.clip(accel, -1.0, 1.0)))

    # -- route --------------------------------------------------------------------------
    def _replan(self, polyline: np.ndarray) -> None:
        """The episode re-planned the route: plan the same route here to know its lanes."""
        route = None
        old = self.info.route
        try:
            heading = math.atan2(*(polyline[1] - polyline[0])[::-1])
            edge, lane, pos = self.facts.graph.locate(float(polyline[0, 0]), float(polyline[0, 1]), heading)
            goal_lane = old.pieces[-1].lane_id
            shape = self.facts.graph.lane_shape(goal_lane)
            gcum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(shape, axis=0), axis=1))])
            goal_pos = project_polyline(shape, gcum, float(polyline[-1, 0]), float(polyline[-1, 1]))[0]
            candidate = plan(self.facts.graph, edge, pos, old.edges[-1], goal_pos, start_lane=lane)
            plen = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).sum())
            if abs(candidate.length_m - plen) < 1.0:
                route = candidate
        except (BidError, IndexError, ValueError):
            route = None
        if route is None:
            log.debug("expert: re-planned route not reproduced; following its polyline only")
        self.plan = _build_plan(polyline, route, self.facts, self.cfg, self.speed_limit_mps)
        self._amber = {}
        self._lc = {}
        self._stalled = {}
        self._ped_wait = {}

    def _steer(self, snap: Snapshot, s_c: float, v: float) -> float:
        """Pure pursuit of a point look-ahead metres on, plus the path curvature fed forward.

        Pure pursuit alone cuts corners by about ld²/2R; the pursuit term here is the
        difference between the actual pose and the ideal pose on the path, so on the path
        the wheel angle is exactly the one that holds the path's curvature.
        """
        ego = snap.ego
        p = self.params
        # Where the ego is on our own (widened) path, near its route progress.
        s_c = float(self._project(np.array([[ego.x_m, ego.y_m]]), s_c)[0][0])
        ld = min(self.cfg.lookahead_m + self.cfg.lookahead_s * v, self.cfg.lookahead_max_m)
        tx, ty = self._pursuit_target(snap, s_c, ld)
        lr = p.wheelbase_m / 2
        kappa = 0.0 if self._active_lane_change() is not None else float(
            self.plan.curvature[self.plan.index(s_c + self.cfg.ff_preview_m + self.cfg.ff_preview_s * v)])
        beta = math.asin(min(max(kappa * lr, -0.95), 0.95))  # body slip at the centre
        delta_ff = math.atan(2.0 * math.tan(beta))
        px, py = self.plan.point(s_c)
        ph = float(self.plan.heading[self.plan.index(s_c)])
        if self.nudge_m:
            th = float(self.plan.heading[self.plan.index(s_c + ld)])
            px, py = px - self.nudge_m * math.sin(ph), py + self.nudge_m * math.cos(ph)
            tx, ty = tx - self.nudge_m * math.sin(th), ty + self.nudge_m * math.cos(th)
        actual = _pursuit_angle(ego.x_m, ego.y_m, ego.yaw_rad, tx, ty, p.wheelbase_m)
        if self._active_lane_change() is not None:
            return float(np.clip(-actual / p.max_wheel_rad, -1.0, 1.0))  # off the plan: plain pursuit
        ideal = _pursuit_angle(px, py, ph - beta, tx, ty, p.wheelbase_m)
        delta = delta_ff + actual - ideal
        return float(np.clip(-delta / p.max_wheel_rad, -1.0, 1.0))

    def _pursuit_target(self, snap: Snapshot, s_c: float, ld: float) -> tuple[float, float]:
        s_t = s_c + ld
        x, y = self.plan.point(s_t)
        active = self._active_lane_change()
        if active is not None:
            change, st = active
            # On the entry lane until the gap opens, then across from where the ego is.
            lane = self.facts.map.lane(change.entry_lane)
            ls, _, _ = lane.project(snap.ego.x_m, snap.ego.y_m)
            lx, ly, _ = lane.point_at(ls + ld)
            w = 0.0
            if st.began is not None:
                t = min(max((s_t - st.began) / st.span_m, 0.0), 1.0)
                w = t * t * (3.0 - 2.0 * t)
            x, y = lx + w * (x - lx), ly + w * (y - ly)
        return x, y

    # -- vehicles ahead -------------------------------------------------------------------
    def _window(self, s_c: float) -> slice:
        p = self.plan
        return slice(p.index(s_c - 8.0), p.index(s_c + self.cfg.horizon_m) + 1)

    def _project(self, pts: np.ndarray, s_c: float):
        """(s, lateral, path heading) of points (N, 2) on the route window around s_c."""
        p = self.plan
        w = self._window(s_c)
        xy, hd, ss = p.xy[w], p.heading[w], p.s[w]
        d2 = ((pts[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
        k = np.argmin(d2, axis=1)
        rel = pts - xy[k]
        c, s = np.cos(hd[k]), np.sin(hd[k])
        along = rel[:, 0] * c + rel[:, 1] * s
        lat = -rel[:, 0] * s + rel[:, 1] * c
        return ss[k] + along, lat, hd[k]

    def _vehicles(self, snap: Snapshot, s_c: float, s_f: float) -> list[_Constraint]:
        veh = snap.vehicles
        ego = snap.ego
        if not len(veh):
            return []
        near = np.hypot(veh.xy[:, 0] - ego.x_m, veh.xy[:, 1] - ego.y_m) < self.cfg.horizon_m + 10.0
        if not near.any():
            return []
        idx = np.nonzero(near)[0]
        xy, yaw, speed, size = veh.xy[idx], veh.yaw_rad[idx], veh.speed_mps[idx], veh.size[idx]
        s, lat, hd = self._project(xy, s_c)
        dth = _wrap(yaw - hd)
        half_w = 0.5 * (np.abs(size[:, 0] * np.sin(dth)) + np.abs(size[:, 1] * np.cos(dth)))
        half_l = 0.5 * (np.abs(size[:, 0] * np.cos(dth)) + np.abs(size[:, 1] * np.sin(dth)))
        reach = self.params.width_m / 2 + half_w + self.cfg.corridor_margin_m
        inside = np.abs(lat) < reach
        active = self._active_lane_change()
        if active is not None:
            # Kept to the entry lane: its corridor, not the route's (the target lane, where
            # the gap check looks); while changing across, both.
            lane = self.facts.map.lane(active[0].entry_lane)
            on_entry = np.array([abs(lane.project(float(px), float(py))[1]) for px, py in xy]) < reach
            inside = on_entry if active[1].waiting else inside | on_entry
        # Cut-ins: running our way and inside the corridor within a second.
        fut = xy + speed[:, None] * np.column_stack([np.cos(yaw), np.sin(yaw)])
        fs, flat, _ = self._project(fut, s_c)
        cut_in = (np.abs(dth) < math.radians(30)) & (np.abs(flat) < reach) & (fs > s)
        hit = (inside | cut_in) & (s > s_c) & (s - half_l - s_f < self.cfg.horizon_m)
        out = []
        for j in np.nonzero(hit)[0]:
            gap = max(float(s[j] - half_l[j] - s_f), 0.1)
            along_v = float(speed[j] * math.cos(dth[j]))
            out.append(_Constraint(gap, along_v, self.cfg.min_gap_m, self.cfg.headway_s,
                                   f"vehicle {veh.ids[idx[j]]}"))
        return out

    # -- pedestrians ----------------------------------------------------------------------
    def _minor_link_ahead(self, snap: Snapshot, s_f: float) -> bool:
        """Whether the ego is at or in a junction on a link that must yield (pedestrians
        there may have green at the same time)."""
        for jn in self.plan.junctions:
            if jn.s_out < s_f - self.params.length_m:
                continue
            if jn.s_in - s_f > 15.0 or jn.link is None:
                return False
            return self._link_char(snap, jn.link) == MINOR
        return False

    def _pedestrians(self, snap: Snapshot, s_c: float, s_f: float, minor: bool = False
                     ) -> tuple[list[_Constraint], float]:
        """Pedestrians in the path or walking into it within ped_predict_s (off the kerb),
        and the sideways nudge (m, + left) that passes those standing at its edge.

        For a pedestrian on or entering a crossing the ego stops before the crossing, not on
        it; once on the crossing it clears it unless a pedestrian is about to be hit.
        """
        peds = snap.pedestrians
        ego = snap.ego
        if not len(peds):
            return [], 0.0
        near = np.hypot(peds.xy[:, 0] - ego.x_m, peds.xy[:, 1] - ego.y_m) < 45.0
        if not near.any():
            return [], 0.0
        idx = np.nonzero(near)[0]
        cfg = self.cfg
        ts = np.arange(0.0, cfg.ped_predict_s + 1e-9, 0.5)
        speed = peds.speed_mps[idx]
        vel = speed[:, None] * np.column_stack([np.cos(peds.yaw_rad[idx]), np.sin(peds.yaw_rad[idx])])
        pts = peds.xy[idx][:, None, :] + ts[None, :, None] * vel[:, None, :]  # (N, T, 2)
        flat = pts.reshape(-1, 2)
        s, lat, hd = self._project(flat, s_c)
        s, lat = s.reshape(len(idx), len(ts)), lat.reshape(len(idx), len(ts))
        hd = hd.reshape(len(idx), len(ts))[:, 0]
        body = self.params.width_m / 2 + 0.3
        walking = speed > 0.3
        # Standing: pass with a nudge if it takes little, else stop.
        clear = body + cfg.ped_clearance_m
        rear = s_c - self.params.length_m / 2
        need = clear - np.abs(lat[:, 0])
        standing = ~walking & (s[:, 0] > rear - 0.5) & (s[:, 0] < s_f + 20.0) & (need > 0.0)
        left = float(need[standing & (lat[:, 0] < 0)].max(initial=0.0))
        right = float(need[standing & (lat[:, 0] >= 0)].max(initial=0.0))
        nudge = 0.0
        if (left > 0.0) != (right > 0.0) and max(left, right) <= cfg.max_nudge_m:
            nudge = left - right
            standing[:] = False
        danger = np.zeros(s.shape, bool)
        danger[:, 0] = standing & (s[:, 0] > s_f - 0.5)
        if minor and self.plan.crossings:
            # On a yielding link, a pedestrian waiting at a crossing ahead may have green
            # now: wait for it to walk, for a while.
            at_crossing = np.zeros(len(idx), bool)
            for c_in, c_out in self.plan.crossings:
                at_crossing |= (s[:, 0] > c_in - 1.5) & (s[:, 0] < c_out + 1.5)
            waiting = ~walking & at_crossing & (np.abs(lat[:, 0]) < body + 1.3) & (s[:, 0] > s_f - 0.5)
            patience = self._ped_wait
            self._ped_wait = {}
            for j in np.nonzero(waiting)[0]:
                pid = peds.ids[idx[j]]
                waited = patience.get(pid, 0.0) + (DT_S if ego.speed_mps < 0.3 else 0.0)
                self._ped_wait[pid] = waited
                if waited < cfg.ped_patience_s:
                    danger[j, 0] = True
        reach = np.where(ts[None, :] > 0, body + cfg.ped_margin_m, body + 0.5)
        moving = walking[:, None] & (s > s_f - 0.5) & (s < s_f + 35.0) & (np.abs(lat) < reach)
        if moving.any():
            on_kerb = np.zeros(moving.size, bool)
            a = moving.ravel()
            on_kerb[a] = shapely.contains_xy(self.facts.kerb, flat[a, 0], flat[a, 1])
            # Pedestrians keep to kerbs, crossings and walking areas: a straight-line guess that
            # cuts through a junction counts only where it meets the path on a crossing or on a
            # walking area that reaches over the lanes.
            on_crossing = np.zeros(s.shape, bool)
            for c_in, c_out in self.plan.crossings:
                on_crossing |= (s > c_in - 0.5) & (s < c_out + 0.5)
            on_road_walk = np.zeros(moving.size, bool)
            on_road_walk[a] = shapely.contains_xy(self.facts.walk_on_road, flat[a, 0], flat[a, 1])
            plausible = (ts[None, :] == 0) | on_crossing | on_road_walk.reshape(moving.shape)
            danger |= moving & ~on_kerb.reshape(moving.shape) & plausible
        out = self._right_hook(snap, idx, s[:, 0], lat[:, 0], hd, walking, s_c, s_f)
        for j in np.nonzero(danger.any(axis=1))[0]:
            first = float(s[j][danger[j]].min())
            gap, s0 = first - 0.3 - s_f, cfg.ped_gap_m
            for c_in, c_out in self.plan.crossings:
                if c_in - 1.5 <= first <= c_out + 1.5:
                    # Stop before the junction's first crossing not yet entered, not between two.
                    entries = [a for a, _ in self.plan.crossings
                               if c_in - 25.0 <= a <= c_in and s_f < a + 0.3]
                    if entries:
                        gap, s0 = min(entries) - cfg.crossing_gap_m - s_f, 0.3
                    elif not danger[j, :3].any():
                        gap = None  # on the crossing already: clear it unless it is imminent
                    break
            if gap is not None:
                out.append(_Constraint(max(gap, 0.1), 0.0, s0, 0.5, f"pedestrian {peds.ids[idx[j]]}"))
        return out, nudge

    def _right_hook(self, snap: Snapshot, idx: np.ndarray, s: np.ndarray, lat: np.ndarray,
                    path_heading: np.ndarray, walking: np.ndarray, s_c: float, s_f: float
                    ) -> list[_Constraint]:
        """Pedestrians walking beside the car, its way, towards a crossing it is about to
        drive over as it turns: walking straight on, they step onto it as the car gets there.
        A crossing the car drives over without turning runs along their way: they keep to the
        kerb beside it."""
        ahead = [(a, b) for a, b in self.plan.crossings if s_f - 0.3 < a < s_f + 12.0]
        if not ahead:
            return []
        peds = snap.pedestrians
        v = snap.ego.speed_mps
        yaw = peds.yaw_rad[idx]
        same_way = np.cos(yaw - path_heading) > 0.5
        out = []
        for c_in, c_out in ahead:
            crossing_heading = self.plan.heading[self.plan.index(0.5 * (c_in + c_out))]
            onto = np.abs(np.cos(yaw - crossing_heading)) < 0.5
            beside = walking & same_way & onto & (s > s_c - 8.0) & (s < c_in + 1.0) & (np.abs(lat) < 4.5)
            for j in np.nonzero(beside)[0]:
                t_ped = max(c_in - s[j], 0.0) / max(float(peds.speed_mps[idx[j]]), 0.5)
                t_clear = _travel_time(c_out - s_f + self.params.length_m, v, 1.5, max(v, 4.0))
                if t_ped < t_clear + 1.0:
                    out.append(_Constraint(max(ahead[0][0] - self.cfg.crossing_gap_m - s_f, 0.1), 0.0,
                                           0.3, 0.5, f"pedestrian {peds.ids[idx[j]]} beside"))
        return out

    # -- signals --------------------------------------------------------------------------
    def _light(self, snap: Snapshot, s_f: float, v: float) -> list[_Constraint]:
        d = snap.next_light_dist_m
        state = snap.next_light_state
        if not math.isfinite(d) or d < 0.0 or state not in (RED, YELLOW):
            return []
        stop = _Constraint(max(d - self.cfg.stop_line_gap_m, 0.1), 0.0, 0.3, 0.4, "red light")
        if state == RED:
            return [stop] if d < 80.0 else []
        key = round(s_f + d)  # the stop line's place on the route
        first_s, go = self._amber.get(key, (snap.time_s, None))
        if go is None and d < 80.0:
            room = d - self.cfg.stop_line_gap_m
            need = v * v / (2.0 * max(room, 0.1))
            if need <= self.cfg.amber_decel_mps2:
                go = False
            else:  # cannot stop comfortably: go if the line is crossed before red
                left = self.cfg.amber_s - (snap.time_s - first_s) - 0.3
                go = d / max(v, 0.1) < left or need > 0.9 * self.params.max_brake_mps2
        self._amber[key] = (first_s, go)
        if go or go is None:
            return []
        stop.reason = "amber light"
        return [stop]

    # -- junctions --------------------------------------------------------------------------
    def _junction(self, snap: Snapshot, s_c: float, s_f: float, v: float,
                  others: list[_Constraint]) -> list[_Constraint]:
        rear = s_c - self.params.length_m / 2
        for jn in self.plan.junctions:
            if jn.s_out < rear:
                continue
            if jn.s_in - s_f > self.cfg.junction_look_m:
                return []
            return self._junction_rules(snap, jn, s_f, v, others)
        return []

    def _link_char(self, snap: Snapshot, link: _Link) -> str:
        state = snap.tls_states.get(link.tls_id, "") if link.tls_id else ""
        if link.link_index < 0 or link.link_index >= len(state):
            return link.static
        c = state[link.link_index]
        if c in "Gg":
            return c
        if c in "yYu":
            return "y"
        if c in "rRs":
            return STOP
        return link.static  # off: as if unsignalised

    def _junction_rules(self, snap: Snapshot, jn: _Junction, s_f: float, v: float,
                        others: list[_Constraint]) -> list[_Constraint]:
        before = s_f < jn.s_in + 0.5
        entry = _Constraint(max(jn.s_in - 0.5 - s_f, 0.1), 0.0, 0.3, 0.4, "")
        out = []
        # Gridlock: do not enter unless there is room for us beyond the junction.
        if before:
            for c in others:
                if not c.reason.startswith("vehicle"):
                    continue
                lead_rear = s_f + c.gap_m
                if lead_rear < jn.s_out + self.params.length_m + 1.5 and c.speed_mps < 2.0 \
                        and lead_rear > jn.s_in - 0.5:
                    out.append(_Constraint(entry.gap_m, 0.0, 0.3, 0.4, f"exit blocked ({c.reason})"))
                    break
        if jn.link is None or not jn.conflicts:
            return out
        ours = self._link_char(snap, jn.link)
        veh = snap.vehicles
        if not len(veh):
            return out
        centre = self.plan.point(0.5 * (jn.s_in + jn.s_out))
        near = np.hypot(veh.xy[:, 0] - centre[0], veh.xy[:, 1] - centre[1]) < 60.0
        by_link = {id(c.other): c for c in jn.conflicts}
        v_cross = float(self.plan.v_profile[self.plan.index(0.5 * (jn.s_in + jn.s_out))])
        stalled = self._stalled
        self._stalled = {}
        for i in np.nonzero(near)[0]:
            vid = veh.ids[i]
            standing = veh.speed_mps[i] < 0.3
            if standing and stalled.get(vid, 0.0) >= self.cfg.deadlock_patience_s:
                # It stood while the ego waited for it, each waiting for the other (or it
                # for something that never moves): the ego takes the turn while it stands.
                # It stays a constraint if it is in the path.
                self._stalled[vid] = stalled[vid]
                continue
            for link, pos in self._vehicle_links(veh, int(i), jn.node):
                c = by_link.get(id(link))
                if c is None:
                    continue
                if self._must_yield(snap, veh, int(i), link, pos, c, ours, s_f, v, v_cross):
                    if standing:
                        self._stalled[vid] = stalled.get(vid, 0.0) + (DT_S if v < 0.3 else 0.0)
                    # On green, wait inside the junction just before the conflict zone when
                    # there is room (a left turn waits for a gap, and clears at the phase end).
                    inside_wait = ours == MINOR and c.s_in - jn.s_in >= 3.0 and not out
                    if before and not inside_wait:
                        gap = entry.gap_m
                    else:
                        gap = c.s_in - 1.0 - s_f
                        # Not standing on a crossing, where pedestrians walk into the car
                        # when theirs turns green, if it can still stop before it.
                        off = self._off_crossings(c.s_in - 1.0, s_f) - s_f
                        if v * v / (2.0 * 6.0) <= off < gap:
                            gap = off
                    # Committed: too close to stop before the zone; clear it instead.
                    if gap < v * v / (2.0 * 6.0) or (not before and c.s_in - s_f < 0.5):
                        continue
                    out.append(_Constraint(max(gap, 0.1), 0.0, 0.3, 0.4, f"yield to {veh.ids[i]}"))
                    return out
        return out

    def _off_crossings(self, stop_s: float, s_f: float) -> float:
        """The stop point (route s of the front bumper) moved back, if need be, so that the
        car's body stands on no crossing it has not yet entered."""
        for a, b in reversed(self.plan.crossings):
            if s_f < a + 0.3 and a < stop_s and b > stop_s - self.params.length_m:
                stop_s = a - self.cfg.crossing_gap_m
        return stop_s

    def _vehicle_links(self, veh: Actors, i: int, node: str) -> list[tuple[_Link, float]]:
        """Links through the junction the vehicle may take, with its centre's position along
        each (negative: still on the incoming lane)."""
        x, y = veh.xy[i]
        yaw = veh.yaw_rad[i]
        found = []
        best = None
        for lane_id, dist, s, heading in self.facts.map.nearest_lanes(float(x), float(y), 2.5):
            if abs(_wrap(yaw - heading)) > math.radians(50):
                continue
            if best is None:
                best = dist
            elif dist > best + 1.0:
                break
            if lane_id in self.facts.by_via:
                found += [(lk, off + s) for lk, off in self.facts.by_via[lane_id] if lk.junction == node]
            else:
                rest = self.facts.lane_length.get(lane_id, 0.0) - s
                found += [(lk, -rest) for lk in self.facts.by_incoming.get(lane_id, ()) if lk.junction == node]
        return found

    def _must_yield(self, snap: Snapshot, veh: Actors, i: int, link: _Link, pos: float,
                    c: _Conflict, ours: str, s_f: float, v: float, v_cross: float) -> bool:
        cfg = self.cfg
        length = float(veh.size[i, 0])
        front = pos + length / 2
        if pos - length / 2 > c.a_out:
            return False  # it has left the zone
        speed = float(veh.speed_mps[i])
        inside = pos > -length / 2  # on the connector
        theirs = self._link_char(snap, link)
        to_line = -front  # its front bumper to its stop line
        can_stop = speed * speed / (2.0 * 4.0) < to_line - 0.5
        if not inside:
            if theirs == STOP and can_stop:
                return False
            if theirs == "y" and can_stop:
                return False
            if to_line > 40.0:
                return False
        # Time windows at the conflict zone.
        d_in = c.a_in - front
        d_out = c.a_out - pos + length / 2
        a_other = 1.5 if speed < 3.0 else 0.0
        t_in = _travel_time(d_in, speed, a_other, 8.0)
        t_out = _travel_time(d_out, speed, a_other, 8.0)
        e_in = _travel_time(c.s_in - s_f, v, 1.5, v_cross)
        e_out = _travel_time(c.s_out - s_f + self.params.length_m, v, 1.5, v_cross)
        if t_in > e_out + cfg.conflict_buffer_s or t_out < e_in - cfg.conflict_buffer_s:
            return False
        if inside:
            if speed < 0.3 and d_in > 1.0 and ours == PRIORITY:
                return False  # waiting inside for us
            return True
        if theirs == PRIORITY:
            if ours == PRIORITY:
                return t_in < e_in  # first come, first served (merges)
            return True
        if theirs == MINOR:
            return not can_stop or (ours != PRIORITY and t_in < e_in)
        return not can_stop  # amber or red it cannot stop for

    # -- lane changes -------------------------------------------------------------------------
    def _update_lane_changes(self, snap: Snapshot, s_c: float, s_f: float) -> list[_Constraint]:
        """Checks the gap before the route's lane change; without one, keeps to the entry
        lane and changes later from where the ego is, or stops before the road ends."""
        for i, change in enumerate(self.plan.lane_changes):
            st = self._lc.setdefault(i, _LaneChangeState())
            if st.done:
                continue
            if st.began is not None:
                if s_c > st.began + st.span_m + 5.0:
                    st.done = True
                    continue
                return []
            if s_c < change.s0 - 2.0:
                return []
            ok = self._gap_ok(snap, change)
            if not st.waiting:
                if ok:
                    st.done = True  # the route's own blend across
                    continue
                st.waiting = True
            if ok:
                st.waiting = False
                st.began = s_c
                st.span_m = max(12.0, 2.0 * snap.ego.speed_mps)
                return []
            if s_c > change.s_limit:
                st.done = True  # too late: the route will be re-joined as it may
                st.waiting = False
                continue
            return [_Constraint(max(change.s_limit - 3.0 - s_f, 0.1), 0.0, 0.5, 0.4,
                                "waiting for a lane change gap")]
        return []

    def _active_lane_change(self) -> tuple[_LaneChange, _LaneChangeState] | None:
        for i, change in enumerate(self.plan.lane_changes):
            st = self._lc.get(i)
            if st is not None and not st.done and (st.waiting or st.began is not None):
                return change, st
        return None

    def _gap_ok(self, snap: Snapshot, change: _LaneChange) -> bool:
        veh = snap.vehicles
        if not len(veh):
            return True
        ego = snap.ego
        target = self.facts.map.lane(change.target_lane)
        es, _, _ = target.project(ego.x_m, ego.y_m)
        cfg = self.cfg
        half = self.params.length_m / 2
        v = ego.speed_mps
        near = np.nonzero(np.hypot(veh.xy[:, 0] - ego.x_m, veh.xy[:, 1] - ego.y_m) < 60.0)[0]
        for i in near:
            vs, vlat, vh = target.project(float(veh.xy[i, 0]), float(veh.xy[i, 1]))
            if abs(vlat) > target.width_m / 2 + 0.5 or abs(_wrap(veh.yaw_rad[i] - vh)) > math.radians(40):
                continue
            if vs <= 0.0 and abs(vlat) > 0.3:  # beyond the lane's start: not on it
                continue
            other_half = float(veh.size[i, 0]) / 2
            u = float(veh.speed_mps[i])
            if vs >= es:  # ahead on the target lane
                gap = vs - other_half - (es + half)
                need = cfg.lane_change_min_gap_m + cfg.lane_change_gap_s * v + max(0.0, v - u) * 1.5
            else:
                gap = es - half - (vs + other_half)
                need = cfg.lane_change_min_gap_m + cfg.lane_change_gap_s * u + max(0.0, u - v) * 2.0
            if gap < need:
                return False
        return True


__all__ = ["Expert", "ExpertConfig"]
