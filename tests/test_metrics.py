"""Leaderboard / NoCrash metrics against hand-computed episodes."""

import json
import math

import pytest

from bid_sim.errors import BidError
from bid_sim.metrics import (
    BLOCKED,
    COLLISION_LAYOUT,
    COLLISION_PEDESTRIAN,
    COLLISION_VEHICLE,
    COUNT_KEYS,
    INFRACTION_KINDS,
    OUTSIDE_LANE,
    RED_LIGHT,
    ROUTE_DEVIATION,
    STOP_SIGN,
    TIMEOUT,
    Infraction,
    aggregate,
    dedup_collisions,
    episode_metrics,
    format_table,
    stats,
)


def inf(kind: str, t: float = 0.0, actor: str = "") -> Infraction:
    return Infraction(kind=kind, time_s=t, x_m=1.0, y_m=2.0, actor=actor)


def metrics(**kwargs):
    args = {
        "route_length_m": 1000.0,
        "completed_m": 1000.0,
        "completed": True,
        "infractions": [],
        "outside_lane_m": 0.0,
    }
    args.update(kwargs)
    return episode_metrics(**args)


# --- Infraction -----------------------------------------------------------------------


def test_infraction_kinds_are_the_nine_leaderboard_kinds():
    assert INFRACTION_KINDS == (
        "collision_pedestrian",
        "collision_vehicle",
        "collision_layout",
        "red_light",
        "stop_sign",
        "outside_lane",
        "route_deviation",
        "blocked",
        "timeout",
    )


def test_unknown_kind_raises_value_error():
    with pytest.raises(ValueError, match="unknown infraction kind 'speeding'"):
        Infraction(kind="speeding", time_s=0.0, x_m=0.0, y_m=0.0)


def test_infraction_round_trips_through_json():
    original = Infraction(
        kind=COLLISION_LAYOUT,
        time_s=12.5,
        x_m=-3.25,
        y_m=8.0,
        actor="building:12",
        detail="1.2 m/s",
    )
    data = json.loads(json.dumps(original.to_dict()))
    assert data == {
        "kind": "collision_layout",
        "time_s": 12.5,
        "x_m": -3.25,
        "y_m": 8.0,
        "actor": "building:12",
        "detail": "1.2 m/s",
    }
    assert Infraction.from_dict(data) == original


def test_from_dict_defaults_actor_and_detail_and_validates_kind():
    assert Infraction.from_dict({"kind": "red_light", "time_s": 1, "x_m": 2, "y_m": 3}) == (
        Infraction(kind=RED_LIGHT, time_s=1.0, x_m=2.0, y_m=3.0)
    )
    with pytest.raises(ValueError):
        Infraction.from_dict({"kind": "nope", "time_s": 1, "x_m": 2, "y_m": 3})


def test_infraction_is_frozen():
    with pytest.raises(AttributeError):
        inf(RED_LIGHT).time_s = 3.0


# --- episode_metrics ------------------------------------------------------------------


def test_completed_clean_route():
    m = metrics(route_length_m=850.0, completed_m=850.0)
    assert m == {
        "RC": 100.0,
        "IP": 1.0,
        "DS": 100.0,
        "SR": 100.0,
        "SSR": 100.0,
        "CV": 0,
        "CP": 0,
        "CL": 0,
        "TL": 0,
        "SS": 0,
        "OL": 0,
        "RD": 0,
        "ABD": 0,
        "TO": 0,
        "km": pytest.approx(0.85),
    }


def test_collisions_and_red_light_at_sixty_percent():
    # IP = 0.5 (pedestrian) * 0.6 * 0.6 (two vehicles) * 0.7 (red light) = 0.126
    m = metrics(
        completed_m=600.0,
        completed=False,
        infractions=[
            inf(COLLISION_PEDESTRIAN, 10.0, "ped:1"),
            inf(COLLISION_VEHICLE, 20.0, "veh:1"),
            inf(COLLISION_VEHICLE, 40.0, "veh:2"),
            inf(RED_LIGHT, 50.0, "tl:3"),
        ],
    )
    assert m["RC"] == pytest.approx(60.0)
    assert m["IP"] == pytest.approx(0.126)
    assert m["DS"] == pytest.approx(7.56)
    assert (m["SR"], m["SSR"]) == (0.0, 0.0)
    assert (m["CP"], m["CV"], m["TL"], m["CL"], m["SS"]) == (1, 2, 1, 0, 0)
    assert m["km"] == pytest.approx(0.6)


