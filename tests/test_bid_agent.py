"""The BID agent in the closed loop: a real (tiny, briefly trained) checkpoint drives the ego
through SUMO from rendered frames; loading by name; bad checkpoints."""

import json
from pathlib import Path

import pytest
from render_scenes import street_scene

from bid_model.agent import BIDAgent
from bid_model.config import tiny
from bid_model.train import train
from bid_sim.cli import _drive_options, build_parser, main
from bid_sim.ego import EgoParams
from bid_sim.episode import run_episode
from bid_sim.errors import BidError
from bid_sim.evaluate import load_agent
from bid_sim.render import Renderer
from bid_sim.town_map import load_town_map


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    cfg = tiny()
    train(out, type(cfg)(cfg.model, cfg.train.with_epochs(1)), synthetic=True, progress=False)
    return out / "last.pt"


class Spy(BIDAgent):
    """Keeps the controls it produced and the command it was given."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.controls, self.commands = [], []

    def act(self, obs):
        c = super().act(obs)
        self.controls.append((c.steer, c.accel))
        self.commands.append(obs.command)
        return c


def test_bid_agent_drives_from_frames(checkpoint, town02):
    agent = Spy(checkpoint)
    renderer = Renderer(load_town_map(town02), weather="WetSunset")
    r = run_episode(town02, 0, "WetSunset", "normal", 0, agent, renderer=renderer, replan=True, max_steps=15)
    assert r.steps == 15 and len(agent.controls) == 15
    assert all(-1.0 <= s <= 1.0 and -1.0 <= a <= 1.0 for s, a in agent.controls)
    assert len(set(agent.controls)) > 1  # it reacts to what it sees
    assert set(agent.commands) <= set(range(1, 7))


def test_lesion_changes_the_controls(checkpoint, town02):
    renderer = Renderer(load_town_map(town02), weather="ClearNoon")
    intact, lesioned = Spy(checkpoint), Spy(checkpoint, lesions={"IT": "zero"})
    for agent in (intact, lesioned):
        run_episode(town02, 0, "ClearNoon", "none", 0, agent, renderer=renderer, max_steps=3)
    assert intact.controls[0] != lesioned.controls[0]


def test_loaded_by_name_and_overlay(checkpoint, town02):
    agent = load_agent("bid", str(checkpoint))
    assert isinstance(agent, BIDAgent)
    renderer = Renderer(load_town_map(town02))
    assert agent.overlay(None) is None  # nothing driven yet
    run_episode(town02, 0, "ClearNoon", "none", 0, agent, renderer=renderer, max_steps=2)
    frame = renderer.render(street_scene(load_town_map(town02)))
    img = agent.overlay(frame)
    assert img.shape == frame.shape and img.dtype == frame.dtype


def test_bid_agent_needs_a_checkpoint(tmp_path, capsys):
    assert main(["evaluate", "--town", "02", "--agent", "bid", "--out", str(tmp_path / "r")]) == 2
    assert "--checkpoint" in capsys.readouterr().err
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    assert main(["evaluate", "--town", "02", "--agent", "bid", "--checkpoint", str(bad),
                 "--out", str(tmp_path / "r2")]) == 2
    assert "checkpoint" in capsys.readouterr().err


def test_lesion_study_writes_table_and_chart(checkpoint, tmp_path, capsys):
    assert main(["lesion", "--checkpoint", str(checkpoint), "--town", "02", "--density", "none",
                 "--weathers", "WetSunset", "--routes", "3", "--areas", "IT,OFC", "--workers", "1", "--max-steps", "30",
                 "--out", str(tmp_path)]) == 0
    md = (tmp_path / "lesion.md").read_text()
    assert "| intact |" in md and "| IT |" in md and "| OFC |" in md and "| SR | RC | TL |" in md
    assert (tmp_path / "lesion.png").stat().st_size > 1000
    assert main(["lesion", "--checkpoint", str(checkpoint), "--areas", "V1", "--out", str(tmp_path / "x")]) == 2
    assert "cannot lesion 'V1'" in capsys.readouterr().err


def test_exported_checkpoint_drives_the_same_and_is_smaller(checkpoint, town02, tmp_path, capsys):
    shipped = tmp_path / "bid_tiny.pt"
    assert main(["export", str(checkpoint.parent), "--which", "last.pt", "--out", str(shipped),
                 "--recipe", "bid train --preset tiny --synthetic"]) == 0
    assert "bid_tiny.pt" in capsys.readouterr().out
    assert shipped.stat().st_size < checkpoint.stat().st_size  # no optimiser state
    card = json.loads(shipped.with_suffix(".json").read_text())
    assert card["recipe"] == "bid train --preset tiny --synthetic" and card["config"]["model"]["preset"] == "tiny"
    renderer = Renderer(load_town_map(town02), weather="WetSunset")
    a, b = Spy(checkpoint), Spy(shipped)
    for agent in (a, b):
        run_episode(town02, 1, "WetSunset", "none", 0, agent, renderer=renderer, max_steps=4)
    assert a.controls == b.controls


def test_results_of_a_checkpoint_rewritten_in_place_are_not_resumed(checkpoint, tmp_path, capsys):
    ckpt = tmp_path / "bid.pt"
    ckpt.write_bytes(checkpoint.read_bytes())
    args = ["evaluate", "--town", "02", "--density", "none", "--weathers", "WetSunset", "--routes", "3",
            "--agent", "bid", "--checkpoint", str(ckpt), "--workers", "1", "--max-steps", "3",
            "--out", str(tmp_path / "res")]
    assert main(args) == 0
    assert main(args) == 0  # the same file: resumes (nothing left to run)
    assert main(["export", str(checkpoint.parent), "--which", "last.pt", "--out", str(ckpt)]) == 0
    assert main(args) == 2
    assert "checkpoint file changed" in capsys.readouterr().err


def test_forecast_brake_brakes_to_the_forecast_speed(checkpoint, tmp_path, capsys):
    """With --forecast-brake the agent brakes at least as hard as reaching the speed its
    network forecasts 1 s ahead takes; without it, it drives on the control head alone."""
    import dataclasses

    import numpy as np
    import torch

    from bid_model.config import RunConfig
    from bid_model.data import command_one_hot, prepare_frame
    from bid_sim.agents import Observation

    cfg = tiny()
    run = RunConfig(dataclasses.replace(cfg.model, forecast_s=(1.0, 2.0)),
                    dataclasses.replace(cfg.train.with_epochs(1), lambda_forecast=0.5))
    train(tmp_path / "fc", run, synthetic=True, progress=False)
    frame = np.random.default_rng(0).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    plain, braking = BIDAgent(tmp_path / "fc" / "last.pt"), BIDAgent(tmp_path / "fc" / "last.pt", forecast_brake=1.0)
    x = prepare_frame(frame, run.model.frame_hw)[None]
    with torch.no_grad():
        control, ahead = braking.model(x, x, command_one_hot(4), forecast=True)
    fast = float(ahead[0, 0]) + 4.0  # 4 m/s above the forecast: 0.5 of full braking (8 m/s²)
    obs = Observation(frame, frame, 4, fast, None)
    assert plain.act(obs).accel == pytest.approx(float(control[0, 1]), abs=1e-6)
    assert braking.act(obs).accel == pytest.approx(min(float(control[0, 1]), -0.5), abs=1e-5)
    slow = Observation(frame, frame, 4, max(float(ahead[0, 0]) - 1.0, 0.0), None)
    braking.reset(None)
    assert braking.act(slow).accel == pytest.approx(float(control[0, 1]), abs=1e-6)
    with pytest.raises(BidError, match="no speed forecast"):
        BIDAgent(checkpoint, forecast_brake=1.0)
    assert main(["evaluate", "--agent", "expert", "--forecast-brake", "1", "--out", str(tmp_path / "x")]) == 2
    assert "option of --agent bid" in capsys.readouterr().err


def test_max_speed_brakes_an_ego_faster_than_the_cap(checkpoint, tmp_path, capsys):
    """With max_speed the agent brakes 1 share of full braking per m/s over the cap, with or
    without the other brakes; at or below it, the control head drives as without it."""
    import math

    import numpy as np

    from bid_model.agent import cruise_brake
    from bid_sim.agents import Observation

    assert cruise_brake(8.0, 9.0) == cruise_brake(9.0, 9.0) == 0.0
    assert cruise_brake(9.5, 9.0) == pytest.approx(0.5) and cruise_brake(12.0, 9.0) == 1.0
    frame = np.random.default_rng(1).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    plain, capped = BIDAgent(checkpoint), BIDAgent(checkpoint, max_speed=9.0)
    for speed, brake in ((5.0, 0.0), (9.0, 0.0), (9.25, 0.25), (11.0, 1.0)):
        plain.reset(None)
        capped.reset(None)
        head = plain.act(Observation(frame, frame, 4, speed, None))
        got = capped.act(Observation(frame, frame, 4, speed, None))
        assert got.steer == head.steer
        assert got.accel == pytest.approx(min(head.accel, -brake) if brake else head.accel, abs=1e-6)
    for bad in (-1.0, math.nan, 1e3):
        with pytest.raises(BidError, match="max_speed is a speed in m/s"):
            BIDAgent(checkpoint, max_speed=bad)
    assert main(["evaluate", "--agent", "expert", "--max-speed", "9", "--out", str(tmp_path / "x")]) == 2
    assert "--max-speed is an option of --agent bid" in capsys.readouterr().err


def test_turn_speed_brakes_only_under_a_turn_command(checkpoint, tmp_path, capsys):
    """With turn_speed the agent brakes as max_speed does while the command is LEFT or RIGHT; on
    STRAIGHT, LANEFOLLOW and lane changes, or at or below the cap, the control head drives."""
    import numpy as np

    from bid_sim.agents import Observation
    from bid_sim.routes import CHANGELANELEFT, LANEFOLLOW, LEFT, RIGHT, STRAIGHT

    frame = np.random.default_rng(3).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    plain, capped = BIDAgent(checkpoint), BIDAgent(checkpoint, turn_speed=4.0)
    for command in (LEFT, RIGHT, STRAIGHT, LANEFOLLOW, CHANGELANELEFT):
        for speed, brake in ((3.0, 0.0), (4.0, 0.0), (4.5, 0.5), (7.0, 1.0)):
            plain.reset(None)
            capped.reset(None)
            head = plain.act(Observation(frame, frame, command, speed, None))
            got = capped.act(Observation(frame, frame, command, speed, None))
            assert got.steer == head.steer
            want = min(head.accel, -brake) if brake and command in (LEFT, RIGHT) else head.accel
            assert got.accel == pytest.approx(want, abs=1e-6), (command, speed)
    with pytest.raises(BidError, match="turn_speed is a speed in m/s"):
        BIDAgent(checkpoint, turn_speed=-2.0)
    assert main(["evaluate", "--agent", "expert", "--turn-speed", "4", "--out", str(tmp_path / "x")]) == 2
    assert "--turn-speed is an option of --agent bid" in capsys.readouterr().err


def test_start_cap_holds_the_metres_after_a_stand_under_the_cap(checkpoint, tmp_path, capsys):
    """With start_cap, standing 1 s makes the next start_cap_m metres a start: faster than the
    cap there, the agent brakes as max_speed does; past them, or never having stood, it does
    not."""
    import numpy as np

    from bid_sim.agents import Observation

    frame = np.random.default_rng(2).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    plain, capped = BIDAgent(checkpoint), BIDAgent(checkpoint, start_cap=2.5, start_cap_m=3.0)

    def drive(speeds):
        plain.reset(None)
        capped.reset(None)
        out = []
        for v in speeds:
            head, got = plain.act(Observation(frame, frame, 4, v, None)), capped.act(Observation(frame, frame, 4, v, None))
            assert got.steer == head.steer
            out.append((head.accel, got.accel))
        return out

    never_stood = drive([3.5] * 5)
    assert all(got == pytest.approx(head, abs=1e-6) for head, got in never_stood)
    started = drive([0.0] * 10 + [3.5] * 12)  # stood 1 s, then 3 m at 3.5 m/s take 9 steps
    assert all(got == pytest.approx(head, abs=1e-6) for head, got in started[:10])
    assert all(got == pytest.approx(min(head, -1.0), abs=1e-6) for head, got in started[10:19])
    assert all(got == pytest.approx(head, abs=1e-6) for head, got in started[19:])
    for bad in ({"start_cap": -1.0}, {"start_cap": 2.0, "start_cap_m": 0.0}, {"start_cap_m": 5.0}):
        with pytest.raises(BidError, match="start_cap"):
            BIDAgent(checkpoint, **bad)
    assert main(["evaluate", "--agent", "expert", "--start-cap", "2", "--out", str(tmp_path / "x")]) == 2
    assert "--start-cap is an option of --agent bid" in capsys.readouterr().err


def test_pedestrian_brake_stops_short_of_a_seen_pedestrian_and_holds_near_one():
    from bid_model.agent import pedestrian_brake

    assert pedestrian_brake(0.1, 10.0) == 0.0  # seen nowhere within 20 m
    # 12.5 m ahead at 10 m/s: stop 2 m short, 100 / (2 · 10.5) m/s² of 8.
    assert pedestrian_brake(0.5, 10.0) == pytest.approx(100 / 21 / 8)
    assert pedestrian_brake(0.5, 1.0) == pytest.approx(1 / 21 / 8)  # slow and 12.5 m off: barely
    assert pedestrian_brake(0.8, 1.0) == 1.0  # 5 m off and slow: stay standing
    assert pedestrian_brake(0.8, 0.0) == 1.0
    assert pedestrian_brake(1.0, 12.0) == 1.0  # at the bumper: all it has
    # A shorter hold (--pedestrian-hold): 7 m off and standing is no longer held, only stopped short of.
    assert pedestrian_brake(0.72, 0.0) == 1.0
    assert pedestrian_brake(0.72, 0.0, hold_m=6.0) == 0.0
    assert pedestrian_brake(0.72, 1.5, hold_m=6.0) == pytest.approx(2.25 / 10 / 8)
    assert pedestrian_brake(0.8, 1.0, hold_m=6.0) == 1.0  # 5 m off: held
    assert pedestrian_brake(0.9, 0.0, hold_m=0.0) == pytest.approx(0.0)  # never held; standing asks nothing


def test_crossing_brake_stops_2_m_short_of_an_occupied_crossing_and_holds_near_one():
    from bid_model.agent import crossing_brake

    assert crossing_brake(0.1, 10.0) == 0.0  # seen nowhere within 20 m
    # 12.5 m ahead at 10 m/s: stop 2 m short, 100 / (2 · 10.5) m/s² of 8.
    assert crossing_brake(0.5, 10.0) == pytest.approx(100 / 21 / 8)
    assert crossing_brake(0.5, 1.0) == 0.0  # slow and 12.5 m off: below BIND_SHARE, brake later
    assert crossing_brake(0.8, 1.0) == crossing_brake(0.8, 0.0) == 1.0  # 5 m off and slow: stay standing
    assert crossing_brake(0.72, 0.0) == 0.0  # 7 m off, standing: not held
    assert crossing_brake(0.8, 2.5) == pytest.approx(6.25 / 6 / 8)  # 5 m off at 2.5 m/s: stop 2 m short


def test_crossing_brake_reads_the_fourth_hazard_output(recorded, tmp_path):
    import dataclasses

    import numpy as np
    import torch

    from bid_model.agent import crossing_brake
    from bid_model.config import RunConfig
    from bid_sim.agents import Observation

    cfg = tiny()
    run = RunConfig(dataclasses.replace(cfg.model, hazard=True, hazard_light=True, hazard_sc=True,
                                        hazard_crossing=True),
                    dataclasses.replace(cfg.train.with_epochs(1), lambda_hazard=1.0))
    train(tmp_path / "x", run, data=recorded, progress=False)
    plain = BIDAgent(tmp_path / "x" / "last.pt")
    braking = BIDAgent(tmp_path / "x" / "last.pt", crossing_brake=1.0)
    frame = np.random.default_rng(0).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    for agent in (plain, braking):
        with torch.no_grad():  # the head and SC see nothing; the crossing map says 0.6 everywhere
            agent.model.hazard_head[-1].weight.zero_()
            agent.model.hazard_head[-1].bias.zero_()
            agent.model.hazard_sc.priority[-1].weight.zero_()
            agent.model.hazard_sc.priority[-1].bias.zero_()
            agent.model.hazard_crossing.priority[-1].weight.zero_()
            agent.model.hazard_crossing.priority[-1].bias.fill_(0.6)
        agent.reset(None)
    obs = Observation(frame, frame, 4, 6.0, None)
    free = plain.act(obs).accel
    assert braking.act(obs).accel == pytest.approx(min(free, -crossing_brake(0.6, 6.0)), abs=1e-5)
    run = RunConfig(dataclasses.replace(cfg.model, hazard=True, hazard_light=True),
                    dataclasses.replace(cfg.train.with_epochs(1), lambda_hazard=1.0))
    train(tmp_path / "hz", run, data=recorded, progress=False)
    with pytest.raises(BidError, match="no crossing output; train one with --hazard-crossing"):
        BIDAgent(tmp_path / "hz" / "last.pt", crossing_brake=1.0)


def test_vehicle_brake_keeps_a_headway_behind_a_seen_vehicle():
    from bid_model.agent import vehicle_brake

    assert vehicle_brake(0.1, 10.0) == 0.0  # seen nowhere within 20 m
    assert vehicle_brake(0.4, 10.0) == 0.0  # 15 m off at 10 m/s: beyond 1 s + 4 m
    # 10 m off at 10 m/s: within 14 m; stop 1 m short, 100 / (2 · 9) m/s² of 8.
    assert vehicle_brake(0.6, 10.0) == pytest.approx(100 / 18 / 8)
    assert vehicle_brake(0.9, 0.0) == 0.0  # standing behind it: nothing to brake
    assert vehicle_brake(0.9, 3.0) == pytest.approx(9 / 3 / 8)  # 2.5 m off at 3 m/s
    assert vehicle_brake(1.0, 8.0) == 1.0
    assert vehicle_brake(0.9, 1.0) == 0.0  # 2.5 m off at 1 m/s: 1/3/8 is below BIND_SHARE, close up
    # With a hold distance (path_memory: 3 m; --vehicle-hold M), within it and slow (below 2 m/s) it holds the ego standing.
    assert vehicle_brake(0.9, 1.0, 3.0) == vehicle_brake(0.9, 0.0, 3.0) == 1.0
    assert vehicle_brake(0.84, 1.0, 3.0) == 0.0  # 4 m off: as without
    assert vehicle_brake(0.84, 1.0, 5.0) == 1.0  # held within 5 m
    assert vehicle_brake(0.9, 2.5, 3.0) == pytest.approx(6.25 / 3 / 8)  # not at 2.5 m/s


def test_path_memory_keeps_what_was_seen_near_once_the_head_loses_it():
    from bid_model.agent import PathMemory

    mem = PathMemory(keep_s=1.0)  # 10 steps
    assert mem.update((0.0, 0.8, 0.3), 4.0) == pytest.approx((0.0, 0.8, 0.3))  # a car seen 5 m ahead
    # Lost: it stays, 0.4 m nearer for every step at 4 m/s, as if standing; the light is never kept.
    got = mem.update((0.0, 0.0, 0.0), 4.0)
    assert got[0] == 0.0 and got[1] == pytest.approx(1 - 4.6 / 25) and got[2] == 0.0
    for _ in range(9):
        got = mem.update((0.0, 0.0, 0.0), 0.2)
    assert got[1] == pytest.approx(1 - (4.6 - 9 * 0.02) / 25)
    assert mem.update((0.0, 0.0, 0.0), 0.2) == (0.0, 0.0, 0.0)  # the 11th step unseen: forgotten
    # Drawn nearer by 2 m at most: a false sighting 5 m ahead never comes within 3 m.
    mem.update((0.0, 0.8, 0.0), 4.0)
    for _ in range(10):
        got = mem.update((0.0, 0.0, 0.0), 4.0)
    assert got[1] == pytest.approx(1 - 3.0 / 25)
    # Seen farther than REMEMBER_M (10 m): never kept; a pedestrian is kept as a car is.
    mem.reset()
    mem.update((0.6, 0.6, 0.0), 5.0)
    assert mem.update((0.0, 0.0, 0.0), 5.0) == (0.0, 0.0, 0.0)
    mem.update((0.84, 0.0, 0.0), 5.0)  # a pedestrian 4 m ahead
    assert mem.update((0.0, 0.0, 0.0), 5.0)[0] == pytest.approx(1 - 3.5 / 25)
    # A reading is what there is now: a car followed at its speed, seen farther, is farther.
    mem.update((0.0, 0.92, 0.0), 3.0)
    assert mem.update((0.0, 0.8, 0.0), 3.0)[1] == pytest.approx(0.8)
    assert mem.update((0.0, 0.0, 0.0), 3.0)[1] == pytest.approx(1 - 4.7 / 25)


def test_pedestrian_memory_keeps_her_alone_and_draws_her_nearer_all_the_way():
    from bid_model.agent import PEDESTRIAN_REMEMBER_M, PathMemory, pedestrian_brake

    mem = PathMemory(keep_s=1.0, kinds=(0,), remember_m=PEDESTRIAN_REMEMBER_M, close_m=None, learn_mps=2.0)
    # Seen 7.5 m ahead (within 8 m, farther than path_memory's 6 m), a car 5 m ahead beside her.
    assert mem.update((0.7, 0.8, 0.0), 4.0) == pytest.approx((0.7, 0.8, 0.0))
    got = mem.update((0.0, 0.0, 0.0), 4.0)  # both lost: she stays, 0.4 m nearer; the car goes
    assert got[0] == pytest.approx(1 - 7.1 / 25) and got[1] == 0.0
    for _ in range(9):  # driven on at 4 m/s: 3.6 m more, past the 2 m path_memory stops at
        got = mem.update((0.0, 0.0, 0.0), 4.0)
    assert got[0] == pytest.approx(1 - 3.5 / 25)
    assert pedestrian_brake(got[0], 4.0) == pytest.approx(16 / (2 * 1.5) / 8)  # to stop 2 m short of her
    assert pedestrian_brake(got[0], 1.0) == 1.0  # slow within the hold: held
    assert mem.update((0.0, 0.0, 0.0), 0.0) == (0.0, 0.0, 0.0)  # the 11th step unseen: forgotten
    mem.update((0.9, 0.0, 0.0), 6.0)  # 2.5 m ahead, then 3 m driven: she is at the bumper, not behind it
    assert mem.update((0.0, 0.0, 0.0), 30.0)[0] == pytest.approx(1.0)
    mem.reset()
    mem.update((0.66, 0.0, 0.0), 4.0)  # 8.5 m ahead: not kept
    assert mem.update((0.0, 0.0, 0.0), 4.0) == (0.0, 0.0, 0.0)
    mem.update((0.8, 0.0, 0.0), 1.0)  # seen by an ego slower than 2 m/s: not kept...
    assert mem.update((0.0, 0.0, 0.0), 1.0) == (0.0, 0.0, 0.0)
    mem.update((0.8, 0.0, 0.0), 3.0)  # ...and a memory the slow ego reads again only ages
    for _ in range(10):
        mem.update((0.8, 0.0, 0.0), 0.0)
    assert mem.update((0.0, 0.0, 0.0), 0.0) == (0.0, 0.0, 0.0)


def test_clear_to_move_off_needs_nothing_seen_within_8_m():
    from bid_model.agent import clear_to_move_off

    assert clear_to_move_off((0.0, 0.0, 0.0))
    assert clear_to_move_off((0.6, 0.6, 0.6))  # a pedestrian, a car and a red light 10 m off
    assert not clear_to_move_off((0.7, 0.0, 0.0))  # a pedestrian 7.5 m off
    assert not clear_to_move_off((0.0, 0.7, 0.0))
    assert not clear_to_move_off((0.0, 0.0, 0.9))  # at the stop line of a red light


def one_input(hw, seed: int, command: int, speed_mps: float):
    """A batch of one: random frames t and t−1 (uint8), a one-hot command and a speed."""
    import torch

    frame, prev = torch.randint(0, 256, (2, 1, 3, *hw), dtype=torch.uint8,
                                generator=torch.Generator().manual_seed(seed))
    cmd = torch.zeros(1, 6)
    cmd[0, command] = 1.0
    return frame, prev, cmd, torch.tensor([speed_mps])


def test_the_shipped_checkpoint_takes_the_flags_make_drives_it_with():
    """`make demo` and `make evaluate` drive checkpoints/bid_small.pt with the Makefile's
    SHIPPED_DRIVE: its hazard head must have the three outputs those brakes and move-off read,
    SC beside it (the nearer of the two counts), and reading them leaves the control head's
    output as it is."""
    import torch

    root = Path(__file__).resolve().parents[1]
    makefile = (root / "Makefile").read_text().splitlines()
    words = next(ln for ln in makefile if ln.startswith("SHIPPED_DRIVE :=")).split(":=", 1)[1].split()
    options: dict[str, float | bool] = {}
    for i, word in enumerate(words):  # a flag takes the value after it, or is a switch
        if word.startswith("--"):
            valued = i + 1 < len(words) and not words[i + 1].startswith("--")
            options[word.removeprefix("--").replace("-", "_")] = float(words[i + 1]) if valued else True
    assert set(options) == {"vehicle_brake", "light_brake", "move_off", "hazard_brake", "pedestrian_hold",
                            "max_speed", "light_still", "light_short", "move_off_green"}
    shipped = root / "checkpoints" / "bid_small.pt"
    agent = BIDAgent(shipped, **options)
    assert agent.light_brake == agent.hazard_brake == 1.0 and agent.vehicle_brake == 2.0 and agent.move_off_steps == 80
    assert agent.pedestrian_hold_m == 6.0 and agent.max_speed == 9.0 and agent.light_still is True
    assert agent.light_short_m == 2.5 and agent.green_steps == 10
    assert agent.config.model.hazard_sc
    plain = BIDAgent(shipped)
    frame, prev, cmd, speed = one_input(plain.hw, seed=0, command=3, speed_mps=3.0)
    with torch.inference_mode():
        control, near = agent.model(frame, prev, cmd, speed, hazard=True)
        assert torch.equal(control, plain.model(frame, prev, cmd, speed))
    assert near.shape == (1, 3)  # pedestrian, vehicle, red light
    with torch.inference_mode():
        feats = agent.model.forward_features(frame, prev, cmd, speed)
    assert torch.all(near[:, :2] >= feats["SC"]) and torch.allclose(near[:, 2:], agent.model.hazard_head(feats["MPC"].mean(1))[:, 2:])


def test_hazard_brake_brakes_for_the_pedestrian_the_head_sees(checkpoint, recorded, tmp_path, capsys):
    """With --hazard-brake the agent brakes at least as pedestrian_brake asks for what its
    hazard head says; without it, or with nothing seen, it drives on the control head."""
    import dataclasses

    import numpy as np
    import torch

    from bid_model.agent import MOVE_OFF_ACCEL, light_brake, pedestrian_brake, vehicle_brake
    from bid_model.checkpoint import load_checkpoint, save_checkpoint
    from bid_model.config import RunConfig
    from bid_sim.agents import Observation

    cfg = tiny()
    run = RunConfig(dataclasses.replace(cfg.model, hazard=True, hazard_light=True),
                    dataclasses.replace(cfg.train.with_epochs(1), lambda_hazard=1.0))
    train(tmp_path / "hz", run, data=recorded, progress=False)
    plain = BIDAgent(tmp_path / "hz" / "last.pt")
    braking = BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0)
    frame = np.random.default_rng(0).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    obs = Observation(frame, frame, 4, 6.0, None)
    free = plain.act(obs).accel
    last = braking.model.hazard_head[-1]
    for nearness in (0.0, 0.6, 0.9):
        with torch.no_grad():  # the head says a pedestrian at this nearness, whatever it sees
            last.weight.zero_()
            last.bias.copy_(torch.tensor([nearness, 0.9, 0.9]))
        braking.reset(None)
        want = -pedestrian_brake(nearness, 6.0)
        assert braking.act(obs).accel == pytest.approx(min(free, want) if want < 0 else free, abs=1e-5)
    # Standing with a pedestrian seen 7 m ahead: held at 8 m, not with --pedestrian-hold 6.
    still = Observation(frame, frame, 4, 0.0, None)
    short = BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, pedestrian_hold=6.0)
    for agent in (plain, braking, short):
        with torch.no_grad():
            agent.model.hazard_head[-1].weight.zero_()
            agent.model.hazard_head[-1].bias.copy_(torch.tensor([0.72, 0.0, 0.0]))
        agent.reset(None)
    free_still = plain.act(still).accel
    assert braking.act(still).accel == pytest.approx(-1.0)
    assert short.act(still).accel == pytest.approx(free_still, abs=1e-5) and free_still > -1.0
    # A vehicle 2.5 m ahead (nearness 0.9 above) is braked for only with vehicle_brake.
    both = BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=0.5)
    with torch.no_grad():
        both.model.hazard_head[-1].weight.zero_()
        both.model.hazard_head[-1].bias.copy_(torch.tensor([0.0, 0.9, 0.0]))
    both.reset(None)
    assert both.act(obs).accel == pytest.approx(min(free, -0.5 * vehicle_brake(0.9, 6.0)), abs=1e-5)
    # A red light's stop line 5 m ahead (nearness 0.8) is braked for only with light_brake, to
    # stop 1 m short; a standing ego is not held (moving off is the control head's call).
    assert light_brake(0.0, 6.0) == 0.0 and light_brake(0.8, 6.0) == pytest.approx(36 / 8 / EgoParams.max_brake_mps2)
    assert light_brake(0.8, 0.0) == 0.0 and light_brake(0.8, 0.5) == 0.0  # creeping up: below BIND_SHARE
    # With light_short 2.5 it stops 2.5 m short, where the camera sees the red lamp whole.
    assert light_brake(0.8, 6.0, 2.5) == pytest.approx(36 / 5 / EgoParams.max_brake_mps2)
    lights = BIDAgent(tmp_path / "hz" / "last.pt", light_brake=1.0)
    farther = BIDAgent(tmp_path / "hz" / "last.pt", light_brake=1.0, light_short=2.5)
    for agent in (lights, both, farther):
        with torch.no_grad():
            agent.model.hazard_head[-1].weight.zero_()
            agent.model.hazard_head[-1].bias.copy_(torch.tensor([0.0, 0.0, 0.8]))
        agent.reset(None)
    assert lights.act(obs).accel == pytest.approx(min(free, -light_brake(0.8, 6.0)), abs=1e-5)
    assert farther.act(obs).accel == pytest.approx(min(free, -light_brake(0.8, 6.0, 2.5)), abs=1e-5)
    assert farther.act(obs).accel < lights.act(obs).accel
    for kwargs, says in (({}, "add light_brake"), ({"light_brake": 1.0, "light_short": 20.0}, "from 0 to 12.5 m")):
        with pytest.raises(BidError, match=says):
            BIDAgent(tmp_path / "hz" / "last.pt", **{"light_short": 2.5, **kwargs})
    assert both.act(obs).accel == pytest.approx(free, abs=1e-5)
    # move_off: a control head that stands (accel forced to about -0.76) is overruled once the
    # ego has stood 0.3 s (3 steps) with the head seeing nothing, and not while it sees a light.
    still = Observation(frame, frame, 4, 0.0, None)
    going = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.3)
    with torch.no_grad():
        going.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, -100.0]))
        going.model.areas["CPC"].head[-1].weight.zero_()
    head = going.model.hazard_head[-1]
    for bias in ([0.0, 0.0, 0.0], [0.0, 0.0, 0.9], [0.0, 0.0, 0.0]):
        with torch.no_grad():
            head.weight.zero_()
            head.bias.copy_(torch.tensor(bias))
        got = [going.act(still).accel for _ in range(3)]
        if bias[2]:  # a red light seen: it stands as the control head says
            assert got == pytest.approx([-1.0] * 3, abs=1e-5)
        else:  # clear: the third standing step moves off (the count starts again after the light)
            assert got == pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5)
    assert going.act(Observation(frame, frame, 4, 1.0, None)).accel == pytest.approx(MOVE_OFF_ACCEL)
    assert going.act(Observation(frame, frame, 4, 2.5, None)).accel == pytest.approx(-1.0, abs=1e-5)  # moved off
    going.reset(None)
    assert going.act(still).accel == pytest.approx(-1.0, abs=1e-5)
    # move_off_to: moving off drives on to that speed before the control head has the ego again.
    further = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.3, move_off_to=4.0)
    further.model.load_state_dict(going.model.state_dict())
    got = [further.act(Observation(frame, frame, 4, v, None)).accel for v in (0.0, 0.0, 0.0, 2.5, 3.9, 4.0)]
    assert got == pytest.approx([-1.0, -1.0] + [MOVE_OFF_ACCEL] * 3 + [-1.0], abs=1e-5)
    with pytest.raises(BidError, match="move_off_to is the speed move_off drives to"):
        BIDAgent(tmp_path / "hz" / "last.pt", light_brake=1.0, move_off_to=4.0)
    # move_off_braked: after a stop the pedestrian brake made against a control head asking to go,
    # it moves off once clear for 0.2 s (2 steps), not move_off's 0.8 s; a stop of the head's own
    # still waits move_off's. The control head stands (as `going`'s) unless told to go.
    prompt = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, move_off_braked=0.2, hazard_brake=1.0)
    patient = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, hazard_brake=1.0)

    def set_bias(agents, cpc_accel, pedestrian, light=0.0):
        with torch.no_grad():
            for agent in agents:
                agent.model.areas["CPC"].head[-1].weight.zero_()
                agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, cpc_accel]))
                agent.model.hazard_head[-1].weight.zero_()
                agent.model.hazard_head[-1].bias.copy_(torch.tensor([pedestrian, 0.0, light]))

    for agent in (prompt, patient):
        agent.reset(None)
        set_bias([agent], 100.0, 0.9)  # the head says go; a pedestrian 2.5 m ahead at 3 m/s
        assert agent.act(Observation(frame, frame, 4, 3.0, None)).accel == pytest.approx(-1.0)
        set_bias([agent], -100.0, 0.0)  # stood; the pedestrian gone, the head stands
    got = [prompt.act(still).accel for _ in range(3)]
    assert got == pytest.approx([-1.0, MOVE_OFF_ACCEL, MOVE_OFF_ACCEL], abs=1e-5)
    assert [patient.act(still).accel for _ in range(8)] == pytest.approx([-1.0] * 7 + [MOVE_OFF_ACCEL], abs=1e-5)
    prompt.reset(None)  # standing where the head itself stopped: move_off's wait
    assert [prompt.act(still).accel for _ in range(8)] == pytest.approx([-1.0] * 7 + [MOVE_OFF_ACCEL], abs=1e-5)
    with pytest.raises(BidError, match="add move_off"):
        BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, move_off_braked=2.0)
    with pytest.raises(BidError, match="from 0 to move_off"):
        BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, move_off_braked=2.0)
    # move_off_green: after a stop at a red light it moves off once clear for 0.2 s, not move_off's
    # 0.8 s, whether it came to stand reading one within 8 m or stood before one that turned green;
    # a stop for nothing the head read as a light still waits move_off's.
    green = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, move_off_green=0.2, light_brake=1.0)
    slow = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, light_brake=1.0)

    for agent in (green, slow):
        agent.reset(None)
        set_bias([agent], 100.0, 0.0, 0.8)  # the head says go; a red light's line 5 m ahead at 3 m/s
        assert agent.act(Observation(frame, frame, 4, 3.0, None)).accel == pytest.approx(-light_brake(0.8, 3.0))
        set_bias([agent], -100.0, 0.0, 0.0)  # stood; the light reads green, the head stands
    assert [green.act(still).accel for _ in range(3)] == pytest.approx([-1.0, MOVE_OFF_ACCEL, MOVE_OFF_ACCEL], abs=1e-5)
    assert [slow.act(still).accel for _ in range(8)] == pytest.approx([-1.0] * 7 + [MOVE_OFF_ACCEL], abs=1e-5)
    green.reset(None)  # standing before a red light 2.5 m on, which turns green
    set_bias([green], -100.0, 0.0, 0.9)
    assert [green.act(still).accel for _ in range(3)] == pytest.approx([-1.0] * 3, abs=1e-5)
    set_bias([green], -100.0, 0.0, 0.0)
    assert [green.act(still).accel for _ in range(3)] == pytest.approx([-1.0, MOVE_OFF_ACCEL, MOVE_OFF_ACCEL], abs=1e-5)
    green.reset(None)  # standing where the head itself stopped, no light seen: move_off's wait
    assert [green.act(still).accel for _ in range(8)] == pytest.approx([-1.0] * 7 + [MOVE_OFF_ACCEL], abs=1e-5)
    # green_far 14 m: a red light read 0.6 (10 m, clear) holds the shorter wait; read 0.0 it counts
    far = BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, move_off_green=0.2, light_brake=1.0, green_far=14.0)
    for agent in (green, far):
        agent.reset(None)
        set_bias([agent], -100.0, 0.0, 0.9)  # standing before a red light 2.5 m on, read 10 m off from here
        agent.act(still)
        set_bias([agent], -100.0, 0.0, 0.6)
    assert [green.act(still).accel for _ in range(2)] == pytest.approx([-1.0, MOVE_OFF_ACCEL], abs=1e-5)
    assert [far.act(still).accel for _ in range(8)] == pytest.approx([-1.0] * 7 + [MOVE_OFF_ACCEL], abs=1e-5)
    far.reset(None)
    set_bias([far], -100.0, 0.0, 0.9)
    far.act(still)
    set_bias([far], -100.0, 0.0, 0.0)
    assert [far.act(still).accel for _ in range(3)] == pytest.approx([-1.0, MOVE_OFF_ACCEL, MOVE_OFF_ACCEL], abs=1e-5)
    for kwargs, says in (({"move_off": 0.8}, "add move_off and light_brake"), ({"light_brake": 1.0}, "add move_off"),
                         ({"move_off": 0.8, "light_brake": 1.0, "move_off_green": 2.0}, "from 0 to move_off")):
        with pytest.raises(BidError, match=says):
            BIDAgent(tmp_path / "hz" / "last.pt", **{"move_off_green": 0.2, **kwargs})
    for kwargs, says in (({"move_off": 0.8, "light_brake": 1.0}, "add move_off_green"),
                         ({"move_off": 0.8, "light_brake": 1.0, "move_off_green": 0.2, "green_far": 5.0}, "from 8 to 25")):
        with pytest.raises(BidError, match=says):
            BIDAgent(tmp_path / "hz" / "last.pt", **{"green_far": 14.0, **kwargs})
    # light_hold: creeping at 0.5 m/s up to a red light read 5 m off, the light brake asks nothing
    # (below BIND_SHARE) and the head rolls on; held, the ego stops. Read 10 m off, or at 3 m/s, as before.
    loose = BIDAgent(tmp_path / "hz" / "last.pt", light_brake=1.0)
    held = BIDAgent(tmp_path / "hz" / "last.pt", light_brake=1.0, light_hold=True)
    creeping, driving = Observation(frame, frame, 4, 0.5, None), Observation(frame, frame, 4, 3.0, None)
    for light, speed, want in ((0.8, creeping, -1.0), (0.6, creeping, 1.0), (0.8, driving, -light_brake(0.8, 3.0))):
        for agent in (loose, held):
            agent.reset(None)
            set_bias([agent], 100.0, 0.0, light)
        assert held.act(speed).accel == pytest.approx(want, abs=1e-5), (light, speed.speed_mps)
        assert loose.act(speed).accel == pytest.approx(1.0 if speed is creeping else want, abs=1e-5)
    with pytest.raises(BidError, match="add light_brake"):
        BIDAgent(tmp_path / "hz" / "last.pt", move_off=0.8, light_hold=True)
    # vehicle_hold 3 m: creeping at 0.6 m/s up to a car read 2 m off, the vehicle brake asks nothing
    # (below BIND_SHARE) and the head rolls on; held, the ego stops. Read 4 m off, or at 3 m/s, as before.
    loose = BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0)
    held = BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0, vehicle_hold=3.0)
    creeping, driving = Observation(frame, frame, 4, 0.6, None), Observation(frame, frame, 4, 3.0, None)
    for car, speed, want in ((0.92, creeping, -1.0), (0.84, creeping, 1.0), (0.92, driving, -vehicle_brake(0.92, 3.0))):
        for agent in (loose, held):
            agent.reset(None)
            set_bias([agent], 100.0, 0.0)
            with torch.no_grad():
                agent.model.hazard_head[-1].bias[1] = car
        assert held.act(speed).accel == pytest.approx(want, abs=1e-5), (car, speed.speed_mps)
        assert loose.act(speed).accel == pytest.approx(1.0 if speed is creeping else want, abs=1e-5)
    with pytest.raises(BidError, match="add vehicle_brake"):
        BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, vehicle_hold=3.0)
    with pytest.raises(BidError, match="from 0 to 8 m"):
        BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0, vehicle_hold=9.0)

    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--light-brake", "1", "--light-hold"])
    assert _drive_options(args, None) == {"light_brake": 1.0, "light_hold": True}
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--vehicle-brake", "2", "--vehicle-hold", "5"])
    assert _drive_options(args, None) == {"vehicle_brake": 2.0, "vehicle_hold": 5.0}
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--move-off-green", "0"])
    assert _drive_options(args, None) == {"move_off_green": 0.0}  # no wait is kept
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--move-off-green", "1", "--green-far", "14"])
    assert _drive_options(args, None) == {"move_off_green": 1.0, "green_far": 14.0}
    for to in (0.0, -1.0, float("nan")):
        with pytest.raises(BidError, match="move_off_to is a speed in m/s"):
            BIDAgent(tmp_path / "hz" / "last.pt", move_off=8.0, move_off_to=to)
    # A head trained before the red-light output existed: light_brake is refused, the rest drives.
    old = load_checkpoint(tmp_path / "hz" / "last.pt")
    old["config"]["model"]["hazard_light"] = False
    old["model"] = {k: (v[:2] if k.startswith("hazard_head.2.") else v) for k, v in old["model"].items()}
    save_checkpoint(tmp_path / "old.pt", old)
    BIDAgent(tmp_path / "old.pt", vehicle_brake=1.0).act(obs)
    for option in ("light_brake", "move_off"):
        with pytest.raises(BidError, match="no red-light output"):
            BIDAgent(tmp_path / "old.pt", **{option: 1.0})
    for option in ("hazard_brake", "vehicle_brake", "light_brake", "move_off", "path_memory"):
        with pytest.raises(BidError, match="no hazard head"):
            BIDAgent(checkpoint, **{option: 1.0})
    with pytest.raises(BidError, match="path_memory is read by the brakes"):
        BIDAgent(tmp_path / "hz" / "last.pt", path_memory=3.0)
    with pytest.raises(BidError, match="path_memory must be 0 or more"):
        BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0, path_memory=-1.0)
    with pytest.raises(BidError, match="pedestrian_memory is read by the pedestrian brake"):
        BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0, pedestrian_memory=3.0)
    with pytest.raises(BidError, match="keep path_memory or pedestrian_memory"):
        BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, path_memory=3.0, pedestrian_memory=3.0)
    with pytest.raises(BidError, match="pedestrian_memory must be 0 or more"):
        BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, pedestrian_memory=-1.0)
    walker = BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, vehicle_brake=1.0, pedestrian_memory=3.0)
    assert walker.memory.kinds == (0,)
    walker.act(obs)  # the vehicle brake does not hold: the memory keeps no vehicle
    with pytest.raises(BidError, match="pedestrian_hold is read by the pedestrian brake"):
        BIDAgent(tmp_path / "hz" / "last.pt", vehicle_brake=1.0, pedestrian_hold=6.0)
    for hold in (-1.0, 26.0, float("nan")):
        with pytest.raises(BidError, match="pedestrian_hold is a distance from 0 to 25 m"):
            BIDAgent(tmp_path / "hz" / "last.pt", hazard_brake=1.0, pedestrian_hold=hold)
    for flag in ("--hazard-brake", "--vehicle-brake", "--light-brake", "--move-off", "--path-memory",
                 "--pedestrian-memory", "--pedestrian-hold", "--move-off-to"):
        assert main(["evaluate", "--agent", "expert", flag, "1", "--out", str(tmp_path / "x")]) == 2
        assert f"{flag} is an option of --agent bid" in capsys.readouterr().err


def test_sc_still_makes_sc_read_frame_t_alone_and_leaves_the_control_head(checkpoint):
    """`bid evaluate --sc-still`: the shipped SC reads frame t with its change since t−1 zeroed;
    the control head reads both frames as before. A checkpoint without SC is refused."""
    import torch

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    still, plain = BIDAgent(shipped, sc_still=True), BIDAgent(shipped)
    assert still.config.model.sc_still and not plain.config.model.sc_still
    frame, prev, cmd, speed = one_input(plain.hw, seed=1, command=2, speed_mps=5.0)
    with torch.inference_mode():
        seen = still.model.forward_features(frame, prev, cmd, speed)
        assert torch.equal(seen["SC"], plain.model.forward_features(frame, frame, cmd, speed)["SC"])
        assert not torch.equal(seen["SC"], plain.model.forward_features(frame, prev, cmd, speed)["SC"])
        assert torch.equal(still.model(frame, prev, cmd, speed), plain.model(frame, prev, cmd, speed))
    with pytest.raises(BidError, match="no SC"):
        BIDAgent(checkpoint, sc_still=True)


def test_sc_still_moving_reads_sc_still_only_while_the_ego_moves(checkpoint, tmp_path, capsys):
    """`bid evaluate --sc-still-moving`: the shipped SC reads frame t alone while the ego moves
    (0.3 m/s or faster) and both frames, as trained, while it stands; the control head reads
    both frames either way. It needs SC, and is not taken with --sc-still."""
    import numpy as np
    import torch

    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 255, (300, 900, 3), dtype=np.uint8) for _ in range(2)]

    def sc_seen(agent, speed_mps):
        """SC's output on the second of two steps at speed_mps, and the control."""
        seen = []
        forward_hazard = agent.model.forward_hazard

        def spy(features, *a, **kw):
            seen.append(features["SC"].clone())
            return forward_hazard(features, *a, **kw)

        agent.model.forward_hazard = spy
        agent.reset(None)
        controls = [agent.act(Observation(f, f, 4, speed_mps, None)) for f in frames]
        return seen[-1], controls[-1]

    plain = BIDAgent(shipped, hazard_brake=1.0)
    still = BIDAgent(shipped, hazard_brake=1.0, sc_still=True)
    moving = BIDAgent(shipped, hazard_brake=1.0, sc_still_moving=True)
    for speed, like in ((5.0, still), (0.3, still), (0.29, plain), (0.0, plain)):
        got, control = sc_seen(moving, speed)
        want, want_control = sc_seen(like, speed)
        assert torch.equal(got, want) and control == want_control, speed
    assert not torch.equal(sc_seen(still, 5.0)[0], sc_seen(plain, 5.0)[0])  # the two readings differ
    assert not moving.config.model.sc_still  # the checkpoint's own reading, as loaded
    with pytest.raises(BidError, match="no SC"):
        BIDAgent(checkpoint, sc_still_moving=True)
    with pytest.raises(BidError, match="keep one"):
        BIDAgent(shipped, sc_still=True, sc_still_moving=True)
    assert main(["evaluate", "--agent", "expert", "--sc-still-moving", "--out", str(tmp_path / "x")]) == 2
    assert "--sc-still-moving is an option of --agent bid" in capsys.readouterr().err


