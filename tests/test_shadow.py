"""The shadow probe: a real (tiny, briefly trained) BID drives through SUMO while the expert
labels alongside; the probe must not change how the BID drives."""

import dataclasses
import importlib.util
from pathlib import Path

import pytest

from bid_model.agent import BIDAgent
from bid_model.config import tiny
from bid_model.shadow import ShadowStep, probe_episode, tally, window
from bid_model.train import train
from bid_sim.episode import run_episode
from bid_sim.render import Renderer
from bid_sim.town_map import load_town_map

STEPS = 12


@pytest.fixture(scope="module")
def speed_checkpoint(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    cfg = tiny()
    cfg = type(cfg)(dataclasses.replace(cfg.model, speed_input=True), cfg.train.with_epochs(1))
    train(out, cfg, synthetic=True, progress=False)
    return out / "last.pt"


class Spy(BIDAgent):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.controls = []

    def act(self, obs):
        c = super().act(obs)
        self.controls.append((c.steer, c.accel))
        return c


def test_the_bid_drives_as_without_the_probe(speed_checkpoint, town02, one_thread):
    result, steps = probe_episode(speed_checkpoint, "02", 0, "WetSunset", "normal", 0, max_steps=STEPS,
                                  probe_speeds=(0.0, 5.0))
    alone = Spy(speed_checkpoint)
    run_episode(town02, 0, "WetSunset", "normal", 0, alone, replan=True, max_steps=STEPS,
                renderer=Renderer(load_town_map(town02), weather="WetSunset", seed=0))
    assert result.steps == len(steps) == STEPS
    assert [s.bid for s in steps] == alone.controls
    assert all(-1.0 <= a <= 1.0 for s in steps for a in s.expert) and all(s.reason for s in steps)
    assert [s.step for s in steps] == list(range(STEPS))
    # The ego starts at rest: the network asked at 0 m/s answers what it did at the start.
    assert steps[0].speed_mps == 0.0 and steps[0].accel_at[0] == pytest.approx(steps[0].bid[1], abs=1e-5)
    assert all(len(s.accel_at) == 2 for s in steps)


def test_the_bid_drives_with_the_runs_drive_options_and_its_brakes_inputs_are_logged(town02, one_thread):
    """With `options` (a run's drive options) the BID drives as `bid evaluate` drove it; each step
    keeps the control head's accel, the nearness the brakes read and the ego's lateral offset."""
    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    options = {"vehicle_brake": 2.0, "light_brake": 1.0, "move_off": 8.0, "hazard_brake": 1.0, "max_speed": 0.5}
    result, steps = probe_episode(shipped, "02", 0, "WetSunset", "normal", 0, max_steps=30, probe_speeds=(0.0,),
                                  options=options)
    alone = Spy(shipped, **options)
    run_episode(town02, 0, "WetSunset", "normal", 0, alone, replan=True, max_steps=30,
                renderer=Renderer(load_town_map(town02), weather="WetSunset", seed=0))
    assert [s.bid for s in steps] == alone.controls
    assert all(len(s.near) == 3 and s.head_accel is not None for s in steps)
    assert result.steps == 30 and all(isinstance(s.lateral_m, float) and abs(s.lateral_m) < 2.0 for s in steps)
    # Above the 0.5 m/s cap the accel driven is the cap's braking, whatever the control head asks.
    capped = [s for s in steps if s.speed_mps > 0.6]
    assert capped and all(s.bid[1] < -0.05 and s.bid[1] <= s.head_accel for s in capped)
    assert any(s.head_accel > 0.0 for s in capped)
    _, plain = probe_episode(shipped, "02", 0, "WetSunset", "normal", 0, max_steps=30, probe_speeds=(0.0,))
    assert all(s.near == () for s in plain) and max(s.speed_mps for s in plain) > 1.5


def test_without_speed_input_nothing_is_asked(town02, one_thread, tmp_path):
    cfg = tiny()
    train(tmp_path, type(cfg)(cfg.model, cfg.train.with_epochs(1)), synthetic=True, progress=False)
    _, steps = probe_episode(tmp_path / "last.pt", "02", 0, "ClearNoon", "none", 0, max_steps=2)
    assert [s.accel_at for s in steps] == [(), ()]


def _step(t, v, bid_accel, expert_accel, accel_at=()):
    return ShadowStep(int(t * 10), t, v, (0.0, bid_accel), (0.0, expert_accel), "vehicle veh1", accel_at)


def test_tally_and_window():
    steps = [_step(1.0, 5.0, 0.5, -0.5, (0.6, 0.4, -0.3)),  # drove on; brakes at 8 m/s: speed-led
             _step(1.1, 5.0, 0.5, -0.5, (0.6, 0.4, 0.3)),  # drove on whatever the speed
             _step(1.2, 5.0, -0.3, -0.5, (0.6, 0.4, -0.3)),  # braked too
             _step(1.3, 5.0, 0.5, 0.2, (0.6, 0.4, -0.3))]  # the expert did not brake
    assert tally(steps, (0.0, 4.0, 8.0)) == {"steps": 4, "expert_braked": 3, "bid_braked": 1, "bid_braked_hard": 0,
                                            "bid_drove_on": 2, "speed_led": 1}
    assert [s.time_s for s in window(steps, 1.25, 0.2)] == [1.1, 1.2]


def test_tool_refuses_a_folder_that_is_not_an_evaluation(tmp_path, capsys):
    path = Path(__file__).resolve().parents[1] / "tools" / "probe_contacts.py"
    spec = importlib.util.spec_from_file_location("probe_contacts", path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.main([str(tmp_path)]) == 2
    assert "not a bid evaluate folder" in capsys.readouterr().err