def test_outside_lane_share_scales_ip():
    # 20 m of 200 m driven outside the lane: factor 1 - 0.1.
    m = metrics(route_length_m=400.0, completed_m=200.0, completed=False, outside_lane_m=20.0)
    assert m["RC"] == pytest.approx(50.0)
    assert m["IP"] == pytest.approx(0.9)
    assert m["DS"] == pytest.approx(45.0)


def test_outside_lane_share_combines_with_penalties():
    m = metrics(
        completed_m=200.0, completed=False, outside_lane_m=50.0, infractions=[inf(STOP_SIGN)]
    )
    assert m["IP"] == pytest.approx(0.8 * 0.75)
    assert m["DS"] == pytest.approx(20.0 * 0.6)


def test_red_light_only_is_success_but_not_strict_success():
    m = metrics(infractions=[inf(RED_LIGHT, 5.0, "tl:1")])
    assert m["SR"] == 100.0
    assert m["SSR"] == 0.0
    assert m["IP"] == pytest.approx(0.7)
    assert m["DS"] == pytest.approx(70.0)
    assert m["TL"] == 1


@pytest.mark.parametrize(
    ("kind", "factor"),
    [
        (COLLISION_PEDESTRIAN, 0.50),
        (COLLISION_VEHICLE, 0.60),
        (COLLISION_LAYOUT, 0.65),
        (RED_LIGHT, 0.70),
        (STOP_SIGN, 0.80),
        (OUTSIDE_LANE, 1.0),
        (ROUTE_DEVIATION, 1.0),
        (BLOCKED, 1.0),
        (TIMEOUT, 1.0),
    ],
)
def test_penalty_factor_per_occurrence(kind, factor):
    assert metrics(infractions=[inf(kind)])["IP"] == pytest.approx(factor)
    assert metrics(infractions=[inf(kind), inf(kind, 9.0)])["IP"] == pytest.approx(factor**2)


@pytest.mark.parametrize(
    ("kind", "key", "sr"),
    [
        (COLLISION_PEDESTRIAN, "CP", 0.0),
        (COLLISION_VEHICLE, "CV", 0.0),
        (COLLISION_LAYOUT, "CL", 0.0),
        (RED_LIGHT, "TL", 100.0),
        (STOP_SIGN, "SS", 100.0),
        (OUTSIDE_LANE, "OL", 100.0),
        (ROUTE_DEVIATION, "RD", 100.0),
        (BLOCKED, "ABD", 100.0),
        (TIMEOUT, "TO", 100.0),
    ],
)
def test_each_kind_is_counted_and_breaks_strict_success(kind, key, sr):
    m = metrics(infractions=[inf(kind), inf(kind, 30.0)])
    assert m[key] == 2
    assert sum(m[k] for k in COUNT_KEYS) == 2
    assert m["SR"] == sr
    assert m["SSR"] == 0.0


def test_uncompleted_clean_route_is_no_success():
    m = metrics(completed_m=999.0, completed=False)
    assert m["RC"] == pytest.approx(99.9)
    assert m["DS"] == pytest.approx(99.9)
    assert (m["SR"], m["SSR"]) == (0.0, 0.0)


def test_completed_flag_forces_full_route_completion():
    assert metrics(completed_m=990.0, completed=True)["RC"] == 100.0


def test_route_completion_is_clamped_to_100():
    m = metrics(completed_m=1200.0, completed=False)
    assert m["RC"] == 100.0
    assert m["SR"] == 0.0


