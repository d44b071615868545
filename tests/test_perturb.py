"""Recovery data: Perturbed steers the car off now and then while the label stays the
expert's, and the episode records the label, not what the car executed."""

import numpy as np
import pytest

from bid_sim.agents import EpisodeInfo, Observation, Scripted
from bid_sim.ego import Control, EgoParams
from bid_sim.episode import run_episode
from bid_sim.errors import BidError
from bid_sim.expert import Expert
from bid_sim.perturb import PULSE_STEER, Perturbed


def _info(seed: int) -> EpisodeInfo:
    return EpisodeInfo("Town02", 0, "ClearNoon", "none", seed, None, EgoParams())


def _drive(agent: Perturbed, seed: int, steps: int, speed: float) -> tuple[list[Control], list[bool]]:
    agent.reset(_info(seed))
    out, flags = [], []
    for _ in range(steps):
        out.append(agent.act(Observation(None, None, 4, speed, None)))
        flags.append(agent.perturbed)
    return out, flags


def test_pulses_take_their_share_and_labels_stay_clean():
    inner = Scripted(lambda step, obs: Control(0.05, 0.3))
    agent = Perturbed(inner, 0.2)
    executed, flags = _drive(agent, seed=7, steps=4000, speed=6.0)
    assert agent.label == Control(0.05, 0.3)
    offsets = np.array([c.steer - 0.05 for c in executed])
    assert 0.15 < np.mean(flags) < 0.25
    assert np.all(np.abs(offsets[~np.array(flags)]) < 1e-12)
    assert 0.05 < np.abs(offsets).max() <= PULSE_STEER[1] + 1e-9
    assert (offsets > 0.01).any() and (offsets < -0.01).any()  # both directions
    assert all(c.accel == 0.3 for c in executed)


def test_no_pulses_when_slow_and_same_seed_same_noise():
    agent = Perturbed(Scripted(lambda step, obs: Control(0.0, 0.0)), 0.3)
    _, slow = _drive(agent, seed=1, steps=500, speed=1.0)
    assert not any(slow)
    a, _ = _drive(agent, seed=2, steps=300, speed=5.0)
    b, _ = _drive(agent, seed=2, steps=300, speed=5.0)
    c, _ = _drive(agent, seed=3, steps=300, speed=5.0)
    assert a == b and a != c


@pytest.mark.parametrize("share", [-0.1, 1.0])
def test_bad_share_is_refused(share):
    with pytest.raises(BidError, match="perturb"):
        Perturbed(Expert(), share)


class _Labels:
    """A recorder that keeps what the episode writes."""

    def __init__(self):
        self.controls = []

    def write(self, snap, frame, control):
        self.controls.append(control)


def test_episode_records_the_experts_label_not_the_executed_control(town02):
    agent = Perturbed(Expert(), 0.5)
    labels, executed = _Labels(), []
    act = agent.act

    def spy(obs):
        c = act(obs)
        executed.append((c, agent.label))
        return c

    agent.act = spy
    run_episode(town02, 0, "ClearNoon", "none", 4, agent, recorder=labels, max_steps=120)
    assert labels.controls == [label for _, label in executed]
    assert any(c != label for c, label in executed)  # the car was pushed at least once
