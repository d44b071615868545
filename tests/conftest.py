"""Shared fixtures: towns are built once per session (netconvert on demand)."""

import pytest

from bid_sim.routes import plan_spec, road_graph, route_by_index
from bid_sim.towns import resolve_town


@pytest.fixture(scope="session")
def town02():
    return resolve_town("02")


@pytest.fixture(scope="session")
def route02(town02):
    return plan_spec(road_graph(town02.net_file), route_by_index(town02, 0))