def test_outside_lane_share_is_clamped_to_one():
    m = metrics(completed_m=100.0, completed=False, outside_lane_m=150.0)
    assert m["IP"] == 0.0
    assert m["DS"] == 0.0


def test_zero_distance_has_no_outside_lane_share():
    m = metrics(completed_m=0.0, completed=False, outside_lane_m=5.0)
    assert (m["RC"], m["IP"], m["DS"], m["km"]) == (0.0, 1.0, 0.0, 0.0)


@pytest.mark.parametrize("length", [0.0, -10.0, math.nan, math.inf])
def test_bad_route_length_raises_value_error(length):
    with pytest.raises(ValueError, match="route_length_m"):
        metrics(route_length_m=length)


@pytest.mark.parametrize(
    ("field", "value"), [("completed_m", -1.0), ("outside_lane_m", -0.5), ("completed_m", math.nan)]
)
def test_negative_distances_raise_value_error(field, value):
    with pytest.raises(ValueError, match=field):
        metrics(**{field: value})


# --- dedup_collisions -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("events", "kept_times"),
    [
        # Window from the last kept event: 3 is within 5 s of 0, 6 is not.
        (
            [
                (COLLISION_VEHICLE, 0.0, "veh:A"),
                (COLLISION_VEHICLE, 3.0, "veh:A"),
                (COLLISION_VEHICLE, 6.0, "veh:A"),
            ],
            [0.0, 6.0],
        ),
        # Dropped events do not extend the window: 4.9 and 9.8 from 0 -> 9.8 kept.
        (
            [
                (COLLISION_LAYOUT, 0.0, "sidewalk"),
                (COLLISION_LAYOUT, 4.9, "sidewalk"),
                (COLLISION_LAYOUT, 9.8, "sidewalk"),
            ],
            [0.0, 9.8],
        ),
        # The window edge is inclusive.
        (
            [
                (COLLISION_VEHICLE, 0.0, "veh:A"),
                (COLLISION_VEHICLE, 5.0, "veh:A"),
                (COLLISION_VEHICLE, 5.01, "veh:A"),
            ],
            [0.0, 5.01],
        ),
        # Different actors are different collisions.
        (
            [
                (COLLISION_VEHICLE, 0.0, "veh:A"),
                (COLLISION_VEHICLE, 1.0, "veh:B"),
                (COLLISION_PEDESTRIAN, 2.0, "ped:A"),
            ],
            [0.0, 1.0, 2.0],
        ),
        # Non-collisions pass through even with the same actor.
        (
            [(RED_LIGHT, 0.0, "tl:1"), (RED_LIGHT, 1.0, "tl:1"), (OUTSIDE_LANE, 1.5, "")],
            [0.0, 1.0, 1.5],
        ),
        # An unidentified actor is never merged.
        ([(COLLISION_LAYOUT, 0.0, ""), (COLLISION_LAYOUT, 1.0, "")], [0.0, 1.0]),
    ],
)
def test_dedup_collisions(events, kept_times):
    infractions = [inf(kind, t, actor) for kind, t, actor in events]
    assert [i.time_s for i in dedup_collisions(infractions)] == kept_times


def test_dedup_preserves_order_and_identity():
    a0 = inf(COLLISION_VEHICLE, 0.0, "veh:A")
    light = inf(RED_LIGHT, 1.0, "tl:1")
    a2 = inf(COLLISION_VEHICLE, 2.0, "veh:A")
    wall = inf(COLLISION_LAYOUT, 3.0, "building:12")
    a7 = inf(COLLISION_VEHICLE, 7.0, "veh:A")
    assert dedup_collisions([a0, light, a2, wall, a7]) == [a0, light, wall, a7]


def test_dedup_custom_window():
    events = [inf(COLLISION_VEHICLE, t, "veh:A") for t in (0.0, 1.0, 2.0, 3.0)]
    assert [i.time_s for i in dedup_collisions(events, window_s=1.5)] == [0.0, 2.0]
    assert [i.time_s for i in dedup_collisions(events, window_s=0.0)] == [0.0, 1.0, 2.0, 3.0]


