"""Shared fixtures: towns are built once per session (netconvert on demand)."""

import pytest

# Load torch before any test starts SUMO: a C++ extension first loaded after libsumo has
# raised an error makes the next SUMO start segfault (see bid_sim/__init__.py).
import torch  # noqa: F401

from bid_sim.routes import plan_spec, road_graph, route_by_index
from bid_sim.towns import resolve_town


@pytest.fixture(scope="session")
def town02():
    return resolve_town("02")


@pytest.fixture(scope="session")
def route02(town02):
    return plan_spec(road_graph(town02.net_file), route_by_index(town02, 0))
