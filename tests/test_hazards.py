"""What stands in the ego's path (bid_model.hazards): the hazard head's targets, on made-up
scenes with known answers and on real recordings."""

import dataclasses
import math

import numpy as np
import pytest
from shapely.geometry import Polygon, box

from bid_model.hazards import (
    HAZARD_AHEAD_M,
    bumper_vehicles,
    crossing_distances,
    file_crossings,
    file_hazards,
    index_crossings,
    index_hazards,
    light_distance,
    path_hazards,
)
from bid_model.recordings import (
    CACHE_DIR,
    find_recordings,
    hazard_nearness,
    open_every_frame,
    open_recordings,
)
from bid_sim.recording import read_episode, read_snapshots
from bid_sim.snapshot import GREEN, RED, YELLOW, Actors, EgoView, Snapshot

FRONT_M = 2.3  # half the ego's 4.6 m


def actors(*rows: tuple[float, float, float, float, float]) -> Actors:
    """(x, y, yaw, length, width) rows."""
    if not rows:
        return Actors.empty()
    return Actors(tuple(f"a{i}" for i in range(len(rows))), np.array([r[:2] for r in rows]),
                  np.array([r[2] for r in rows]), np.zeros(len(rows)),
                  np.array([(r[3], r[4], 1.7) for r in rows]), np.zeros(len(rows), dtype=int))


def snap(step: int, x: float, y: float, yaw: float, peds: Actors | None = None, cars: Actors | None = None) -> Snapshot:
    ego = EgoView(x, y, yaw, 5.0, 4.6, 1.9, 1.5, "e_0", 0.0, 0.0, 0.0, 100.0, 4)
    return Snapshot(step * 0.1, step, ego, cars or Actors.empty(), peds or Actors.empty(), np.zeros(0, np.uint8))


def straight(n: int, step_m: float = 0.5, **scene) -> list[Snapshot]:
    """An ego driving east along y = 0, `step_m` a step; the first snapshot holds `scene`."""
    return [snap(i, i * step_m, 0.0, 0.0, **(scene if i == 0 else {})) for i in range(n)]


def test_a_pedestrian_in_the_path_is_seen_at_its_distance_and_one_beside_it_is_not():
    ped = 0.5
    ahead = path_hazards(straight(80, peds=actors((12.0, 0.0, 0.0, ped, ped))))[0]
    # The corridor is 0.95 + 0.4 m either side of the path, the pedestrian's disc 0.25 m wide:
    # it enters 1.6 m before its centre, counted from the front bumper, in 0.5 m path steps.
    assert ahead[0] == pytest.approx(12.0 - 1.6 - FRONT_M, abs=0.5)
    assert ahead[1] == HAZARD_AHEAD_M  # no vehicle
    beside = path_hazards(straight(80, peds=actors((12.0, 2.2, 0.0, ped, ped))))[0]
    assert beside[0] == HAZARD_AHEAD_M
    far = path_hazards(straight(80, peds=actors((HAZARD_AHEAD_M + 8.0, 0.0, 0.0, ped, ped))))[0]
    assert far[0] == HAZARD_AHEAD_M


def test_the_path_is_the_one_driven_a_turn_not_straight_ahead():
    # A left turn of radius 10 m about (0, 10) after 2 m straight.
    poses = [(x, 0.0, 0.0) for x in np.arange(-2.0, 0.0, 0.5)]
    poses += [(10 * math.sin(a), 10 - 10 * math.cos(a), a) for a in np.arange(0.0, math.pi / 2, 0.05)]
    poses += [(10.0, 10.0 + k * 0.5, math.pi / 2) for k in range(1, 60)]
    on_turn = (10 * math.sin(0.9), 10 - 10 * math.cos(0.9))  # about 9 m along the arc
    straight_on = (11.0, 0.0)  # where the ego would be had it not turned
    scene = {"peds": actors((*on_turn, 0.0, 0.5, 0.5), (*straight_on, 0.0, 0.5, 0.5))}
    snaps = [snap(i, x, y, a, **(scene if i == 0 else {})) for i, (x, y, a) in enumerate(poses)]
    d = path_hazards(snaps)[0, 0]
    assert d == pytest.approx(2.0 + 9.0 - 1.6 - FRONT_M, abs=0.6)
    snaps_straight = [snap(i, x, y, a, peds=actors((*straight_on, 0.0, 0.5, 0.5)) if i == 0 else None)
                      for i, (x, y, a) in enumerate(poses)]
    assert path_hazards(snaps_straight)[0, 0] == HAZARD_AHEAD_M


