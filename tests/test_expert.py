"""The expert on real SUMO: red light, car following, a crossing pedestrian, a route in
traffic, determinism; and its pure helpers."""

import math
from types import SimpleNamespace

import libsumo as traci
import numpy as np
import pytest
import shapely

from bid_sim import metrics as m
from bid_sim.episode import run_episode
from bid_sim.expert import (
    Expert,
    ExpertConfig,
    _build_plan,
    _idm,
    _route_crossings,
    _TownFacts,
    _travel_time,
)
from bid_sim.routes import CHANGELANELEFT, RouteSpec, plan_spec, road_graph, route_by_index
from bid_sim.snapshot import RED, Actors
from bid_sim.town_map import load_town_map
from bid_sim.towns import resolve_town

LONG = RouteSpec("S1", 150.0, "S1", 300.0)  # Town02's long northern street, no junction
THROUGH_J400 = RouteSpec("S1", 290.0, "-S0", 30.0)  # straight over the signalised J400
RIGHT_AT_J400 = RouteSpec("S0", 90.0, "-S2", 20.0)  # a right turn there


class Watched(Expert):
    """The expert, keeping what it saw and did at every step (and an optional per-step hook
    that may change the world, as a test scenario does)."""

    def __init__(self, hook=None, **kw):
        super().__init__(**kw)
        self.hook = hook
        self.seen = []
        self.gaps = []  # gap_m at every step

    def act(self, obs):
        control = super().act(obs)
        self.seen.append((obs.snapshot, control, self.command, self.reason))
        self.gaps.append(self.gap_m)
        if self.hook is not None:
            self.hook(obs.snapshot.step, obs.snapshot)
        return control


def collisions(result):
    return [i for i in result.infractions if i.kind in m.COLLISION_KINDS]


def test_stops_at_the_stop_line_on_red_then_goes_on_green(town02):
    def all_red(world):
        n = len(traci.trafficlight.getRedYellowGreenState("J400"))
        traci.trafficlight.setRedYellowGreenState("J400", "r" * n)

    def green_later(step, snap):
        if step == 250:
            n = len(traci.trafficlight.getRedYellowGreenState("J400"))
            traci.trafficlight.setRedYellowGreenState("J400", "G" * n)

    agent = Watched(green_later)
    r = run_episode(town02, THROUGH_J400, "ClearNoon", "none", 0, agent, on_start=all_red)
    snap, control, _, reason = agent.seen[240]
    assert snap.next_light_state == RED and reason == "red light"
    assert snap.ego.speed_mps < 0.05 and control.accel < 0.0
    assert 0.0 < snap.next_light_dist_m < 2.5  # front bumper just before the line
    assert r.status == "completed" and r.metrics["TL"] == 0
    # stop_line_gap_m 2.5 (bid record --stop-line-gap): it stands 1.5 m farther back.
    farther = Watched(green_later, config=ExpertConfig(stop_line_gap_m=2.5))
    r = run_episode(town02, THROUGH_J400, "ClearNoon", "none", 0, farther, on_start=all_red)
    back, _, _, reason = farther.seen[240]
    assert reason == "red light" and back.ego.speed_mps < 0.05
    assert back.next_light_dist_m - snap.next_light_dist_m == pytest.approx(1.5, abs=0.3)
    assert r.status == "completed" and r.metrics["TL"] == 0


