"""Each infraction, caused on purpose on real SUMO, and the monitor's geometry."""

import math

import numpy as np
import pytest

from bid_sim import metrics as m
from bid_sim.agents import LaneFollower, Scripted, pursuit_steer, speed_accel
from bid_sim.ego import Control, EgoParams, EgoState, box_corners
from bid_sim.episode import run_episode
from bid_sim.infractions import boxes_overlap, contact_side
from bid_sim.routes import RouteSpec, plan_spec, road_graph
from bid_sim.snapshot import RED, YELLOW

LONG = RouteSpec("S1", 150.0, "S1", 300.0)  # Town02's long northern street, no junction


def kinds(result):
    return [i.kind for i in result.infractions]


def test_boxes_overlap():
    a = box_corners(0, 0, 0, 4.6, 1.9)
    assert boxes_overlap(a, box_corners(4.0, 0.5, 0.3, 4.6, 1.9))
    assert not boxes_overlap(a, box_corners(4.8, 0, 0, 4.6, 1.9))
    assert not boxes_overlap(a, box_corners(0, 2.0, 0, 4.6, 1.9))
    assert boxes_overlap(a, box_corners(0, 1.5, math.pi / 2, 0.5, 0.6)) is False
    assert boxes_overlap(a, box_corners(0, 1.0, 0, 0.5, 0.6))


def test_contact_side_in_the_ego_frame():
    ego, params = EgoState(10.0, 5.0, math.pi / 2), EgoParams()  # heading +y: its left is -x
    assert contact_side(ego, params, 10.0, 8.0) == "front"
    assert contact_side(ego, params, 10.3, 2.0) == "rear"
    assert contact_side(ego, params, 9.0, 5.5) == "left"
    assert contact_side(ego, params, 11.0, 4.5) == "right"
    # A corner point: nearer the side face, scaled by the box's half-length and half-width.
    assert contact_side(ego, params, 10.0 + params.width_m, 5.0 + params.length_m * 0.9) == "right"


def test_vehicle_collision_counts_once_per_actor(town02):
    route = plan_spec(road_graph(town02.net_file), LONG)

    def park_ahead(world):
        import libsumo as traci

        world.step_idle(1)
        ahead = traci.vehicle.getLanePosition("ego") + 30.0
        world.place_vehicle("parked", route.pieces[0].lane_id, ahead)

    r = run_episode(town02, LONG, "ClearNoon", "none", 0, LaneFollower(6.0), on_start=park_ahead, max_steps=250)
    hits = [i for i in r.infractions if i.kind == m.COLLISION_VEHICLE]
    assert len(hits) == 1 and hits[0].actor == "parked" and hits[0].detail.startswith("front, ego ")
    # Where the other stood and how fast it went: the parked car, 30 m on along the lane.
    x, y = (float(v) for v in hits[0].detail.split("it at (")[1].split(")")[0].split(", "))
    assert math.hypot(x - hits[0].x_m, y - hits[0].y_m) < 5.0 and hits[0].detail.endswith("), 0.0 m/s")
    assert r.metrics["CV"] == 1 and r.metrics["SR"] == 0 and r.metrics["IP"] == pytest.approx(0.6)


def test_pedestrian_collision(town02):
    def stand_on_sidewalk(world):
        import libsumo as traci

        world.step_idle(1)
        world.place_pedestrian("walker", "S1", traci.vehicle.getLanePosition("ego") + 25.0)

    def drive_at_walker(step, obs):
        e, peds = obs.snapshot.ego, obs.snapshot.pedestrians
        if "walker" not in peds.ids:
            return Control(0.0, 0.0)
        tx, ty = peds.xy[peds.ids.index("walker")]
        return Control(pursuit_steer(e.x_m, e.y_m, e.yaw_rad, tx, ty, EgoParams()), speed_accel(e.speed_mps, 4.0))

    r = run_episode(town02, LONG, "ClearNoon", "none", 0, Scripted(drive_at_walker),
                    on_start=stand_on_sidewalk, max_steps=120)
    hits = [i for i in r.infractions if i.kind == m.COLLISION_PEDESTRIAN]
    assert len(hits) == 1 and hits[0].actor == "walker"
    assert r.metrics["CP"] == 1 and r.metrics["SR"] == 0


def test_layout_collision_and_route_deviation_when_driving_into_the_block(town02):
    def swerve(step, obs):
        return Control(1.0 if step < 12 else 0.0, speed_accel(obs.snapshot.ego.speed_mps, 6.0))

    r = run_episode(town02, LONG, "ClearNoon", "none", 0, Scripted(swerve), max_steps=400)
    assert r.status == "route_deviation"
    assert r.metrics["CL"] >= 1 and r.metrics["RD"] == 1 and r.metrics["OL"] >= 1
    assert r.metrics["SR"] == 0 and r.metrics["RC"] < 20