def test_a_car_ahead_in_the_lane_counts_one_in_the_next_lane_does_not():
    ahead = actors((15.0, 0.0, 0.0, 4.6, 1.9))
    next_lane = actors((6.0, 3.5, 0.0, 4.6, 1.9))
    d = path_hazards(straight(80, cars=ahead))[0]
    # Its rear disc (1.35 m behind the centre, 0.95 m wide) enters the 1.35 m corridor 2.3 m before it.
    assert d[1] == pytest.approx(15.0 - 1.35 - 2.3 - FRONT_M, abs=0.5) and d[0] == HAZARD_AHEAD_M
    assert path_hazards(straight(80, cars=next_lane))[0, 1] == HAZARD_AHEAD_M
    # A car parked across the lane (yaw 90°) is in it.
    across = path_hazards(straight(80, cars=actors((10.0, 0.0, math.pi / 2, 4.6, 1.9))))[0, 1]
    assert across < 10.0 - FRONT_M


def test_a_standing_ego_looks_along_where_it_goes_next_and_past_the_end_straight_on():
    # 30 steps standing, then driving east: the pedestrian ahead is in the path all along.
    poses = [0.0] * 30 + [0.5 * k for k in range(1, 40)]
    peds = actors((8.0, 0.0, 0.0, 0.5, 0.5))
    snaps = [snap(i, x, 0.0, 0.0, peds=peds) for i, x in enumerate(poses)]
    d = path_hazards(snaps)[:, 0]
    assert np.all(d[:30] == d[0]) and d[0] == pytest.approx(8.0 - 1.6 - FRONT_M, abs=0.5)
    # The last snapshots: the path goes on straight along the last heading.
    last = [snap(0, 0.0, 0.0, math.pi / 2, peds=actors((0.0, 10.0, 0.0, 0.5, 0.5)))]
    assert path_hazards(last)[0, 0] == pytest.approx(10.0 - 1.6 - FRONT_M, abs=0.5)
    assert path_hazards([]).shape == (0, 2)


def left_turn() -> list[tuple[float, float, float]]:
    """Poses (x, y, yaw) 0.5 m apart (5 m/s at 0.1 s a step): 2 m east, a left turn of radius
    10 m about (0, 10), then north."""
    poses = [(x, 0.0, 0.0) for x in np.arange(-2.0, 0.0, 0.5)]
    poses += [(10 * math.sin(a), 10 - 10 * math.cos(a), a) for a in np.arange(0.0, math.pi / 2, 0.05)]
    return poses + [(10.0, 10.0 + k * 0.5, math.pi / 2) for k in range(1, 60)]