def test_move_off_sc_waits_for_what_sc_sees_not_the_head(tmp_path, capsys):
    """`bid evaluate --move-off-sc`: a standing ego moves off while the hazard head reads a
    vehicle near and SC reads none, and waits while SC reads one; the brakes read the larger of
    the two either way. It needs move-off and SC, and is not taken with path memory."""
    import numpy as np
    import torch

    from bid_model.agent import MOVE_OFF_ACCEL, vehicle_brake
    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    frame = np.random.default_rng(4).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    agents = {"sc": BIDAgent(shipped, move_off=0.3, vehicle_brake=1.0, move_off_sc=True),
              "both": BIDAgent(shipped, move_off=0.3, vehicle_brake=1.0)}

    def see(head_vehicle: float, sc_vehicle: float) -> None:
        with torch.no_grad():
            for agent in agents.values():
                agent.model.areas["CPC"].head[-1].weight.zero_()  # the control head stands
                agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, -100.0]))
                agent.model.hazard_head[-1].weight.zero_()
                agent.model.hazard_head[-1].bias.copy_(torch.tensor([0.0, head_vehicle, 0.0]))
                agent.model.hazard_sc.priority[-1].weight.zero_()
                agent.model.hazard_sc.priority[-1].bias.copy_(torch.tensor([0.0, sc_vehicle]))
                agent.reset(None)

    still = Observation(frame, frame, 4, 0.0, None)
    see(head_vehicle=0.9, sc_vehicle=0.0)
    assert [agents["sc"].act(still).accel for _ in range(3)] == pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5)
    assert [agents["both"].act(still).accel for _ in range(3)] == pytest.approx([-1.0] * 3, abs=1e-5)
    see(head_vehicle=0.0, sc_vehicle=0.9)
    assert [agents["sc"].act(still).accel for _ in range(3)] == pytest.approx([-1.0] * 3, abs=1e-5)
    # Moving, the vehicle brake reads the larger of the two, as without move_off_sc.
    see(head_vehicle=0.0, sc_vehicle=0.0)
    with torch.no_grad():
        for agent in agents.values():
            agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, 100.0]))
            agent.model.hazard_head[-1].bias.copy_(torch.tensor([0.0, 0.7, 0.0]))
    moving = Observation(frame, frame, 4, 6.0, None)
    assert 0 < vehicle_brake(0.7, 6.0) < 1
    assert agents["sc"].act(moving).accel == pytest.approx(-vehicle_brake(0.7, 6.0), abs=1e-5)
    assert agents["both"].act(moving).accel == pytest.approx(-vehicle_brake(0.7, 6.0), abs=1e-5)
    # merge_hazard of the head's and SC's columns is the hazard output the brakes read.
    frame_t, prev, cmd, speed = one_input(agents["sc"].hw, seed=2, command=2, speed_mps=0.0)
    model = BIDAgent(shipped).model
    with torch.inference_mode():
        apart = model(frame_t, prev, cmd, speed, hazard=True, hazard_apart=True)[1]
        assert torch.equal(model.merge_hazard(apart), model(frame_t, prev, cmd, speed, hazard=True)[1])
    with pytest.raises(BidError, match="add move_off"):
        BIDAgent(shipped, vehicle_brake=1.0, move_off_sc=True)
    from bid_model.checkpoint import load_checkpoint, save_checkpoint

    blind = load_checkpoint(shipped)  # the shipped checkpoint with its SC taken out
    blind["config"]["model"]["hazard_sc"] = False
    blind["model"] = {k: v for k, v in blind["model"].items() if not k.startswith("hazard_sc.")}
    save_checkpoint(tmp_path / "no_sc.pt", blind)
    assert BIDAgent(tmp_path / "no_sc.pt", move_off=8.0).move_off_steps == 80
    with pytest.raises(BidError, match="no SC for move_off_sc"):
        BIDAgent(tmp_path / "no_sc.pt", move_off=8.0, move_off_sc=True)
    with pytest.raises(BidError, match="keep one"):
        BIDAgent(shipped, move_off=8.0, move_off_sc=True, path_memory=2.0)
    assert main(["evaluate", "--agent", "expert", "--move-off-sc", "--out", str(tmp_path / "x")]) == 2
    assert "--move-off-sc is an option of --agent bid" in capsys.readouterr().err