def test_follows_a_slower_car_without_collision(town02):
    route = plan_spec(road_graph(town02.net_file), LONG)

    def slow_car_ahead(world):
        world.step_idle(1)
        ahead = traci.vehicle.getLanePosition("ego") + 35.0
        world.place_vehicle("slow", route.pieces[0].lane_id, ahead, speed_mps=4.0)

    agent = Watched()
    r = run_episode(town02, LONG, "ClearNoon", "none", 0, agent, on_start=slow_car_ahead, max_steps=300)
    assert not collisions(r)
    gaps, speeds = [], []
    for snap, _, _, _ in agent.seen:
        if "slow" in snap.vehicles.ids:
            i = snap.vehicles.ids.index("slow")
            x, y = snap.vehicles.xy[i]
            gaps.append(math.hypot(x - snap.ego.x_m, y - snap.ego.y_m) - 4.6)
            speeds.append(snap.ego.speed_mps)
    assert min(gaps) > 2.5
    assert max(speeds) > 5.0  # it closed up first ...
    assert speeds[-1] == pytest.approx(4.0, abs=0.6)  # ... then follows at the lead's speed
    assert 4.0 < gaps[-1] < 15.0
    assert any(reason.startswith("vehicle slow") for _, _, _, reason in agent.seen[-50:])
    # gap_m: how far ahead what limits the speed is (the lead's rear, from the front bumper).
    following = [(gap, snap) for (snap, _, _, reason), gap in zip(agent.seen, agent.gaps, strict=True)
                 if reason == "vehicle slow"]
    assert following
    off = []
    for gap, snap in following:
        x, y = snap.vehicles.xy[snap.vehicles.ids.index("slow")]
        off.append(gap - (math.hypot(x - snap.ego.x_m, y - snap.ego.y_m) - 4.6))
    assert np.median(np.abs(off)) < 0.01 and max(np.abs(off)) < 1.5  # along the route, not the chord, on a bend
    assert all(gap == math.inf for (_, _, _, reason), gap in zip(agent.seen, agent.gaps, strict=True)
               if reason == "speed")


def test_waits_for_a_pedestrian_in_its_path(town02):
    route = plan_spec(road_graph(town02.net_file), LONG)
    x, y, _ = route.point_at(40.0)

    def place(world):
        world.step_idle(1)
        world.place_pedestrian("walker", "S1", traci.vehicle.getLanePosition("ego") + 40.0)

    def stand_in_the_lane_then_leave(step, snap):
        if step < 150:  # held on the lane centre, 40 m ahead of the start
            traci.person.moveToXY("walker", "S1", x, y, -1073741824.0, 2)
        elif step == 150:
            traci.person.remove("walker")

    agent = Watched(stand_in_the_lane_then_leave)
    r = run_episode(town02, LONG, "ClearNoon", "none", 0, agent, on_start=place, max_steps=400)
    assert not collisions(r)
    snap, _, _, reason = agent.seen[145]
    assert reason == "pedestrian walker" and snap.ego.speed_mps < 0.05
    i = snap.pedestrians.ids.index("walker")
    gap = math.hypot(*(snap.pedestrians.xy[i] - (snap.ego.x_m, snap.ego.y_m))) - 2.3
    assert 1.5 < gap < 6.0  # stopped a few metres short of it
    assert r.status == "completed"  # and drove on once it had gone


def test_completes_a_short_route_in_traffic(town02):
    agent = Watched()
    r = run_episode(town02, 3, "ClearNoon", "normal", 0, agent)
    assert r.status == "completed"
    assert not collisions(r) and r.metrics["TL"] == 0
    commands = {c for _, _, c, _ in agent.seen}
    assert commands <= set(range(1, 7)) and 4 in commands and len(commands) >= 2
    assert all(-1.0 <= c.steer <= 1.0 and -1.0 <= c.accel <= 1.0 for _, c, _, _ in agent.seen)


def test_same_seed_same_controls(town02):
    def controls(seed):
        agent = Watched()
        run_episode(town02, 5, "ClearNoon", "crowded", seed, agent, max_steps=250)
        return [(c.steer, c.accel) for _, c, _, _ in agent.seen]

    a, b = controls(2), controls(2)
    assert a == b and len(a) == 250


def test_idm_and_travel_time():
    cfg = ExpertConfig()
    assert _idm(0.0, 10.0, 1e9, 0.0, cfg, 3.0, 1.3) == pytest.approx(cfg.accel_mps2)
    assert _idm(10.0, 10.0, 1e9, 0.0, cfg, 3.0, 1.3) == pytest.approx(0.0, abs=1e-6)
    assert _idm(10.0, 10.0, 10.0, 0.0, cfg, 3.0, 1.3) < -cfg.comfort_decel_mps2  # closing fast
    assert _idm(0.0, 10.0, 0.01, 0.0, cfg, 3.0, 1.3) < -100  # touching
    assert _travel_time(10.0, 10.0, 0.0, 10.0) == pytest.approx(1.0)
    assert _travel_time(2.0, 0.0, 1.0, 10.0) == pytest.approx(2.0)  # 1/2 a t² = 2
    assert _travel_time(-1.0, 3.0, 1.0, 10.0) == 0.0