def test_the_bumper_corridor_runs_along_the_heading_and_turn_now_not_the_path_driven():
    poses = left_turn()
    # A car standing to the right of straight on: the ego turns away from it, so it is never
    # in the path; ahead of the bumper while the ego still heads east, its rear disc
    # (1.35 m behind its centre, 1.9 m right) enters the 1.35 m corridor 4.35 m from the ego's centre.
    cars = actors((5.0, -1.9, 0.0, 4.6, 1.9))
    snaps = [snap(i, x, y, a, cars=cars) for i, (x, y, a) in enumerate(poses)]
    assert path_hazards(snaps)[0, 1] == HAZARD_AHEAD_M
    near = bumper_vehicles(snaps, 6.0)
    assert near[0] == pytest.approx(4.35 - FRONT_M, abs=0.5)
    assert bumper_vehicles(snaps, 1.5)[0] == HAZARD_AHEAD_M  # farther than asked
    assert near[-1] == HAZARD_AHEAD_M  # heading north, long past it
    # In the turn the corridor bends with it (yaw rate 0.5 rad/s at 5 m/s: radius 10 m): a car
    # standing on the circle 9 m further round is ahead of the bumper, as it is in the path; on
    # a straight corridor it would be 3.8 m to the left of it.
    t = 10
    a = poses[t][2] + 0.9
    on_circle = actors((10 * math.sin(a), 10 - 10 * math.cos(a), a, 4.6, 1.9))
    turning = [snap(i, x, y, yaw, cars=on_circle) for i, (x, y, yaw) in enumerate(poses)]
    assert bumper_vehicles(turning, 10.0)[t] == pytest.approx(path_hazards(turning)[t, 1], abs=0.6)
    assert bumper_vehicles(turning, 10.0)[t] < 9.0 - FRONT_M
    # Standing (or at the first snapshot) there is no turn: straight on.
    standing = [dataclasses.replace(s, ego=dataclasses.replace(s.ego, speed_mps=0.0)) for s in turning]
    assert bumper_vehicles(standing, 10.0)[t] == HAZARD_AHEAD_M
    assert bumper_vehicles([], 6.0).shape == (0,)


def walking(x0: float, y0: float, n: int = 80, vy_mps: float = 1.5) -> list[Snapshot]:
    """`straight`'s ego at 5 m/s with a pedestrian walking north from (x0, y0), present throughout."""
    return [snap(i, i * 0.5, 0.0, 0.0, peds=actors((x0, y0 + vy_mps * 0.1 * i, math.pi / 2, 0.5, 0.5)))
            for i in range(n)]


def test_with_a_look_ahead_a_pedestrian_about_to_walk_into_the_path_is_in_it_already():
    # 3 m south of the path, 1.5 m/s north: in the corridor (1.35 + 0.25 m) from 1 s on, ahead of the ego.
    snaps = walking(10.0, -3.0)
    now, ahead = path_hazards(snaps)[0, 0], path_hazards(snaps, ped_ahead_s=1.5)[0, 0]
    assert now == HAZARD_AHEAD_M
    # Where it will be: its disc enters the corridor about 0.56 m before x = 10, from the front at t.
    assert ahead == pytest.approx(10.0 - 0.56 - FRONT_M, abs=0.6)
    # Half a second of look-ahead is not enough for it, and once it is in the path both agree.
    assert path_hazards(snaps, ped_ahead_s=0.5)[0, 0] == HAZARD_AHEAD_M
    assert path_hazards(snaps, ped_ahead_s=1.5)[12, 0] == pytest.approx(path_hazards(snaps)[12, 0], abs=1e-6)
    # One that crosses where the ego has already passed is not in its way, nor one that stays on the kerb.
    assert path_hazards(walking(1.0, -3.0), ped_ahead_s=1.5)[0, 0] == HAZARD_AHEAD_M
    assert path_hazards(walking(10.0, -3.0, vy_mps=0.0), ped_ahead_s=1.5)[0, 0] == HAZARD_AHEAD_M
    # Near the episode's end there is less future to look at: no error, what there is.
    assert path_hazards(snaps[:3], ped_ahead_s=1.5).shape == (3, 2)


def walkers(*rows: tuple[float, float, float, float]) -> Actors:
    """Pedestrians (x, y, yaw, speed), 0.5 m boxes."""
    a = actors(*((x, y, yaw, 0.5, 0.5) for x, y, yaw, _ in rows))
    return Actors(a.ids, a.xy, a.yaw_rad, np.array([r[3] for r in rows], dtype=float), a.size, a.colour)