def test_a_move_off_head_decides_moving_off_and_the_first_head_braking(tmp_path, two_heads):
    """A checkpoint with a move-off head (`bid train --move-off-head`): a standing ego moves off
    while only the first hazard head reads a vehicle near, and waits while the move-off head
    reads one, or while the first head reads a red light near; moving, the brakes read the first
    head alone. The head reads MPC merged without the speed token, so the speed does not change
    what it says."""
    import numpy as np
    import torch

    from bid_model.agent import MOVE_OFF_ACCEL, vehicle_brake
    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    two_heads(speed=False)  # the shipped network with its head copied as the move-off head
    agent = BIDAgent(tmp_path / "two.pt", move_off=0.3, vehicle_brake=1.0)
    frame = np.random.default_rng(4).integers(0, 255, (300, 900, 3), dtype=np.uint8)

    def see(first: float, move_off: float, accel: float, light: tuple[float, float] = (0.0, 0.0)) -> None:
        with torch.no_grad():
            agent.model.areas["CPC"].head[-1].weight.zero_()
            agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, accel]))
            agent.model.hazard_sc.priority[-1].weight.zero_()  # SC sees nothing
            agent.model.hazard_sc.priority[-1].bias.zero_()
            for head, vehicle, red in ((agent.model.hazard_head, first, light[0]),
                                       (agent.model.hazard_move_off, move_off, light[1])):
                head[-1].weight.zero_()
                head[-1].bias.copy_(torch.tensor([0.0, vehicle, red]))
        agent.reset(None)

    still = Observation(frame, frame, 4, 0.0, None)
    see(first=0.9, move_off=0.0, accel=-100.0)
    assert [agent.act(still).accel for _ in range(3)] == pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5)
    see(first=0.0, move_off=0.9, accel=-100.0)
    assert [agent.act(still).accel for _ in range(3)] == pytest.approx([-1.0] * 3, abs=1e-5)
    see(first=0.0, move_off=0.0, accel=-100.0, light=(0.9, 0.0))  # the red light is the first head's
    assert [agent.act(still).accel for _ in range(3)] == pytest.approx([-1.0] * 3, abs=1e-5)
    see(first=0.0, move_off=0.0, accel=-100.0, light=(0.0, 0.9))
    assert [agent.act(still).accel for _ in range(3)] == pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5)
    moving = Observation(frame, frame, 4, 6.0, None)
    see(first=0.7, move_off=0.0, accel=100.0)
    assert agent.act(moving).accel == pytest.approx(-vehicle_brake(0.7, 6.0), abs=1e-5)
    see(first=0.0, move_off=0.7, accel=100.0)
    assert agent.act(moving).accel == pytest.approx(1.0, abs=1e-5)
    # The move-off head's output is its own, read from MPC without the speed; SC merged in.
    model = BIDAgent(tmp_path / "two.pt").model
    outs = []
    for speed_mps in (0.0, 7.0):
        frame_t, prev, cmd, speed = one_input(agent.hw, seed=2, command=2, speed_mps=speed_mps)
        with torch.inference_mode():
            feats = model.forward_features(frame_t, prev, cmd, speed)
            _, first, second = model(frame_t, prev, cmd, speed, hazard=True, move_off=True)
            assert torch.equal(first, model.forward_hazard(feats))
            own = model.hazard_move_off(feats["MPC_speedless"].mean(1))
            assert torch.allclose(second, model.merge_hazard(torch.cat([own, feats["SC"]], dim=1)))
        outs.append(second)
    assert torch.allclose(outs[0], outs[1], atol=1e-6)
    with pytest.raises(BidError, match="no move-off head"):
        BIDAgent(shipped).model(frame_t, prev, cmd, speed, hazard=True, move_off=True)