def test_dedup_negative_window_raises():
    with pytest.raises(ValueError, match="window_s"):
        dedup_collisions([], window_s=-1.0)


# --- aggregate / stats ----------------------------------------------------------------


def row(seed, density, weather, **values):
    base = {"seed": seed, "density": density, "weather": weather, "town": "02"}
    base.update(dict.fromkeys(COUNT_KEYS, 0))
    base.update(values)
    return base


# Two seeds x two densities; seed 0 ran in clear weather, seed 1 in rain.
ROWS = [
    row(0, "dense", "clear", SR=100.0, SSR=0.0, RC=100.0, IP=0.7, DS=70.0, TL=1, km=1.0),
    row(0, "empty", "clear", SR=100.0, SSR=100.0, RC=100.0, IP=1.0, DS=100.0, km=0.5),
    row(1, "dense", "rain", SR=0.0, SSR=0.0, RC=60.0, IP=0.126, DS=7.56, CP=1, CV=2, TL=1, km=0.3),
    row(1, "empty", "rain", SR=0.0, SSR=0.0, RC=50.0, IP=0.9, DS=45.0, OL=1, km=0.2),
]


def test_aggregate_all():
    s = aggregate(ROWS)["all"]
    # Seed means: SR 100 / 0, SSR 50 / 0, RC 100 / 55, IP 0.85 / 0.513, DS 85 / 26.28.
    expected = {
        "SR": 50.0,
        "SR_std": 50.0,
        "SSR": 25.0,
        "SSR_std": 25.0,
        "RC": 77.5,
        "RC_std": 22.5,
        "IP": 0.6815,
        "IP_std": 0.1685,
        "DS": 55.64,
        "DS_std": 29.36,
        "CV": 2,
        "CV_per_km": 1.0,
        "CP": 1,
        "CP_per_km": 0.5,
        "CL": 0,
        "CL_per_km": 0.0,
        "TL": 2,
        "TL_per_km": 1.0,
        "SS": 0,
        "SS_per_km": 0.0,
        "OL": 1,
        "OL_per_km": 0.5,
        "RD": 0,
        "RD_per_km": 0.0,
        "ABD": 0,
        "ABD_per_km": 0.0,
        "TO": 0,
        "TO_per_km": 0.0,
        "episodes": 4,
        "seeds": 2,
        "km": 2.0,
    }
    assert s == pytest.approx(expected)
    assert set(s) == set(expected)
    assert all(type(s[k]) is int for k in [*COUNT_KEYS, "episodes", "seeds"])


def test_aggregate_by_density():
    by = aggregate(ROWS)["by_density"]
    assert list(by) == ["dense", "empty"]
    dense, empty = by["dense"], by["empty"]
    assert (dense["SR"], dense["SR_std"]) == pytest.approx((50.0, 50.0))
    assert (dense["SSR"], dense["SSR_std"]) == pytest.approx((0.0, 0.0))
    assert (dense["RC"], dense["RC_std"]) == pytest.approx((80.0, 20.0))
    assert (dense["IP"], dense["IP_std"]) == pytest.approx((0.413, 0.287))
    assert (dense["DS"], dense["DS_std"]) == pytest.approx((38.78, 31.22))
    assert (dense["TL"], dense["TL_per_km"]) == (2, pytest.approx(2 / 1.3))
    assert (dense["CV"], dense["CV_per_km"]) == (2, pytest.approx(2 / 1.3))
    assert (dense["CP"], dense["CP_per_km"]) == (1, pytest.approx(1 / 1.3))
    assert (dense["episodes"], dense["seeds"], dense["km"]) == (2, 2, pytest.approx(1.3))

    assert (empty["SSR"], empty["SSR_std"]) == pytest.approx((50.0, 50.0))
    assert (empty["RC"], empty["RC_std"]) == pytest.approx((75.0, 25.0))
    assert (empty["IP"], empty["IP_std"]) == pytest.approx((0.95, 0.05))
    assert (empty["DS"], empty["DS_std"]) == pytest.approx((72.5, 27.5))
    assert (empty["OL"], empty["OL_per_km"]) == (1, pytest.approx(1 / 0.7))
    assert (empty["TL"], empty["TL_per_km"]) == (0, 0.0)