class LightAware(LaneFollower):
    """Stops for red and amber at the stop line (what the expert will do)."""

    def act(self, obs):
        c = super().act(obs)
        s = obs.snapshot
        if s.next_light_state in (RED, YELLOW) and 0.0 < s.next_light_dist_m < 12.0:
            return Control(c.steer, -1.0)
        return c


@pytest.mark.parametrize("agent, runs_red", [(LaneFollower(6.0), True), (LightAware(6.0), False)])
def test_red_light_runs(town02, agent, runs_red):
    r = run_episode(town02, 0, "ClearNoon", "none", 0, agent, max_steps=2500)
    reds = [i for i in r.infractions if i.kind == m.RED_LIGHT]
    assert r.status == "completed"
    assert bool(reds) == runs_red
    assert r.metrics["TL"] == len(reds)
    if runs_red:
        assert all(i.actor.startswith("J") for i in reds)
        assert r.metrics["SR"] == 100 and r.metrics["SSR"] == 0


def test_outside_lane_in_the_opposite_lane(town02):
    class Wrong(LaneFollower):
        def act(self, obs):
            e = obs.snapshot.ego
            line = obs.snapshot.route_polyline
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
            s = e.route_s_m + 8.0
            x, y = np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])
            i = min(np.searchsorted(cum, s), len(line) - 1)
            h = math.atan2(*(line[i] - line[i - 1])[::-1])
            side = 4.0 if obs.snapshot.step > 30 else 0.0  # move over into the oncoming lane
            tx, ty = x - side * math.sin(h), y + side * math.cos(h)
            return Control(pursuit_steer(e.x_m, e.y_m, e.yaw_rad, tx, ty, self.params), speed_accel(e.speed_mps, 6.0))

    r = run_episode(town02, LONG, "ClearNoon", "none", 0, Wrong(), max_steps=400)
    assert r.status == "completed"
    assert r.metrics["OL"] >= 1 and r.outside_lane_m > 50.0
    share = min(r.outside_lane_m, r.completed_m) / r.completed_m
    assert r.metrics["IP"] == pytest.approx(1.0 - share, rel=1e-3)
    assert r.metrics["SR"] == 100 and r.metrics["SSR"] == 0


def test_blocked_after_90_s_standing(town02):
    r = run_episode(town02, LONG, "ClearNoon", "none", 0, Scripted(lambda i, o: Control(0.0, -1.0)))
    assert r.status == "blocked" and r.time_s == pytest.approx(90.0, abs=0.2)
    assert r.metrics["ABD"] == 1 and r.metrics["RC"] == 0
    # every step it stood is counted, and with no traffic and no light near, for nothing
    assert set(r.standing_s) == {"light", "vehicle", "pedestrian", "nothing"}
    assert r.standing_s["nothing"] == pytest.approx(r.time_s, abs=0.2) and sum(r.standing_s.values()) <= r.time_s


def test_timeout_when_too_slow(town02):
    spec = RouteSpec("S1", 150.0, "S1", 230.0)
    creep = Scripted(lambda i, o: Control(0.0, speed_accel(o.snapshot.ego.speed_mps, 0.3)))
    r = run_episode(town02, spec, "ClearNoon", "none", 0, creep)
    assert r.status == "timeout"
    assert r.time_s == pytest.approx(r.route_length_m / (5 / 3.6) + 20.0, abs=0.2)
    assert r.metrics["TO"] == 1 and 0 < r.metrics["RC"] < 100


def test_replan_after_a_wrong_turn_corrects_the_route(town02):
    graph = road_graph(town02.net_file)
    planned = RouteSpec("S2", 16.6, "S1", 132.7)  # route 0
    first = plan_spec(graph, planned)
    j = next(p for p in first.pieces if p.junction)
    # Another way out of the same junction: the agent drives its own, wrong, route.
    other_edges = [e for e in graph.net.getEdge(first.edges[0]).getOutgoing() if e.getID() != first.edges[1]]
    wrong = plan_spec(graph, RouteSpec("S2", 16.6, other_edges[0].getID(), 60.0))

    class OwnWay(LaneFollower):
        def act(self, obs):
            e = obs.snapshot.ego
            s, _, _ = wrong.project(e.x_m, e.y_m, self.__dict__.get("s", 0.0))
            self.s = s
            tx, ty, _ = wrong.point_at(s + 6.0)
            return Control(pursuit_steer(e.x_m, e.y_m, e.yaw_rad, tx, ty, self.params), speed_accel(e.speed_mps, 5.0))

    r = run_episode(town02, planned, "ClearNoon", "none", 0, OwnWay(), replan=True, max_steps=250)
    assert r.replans >= 1 and r.status != "route_deviation"
    assert any(i.kind == m.ROUTE_DEVIATION and i.detail == "replanned" for i in r.infractions)
    assert j.command != 4
