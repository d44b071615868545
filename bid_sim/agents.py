"""The Agent protocol and simple scripted agents (for tests and until the expert lands)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from bid_sim.ego import Control, EgoParams
from bid_sim.errors import BidError
from bid_sim.routes import Route
from bid_sim.snapshot import Snapshot


@dataclass(frozen=True)
class EpisodeInfo:
    """What an agent is told when an episode starts."""

    town: str
    route_index: int
    weather: str
    density: str
    seed: int
    route: Route
    params: EgoParams


@dataclass(frozen=True)
class Observation:
    """One step's input: learned agents read the frames, command and speed; the expert the snapshot."""

    frame: np.ndarray | None  # (300, 900, 3) uint8, None when rendering is off
    prev_frame: np.ndarray | None
    command: int
    speed_mps: float
    snapshot: Snapshot


class Agent(Protocol):
    def reset(self, info: EpisodeInfo) -> None: ...

    def act(self, obs: Observation) -> Control: ...


class LaneFollower:
    """Pure pursuit along the planned route at a fixed speed; blind to traffic and lights."""

    def __init__(self, target_speed_mps: float = 6.0, lookahead_m: float = 6.0):
        self.target_speed_mps = target_speed_mps
        self.lookahead_m = lookahead_m
        self.params = EgoParams()
        self._cum: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self, info: EpisodeInfo) -> None:
        self.params = info.params
        self._cum = None

    def act(self, obs: Observation) -> Control:
        ego = obs.snapshot.ego
        line = obs.snapshot.route_polyline
        if self._cum is None or self._cum[0] is not line:  # once per (re-planned) route
            self._cum = (line, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]))
        cum = self._cum[1]
        s = min(ego.route_s_m + self.lookahead_m + 0.5 * ego.speed_mps, cum[-1])
        tx, ty = np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])
        return Control(pursuit_steer(ego.x_m, ego.y_m, ego.yaw_rad, tx, ty, self.params),
                       speed_accel(ego.speed_mps, self.target_speed_mps))


class Scripted:
    """Replays fixed controls: control(step) -> Control. For driving into infractions on purpose."""

    def __init__(self, control_at):
        self.control_at = control_at
        self.step = 0

    def reset(self, info: EpisodeInfo) -> None:
        self.step = 0

    def act(self, obs: Observation) -> Control:
        c = self.control_at(self.step, obs)
        self.step += 1
        return c


def pursuit_steer(x: float, y: float, yaw: float, tx: float, ty: float, params: EgoParams) -> float:
    """Pure-pursuit steering (our convention: +1 = full right) towards the target point."""
    dx, dy = tx - x, ty - y
    alpha = math.atan2(dy, dx) - yaw
    ld = max(math.hypot(dx, dy), 1e-3)
    delta = math.atan2(2.0 * params.wheelbase_m * math.sin(alpha), ld)
    return float(np.clip(-delta / params.max_wheel_rad, -1.0, 1.0))


def speed_accel(speed: float, target: float, gain: float = 0.5) -> float:
    """Proportional speed control mapped to accel in [-1, 1]."""
    return float(np.clip(gain * (target - speed), -1.0, 1.0))


AGENTS = ("expert", "lanefollow")


def make_agent(name: str, speed_mps: float = 6.0) -> Agent:
    """A scripted agent by name: 'expert' (privileged rule-based driver) or 'lanefollow'
    (blind to traffic and lights; speed_mps is its speed)."""
    if name == "expert":
        try:
            from bid_sim.expert import Expert
        except ModuleNotFoundError as e:
            if e.name != "bid_sim.expert":
                raise
            raise BidError("this version has no expert (bid_sim/expert.py); use --agent lanefollow") from e
        return Expert()
    if name == "lanefollow":
        return LaneFollower(target_speed_mps=speed_mps)
    raise BidError(f"unknown agent {name!r}; use one of {', '.join(AGENTS)}")
