"""Shared fixtures: towns are built once per session (netconvert on demand)."""

import shutil
from pathlib import Path

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
def town_with_crossings(tmp_path, monkeypatch):
    """make(name, width_m, zebra_width_m=None): a copy of a built-in town under tmp_path with
    crossings `width_m` wide, painted `zebra_width_m` wide (as wide unless given); from then on
    nets are built under tmp_path."""
    from bid_sim import towns

    def make(name: str, width_m: float, zebra_width_m: float | None = None):
        monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
        folder = tmp_path / f"town{name}_{width_m:g}_{zebra_width_m or width_m:g}"
        shutil.copytree(resolve_town(name).folder, folder)
        toml = folder / "town.toml"
        kept = [ln for ln in toml.read_text().splitlines()
                if not ln.startswith(("crossing_width_m", "zebra_width_m"))]
        keys = [f"crossing_width_m = {width_m:g}"]
        keys += [f"zebra_width_m = {zebra_width_m:g}"] if zebra_width_m else []
        toml.write_text("\n".join(keys + kept) + "\n")  # before its tables
        return resolve_town(folder)

    return make


@pytest.fixture
def one_thread():
    """torch on one thread: tiny tensors gain nothing from threads, and OpenMP threads crawl
    on a busy machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"


@pytest.fixture
def two_heads(tmp_path):
    """make(speed) -> (path, payload): the shipped checkpoint with its hazard head copied in as a
    second head (model.move_off_head; reading the speed with `speed`), saved to tmp_path/two.pt."""
    from bid_model.checkpoint import load_checkpoint, save_checkpoint

    def make(speed: bool = True):
        two = load_checkpoint(SHIPPED)
        two["config"]["model"].update(move_off_head=True, **({"move_off_speed": True} if speed else {}))
        two["model"].update({"hazard_move_off." + k.removeprefix("hazard_head."): v.clone()
                             for k, v in two["model"].items() if k.startswith("hazard_head.")})
        save_checkpoint(tmp_path / "two.pt", two)
        return tmp_path / "two.pt", two

    return make
