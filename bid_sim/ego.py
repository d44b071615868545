"""The ego car: control convention and a kinematic bicycle model integrated at 10 Hz."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DT_S = 0.1


@dataclass(frozen=True)
class Control:
    """Roach/CARLA convention: steer in [-1, 1] (+1 full right), accel in [-1, 1] (<0 brakes)."""

    steer: float = 0.0
    accel: float = 0.0

    @property
    def throttle(self) -> float:
        return max(self.accel, 0.0)

    @property
    def brake(self) -> float:
        return max(-self.accel, 0.0)

    def clipped(self) -> Control:
        """The same control with NaN replaced by 0 and values clamped to [-1, 1]."""
        s = 0.0 if not math.isfinite(self.steer) else min(max(self.steer, -1.0), 1.0)
        a = 0.0 if not math.isfinite(self.accel) else min(max(self.accel, -1.0), 1.0)
        return Control(s, a)

    def to_dict(self) -> dict[str, float]:
        return {"steer": self.steer, "accel": self.accel, "throttle": self.throttle, "brake": self.brake}


@dataclass(frozen=True)
class EgoParams:
    """Geometry and limits of the ego car (DESIGN.md section 3)."""

    length_m: float = 4.6
    width_m: float = 1.9
    height_m: float = 1.5
    wheelbase_m: float = 2.8
    max_wheel_rad: float = math.radians(35.0)
    max_accel_mps2: float = 3.0
    max_brake_mps2: float = 8.0
    max_speed_mps: float = 25.0


@dataclass(frozen=True)
class EgoState:
    """Pose of the box centre in the world frame and forward speed."""

    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float = 0.0

    def front_bumper(self, params: EgoParams) -> tuple[float, float]:
        h = params.length_m / 2
        return self.x_m + h * math.cos(self.yaw_rad), self.y_m + h * math.sin(self.yaw_rad)

    def corners(self, params: EgoParams) -> np.ndarray:
        """(4, 2) box corners, counter-clockwise from front-left."""
        return box_corners(self.x_m, self.y_m, self.yaw_rad, params.length_m, params.width_m)


def box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.array([x, y])


def step(state: EgoState, control: Control, params: EgoParams, dt_s: float = DT_S) -> EgoState:
    """One kinematic-bicycle step about the centre of mass (half-way along the wheelbase).

    Steering right (steer > 0) turns clockwise, i.e. decreases yaw. No reverse: speed stops at 0.
    """
    c = control.clipped()
    delta = -c.steer * params.max_wheel_rad
    a = c.throttle * params.max_accel_mps2 - c.brake * params.max_brake_mps2
    v0 = state.speed_mps
    v1 = min(max(v0 + a * dt_s, 0.0), params.max_speed_mps)
    v = 0.5 * (v0 + v1)  # trapezoid: the distance matches the speed change within the step
    lr = params.wheelbase_m / 2
    beta = math.atan(0.5 * math.tan(delta))
    yaw = state.yaw_rad + v / lr * math.sin(beta) * dt_s
    mid = 0.5 * (state.yaw_rad + yaw)
    x = state.x_m + v * math.cos(mid + beta) * dt_s
    y = state.y_m + v * math.sin(mid + beta) * dt_s
    yaw = math.atan2(math.sin(yaw), math.cos(yaw))
    return EgoState(x, y, yaw, v1)


def sumo_angle_deg(yaw_rad: float) -> float:
    """SUMO's heading (degrees clockwise from north) for a world yaw."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0


def yaw_from_sumo(angle_deg: float) -> float:
    """World yaw (radians CCW from +x, in (-pi, pi]) for a SUMO heading."""
    yaw = math.radians(90.0 - angle_deg)
    return math.atan2(math.sin(yaw), math.cos(yaw))
