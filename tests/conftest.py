"""Shared fixtures: towns are built once per session (netconvert on demand)."""

import pytest

from bid_sim.record import record
from bid_sim.routes import plan_spec, road_graph, route_by_index
from bid_sim.towns import resolve_town

# Two short lane-follower episodes of Town02, recorded once per test session.
RECORD_STEPS = 25
RECORD_PLAN = {"town": "02", "episodes": 2, "weathers": ("ClearNoon", "HardRainNoon"),
               "densities": ("normal",), "seed": 3, "workers": 1, "agent": "lanefollow",
               "max_steps": RECORD_STEPS, "progress": False}


@pytest.fixture(scope="session")
def town02():
    return resolve_town("02")


@pytest.fixture(scope="session")
def route02(town02):
    return plan_spec(road_graph(town02.net_file), route_by_index(town02, 0))


@pytest.fixture(scope="session")
def recorded(tmp_path_factory):
    """A folder with the two recordings of RECORD_PLAN (tests must not change it)."""
    out = tmp_path_factory.mktemp("rec")
    summary = record(out=out, **RECORD_PLAN)
    assert summary["recorded"] == 2 and not summary["failed"]
    return out


@pytest.fixture
def one_thread():
    """torch on one thread: tiny tensors gain nothing from threads, and OpenMP threads crawl
    on a busy machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