def test_move_off_light_waits_for_the_move_off_heads_red_light_and_the_first_heads_path(tmp_path, two_heads):
    """With `move_off_light` (a move-off head reading the speed, `bid train --move-off-head
    --move-off-speed`), move-off waits for the move-off head's red light and the first head's
    pedestrian and vehicle; the brakes still read the first head."""
    import numpy as np
    import torch

    from bid_model.agent import MOVE_OFF_ACCEL
    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    two_heads()
    agent = BIDAgent(tmp_path / "two.pt", move_off=0.3, move_off_light=True)
    frame = np.random.default_rng(4).integers(0, 255, (300, 900, 3), dtype=np.uint8)

    def see(first: tuple[float, float], second: tuple[float, float]) -> list[float]:
        """(vehicle, red light) each head reads; the control head brakes hard: three steps' accel."""
        with torch.no_grad():
            agent.model.areas["CPC"].head[-1].weight.zero_()
            agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, -100.0]))
            agent.model.hazard_sc.priority[-1].weight.zero_()  # SC sees nothing
            agent.model.hazard_sc.priority[-1].bias.zero_()
            for head, (vehicle, red) in ((agent.model.hazard_head, first), (agent.model.hazard_move_off, second)):
                head[-1].weight.zero_()
                head[-1].bias.copy_(torch.tensor([0.0, vehicle, red]))
        agent.reset(None)
        still = Observation(frame, frame, 4, 0.0, None)
        return [agent.act(still).accel for _ in range(3)]

    moves, waits = pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5), pytest.approx([-1.0] * 3, abs=1e-5)
    assert see(first=(0.0, 0.9), second=(0.0, 0.0)) == moves  # the first head's red light is not read
    assert see(first=(0.0, 0.0), second=(0.0, 0.9)) == waits  # the move-off head's is
    assert see(first=(0.0, 0.0), second=(0.9, 0.0)) == moves  # its vehicle is not
    assert see(first=(0.9, 0.0), second=(0.0, 0.0)) == waits  # the first head's is
    # The move-off head reads MPC with the speed token, as the first head does.
    model = BIDAgent(tmp_path / "two.pt").model
    frame_t, prev, cmd, speed = one_input(agent.hw, seed=2, command=2, speed_mps=3.0)
    with torch.inference_mode():
        feats = model.forward_features(frame_t, prev, cmd, speed)
        _, first, second = model(frame_t, prev, cmd, speed, hazard=True, move_off=True)
    assert "MPC_speedless" not in feats and torch.equal(first, second)  # the same weights, the same input
    with pytest.raises(BidError, match="add move_off"):
        BIDAgent(tmp_path / "two.pt", move_off_light=True)
    with pytest.raises(BidError, match="has none"):
        BIDAgent(shipped, move_off=8, move_off_light=True)