def test_act_before_reset_is_a_clear_error():
    from bid_sim.errors import BidError

    with pytest.raises(BidError, match="reset"):
        Expert().act(None)


def test_lane_change_waits_for_a_gap_on_the_target_lane():
    from bid_sim.towns import resolve_town

    town05 = resolve_town("05")
    spec = RouteSpec("-S15", 2.5, "-S8", 30.0)  # right turn onto S14, then its left lane
    route = plan_spec(road_graph(town05.net_file), spec)
    change = next(p for p in route.pieces if p.command == CHANGELANELEFT)
    x, y, _ = route.point_at(change.s0_m + 10.0)

    def park_on_the_target_lane(world):
        from bid_sim.town_map import load_town_map

        pos, _, _ = load_town_map(town05).lane(change.lane_id).project(x, y)
        world.place_vehicle("parked", change.lane_id, pos + 2.3)  # front bumper position
        traci.vehicle.setLaneChangeMode("parked", 0)  # stay on the target lane

    class Tracked(Watched):
        def act(self, obs):
            control = super().act(obs)
            self.states.append(self.lane_change)
            return control

    agent = Tracked()
    agent.states = []
    r = run_episode(town05, spec, "ClearNoon", "none", 0, agent, on_start=park_on_the_target_lane)
    assert not collisions(r) and r.status == "completed"
    assert "waiting" in agent.states and "changing" in agent.states
    junction = next(p for p in route.pieces if p.junction and p.s0_m > change.s0_m)
    lanes = [snap.ego.lane_id for snap, _, _, _ in agent.seen
             if change.s1_m + 3.0 < snap.ego.route_s_m < junction.s0_m - 2.0 and snap.ego.lane_id]
    assert lanes and set(lanes) <= {change.lane_id}  # on the target lane before the junction


def test_a_replanned_route_is_understood_from_its_polyline(town02, route02):
    """After a re-plan the expert only sees the new polyline; it re-plans the same route to
    know its lanes, junctions and signals."""
    from bid_sim.agents import EpisodeInfo
    from bid_sim.ego import EgoParams
    from bid_sim.routes import plan, route_by_index

    expert = Expert()
    expert.reset(EpisodeInfo("Town02", 0, "ClearNoon", "none", 0, route02, EgoParams()))
    graph = road_graph(town02.net_file)
    spec = route_by_index(town02, 0)
    piece = route02.pieces[3]  # a road piece after the first junction
    fresh = plan(graph, piece.edge, 20.0, spec.goal_edge, spec.goal_pos_m, start_lane=1)
    expert._replan(fresh.polyline)
    expected = []
    for p in fresh.pieces:
        if p.junction and (not expected or expected[-1] != p.junction):
            expected.append(p.junction)
    assert [j.node for j in expert.plan.junctions] == expected and expected
    assert all(j.link is not None and j.conflicts for j in expert.plan.junctions)
    assert expert.plan.length_m == pytest.approx(fresh.length_m, abs=0.5)


def test_a_walking_area_over_a_driving_lane_is_not_kerb():
    """Town05's walking areas reach over its ring road: a pedestrian there walks into the
    expert's lane (route 8, normal, seed 0 hit one at 13.9 m/s) and must not count as on the kerb."""
    town = resolve_town("05")
    facts = _TownFacts(load_town_map(town), road_graph(town.net_file))
    ped = np.array([[-235.5, -78.73], [-234.2, -78.73]])  # where it walked, on lane S22_3's side
    walk = shapely.union_all([shapely.Polygon(r) for r in facts.map.sidewalks])
    assert shapely.contains_xy(walk, ped[:, 0], ped[:, 1]).all()  # inside a walking area ...
    assert not shapely.contains_xy(facts.kerb, ped[:, 0], ped[:, 1]).any()  # ... yet in the road
    centres = np.concatenate([lane.centre for lane in facts.map.lanes if not lane.internal])
    assert not shapely.contains_xy(facts.kerb, centres[:, 0], centres[:, 1]).any()