def test_an_occupied_crossing_on_the_path_is_seen_where_the_path_enters_it():
    # A zebra crossing 3 m wide across the ego's road (x 15..18), one beside its path (y 6..9).
    zebra, aside = box(15.0, -5.0, 18.0, 5.0), box(15.0, 6.0, 18.0, 9.0)
    ahead = crossing_distances(straight(80, peds=walkers((16.5, 3.0, math.pi / 2, 0.0))), [zebra, aside])
    assert ahead[0] == pytest.approx(15.0 - FRONT_M, abs=0.5)
    assert np.all(ahead[1:] == HAZARD_AHEAD_M)  # the pedestrian is in the first snapshot only
    # Nobody on it, or only on the one off the path, or only on the kerb beyond it, or waiting
    # at its end for a green (SUMO's stand within 0.1 m of it): none.
    for peds in (Actors.empty(), walkers((16.5, 7.5, 0.0, 1.2)), walkers((16.5, 6.5, 0.0, 0.0)),
                 walkers((16.5, 5.05, -math.pi / 2, 0.0))):
        assert crossing_distances(straight(80, peds=peds), [zebra, aside])[0] == HAZARD_AHEAD_M
    # Walking onto it within a second counts; walking away from the path beside it does not,
    # nor does a crossing the front is already on.
    onto = walkers((16.5, 5.8, -math.pi / 2, 1.3))
    assert crossing_distances(straight(80, peds=onto), [zebra])[0] == pytest.approx(15.0 - FRONT_M, abs=0.5)
    away = walkers((16.5, 3.5, math.pi / 2, 1.3))
    assert crossing_distances(straight(80, peds=away), [zebra])[0] == HAZARD_AHEAD_M
    towards = walkers((16.5, 3.5, -math.pi / 2, 1.3))
    assert crossing_distances(straight(80, peds=towards), [zebra])[0] < HAZARD_AHEAD_M
    on_it = [snap(0, 13.5, 0.0, 0.0, peds=walkers((16.5, 0.0, 0.0, 0.0))), *straight(80)[1:]]
    assert crossing_distances(on_it, [zebra])[0] == HAZARD_AHEAD_M
    far = [snap(0, -20.0, 0.0, 0.0, peds=walkers((16.5, 0.0, 0.0, 0.0))), *straight(80)[1:]]
    assert crossing_distances(far, [zebra])[0] == HAZARD_AHEAD_M  # 32.7 m off: beyond reach
    assert crossing_distances([], [zebra]).shape == (0,)
    assert isinstance(zebra, Polygon)


