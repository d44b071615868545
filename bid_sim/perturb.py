"""Perturbed demonstrations: the expert drives, noise steers, the expert's answer is the label.

A policy trained only on clean expert driving never sees the car off the lane centre, so
in closed loop a small error grows (covariate shift). As in conditional imitation
learning (Codevilla et al., 2018), `Perturbed` adds short triangular steering pulses to
what the car executes, while the recorded label stays the expert's own control, which
steers back: the recordings then hold recoveries. Pulses start at random (seeded by the
episode), only above a walking pace, and take about `share` of the driving time.
"""

from __future__ import annotations

import numpy as np

from bid_sim.agents import Agent, EpisodeInfo, Observation
from bid_sim.ego import Control
from bid_sim.errors import BidError

PULSE_STEPS = (5, 16)  # duration, 0.5 to 1.5 s at 10 Hz
PULSE_STEER = (0.1, 0.35)  # peak steering offset
MIN_SPEED_MPS = 2.0


class Perturbed:
    """Wraps an agent: executes its control plus a steering pulse now and then.

    `label` is the wrapped agent's own control of the last step; the episode records it
    instead of the executed control. `perturbed` says whether a pulse was on.
    """

    def __init__(self, agent: Agent, share: float):
        if not 0.0 <= share < 1.0:
            raise BidError(f"--perturb must be a share of time in [0, 1), got {share}")
        self.agent, self.share = agent, share
        mean_steps = sum(PULSE_STEPS) / 2
        self._start_p = share / (mean_steps * (1.0 - share)) if share else 0.0
        self._rng = np.random.default_rng(0)
        self._pulse: np.ndarray | None = None
        self._at = 0
        self.label: Control | None = None
        self.perturbed = False

    def reset(self, info: EpisodeInfo) -> None:
        self.agent.reset(info)
        self._rng = np.random.default_rng((info.seed, 0x9E27))
        self._pulse, self._at = None, 0
        self.label, self.perturbed = None, False

    def act(self, obs: Observation) -> Control:
        control = self.agent.act(obs)
        self.label = control
        # The draws happen every step, so the noise depends on the seed and the step only.
        start, steps, peak, sign = (self._rng.random(), self._rng.integers(*PULSE_STEPS),
                                    self._rng.uniform(*PULSE_STEER), self._rng.choice((-1.0, 1.0)))
        if self._pulse is None and obs.speed_mps > MIN_SPEED_MPS and start < self._start_p:
            ramp = 1.0 - np.abs(np.linspace(-1.0, 1.0, int(steps) + 2)[1:-1])  # triangle, no zero ends
            self._pulse, self._at = sign * peak * ramp, 0
        self.perturbed = self._pulse is not None
        if self._pulse is None:
            return control
        offset = float(self._pulse[self._at])
        self._at += 1
        if self._at == len(self._pulse):
            self._pulse = None
        return Control(float(np.clip(control.steer + offset, -1.0, 1.0)), control.accel)
