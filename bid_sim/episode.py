"""One episode: one route in one town under one weather, density and seed, with one agent."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from bid_sim import __version__
from bid_sim import metrics as m
from bid_sim.agents import Agent, EpisodeInfo, Observation
from bid_sim.ego import EgoParams, EgoState, step
from bid_sim.errors import BidError
from bid_sim.infractions import BLOCKED_SPEED_MPS, DEVIATION_M, Monitor
from bid_sim.metrics import STANDING_AHEAD_M, STANDING_LIGHT_M, STANDING_REASONS, Infraction
from bid_sim.routes import (
    COMMAND_NAMES,
    Route,
    RouteSpec,
    plan,
    plan_spec,
    road_graph,
    route_by_index,
)
from bid_sim.snapshot import OFF, RED, YELLOW, Actors, EgoView, Snapshot, light_code
from bid_sim.town_map import load_town_map
from bid_sim.towns import Town, resolve_town
from bid_sim.weather import check_weather
from bid_sim.world import DT_S, World

log = logging.getLogger(__name__)

TIMEOUT_SPEED_MPS = 5.0 / 3.6
TIMEOUT_EXTRA_S = 20.0
GOAL_RADIUS_M = 10.0
PROGRESS_RADIUS_M = 10.0
REPLAN_LATERAL_M = 6.0  # farther than this from the route on another lane: re-plan


@dataclass
class EpisodeResult:
    """Everything an episode produced: ids, status, distances, infractions and metrics."""

    town: str
    route_index: int
    weather: str
    density: str
    seed: int
    agent: str
    status: str  # completed | blocked | route_deviation | timeout | gave_up (bid_sim.perturb.Dagger)
    steps: int
    time_s: float
    route_length_m: float
    completed_m: float
    driven_m: float
    outside_lane_m: float
    replans: int
    infractions: list[Infraction] = field(default_factory=list)
    # Seconds standing (slower than BLOCKED_SPEED_MPS) by what stood there: at a red or amber
    # light, behind a vehicle, before a pedestrian, or with nothing near (standing_reason).
    standing_s: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    version: str = __version__

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["infractions"] = [i.to_dict() for i in self.infractions]
        return d

    def row(self) -> dict[str, Any]:
        """A flat row for metrics.aggregate."""
        return {"town": self.town, "route": self.route_index, "weather": self.weather,
                "density": self.density, "seed": self.seed, **self.metrics}


class Progress:
    """Route progress with re-planning: completed distance is measured on the first route."""

    def __init__(self, route: Route):
        self.route = route
        self.first_length_m = route.length_m
        self.offset_m = 0.0  # completed distance at the current route's start
        self.s_m = 0.0
        self.lateral_m = 0.0
        self.heading_rad = 0.0
        self.completed_m = 0.0

    def update(self, x: float, y: float) -> float:
        """Projects the ego onto the route; returns the progress gained this step (m)."""
        s, lat, heading = self.route.project(x, y, self.s_m)
        # Progress counts only near the route (the leaderboard's 10 m waypoint threshold).
        gained = max(0.0, s - self.s_m) if abs(lat) < PROGRESS_RADIUS_M else 0.0
        self.s_m += gained
        self.lateral_m, self.heading_rad = lat, heading
        self.completed_m = min(self.first_length_m, max(self.completed_m, self.offset_m + self.s_m))
        return gained

    def replace(self, route: Route) -> None:
        self.offset_m = self.first_length_m - route.length_m
        self.route = route
        self.s_m = 0.0


def run_episode(
    town: Town | str,
    route: int | RouteSpec,
    weather: str,
    density: str,
    seed: int,
    agent: Agent,
    recorder=None,
    renderer=None,
    replan: bool = False,
    max_steps: int | None = None,
    params: EgoParams = EgoParams(),
    on_start=None,
    on_step=None,
) -> EpisodeResult:
    """Runs one episode to its end and scores it (DESIGN.md section 7).

    replan: on leaving the route, plan a new one from where the ego is and correct the
    command (evaluation, as in the paper); otherwise the episode ends at 30 m off route.
    on_start: called with the World once traffic is in, to set up a scenario; on_step: with the
    World and each step's Snapshot before the agent acts (bid_sim.walkers.CrossingWalkers).
    """
    town = town if isinstance(town, Town) else resolve_town(town)
    check_weather(weather)
    town.density(density)
    if seed < 0:
        raise BidError(f"seed must be >= 0, got {seed}")
    route_index = route if isinstance(route, int) else -1
    spec = route_by_index(town, route) if isinstance(route, int) else route
    graph = road_graph(town.net_file)
    planned = plan_spec(graph, spec)
    town_map = load_town_map(town)
    lights = _route_lights(planned, graph)
    monitor = Monitor(town_map, graph, params)
    progress = Progress(planned)
    timeout_s = planned.length_m / TIMEOUT_SPEED_MPS + TIMEOUT_EXTRA_S
    info = EpisodeInfo(town.name, route_index, weather, density, seed, planned, params)
    agent_name = type(agent).__name__
    status = "timeout"
    driven = 0.0
    replans = 0
    standing = dict.fromkeys(STANDING_REASONS, 0.0)
    world = World(town, density, seed, planned, params, town_map)
    try:
        if on_start is not None:
            on_start(world)
        ego = world.ego
        snap = world.snapshot(_view(ego, progress, params, town_map))
        snap = _with_light(snap, progress, lights, params)
        agent.reset(info)
        prev_frame = None
        noted = 0  # infractions passed on to the recorder's note(), if it has one
        while True:
            if on_step is not None:
                on_step(world, snap)
            frame = renderer.render(snap) if renderer is not None else None
            obs = Observation(frame, prev_frame if prev_frame is not None else frame,
                              snap.ego.command, ego.speed_mps, snap)
            control = agent.act(obs)
            if getattr(agent, "gave_up", False):  # a data-collecting agent ends a dead end
                status = "gave_up"
                break
            if recorder is not None:
                # A wrapper that perturbs what the car executes (bid_sim.perturb) gives the label.
                label = getattr(agent, "label", None)
                recorder.write(snap, frame, control if label is None else label)
                if hasattr(recorder, "note"):
                    for inf in monitor.infractions[noted:]:
                        recorder.note(inf)
                    noted = len(monitor.infractions)
            prev_frame = frame
            new = step(ego, control, params, DT_S)
            world.advance(new)
            driven += math.hypot(new.x_m - ego.x_m, new.y_m - ego.y_m)
            gained = progress.update(new.x_m, new.y_m)
            if replan and _left_route(progress, monitor, new):
                try:
                    edge, lane, pos = graph.locate(new.x_m, new.y_m, new.yaw_rad)
                    fresh = plan(graph, edge, pos, spec.goal_edge, spec.goal_pos_m, start_lane=lane)
                except BidError:
                    fresh = None
                if fresh is not None:
                    replans += 1
                    monitor.infractions.append(
                        Infraction(m.ROUTE_DEVIATION, round(world.step_count * DT_S, 2),
                                   round(new.x_m, 2), round(new.y_m, 2), detail="replanned"))
                    progress.replace(fresh)
                    progress.update(new.x_m, new.y_m)
                    world.set_route(fresh)
                    lights = _route_lights(fresh, graph)
            snap = world.snapshot(_view(new, progress, params, town_map))
            snap = _with_light(snap, progress, lights, params)
            monitor.check(snap, ego, new, progress.route, progress.s_m, gained)
            if new.speed_mps < BLOCKED_SPEED_MPS:
                standing[standing_reason(snap)] += DT_S
            ego = new
            t = world.step_count * DT_S
            goal = progress.route.polyline[-1]
            if (progress.completed_m > 0.99 * progress.first_length_m
                    and math.hypot(ego.x_m - goal[0], ego.y_m - goal[1]) < GOAL_RADIUS_M):
                status = "completed"
                break
            if abs(progress.lateral_m) > DEVIATION_M:
                status = "route_deviation"
                monitor.infractions.append(Infraction(m.ROUTE_DEVIATION, round(t, 2), round(ego.x_m, 2), round(ego.y_m, 2)))
                break
            if monitor.blocked:
                status = "blocked"
                monitor.infractions.append(Infraction(m.BLOCKED, round(t, 2), round(ego.x_m, 2), round(ego.y_m, 2)))
                break
            if t >= timeout_s or (max_steps is not None and world.step_count >= max_steps):
                status = "timeout"
                monitor.infractions.append(Infraction(m.TIMEOUT, round(t, 2), round(ego.x_m, 2), round(ego.y_m, 2)))
                break
    finally:
        world.close()
    infractions = monitor.infractions
    metrics = m.episode_metrics(
        route_length_m=progress.first_length_m,
        completed_m=progress.completed_m,
        completed=status == "completed",
        infractions=infractions,
        outside_lane_m=min(monitor.outside_lane_m, progress.completed_m),
    )
    return EpisodeResult(
        town=town.name, route_index=route_index, weather=weather, density=density, seed=seed,
        agent=agent_name, status=status, steps=world.step_count, time_s=round(world.step_count * DT_S, 2),
        route_length_m=round(progress.first_length_m, 2), completed_m=round(progress.completed_m, 2),
        driven_m=round(driven, 2), outside_lane_m=round(monitor.outside_lane_m, 2), replans=replans,
        infractions=infractions, metrics=metrics, standing_s={k: round(v, 1) for k, v in standing.items()},
    )


def standing_reason(snap: Snapshot) -> str:
    """What the ego stands for, from the privileged state (one of STANDING_REASONS): a red or
    amber light on its route within STANDING_LIGHT_M, else a vehicle, else a pedestrian
    within STANDING_AHEAD_M straight ahead of its front bumper and within its width (plus the
    other's half width), else nothing. A car or person on the turn it is about to take, or
    one crossing beside it, counts as nothing: this says where time goes, not who was right."""
    if snap.next_light_state in (RED, YELLOW) and snap.next_light_dist_m <= STANDING_LIGHT_M:
        return "light"
    if _ahead(snap.ego, snap.vehicles):
        return "vehicle"
    if _ahead(snap.ego, snap.pedestrians):
        return "pedestrian"
    return "nothing"


def _ahead(ego: EgoView, actors: Actors) -> bool:
    if not len(actors):
        return False
    c, s = math.cos(ego.yaw_rad), math.sin(ego.yaw_rad)
    dx, dy = actors.xy[:, 0] - ego.x_m, actors.xy[:, 1] - ego.y_m
    forward = dx * c + dy * s - ego.length_m / 2 - actors.size[:, 0] / 2
    lateral = abs(-dx * s + dy * c) - actors.size[:, 1] / 2
    return bool(((forward > -ego.length_m / 2) & (forward <= STANDING_AHEAD_M) & (lateral < ego.width_m / 2)).any())


def _left_route(progress: Progress, monitor: Monitor, ego: EgoState) -> bool:
    return abs(progress.lateral_m) > REPLAN_LATERAL_M and monitor.in_lane(ego)


def _view(ego: EgoState, progress: Progress, params: EgoParams, town_map=None) -> EgoView:
    route = progress.route
    dyaw = ego.yaw_rad - progress.heading_rad
    # Lane matching: the planned route's lane first, then any lane running the ego's way.
    lane_id = route.piece_at(progress.s_m).lane_id if abs(progress.lateral_m) < 2.5 else ""
    if not lane_id and town_map is not None:
        for lid, _dist, _, heading in town_map.nearest_lanes(ego.x_m, ego.y_m, 3.0):
            if math.cos(ego.yaw_rad - heading) > 0.0:
                lane_id = lid
                break
    return EgoView(
        x_m=ego.x_m, y_m=ego.y_m, yaw_rad=ego.yaw_rad, speed_mps=ego.speed_mps,
        length_m=params.length_m, width_m=params.width_m, height_m=params.height_m,
        lane_id=lane_id,
        lateral_m=progress.lateral_m,
        heading_error_rad=math.atan2(math.sin(dyaw), math.cos(dyaw)),
        route_s_m=progress.s_m, route_length_m=route.length_m,
        command=route.command_at(progress.s_m),
    )


def _route_lights(route: Route, graph) -> list[tuple[float, str, int]]:
    """(route s of the stop line, signal id, link index) for each signalised junction ahead."""
    out = []
    pieces = route.pieces
    links = graph.tls_links
    for i in range(1, len(pieces)):
        key = (pieces[i - 1].lane_id, pieces[i].lane_id)
        if key in links:
            out.append((pieces[i].s0_m, *links[key]))
    return out


def _with_light(snap: Snapshot, progress: Progress, lights, params: EgoParams) -> Snapshot:
    front_s = progress.s_m + params.length_m / 2
    for s_stop, tls, idx in lights:
        if s_stop >= front_s - 1.0:
            state = snap.tls_states.get(tls, "")
            code = light_code(state[idx]) if idx < len(state) else OFF
            return replace(snap, next_light_state=code, next_light_dist_m=s_stop - front_s)
    return snap


def describe(result: EpisodeResult) -> str:
    """A short human summary of an episode."""
    mm = result.metrics
    kinds = {}
    for inf in result.infractions:
        kinds[inf.kind] = kinds.get(inf.kind, 0) + 1
    inf_text = ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"
    return (
        f"{result.town} route {result.route_index} {result.weather} {result.density} seed {result.seed} "
        f"agent {result.agent}: {result.status} after {result.time_s:.1f} s, "
        f"RC {mm['RC']:.1f} IP {mm['IP']:.3f} DS {mm['DS']:.1f} SR {mm['SR']:.0f} SSR {mm['SSR']:.0f}; "
        f"driven {result.driven_m:.0f} m of {result.route_length_m:.0f} m; infractions: {inf_text}"
    )


__all__ = ["COMMAND_NAMES", "EpisodeResult", "describe", "run_episode", "standing_reason"]
