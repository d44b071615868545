import math

import numpy as np
import pytest

from bid_sim.errors import BidError
from bid_sim.routes import (
    CHANGELANELEFT,
    CHANGELANERIGHT,
    LANEFOLLOW,
    LEFT,
    RIGHT,
    STRAIGHT,
    RouteSpec,
    generate_routes,
    load_routes,
    plan,
    plan_spec,
    road_graph,
    route_by_index,
)
from bid_sim.towns import resolve_town

# (town, routes, mean length m as in CARLA's route lists, tolerance)
STATS = [("01", 25, 695.0, 0.05), ("02", 25, 356.0, 0.05), ("05", 10, 950.0, 0.25)]


@pytest.mark.parametrize("name, count, mean, tol", STATS)
def test_benchmark_routes_plan_with_carla_like_lengths(name, count, mean, tol):
    town = resolve_town(name)
    graph = road_graph(town.net_file)
    specs = load_routes(town)
    assert len(specs) == count
    lengths = [plan_spec(graph, s).length_m for s in specs]
    assert np.mean(lengths) == pytest.approx(mean, rel=tol)
    assert min(lengths) > 100.0


def test_route_geometry_is_continuous_and_commands_are_turns(town02, route02):
    r = route02
    steps = np.linalg.norm(np.diff(r.polyline, axis=0), axis=1)
    assert steps.max() < 15.0 and r.cum_s[-1] == pytest.approx(r.length_m)
    junction_cmds = {p.command for p in r.pieces if p.junction}
    assert junction_cmds <= {LEFT, RIGHT, STRAIGHT, LANEFOLLOW} and junction_cmds & {LEFT, RIGHT, STRAIGHT}
    assert all(p.command == LANEFOLLOW for p in r.pieces if not p.junction)


def test_command_is_given_20_m_before_the_junction(route02):
    first = next(p for p in route02.pieces if p.junction and p.command != LANEFOLLOW)
    assert route02.command_at(first.s0_m - 25.0) == LANEFOLLOW
    assert route02.command_at(first.s0_m - 15.0) == first.command
    assert route02.command_at(first.s0_m + 1.0) == first.command
    assert route02.command_at(first.s1_m + 1.0) in (LANEFOLLOW, first.command)


def test_turn_direction_matches_geometry(route02):
    """LEFT turns the heading counter-clockwise, RIGHT clockwise."""
    for p in route02.pieces:
        if p.command in (LEFT, RIGHT):
            h0 = route02.point_at(p.s0_m - 3.0)[2]
            h1 = route02.point_at(p.s1_m + 3.0)[2]
            turn = math.atan2(math.sin(h1 - h0), math.cos(h1 - h0))
            assert (turn > 0.5) if p.command == LEFT else (turn < -0.5)


def test_project_round_trip(route02):
    for s in (5.0, 100.0, route02.length_m - 5.0):
        x, y, h = route02.point_at(s)
        ps, lat, _ = route02.project(x + 1.0 * math.cos(h + math.pi / 2), y + 1.0 * math.sin(h + math.pi / 2), s - 3.0)
        assert ps == pytest.approx(s, abs=0.5) and lat == pytest.approx(1.0, abs=0.05)


def test_goal_behind_start_on_same_edge_loops_round(town02):
    graph = road_graph(town02.net_file)
    r = plan(graph, "S3", 60.0, "S3", 20.0)
    assert r.edges[0] == r.edges[-1] == "S3" and len(r.edges) > 2 and r.length_m > 100


def test_town05_routes_change_lanes_when_needed():
    town = resolve_town("05")
    graph = road_graph(town.net_file)
    cmds = set()
    for spec in load_routes(town):
        cmds |= {p.command for p in plan_spec(graph, spec).pieces}
    assert cmds & {CHANGELANELEFT, CHANGELANERIGHT}


def test_bad_route_inputs(town02):
    with pytest.raises(BidError, match="out of range"):
        route_by_index(town02, 25)
    with pytest.raises(BidError, match="not a driving edge"):
        plan_spec(road_graph(town02.net_file), RouteSpec("nope", 0.0, "S1", 5.0))


def test_malformed_routes_toml(tmp_path):
    import shutil

    src = resolve_town("02")
    shutil.copy(src.net_file, tmp_path / "t.net.xml")
    (tmp_path / "routes.toml").write_text("[[route]]\nstart_edge = 3\n")
    with pytest.raises(BidError, match="malformed"):
        load_routes(resolve_town(tmp_path))


def test_town_without_routes_gets_generated_deterministic_ones(tmp_path):
    import shutil

    shutil.copy(resolve_town("02").net_file, tmp_path / "t.net.xml")
    a = load_routes(resolve_town(tmp_path))
    b = load_routes(resolve_town(tmp_path))
    assert a == b and len(a) == 25


def test_road_bends_are_corners_not_junction_turns(town02):
    graph = road_graph(town02.net_file)
    corner = plan_spec(graph, route_by_index(town02, 3))  # the south-east corner, turning right
    (s, turn), = corner.road_bends()
    assert turn == pytest.approx(-90.0, abs=3.0)
    x, y, _ = corner.point_at(s + 30.0)
    assert math.hypot(x - 189.0, y + 300.0) < 10.0
    turns_only = plan_spec(graph, route_by_index(town02, 16))  # eight junction turns, no corner
    assert sum(p.command in (LEFT, RIGHT) for p in turns_only.pieces) == 8
    assert turns_only.road_bends() == []


def test_generated_routes_with_bends_take_one_early():
    town = resolve_town("01")
    graph = road_graph(town.net_file)
    specs = generate_routes(town, count=6, seed=3, bends=True)
    assert len(specs) == 6 and specs == generate_routes(town, count=6, seed=3, bends=True)
    for spec in specs:
        assert any(s <= 250.0 for s, _ in plan_spec(graph, spec).road_bends())
    plain = [plan_spec(graph, spec) for spec in generate_routes(town, count=24, seed=3)]
    assert sum(any(s <= 250.0 for s, _ in r.road_bends()) for r in plain) < 12