def test_vehicle_second_head_brakes_and_moves_off_by_the_second_heads_vehicle(tmp_path, two_heads):
    """With `vehicle_second_head` (a second head refitted for vehicles near a moving ego), the
    vehicle brake and move-off read that head's vehicle; the pedestrian and red light still the
    first head's."""
    import numpy as np
    import torch

    from bid_model.agent import MOVE_OFF_ACCEL
    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    two_heads()
    frame = np.random.default_rng(5).integers(0, 255, (300, 900, 3), dtype=np.uint8)

    def drive(agent: BIDAgent, first: tuple[float, ...], second: tuple[float, ...], speed: float,
              control_accel: float) -> list[float]:
        """(pedestrian, vehicle, red light) each head reads: three steps' accel at `speed`."""
        with torch.no_grad():
            agent.model.areas["CPC"].head[-1].weight.zero_()
            agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, control_accel]))
            agent.model.hazard_sc.priority[-1].weight.zero_()  # SC sees nothing
            agent.model.hazard_sc.priority[-1].bias.zero_()
            for head, near in ((agent.model.hazard_head, first), (agent.model.hazard_move_off, second)):
                head[-1].weight.zero_()
                head[-1].bias.copy_(torch.tensor(near))
        agent.reset(None)
        obs = Observation(frame, frame, 4, speed, None)
        return [agent.act(obs).accel for _ in range(3)]

    brakes = BIDAgent(tmp_path / "two.pt", vehicle_brake=1, hazard_brake=1, light_brake=1, vehicle_second_head=True)
    assert min(drive(brakes, (0.0, 0.0, 0.0), (0.0, 0.9, 0.0), 6.0, 100.0)) < -0.5  # its vehicle
    assert drive(brakes, (0.0, 0.9, 0.0), (0.0, 0.0, 0.0), 6.0, 100.0) == pytest.approx([1.0] * 3)  # not the first's
    assert min(drive(brakes, (0.9, 0.0, 0.0), (0.0, 0.0, 0.0), 6.0, 100.0)) < -0.5  # the first's pedestrian
    assert min(drive(brakes, (0.0, 0.0, 0.9), (0.0, 0.0, 0.0), 6.0, 100.0)) < -0.5  # and red light
    assert drive(brakes, (0.0, 0.0, 0.0), (0.9, 0.0, 0.9), 6.0, 100.0) == pytest.approx([1.0] * 3)  # not its
    mover = BIDAgent(tmp_path / "two.pt", move_off=0.3, vehicle_second_head=True)
    moves, waits = pytest.approx([-1.0, -1.0, MOVE_OFF_ACCEL], abs=1e-5), pytest.approx([-1.0] * 3, abs=1e-5)
    assert drive(mover, (0.0, 0.9, 0.0), (0.0, 0.0, 0.0), 0.0, -100.0) == moves
    assert drive(mover, (0.0, 0.0, 0.0), (0.0, 0.9, 0.0), 0.0, -100.0) == waits
    assert drive(mover, (0.0, 0.0, 0.9), (0.0, 0.0, 0.0), 0.0, -100.0) == waits
    for kwargs, says in (({"vehicle_brake": 1}, None), ({"move_off": 8, "move_off_light": True}, "keep one"),
                         ({}, "add vehicle_brake or move_off")):
        with pytest.raises(BidError, match=says or "has none"):
            BIDAgent(shipped if says is None else tmp_path / "two.pt", vehicle_second_head=True, **kwargs)


