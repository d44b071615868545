"""Benchmark metrics of the CARLA leaderboard 1.0 and NoCrash, as pure functions.

Per episode: route completion (RC, %), infraction penalty (IP, a factor in [0, 1]),
driving score (DS = RC * IP, %), success rate (SR, %: completed without collision),
strict success rate (SSR, %: completed without any infraction) and infraction counts.
Over episodes: means and population stds over seeds, totals and per-km rates.

Nothing here reads or writes files; the callers own I/O.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from bid_sim.errors import BidError

COLLISION_PEDESTRIAN = "collision_pedestrian"
COLLISION_VEHICLE = "collision_vehicle"
COLLISION_LAYOUT = "collision_layout"
RED_LIGHT = "red_light"
STOP_SIGN = "stop_sign"
OUTSIDE_LANE = "outside_lane"
ROUTE_DEVIATION = "route_deviation"
BLOCKED = "blocked"
TIMEOUT = "timeout"

# Why the ego stood (EpisodeResult.standing_s, episode.standing_reason), from the privileged state.
STANDING_REASONS = ("light", "vehicle", "pedestrian", "nothing")
STANDING_LIGHT_M = 10.0  # a red or amber light on the route this near the front bumper
STANDING_AHEAD_M = 8.0  # a vehicle or pedestrian this far beyond the front bumper, in the ego's width

INFRACTION_KINDS: tuple[str, ...] = (
    COLLISION_PEDESTRIAN,
    COLLISION_VEHICLE,
    COLLISION_LAYOUT,
    RED_LIGHT,
    STOP_SIGN,
    OUTSIDE_LANE,
    ROUTE_DEVIATION,
    BLOCKED,
    TIMEOUT,
)
COLLISION_KINDS: frozenset[str] = frozenset(
    {COLLISION_PEDESTRIAN, COLLISION_VEHICLE, COLLISION_LAYOUT}
)

# Leaderboard 1.0 penalty coefficients; outside_lane is penalised by distance share
# instead, and route_deviation / blocked / timeout end the episode (they cost RC).
PENALTY_FACTORS: Mapping[str, float] = {
    COLLISION_PEDESTRIAN: 0.50,
    COLLISION_VEHICLE: 0.60,
    COLLISION_LAYOUT: 0.65,
    RED_LIGHT: 0.70,
    STOP_SIGN: 0.80,
}

# Metric key of each infraction count, in the order the leaderboard reports them.
COUNT_KEYS: Mapping[str, str] = {
    "CV": COLLISION_VEHICLE,
    "CP": COLLISION_PEDESTRIAN,
    "CL": COLLISION_LAYOUT,
    "TL": RED_LIGHT,
    "SS": STOP_SIGN,
    "OL": OUTSIDE_LANE,
    "RD": ROUTE_DEVIATION,
    "ABD": BLOCKED,
    "TO": TIMEOUT,
}
SCORE_KEYS: tuple[str, ...] = ("SR", "SSR", "RC", "IP", "DS")
# Scores reported in percent; IP is a factor and gets more decimals in tables.
PERCENT_KEYS: frozenset[str] = frozenset({"SR", "SSR", "RC", "DS"})


@dataclass(frozen=True)
class Infraction:
    """One infraction event: time in s since episode start, position in m (world frame)."""

    kind: str
    time_s: float
    x_m: float
    y_m: float
    actor: str = ""
    detail: str = ""

    def __post_init__(self) -> None:
        # Code constructs these, so a bad kind is a bug, not a user mistake.
        if self.kind not in INFRACTION_KINDS:
            raise ValueError(
                f"unknown infraction kind {self.kind!r}; expected one of {INFRACTION_KINDS}"
            )

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-friendly dict (floats and strings only)."""
        return {
            "kind": self.kind,
            "time_s": float(self.time_s),
            "x_m": float(self.x_m),
            "y_m": float(self.y_m),
            "actor": self.actor,
            "detail": self.detail,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Infraction:
        """Inverse of :meth:`to_dict`; ``actor`` and ``detail`` may be absent."""
        return cls(
            kind=str(data["kind"]),
            time_s=float(data["time_s"]),
            x_m=float(data["x_m"]),
            y_m=float(data["y_m"]),
            actor=str(data.get("actor", "")),
            detail=str(data.get("detail", "")),
        )


def dedup_collisions(infractions: Iterable[Infraction], window_s: float = 5.0) -> list[Infraction]:
    """Count repeated contact with the same actor once per ``window_s`` seconds.

    A collision whose ``actor`` matches an earlier *kept* collision at most ``window_s``
    seconds after it is dropped. The window runs from the last kept event, not the last
    seen one, so grinding along a wall for a long time still counts every ``window_s``
    (A at t=0, 3, 6 keeps 0 and 6). Collisions with an empty actor are never merged:
    an unidentified actor cannot be shown to be the same one. Non-collision
    infractions pass through; order is preserved. Input should be in time order.
    """
    if not window_s >= 0.0:
        raise ValueError(f"window_s must be >= 0, got {window_s}")
    last_kept: dict[str, float] = {}
    kept: list[Infraction] = []
    for inf in infractions:
        if inf.kind in COLLISION_KINDS and inf.actor:
            previous = last_kept.get(inf.actor)
            if previous is not None and inf.time_s - previous <= window_s:
                continue
            last_kept[inf.actor] = inf.time_s
        kept.append(inf)
    return kept


def _count(infractions: Sequence[Infraction], kind: str) -> int:
    return sum(1 for inf in infractions if inf.kind == kind)


def episode_metrics(
    *,
    route_length_m: float,
    completed_m: float,
    completed: bool,
    infractions: Sequence[Infraction],
    outside_lane_m: float,
) -> dict[str, float]:
    """Score one episode.

    Distances are in m. Returns RC, DS, SR, SSR in percent, IP as a factor in [0, 1],
    the infraction counts (CV, CP, CL, TL, SS, OL, RD, ABD, TO) and ``km`` driven.
    Pass infractions through :func:`dedup_collisions` first if the source repeats them.
    """
    if not (math.isfinite(route_length_m) and route_length_m > 0.0):
        raise ValueError(f"route_length_m must be a finite number > 0, got {route_length_m}")
    if not (math.isfinite(completed_m) and completed_m >= 0.0):
        raise ValueError(f"completed_m must be a finite number >= 0, got {completed_m}")
    if not (math.isfinite(outside_lane_m) and outside_lane_m >= 0.0):
        raise ValueError(f"outside_lane_m must be a finite number >= 0, got {outside_lane_m}")

    # The route's end can be reached with completed_m a little short of the route
    # length (waypoint spacing), so the flag wins.
    if completed:
        rc = 100.0
    else:
        rc = 100.0 * min(max(completed_m / route_length_m, 0.0), 1.0)

    ip = 1.0
    for inf in infractions:
        ip *= PENALTY_FACTORS.get(inf.kind, 1.0)
    outside_share = min(max(outside_lane_m / completed_m, 0.0), 1.0) if completed_m > 0.0 else 0.0
    ip *= 1.0 - outside_share

    collided = any(inf.kind in COLLISION_KINDS for inf in infractions)
    metrics: dict[str, float] = {
        "RC": rc,
        "IP": ip,
        "DS": rc * ip,
        "SR": 100.0 if completed and not collided else 0.0,
        "SSR": 100.0 if completed and not infractions else 0.0,
    }
    for key, kind in COUNT_KEYS.items():
        metrics[key] = _count(infractions, kind)
    metrics["km"] = completed_m / 1000.0
    return metrics


def _field(row: Mapping[str, Any], key: str, index: int) -> Any:
    try:
        return row[key]
    except KeyError:
        raise BidError(
            f"episode row {index} has no {key!r}; re-run the benchmark to regenerate results"
        ) from None


def stats(rows: Sequence[Mapping[str, Any]]) -> dict[str, float | int]:
    """Summarise episode rows (dicts from :func:`episode_metrics` plus ``seed``).

    Scores (SR, SSR, RC, IP, DS) are the mean over seeds of each seed's episode mean,
    with ``<KEY>_std`` the population std over those seed means, so seeds with more
    episodes do not weigh more. Counts are totals with ``<KEY>_per_km`` per km driven.
    """
    if not rows:
        raise BidError("no episodes to aggregate; run the benchmark first")

    by_seed: dict[Any, list[Mapping[str, Any]]] = {}
    for i, row in enumerate(rows):
        by_seed.setdefault(_field(row, "seed", i), []).append(row)

    out: dict[str, float | int] = {}
    for key in SCORE_KEYS:
        seed_means = [
            statistics.fmean(float(_field(r, key, i)) for i, r in enumerate(seed_rows))
            for seed_rows in by_seed.values()
        ]
        out[key] = statistics.fmean(seed_means)
        out[f"{key}_std"] = statistics.pstdev(seed_means) if len(seed_means) > 1 else 0.0

    total_km = math.fsum(float(_field(r, "km", i)) for i, r in enumerate(rows))
    for key in COUNT_KEYS:
        total = sum(int(_field(r, key, i)) for i, r in enumerate(rows))
        out[key] = total
        out[f"{key}_per_km"] = total / total_km if total_km > 0.0 else 0.0

    out["episodes"] = len(rows)
    out["seeds"] = len(by_seed)
    out["km"] = total_km
    return out


def _sort_key(value: Any) -> tuple[int, Any]:
    # Numbers in numeric order ahead of strings, so 2 sorts before 10 and mixed
    # group values do not raise.
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (0, value)
    return (1, str(value))


def aggregate(
    rows: Sequence[Mapping[str, Any]], group_by: Sequence[str] = ("density", "weather")
) -> dict[str, Any]:
    """Return ``{"all": stats, "by_<key>": {value: stats}}`` for each ``group_by`` key.

    Group values are sorted; see :func:`stats` for the fields of each summary.
    """
    if not rows:
        raise BidError("no episodes to aggregate; run the benchmark first")
    result: dict[str, Any] = {"all": stats(rows)}
    for key in group_by:
        groups: dict[Any, list[Mapping[str, Any]]] = {}
        for i, row in enumerate(rows):
            groups.setdefault(_field(row, key, i), []).append(row)
        result[f"by_{key}"] = {
            value: stats(groups[value]) for value in sorted(groups, key=_sort_key)
        }
    return result


def cell(group_stats: Mapping[str, Any], key: str) -> str:
    """One table cell: "mean ± std" for scores, integers for counts."""
    value = group_stats[key]
    if key in COUNT_KEYS or key in ("episodes", "seeds"):
        return str(int(value))
    if key.endswith("_per_km") or key == "km":
        return f"{float(value):.2f}"
    digits = 1 if key in PERCENT_KEYS else 3
    std_key = f"{key}_std"
    if std_key in group_stats:
        return f"{float(value):.{digits}f} ± {float(group_stats[std_key]):.{digits}f}"
    return f"{float(value):.{digits}f}"


def format_table(stats_by_group: Mapping[Any, Mapping[str, Any]], keys: Sequence[str]) -> str:
    """Render summaries from :func:`stats` as a Markdown table, one row per group.

    Scores with a ``_std`` show "mean ± std"; percentages get 1 decimal, IP 3,
    per-km rates and km 2, counts none.
    """
    lines = [
        "| group | " + " | ".join(keys) + " |",
        "|---|" + "---|" * len(keys),
    ]
    for group, group_stats in stats_by_group.items():
        missing = [k for k in keys if k not in group_stats]
        if missing:
            raise BidError(
                f"unknown metric {missing[0]!r} for the table; choose from "
                + ", ".join(k for k in group_stats if not k.endswith("_std"))
            )
        lines.append(f"| {group} | " + " | ".join(cell(group_stats, k) for k in keys) + " |")
    return "\n".join(lines)
