"""Walkers sent across the crossings of the ego's turns (bid record --crossing-walkers), on real
SUMO: which crossings a route meets, a walker standing in the path of a turning expert, the
same walkers for the same seed, and the recordings that say so."""

import math

import numpy as np
import pytest

from bid_sim import metrics as m
from bid_sim import walkers as walkers_module
from bid_sim.cli import main
from bid_sim.episode import run_episode
from bid_sim.errors import BidError
from bid_sim.expert import Expert
from bid_sim.recording import read_facts
from bid_sim.routes import RouteSpec, plan_spec, road_graph
from bid_sim.walkers import CrossingWalkers, route_meetings

RIGHT_AT_J400 = RouteSpec("S0", 90.0, "-S2", 20.0)  # Town02: a right turn at the signalised J400
THROUGH_J400 = RouteSpec("S1", 290.0, "-S0", 30.0)  # straight over it


def test_a_route_meets_the_crossing_over_the_street_each_turn_leads_into(town02):
    graph = road_graph(town02.net_file)
    right = plan_spec(graph, RIGHT_AT_J400)
    [meeting] = route_meetings(graph, right)
    crossing = graph.net.getEdge(meeting.crossing)
    assert {e.getID() for e in crossing.getCrossingEdges()} == {"-S2", "S2"}
    assert crossing.getFromNode().getID() == "J400"
    assert {meeting.start, meeting.goal} == {"-S2", "S2"}
    junction = [p for p in right.pieces if p.junction == "J400"]
    assert junction[0].s0_m < meeting.s_m < junction[-1].s1_m + 3.0  # where the turn ends, past the junction
    assert route_meetings(graph, plan_spec(graph, THROUGH_J400)) == []  # straight on: none


class Watched(Expert):
    def __init__(self):
        super().__init__()
        self.seen = []

    def act(self, obs):
        control = super().act(obs)
        self.seen.append((obs.snapshot, self.reason))
        return control


def _drive(town02, seed, share=1.0):
    walkers = CrossingWalkers(share, seed)
    agent = Watched()
    result = run_episode(town02, RIGHT_AT_J400, "ClearNoon", "none", seed, agent,
                         on_start=walkers.start, on_step=walkers.step, max_steps=400)
    path = []
    for snap, reason in agent.seen:
        ids = snap.pedestrians.ids
        if "walker0" in ids:
            xy = snap.pedestrians.xy[ids.index("walker0")]
            path.append((snap.step, snap.ego.speed_mps, math.hypot(xy[0] - snap.ego.x_m, xy[1] - snap.ego.y_m),
                         *xy, reason))
    return result, walkers, path


def test_a_walker_standing_on_the_crossing_meets_the_turning_expert_at_speed(town02, monkeypatch):
    """Standing in the ego's lane (STAND_SHARE 1 here), sent once it is in the junction: the
    expert comes within 10 m of her still driving, stops short, and drives on once she walks on."""
    monkeypatch.setattr(walkers_module, "STAND_SHARE", 1.0)
    result, walkers, path = _drive(town02, 4)
    assert walkers.sent == ["walker0"] and result.status == "completed"
    assert not [i for i in result.infractions if i.kind in m.COLLISION_KINDS]
    braked = [p for p in path if p[5] == "pedestrian walker0"]
    assert braked, "the expert never braked for her"
    assert max(speed for _, speed, d, *_ in braked if d - 2.3 < 10.0) > 2.0  # at speed within 10 m of her
    assert min(d for _, _, d, *_ in path) > 2.3 + 1.0  # her distance from the ego's centre: stopped short
    stood = [p for p in path if p[1] < 0.05]
    assert len(stood) > 20  # it waited for her
    xy = np.array([p[3:5] for p in path])
    assert np.ptp(xy[:len(stood) // 2], axis=0).max() < 0.05  # she stood still at first
    assert np.ptp(xy, axis=0).max() > 1.0  # then walked on


def test_the_same_seed_sends_the_same_walkers(town02):
    one, two = _drive(town02, 7), _drive(town02, 7)
    assert one[1].sent == two[1].sent == ["walker0"]
    assert one[2] == two[2] and one[0].steps == two[0].steps
    none = _drive(town02, 7, share=0.0)
    assert none[1].sent == [] and none[2] == []


def test_a_share_out_of_range_is_refused():
    with pytest.raises(BidError, match=r"share of the route's turns, from 0 to 1; got 1\.5"):
        CrossingWalkers(1.5, 0)


def test_record_crossing_walkers_is_recorded_and_kept_to(tmp_path, capsys):
    def rec(out, *flags):
        return main(["record", "--town", "02", "--episodes", "1", "--densities", "none", "--weathers", "ClearNoon",
                     "--max-steps", "3", "--workers", "1", *flags, "--out", str(out)])

    assert rec(tmp_path / "walk", "--crossing-walkers", "1") == 0
    assert "walkers sent across the crossings of the routes' turns (--crossing-walkers)" in capsys.readouterr().out
    [f] = sorted((tmp_path / "walk").glob("*.mcap"))
    assert read_facts(f)["crossing_walkers"] == "1"
    assert rec(tmp_path / "walk") == 2
    assert "crossing_walkers '1' here, 'none' planned" in capsys.readouterr().err
    assert rec(tmp_path / "x", "--crossing-walkers", "2") == 2
    err = capsys.readouterr().err.strip()
    assert "--crossing-walkers is a share of the route's turns, from 0 (off) to 1; got 2.0" in err and "\n" not in err
