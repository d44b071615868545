"""The BID drives, the expert labels alongside: what each would do at every step.

A closed-loop failure says where the BID went wrong, not how. `Shadow` puts a checkpoint
in control and runs the expert (which reads the privileged snapshot) beside it, without
letting it act, and logs both controls and the reason the expert gives. For a model with
a speed input it also asks the network, on the same frames, what it would do at other
speeds: a network that brakes at 8 m/s and accelerates at 4 m/s in front of the same car
is regulating a speed it reads off the scene, not seeing how close the car is.
Episodes are deterministic per seed, so a run of `bid evaluate` replays exactly
(`tools/probe_contacts.py` picks its failed episodes and prints the seconds before each
first contact).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from bid_model.agent import BIDAgent
from bid_sim.agents import EpisodeInfo, Observation
from bid_sim.ego import Control

# Speed inputs (m/s) the network is asked about at every step, besides the measured one.
PROBE_SPEEDS: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0)
EXPERT_BRAKES = -0.2  # an expert accel at or below this is braking for something
BID_GOES = 0.1  # a BID accel above this is driving on


@dataclass(frozen=True)
class ShadowStep:
    """One step: the BID's control (which drove) and the expert's (which did not)."""

    step: int
    time_s: float
    speed_mps: float
    bid: tuple[float, float]  # steer, accel
    expert: tuple[float, float]
    reason: str  # what bound the expert's speed: "speed", "vehicle veh12", "red light", ...
    accel_at: tuple[float, ...]  # the BID's accel at PROBE_SPEEDS; () without a speed input
    head_accel: float | None = None  # the control head's accel, before the brakes and move-off
    near: tuple[float, ...] = ()  # the hazard nearness the brakes read (BIDAgent.near); () for none
    lateral_m: float = 0.0  # the ego's offset from the route's centre line (+ left)


class Shadow:
    """A BID checkpoint drives (with `options`, BIDAgent's drive options, as `bid evaluate`
    passes them); the expert labels the same observations and is logged."""

    uses_camera = True

    def __init__(self, checkpoint: str | Path, town: str, probe_speeds: tuple[float, ...] = PROBE_SPEEDS,
                 options: dict | None = None):
        from bid_sim.expert import Expert

        self.bid = BIDAgent(checkpoint, **(options or {}))
        self.expert = Expert(town=town)
        self.probe_speeds = probe_speeds if self.bid.config.model.speed_input else ()
        self.steps: list[ShadowStep] = []

    def reset(self, info: EpisodeInfo) -> None:
        self.bid.reset(info)
        self.expert.reset(info)
        self.steps = []

    def act(self, obs: Observation) -> Control:
        mine = self.bid.act(obs)
        label = self.expert.act(obs)
        self.steps.append(ShadowStep(len(self.steps), round(obs.snapshot.time_s, 2), float(obs.speed_mps),
                                     (mine.steer, mine.accel), (label.steer, label.accel),
                                     self.expert.reason, self._accel_at(), self.bid.head_accel,
                                     tuple(round(x, 3) for x in self.bid.near),
                                     float(obs.snapshot.ego.lateral_m)))
        return mine

    @torch.inference_mode()
    def _accel_at(self) -> tuple[float, ...]:
        if not self.probe_speeds:
            return ()
        frame, prev, cmd, _ = self.bid._inputs
        n = len(self.probe_speeds)
        out = self.bid.model(frame.expand(n, -1, -1, -1), prev.expand(n, -1, -1, -1), cmd.expand(n, -1),
                             torch.tensor(self.probe_speeds, dtype=torch.float32))
        return tuple(float(a) for a in out[:, 1])


def probe_episode(checkpoint: str | Path, town: str, route: int, weather: str, density: str, seed: int,
                  max_steps: int | None = None, probe_speeds: tuple[float, ...] = PROBE_SPEEDS,
                  options: dict | None = None):
    """(EpisodeResult, [ShadowStep]) of one episode as `bid evaluate` runs it (re-planning on), the
    BID driving with `options` (the drive options of the run, its config.json's "options")."""
    from bid_sim.episode import run_episode
    from bid_sim.render import Renderer
    from bid_sim.town_map import load_town_map
    from bid_sim.towns import resolve_town

    t = resolve_town(town)
    agent = Shadow(checkpoint, t.name, probe_speeds, options)
    renderer = Renderer(load_town_map(t), weather=weather, seed=seed)
    result = run_episode(t, route, weather, density, seed, agent, renderer=renderer, replan=True,
                         max_steps=max_steps)
    return result, agent.steps


def window(steps: list[ShadowStep], until_s: float, seconds: float) -> list[ShadowStep]:
    """The steps of the `seconds` up to and including time `until_s`."""
    return [s for s in steps if until_s - seconds <= s.time_s <= until_s]


def tally(steps: list[ShadowStep], probe_speeds: tuple[float, ...] = PROBE_SPEEDS) -> dict[str, int]:
    """How the BID answered where the expert braked: steps the expert braked; of those, the
    BID braked too (as hard as EXPERT_BRAKES), braked hard (−0.5 or harder), drove on; and of
    those it drove on, it would have braked at a higher speed input ("speed_led")."""
    braked = [s for s in steps if s.expert[1] <= EXPERT_BRAKES]
    went = [s for s in braked if s.bid[1] > BID_GOES]
    led = [s for s in went if s.accel_at and any(
        a <= -BID_GOES for v, a in zip(probe_speeds, s.accel_at, strict=True) if v > s.speed_mps)]
    return {"steps": len(steps), "expert_braked": len(braked),
            "bid_braked": sum(s.bid[1] <= EXPERT_BRAKES for s in braked),
            "bid_braked_hard": sum(s.bid[1] <= -0.5 for s in braked),
            "bid_drove_on": len(went), "speed_led": len(led)}
