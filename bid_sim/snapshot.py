"""Snapshot: the immutable state of the world around the ego at one step, free of SUMO handles.

Actor arrays are parallel: row i of ``xy``, ``yaw_rad``, ``size`` ... describes ``ids[i]``.
Positions are box centres in the world frame (m), yaw counter-clockwise from +x (rad).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Signal light codes, as stored in Snapshot.light_states.
RED, YELLOW, GREEN, OFF = 0, 1, 2, 3
_LIGHT_CODE = {"r": RED, "R": RED, "s": RED, "u": YELLOW, "y": YELLOW, "Y": YELLOW,
               "g": GREEN, "G": GREEN, "o": OFF, "O": OFF}


def light_code(sumo_char: str) -> int:
    """Our light code for one character of a SUMO signal state string."""
    return _LIGHT_CODE.get(sumo_char, OFF)


@dataclass(frozen=True)
class Actors:
    """Vehicles or pedestrians near the ego."""

    ids: tuple[str, ...]
    xy: np.ndarray  # (N, 2) float64 box centres, m
    yaw_rad: np.ndarray  # (N,)
    speed_mps: np.ndarray  # (N,)
    size: np.ndarray  # (N, 3) length, width, height, m
    colour: np.ndarray  # (N,) int colour index

    @staticmethod
    def empty() -> Actors:
        return Actors((), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0, int))

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class EgoView:
    """The ego as the snapshot reports it."""

    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float
    length_m: float
    width_m: float
    height_m: float
    lane_id: str  # '' when off every driving lane
    lateral_m: float  # signed offset from the route centre line (+ left)
    heading_error_rad: float  # yaw minus the route heading, wrapped to (-pi, pi]
    route_s_m: float  # progress along the current route
    route_length_m: float
    command: int  # navigation command (CARLA RoadOption numbering)


@dataclass(frozen=True)
class Snapshot:
    """Everything the renderer, the expert and the monitor need at one step."""

    time_s: float
    step: int
    ego: EgoView
    vehicles: Actors
    pedestrians: Actors
    light_states: np.ndarray  # (H,) uint8 light code per TownMap.signal_heads entry
    # Privileged: the expert and the monitor read these, a learned policy never does.
    tls_states: dict[str, str] = field(default_factory=dict)  # SUMO state string per signal
    next_light_state: int = OFF  # state of the ego's next signal on its route
    next_light_dist_m: float = float("inf")  # distance from the front bumper to its stop line
    route_polyline: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
