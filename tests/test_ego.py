import math

import pytest

from bid_sim.ego import Control, EgoParams, EgoState, step, sumo_angle_deg, yaw_from_sumo

P = EgoParams()


def drive(control, n, state=EgoState(0.0, 0.0, 0.0, 0.0)):
    for _ in range(n):
        state = step(state, control, P)
    return state


def test_full_throttle_reaches_3_mps2_and_straight():
    s = drive(Control(0.0, 1.0), 10)
    assert s.speed_mps == pytest.approx(3.0)
    assert s.x_m == pytest.approx(1.5, rel=1e-6) and s.y_m == pytest.approx(0.0) and s.yaw_rad == 0.0


def test_full_brake_stops_without_reversing():
    s = drive(Control(0.0, -1.0), 30, EgoState(0.0, 0.0, 0.0, 10.0))
    assert s.speed_mps == 0.0
    assert s.x_m == pytest.approx(10.0 * 10.0 / (2 * 8.0), rel=0.05)


@pytest.mark.parametrize("steer, sign", [(1.0, -1), (-1.0, 1)])
def test_positive_steer_turns_right(steer, sign):
    s = drive(Control(steer, 0.0), 10, EgoState(0.0, 0.0, 0.0, 5.0))
    assert math.copysign(1, s.yaw_rad) == sign and math.copysign(1, s.y_m) == sign


def test_turn_radius_matches_bicycle_geometry():
    # Circle radius about the centre of mass for the max wheel angle.
    beta = math.atan(0.5 * math.tan(P.max_wheel_rad))
    radius = (P.wheelbase_m / 2) / math.sin(beta)
    s = drive(Control(-1.0, 0.0), 20, EgoState(0.0, 0.0, 0.0, 5.0))
    assert s.yaw_rad == pytest.approx(5.0 * 2.0 / radius, rel=1e-3)


def test_nan_control_is_ignored():
    s = step(EgoState(0, 0, 0, 5.0), Control(float("nan"), float("nan")), P)
    assert s.speed_mps == 5.0 and s.yaw_rad == 0.0


@pytest.mark.parametrize("yaw_deg, sumo_deg", [(0, 90), (90, 0), (180, 270), (-90, 180)])
def test_sumo_angle_convention(yaw_deg, sumo_deg):
    assert sumo_angle_deg(math.radians(yaw_deg)) == pytest.approx(sumo_deg)
    back = yaw_from_sumo(sumo_deg)
    assert math.cos(back) == pytest.approx(math.cos(math.radians(yaw_deg)), abs=1e-9)
    assert math.sin(back) == pytest.approx(math.sin(math.radians(yaw_deg)), abs=1e-9)


def test_control_mapping():
    c = Control(0.2, -0.4)
    assert (c.throttle, c.brake) == (0.0, 0.4)
    assert Control(0.0, 0.7).throttle == 0.7