def test_aggregate_by_weather_single_seed_has_zero_std():
    result = aggregate(ROWS)
    assert set(result) == {"all", "by_density", "by_weather"}
    clear = result["by_weather"]["clear"]
    assert list(result["by_weather"]) == ["clear", "rain"]
    assert clear["seeds"] == 1
    assert (clear["SR"], clear["SSR"], clear["RC"], clear["IP"], clear["DS"]) == pytest.approx(
        (100.0, 50.0, 100.0, 0.85, 85.0)
    )
    assert [clear[f"{k}_std"] for k in ("SR", "SSR", "RC", "IP", "DS")] == [0.0] * 5


def test_stats_weighs_seeds_not_episodes():
    # Seed 0: one episode DS 100; seed 1: three episodes DS 0.
    # Mean of seed means = 50 (an episode mean would give 25).
    rows = [row(0, "dense", "clear", SR=100.0, SSR=100.0, RC=100.0, IP=1.0, DS=100.0, km=1.0)]
    rows += [row(1, "dense", "clear", SR=0.0, SSR=0.0, RC=0.0, IP=1.0, DS=0.0, km=0.0)] * 3
    s = stats(rows)
    assert (s["DS"], s["DS_std"]) == pytest.approx((50.0, 50.0))
    assert (s["episodes"], s["seeds"]) == (4, 2)


def test_zero_km_gives_zero_rates():
    s = stats([row(0, "dense", "clear", SR=0.0, SSR=0.0, RC=0.0, IP=0.5, DS=0.0, CP=1, km=0.0)])
    assert (s["CP"], s["CP_per_km"], s["km"]) == (1, 0.0, 0.0)


def test_numeric_group_values_sort_numerically():
    rows = [
        row(0, 10, "clear", SR=0.0, SSR=0.0, RC=0.0, IP=1.0, DS=0.0, km=0.0),
        row(0, 2, "clear", SR=0.0, SSR=0.0, RC=0.0, IP=1.0, DS=0.0, km=0.0),
    ]
    assert list(aggregate(rows, group_by=("density", "town"))["by_density"]) == [2, 10]
    assert set(aggregate(rows, group_by=("town",))) == {"all", "by_town"}


@pytest.mark.parametrize("func", [aggregate, stats])
def test_empty_rows_raise_bid_error(func):
    with pytest.raises(BidError, match=r"^no episodes to aggregate; run the benchmark first$"):
        func([])


def test_missing_key_raises_bid_error():
    bad = {k: v for k, v in ROWS[0].items() if k != "weather"}
    with pytest.raises(BidError, match="'weather'"):
        aggregate([bad])


# --- format_table ---------------------------------------------------------------------


def test_format_table():
    by = aggregate(ROWS)["by_density"]
    table = format_table(by, ["DS", "IP", "SR", "TL", "TL_per_km", "episodes"])
    assert table == (
        "| group | DS | IP | SR | TL | TL_per_km | episodes |\n"
        "|---|---|---|---|---|---|---|\n"
        "| dense | 38.8 ± 31.2 | 0.413 ± 0.287 | 50.0 ± 50.0 | 2 | 1.54 | 2 |\n"
        "| empty | 72.5 ± 27.5 | 0.950 ± 0.050 | 50.0 ± 50.0 | 0 | 0.00 | 2 |"
    )


def test_format_table_plain_value_without_std():
    assert format_table({"x": {"RC": 12.345, "km": 3.14159}}, ["RC", "km"]).splitlines()[2] == (
        "| x | 12.3 | 3.14 |"
    )


def test_format_table_unknown_key_raises_bid_error():
    with pytest.raises(BidError, match="unknown metric 'XYZ'"):
        format_table(aggregate(ROWS)["by_density"], ["DS", "XYZ"])
