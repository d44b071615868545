"""Weather names (NoCrash ids). Weather changes only the rendering, never the traffic."""

from __future__ import annotations

from bid_sim.errors import BidError

WEATHERS = {
    "ClearNoon": 1,
    "WetNoon": 3,
    "HardRainNoon": 6,
    "ClearSunset": 8,
    "WetSunset": 10,
    "SoftRainSunset": 14,
}
TRAIN = ("ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset")
TEST = ("WetSunset", "SoftRainSunset")


def check_weather(name: str) -> str:
    if name not in WEATHERS:
        raise BidError(f"unknown weather {name!r}; use one of {', '.join(WEATHERS)}")
    return name


def parse_weathers(spec: str) -> tuple[str, ...]:
    """'train', 'test', 'all' or a comma-separated list of names."""
    if spec == "train":
        return TRAIN
    if spec == "test":
        return TEST
    if spec == "all":
        return tuple(WEATHERS)
    return tuple(check_weather(w.strip()) for w in spec.split(",") if w.strip())
