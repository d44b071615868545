import json
import subprocess
import sys

import pytest
from render_scenes import snapshot

from bid_sim.agents import LaneFollower
from bid_sim.cli import main
from bid_sim.episode import EpisodeResult, run_episode, standing_reason
from bid_sim.errors import BidError
from bid_sim.snapshot import RED, YELLOW


def test_scripted_episode_in_town02_crowded_runs_to_a_result(town02):
    r = run_episode(town02, 3, "WetSunset", "crowded", 1, LaneFollower(6.0), max_steps=400)
    assert isinstance(r, EpisodeResult)
    assert r.steps <= 400 and r.driven_m > 50
    for key in ("SR", "SSR", "RC", "IP", "DS", "CV", "CP", "CL", "TL", "OL", "RD", "ABD"):
        assert key in r.metrics
    assert r.metrics["DS"] == pytest.approx(r.metrics["RC"] * r.metrics["IP"])
    json.dumps(r.to_dict())


def test_what_a_standing_ego_stands_for(town02):
    """A red or amber light within 10 m first, then a vehicle, then a pedestrian within 8 m
    of the front bumper in the ego's width; beside it, behind it or farther is nothing."""
    from dataclasses import replace

    from bid_sim.town_map import load_town_map

    tm = load_town_map(town02)
    x, y = 70.0, -306.5  # heading +x: "ahead" is +x (the car is 4.6 m long, the ego's front at x + 2.3)
    assert standing_reason(snapshot(tm, x, y, 0.0)) == "nothing"
    car_at = lambda gap, left=0.0: (x + 2.3 + gap + 2.3, y + left, 0.0, 0)  # noqa: E731  gap: bumper to bumper
    person_at = lambda gap, left=0.0: (x + 2.3 + gap + 0.25, y + left, 0.0, 0)  # noqa: E731
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[car_at(7.5)])) == "vehicle"
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[car_at(8.5)])) == "nothing"
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[car_at(3.0, left=3.5)])) == "nothing"  # next lane
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[car_at(3.0, left=1.5)])) == "vehicle"  # half in
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[(x - 7.0, y, 0.0, 0)])) == "nothing"  # behind
    assert standing_reason(snapshot(tm, x, y, 0.0, pedestrians=[person_at(2.0)])) == "pedestrian"
    assert standing_reason(snapshot(tm, x, y, 0.0, vehicles=[car_at(6.0)], pedestrians=[person_at(2.0)])) == "vehicle"
    at_light = replace(snapshot(tm, x, y, 0.0, vehicles=[car_at(2.0)]), next_light_state=RED, next_light_dist_m=9.0)
    assert standing_reason(at_light) == "light"
    assert standing_reason(replace(at_light, next_light_state=YELLOW)) == "light"
    assert standing_reason(replace(at_light, next_light_dist_m=12.0)) == "vehicle"
    # turned half left, the car dead east is no longer in its way
    assert standing_reason(snapshot(tm, x, y, 1.2, vehicles=[car_at(3.0)])) == "nothing"


def test_same_seed_same_episode(town02):
    a = run_episode(town02, 1, "ClearNoon", "normal", 4, LaneFollower(6.0), max_steps=300)
    b = run_episode(town02, 1, "ClearNoon", "normal", 4, LaneFollower(6.0), max_steps=300)
    assert a.to_dict() == b.to_dict()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["episode", "--town", "09"], "unknown town"),
        (["episode", "--density", "busy"], "unknown density"),
        (["episode", "--weather", "Fog"], "unknown weather"),
        (["episode", "--route", "40"], "out of range"),
        (["episode", "--agent", "nope"], "unknown agent"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_cli_episode_json(capsys):
    assert main(["episode", "--town", "02", "--density", "crowded", "--max-steps", "100", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["town"] == "Town02" and out["steps"] == 100 and out["status"] == "timeout"


def test_negative_seed(town02):
    with pytest.raises(BidError, match="seed"):
        run_episode(town02, 0, "ClearNoon", "none", -1, LaneFollower())


def _in_child(code: str) -> subprocess.CompletedProcess:
    """Runs `code` in a fresh Python process: a libsumo crash fails only the test that asked."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_sumo_error_mid_episode_is_a_bid_error():
    """Run in its own process: after this error libsumo 1.28 can leave the process unable to
    start SUMO again once GEOS (shapely) has run in between (it segfaults)."""
    code = (
        "import libsumo as traci, pytest\n"
        "from bid_sim.agents import LaneFollower\n"
        "from bid_sim.episode import run_episode\n"
        "from bid_sim.errors import BidError\n"
        "def lose_the_ego(world):\n"
        "    traci.vehicle.remove('ego')\n"
        "with pytest.raises(BidError, match='SUMO failed at step 0'):\n"
        "    run_episode('02', 0, 'ClearNoon', 'none', 0, LaneFollower(), on_start=lose_the_ego, max_steps=20)\n"
        "assert not traci.isLoaded()\n"
        "print('ok')\n"
    )
    out = _in_child(code)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_an_agent_failing_before_its_first_step_leaves_sumo_able_to_start_another_town():
    """The ego's first moveToXY waits for a step that never comes; libsumo keeps it past
    close, and the next simulation's first step followed it into the freed ego (a segfault,
    every time when the next town differs). Run in its own process so a crash fails only this."""
    code = (
        "from bid_sim.agents import LaneFollower\n"
        "from bid_sim.episode import run_episode\n"
        "class Broken(LaneFollower):\n"
        "    def act(self, obs):\n"
        "        raise ZeroDivisionError('a bug in the agent')\n"
        "try:\n"
        "    run_episode('02', 3, 'WetSunset', 'none', 0, Broken(), max_steps=20)\n"
        "except ZeroDivisionError:\n"
        "    pass\n"
        "r = run_episode('01', 0, 'WetSunset', 'none', 0, LaneFollower(), max_steps=5)\n"
        "print('ok', r.steps)\n"
    )
    out = _in_child(code)
    assert out.returncode == 0 and out.stdout.strip() == "ok 5", out.stderr[-2000:]