def test_light_still_reads_the_red_light_from_frame_t_alone_below_start_speed(tmp_path, two_heads, capsys):
    """`bid evaluate --light-still`: below START_MPS the red light the light brake and move-off read
    is the first head's on frame t paired with itself; the pedestrian and vehicle, the control
    head and, at START_MPS or faster, the red light too are read from both frames as before."""
    import numpy as np
    import torch

    from bid_model.agent import START_MPS, light_brake
    from bid_sim.agents import Observation

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    still = BIDAgent(shipped, light_brake=1, move_off=8, light_still=True)
    plain = BIDAgent(shipped, light_brake=1, move_off=8)
    rng = np.random.default_rng(6)
    prev_img, img = (rng.integers(0, 255, (300, 900, 3), dtype=np.uint8) for _ in range(2))
    for speed in (0.0, 1.5, START_MPS, 5.0):
        controls = []
        for agent in (still, plain):
            agent.reset(None)
            agent.act(Observation(prev_img, prev_img, 3, speed, None))
            controls.append(agent.act(Observation(img, img, 3, speed, None)))
        frame, prev, cmd, _ = still._inputs
        v = torch.tensor([speed])
        with torch.inference_mode():
            _, pair = plain.model(frame, prev, cmd, v, hazard=True)
            _, alone = plain.model(frame, frame, cmd, v, hazard=True)
        assert not torch.allclose(pair[0, 2], alone[0, 2])
        assert still.near[:2] == pytest.approx(plain.near[:2])
        assert plain.near[:2] == pytest.approx(pair[0, :2].tolist())
        light = alone if speed < START_MPS else pair
        assert still.near[2] == pytest.approx(float(light[0, 2]))
        assert plain.near[2] == pytest.approx(float(pair[0, 2]))
        assert still.head_accel == pytest.approx(plain.head_accel)
        need = light_brake(float(light[0, 2]), speed)
        brake = min(still.head_accel, -need) if need > 0 else still.head_accel
        assert controls[0].accel == pytest.approx(max(brake, -1.0))
    two_heads()
    for path, kwargs, says in ((shipped, {}, "add light_brake or move_off"),
                               (tmp_path / "two.pt", {"move_off": 8, "move_off_light": True}, "keep one")):
        with pytest.raises(BidError, match=says):
            BIDAgent(path, light_still=True, **kwargs)
    assert main(["evaluate", "--agent", "expert", "--light-still", "--out", str(tmp_path / "x")]) == 2
    assert "--light-still is an option of --agent bid" in capsys.readouterr().err

    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--light-still", "--light-short", "0"])
    assert _drive_options(args, None) == {"light_still": True, "light_short": 0.0}  # a gap of 0 is kept