def test_hazards_of_recordings_align_with_the_index_and_are_cached(recorded):
    files, _ = find_recordings(recorded)
    steps, dist = file_hazards(files[0])
    ep = read_episode(files[0], frames=False)
    assert steps.tolist() == ep.steps.tolist() and dist.shape == (len(steps), 2)
    assert np.all((dist >= 0) & (dist <= HAZARD_AHEAD_M))
    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True)
    cached = list((recorded / CACHE_DIR).glob("hazards-*.npy"))
    assert len(cached) == 1
    dist_all = index_hazards(files, train.index.episode, train.index.step, None, workers=1)
    assert np.array_equal(np.load(cached[0]), dist_all)
    light = np.concatenate([[light_distance(s) for s in read_episode(f, frames=False).states] for f in files])
    want = hazard_nearness(np.column_stack([dist_all, light]))
    for data in (train, val):
        for i in (0, len(data) - 1):
            sample = data[i]
            assert sample["hazard"].shape == (3,)
            assert sample["hazard"].tolist() == pytest.approx(want[data.rows[i]].tolist())
    assert desc["hazard_frames"] == {"pedestrian_in_path": int((want[:, 0] > 0).sum()),
                                     "vehicle_in_path": int((want[:, 1] > 0).sum()),
                                     "red_light_ahead": int((want[:, 2] > 0).sum()),
                                     "pedestrians_ahead_s": 0.0}
    # Read back from the cache, the same.
    again = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True)[0]
    assert np.array_equal(again.hazard, train.hazard)
    # Pedestrians where they will be: another cache; as near or nearer, the rest as it was.
    ahead = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True, hazard_ahead_s=1.5)[0]
    assert [p.name for p in (recorded / CACHE_DIR).glob("hazards-*.npy")] != [p.name for p in cached]
    assert np.all(ahead.hazard[:, 0] >= train.hazard[:, 0]) and np.array_equal(ahead.hazard[:, 1:], train.hazard[:, 1:])
    assert "hazard" not in open_recordings(recorded, (48, 144), 0.5, 0)[0][0]
    # With the crossing target, a fourth column from the recordings' town, cached beside them.
    steps, crossing = file_crossings(files[0])
    assert steps.tolist() == ep.steps.tolist() and crossing.shape == (len(steps), 1)
    with_crossing, _, desc = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True, crossing=True)
    assert with_crossing[0]["hazard"].shape == (4,)
    assert np.array_equal(with_crossing.hazard[:, :3], train.hazard)
    want = hazard_nearness(index_crossings(files, train.index.episode, train.index.step, None, workers=1))
    assert np.array_equal(with_crossing.hazard[:, 3:], want)
    assert desc["hazard_frames"]["crossing_occupied"] == int((want > 0).sum())
    assert len(list((recorded / CACHE_DIR).glob("crossings-*.npy"))) == 1


def test_the_bumper_target_of_recordings_is_the_nearer_of_path_and_bumper_and_is_cached(recorded):
    plain = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True)[0]
    assert "vehicle_bumper" not in plain[0]
    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, hazard=True, bumper_m=8.0)
    assert np.array_equal(train.hazard, plain.hazard)  # the first head's targets as they were
    assert len(list((recorded / CACHE_DIR).glob("bumper-*.npy"))) == 1
    files, _ = find_recordings(recorded)
    ahead = [bumper_vehicles([snap for snap, _ in read_snapshots(f)], 8.0) for f in files]
    want = np.maximum(train.hazard[:, 1], hazard_nearness(np.concatenate(ahead)))
    assert np.array_equal(train.bumper, want)
    for data in (train, val):
        sample = data[len(data) - 1]
        assert sample["vehicle_bumper"] == pytest.approx(want[data.rows[len(data) - 1]])
    assert desc["hazard_frames"]["vehicle_in_path_or_bumper"] == int((want > 0).sum())
    assert desc["hazard_frames"]["bumper_m"] == 8.0
    every, _ = open_every_frame(recorded, (48, 144), bumper_m=8.0)
    assert np.array_equal(every.bumper, want)


def test_the_light_target_is_the_distance_to_a_red_or_amber_stop_line_within_reach():
    assert light_distance({"next_light_state": RED, "next_light_dist_m": 12.5}) == 12.5
    assert light_distance({"next_light_state": YELLOW, "next_light_dist_m": -0.3}) == 0.0
    assert light_distance({"next_light_state": RED, "next_light_dist_m": 60.0}) == HAZARD_AHEAD_M
    assert light_distance({"next_light_state": GREEN, "next_light_dist_m": 5.0}) == HAZARD_AHEAD_M
    assert light_distance({"next_light_state": RED, "next_light_dist_m": None}) == HAZARD_AHEAD_M
    assert light_distance({}) == HAZARD_AHEAD_M


def test_nearness_is_one_at_the_bumper_and_zero_out_of_reach():
    assert hazard_nearness(np.array([[0.0, HAZARD_AHEAD_M], [HAZARD_AHEAD_M / 2, 99.0]])).tolist() == [
        [1.0, 0.0], [0.5, 0.0]]