def _planned(town, spec) -> Expert:
    """An expert holding the plan of a route, as reset() makes it, without a simulation."""
    expert = Expert()
    expert.facts = _TownFacts(load_town_map(town), road_graph(town.net_file))
    route = plan_spec(road_graph(town.net_file), spec)
    expert.plan = _build_plan(route.polyline, route, expert.facts, expert.cfg, town.speed_limit_mps)
    return expert


def test_a_route_past_the_same_crossing_twice_has_one_interval_per_pass(town02):
    """Town02's route 1 goes round a block and over one crossing at about 20 m and again at
    about 226 m: one interval for both made the expert take the whole way between for "on a
    crossing", and drive on towards a pedestrian stepping onto it (normal, seed 0)."""
    expert = _planned(town02, route_by_index(town02, 1))
    crossings = _route_crossings(expert.plan.polyline, expert.facts)
    assert all(0.5 < b - a < 8.0 for a, b in crossings)
    assert any(a < 30.0 for a, _ in crossings) and any(220.0 < a < 240.0 for a, _ in crossings)
    assert list(crossings) == sorted(crossings)


def _walker_beside(expert):
    """The ego standing 1 m before the first crossing it reaches at J400, and a
    pedestrian on the sidewalk to its right, beside its front, walking its way at 1.5 m/s
    (at 1.2 m/s it would reach the 2 m crossings' exit crossing after the car has cleared it)."""
    plan = expert.plan
    c_in = plan.crossings[0][0]
    s_f = c_in - 1.0
    s_c = s_f - expert.params.length_m / 2
    x, y = plan.point(s_c)
    h = float(plan.heading[plan.index(s_f)])
    px, py = plan.point(s_f)
    ped = Actors(("walker",), np.array([[px + 3.6 * math.sin(h), py - 3.6 * math.cos(h)]]),
                 np.array([h]), np.array([1.5]), np.array([[0.5, 0.6, 1.75]]), np.array([0]))
    snap = SimpleNamespace(pedestrians=ped, ego=SimpleNamespace(x_m=x, y_m=y, speed_mps=0.0))
    constraints, _ = expert._pedestrians(snap, s_c, s_f)
    return [c.reason for c in constraints]


def test_a_pedestrian_walking_beside_holds_a_right_turn_not_a_straight_drive(town02):
    """Walking straight on, a pedestrian beside the car steps onto the crossing a right turn
    drives over, not onto those the car drives straight over (they run along its way)."""
    assert _walker_beside(_planned(town02, RIGHT_AT_J400)) == ["pedestrian walker beside"]
    assert _walker_beside(_planned(town02, THROUGH_J400)) == []


def test_a_stop_point_is_moved_off_a_crossing_not_yet_entered(town02):
    expert = _planned(town02, THROUGH_J400)
    a, b = expert.plan.crossings[0]
    length, back = expert.params.length_m, a - expert.cfg.crossing_gap_m
    assert expert._off_crossings(b + 1.0, s_f=a - 10.0) == pytest.approx(back)  # body on it
    assert expert._off_crossings(a + 0.5, s_f=a - 10.0) == pytest.approx(back)  # front on it
    assert expert._off_crossings(b + length + 0.5, s_f=a - 10.0) == b + length + 0.5  # beyond
    assert expert._off_crossings(a - 3.0, s_f=a - 10.0) == a - 3.0  # before
    assert expert._off_crossings(b + 1.0, s_f=a + 1.0) == b + 1.0  # on it already


def test_a_lane_change_right_after_a_junction_starts_from_the_lane_the_junction_leads_onto():
    """Town05's route 0 changes lanes just past junction J2296: the entry lane was the
    junction's own (internal) lane, which the car had already left, so it kept to a corridor
    behind it and drove into a car standing on the lane it was really on (normal, seed 2)."""
    town = resolve_town("05")
    expert = _planned(town, route_by_index(town, 0))
    changes = expert.plan.lane_changes
    assert changes
    for change in changes:
        assert not change.entry_lane.startswith(":")
        assert change.entry_lane.rsplit("_", 1)[0] == change.target_lane.rsplit("_", 1)[0]
        assert change.entry_lane != change.target_lane