def test_a_grafted_fine_sc_brakes_for_its_pedestrian_only_while_moving(tmp_path, capsys):
    """`bid graft` of the shipped checkpoint with a second SC at 2× (sp40b's kind): the agent
    prepares frames twice as fine, and the pedestrian brake reads the fine SC's pedestrian while
    the ego moves (0.3 m/s or faster), not while it stands; its vehicle is not read. Then the
    drive options that read it: --fine-logit, --fine-speed, --fine-caution."""
    import numpy as np
    import torch

    from bid_model.agent import CAUTION_STOP_M, caution_brake, pedestrian_brake
    from bid_model.checkpoint import load_checkpoint, save_checkpoint
    from bid_model.config import RunConfig
    from bid_model.hazards import HAZARD_AHEAD_M
    from bid_model.model import BID
    from bid_sim.agents import Observation
    from bid_sim.ego import EgoParams

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    donor = load_checkpoint(shipped)  # the shipped network with a fresh SC at 2×, with presence
    donor["config"]["model"] = {**donor["config"]["model"], "sc_scale": 2, "sc_presence": True}
    torch.manual_seed(0)
    fresh = BID(RunConfig.from_dict(donor["config"]).model).state_dict()
    donor["model"] = {**donor["model"], **{k: v for k, v in fresh.items() if k.startswith("hazard_sc.")}}
    save_checkpoint(tmp_path / "donor.pt", donor)
    assert main(["graft", str(shipped), "--fine-sc", str(tmp_path / "donor.pt"), "--out", str(tmp_path / "g.pt")]) == 0
    assert "at 2x the cortex's resolution (input 128x384)" in capsys.readouterr().out
    agent = BIDAgent(tmp_path / "g.pt", hazard_brake=1.0)
    assert agent.hw == (128, 384)
    with torch.no_grad():  # the control head accelerates; only the fine SC sees anything
        agent.model.areas["CPC"].head[-1].weight.zero_()
        agent.model.areas["CPC"].head[-1].bias.copy_(torch.tensor([0.0, 100.0]))
        agent.model.hazard_head[-1].weight.zero_()
        agent.model.hazard_head[-1].bias.zero_()
        agent.model.hazard_sc.priority[-1].weight.zero_()
        agent.model.hazard_sc.priority[-1].bias.zero_()
        agent.model.hazard_sc_fine.priority[-1].weight.zero_()
        agent.model.hazard_sc_fine.priority[-1].bias.copy_(torch.tensor([0.9, 0.9, 5.0, 5.0]))
    frame = np.random.default_rng(5).integers(0, 255, (300, 900, 3), dtype=np.uint8)
    for speed, brake in ((6.0, pedestrian_brake(0.9, 6.0)), (0.3, pedestrian_brake(0.9, 0.3)),
                         (0.29, 0.0), (0.0, 0.0)):
        agent.reset(None)
        accel = agent.act(Observation(frame, frame, 4, speed, None)).accel
        assert accel == (pytest.approx(-brake, abs=1e-5) if brake > 0 else pytest.approx(1.0)), speed
        assert agent.near[1] == 0.0  # the fine SC's vehicle is not read
    assert pedestrian_brake(0.9, 0.3) > 0

    # `bid evaluate --fine-logit T`: the fine SC's pedestrian counts only where its logit (5 here) is above T;
    # the first SC's threshold is its own (sc_logit) and a checkpoint without a fine SC takes none.
    for logit, brake in ((4.9, pedestrian_brake(0.9, 6.0)), (5.1, 0.0)):
        surer = BIDAgent(tmp_path / "g.pt", hazard_brake=1.0, fine_logit=logit)
        surer.model.load_state_dict(agent.model.state_dict())
        assert surer.model.config.fine_logit == logit and surer.model.config.sc_logit == 0.0
        surer.reset(None)
        accel = surer.act(Observation(frame, frame, 4, 6.0, None)).accel
        assert accel == (pytest.approx(-brake, abs=1e-5) if brake > 0 else pytest.approx(1.0)), logit
    for checkpoint, logit, says in ((shipped, 1.0, "has no fine SC"), (tmp_path / "g.pt", -10.5, "from -10 to 10")):
        with pytest.raises(BidError, match=says):
            BIDAgent(checkpoint, fine_logit=logit)
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--fine-logit", "0.5", "--fine-speed", "0"])
    assert _drive_options(args, None) == {"fine_logit": 0.5, "fine_speed": 0.0}  # from standing: kept

    # `bid evaluate --fine-speed MPS`: the fine SC's pedestrian counts only at MPS or faster.
    for speed, fine_speed, brake in ((6.0, 3.0, pedestrian_brake(0.9, 6.0)), (2.9, 3.0, 0.0),
                                     (0.0, 0.0, pedestrian_brake(0.9, 0.0))):
        later = BIDAgent(tmp_path / "g.pt", hazard_brake=1.0, fine_speed=fine_speed)
        later.model.load_state_dict(agent.model.state_dict())
        later.reset(None)
        accel = later.act(Observation(frame, frame, 4, speed, None)).accel
        assert accel == (pytest.approx(-brake, abs=1e-5) if brake > 0 else pytest.approx(1.0)), (speed, fine_speed)
    for checkpoint, fine_speed, says in ((shipped, 3.0, "no fine SC read while moving"),
                                         (tmp_path / "g.pt", 16.0, "from 0 to 15 m/s")):
        with pytest.raises(BidError, match=says):
            BIDAgent(checkpoint, fine_speed=fine_speed)

    # `bid evaluate --fine-caution MPS`: the fine SC's pedestrian leaves the merge; read within
    # CAUTION_STOP_M she is stopped for as before, farther the ego is only slowed to MPS by where
    # she is read (caution_brake), and not at all at MPS or slower.
    far = 1.0 - 17.5 / HAZARD_AHEAD_M  # 0.3
    assert caution_brake(far, 6.0, 3.0) == pytest.approx((36.0 - 9.0) / (2 * 15.5) / EgoParams.max_brake_mps2)
    assert caution_brake(far, 6.0, 3.0) < pedestrian_brake(far, 6.0)  # slowed for, not stopped for
    assert caution_brake(far, 3.0, 3.0) == 0.0 and caution_brake(0.1, 9.0, 3.0) == 0.0  # unseen below 0.2
    near = 1.0 - 4.0 / HAZARD_AHEAD_M
    assert CAUTION_STOP_M >= 4.0 and caution_brake(near, 2.0, 3.0) == pytest.approx(pedestrian_brake(near, 2.0, 0.0))
    assert caution_brake(near, 0.0, 3.0) == 0.0  # it does not hold a standing ego (the fine SC is not read then)
    for fine_at, speed, brake in ((far, 6.0, caution_brake(far, 6.0, 3.0)), (far, 2.5, 0.0),
                                  (0.9, 6.0, pedestrian_brake(0.9, 6.0)), (0.9, 0.0, 0.0)):
        careful = BIDAgent(tmp_path / "g.pt", hazard_brake=1.0, fine_caution=3.0)
        careful.model.load_state_dict(agent.model.state_dict())
        with torch.no_grad():
            careful.model.hazard_sc_fine.priority[-1].bias[0] = fine_at
        careful.reset(None)
        accel = careful.act(Observation(frame, frame, 4, speed, None)).accel
        assert accel == (pytest.approx(-brake, abs=1e-5) if brake > 0 else pytest.approx(1.0)), (fine_at, speed)
        assert careful.near[0] == 0.0  # the merge the other brakes read holds no fine SC
    for checkpoint, options, says in ((shipped, {"hazard_brake": 1.0}, "no fine SC read while moving"),
                                      (tmp_path / "g.pt", {}, "add hazard_brake"),
                                      (tmp_path / "g.pt", {"hazard_brake": 1.0, "fine_caution": -1.0}, "0 \\(off\\)")):
        with pytest.raises(BidError, match=says):
            BIDAgent(checkpoint, **{"fine_caution": 3.0, **options})
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--fine-caution", "3"])
    assert _drive_options(args, None) == {"fine_caution": 3.0}
    assert _drive_options(build_parser().parse_args(["evaluate", "--fine-caution", "0"]), None) is None
