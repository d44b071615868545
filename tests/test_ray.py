"""Episodes as Ray tasks (bid_sim.cluster) give what local processes give: `record` the same
MCAP files byte for byte, `evaluate` the same episode lines and summary, timings aside.

Ray runs on a local instance of 2 CPUs; the tests that need it are skipped without Ray
(`make test` installs it with the cluster extra)."""

import json
import sys

import pytest
from conftest import RECORD_PLAN

from bid_sim import cluster
from bid_sim.cli import main
from bid_sim.evaluate import evaluate, read_lines
from bid_sim.record import record

EVAL = {"town": "02", "densities": ("normal",), "weathers": ("ClearNoon",), "seeds": 1,
        "routes": [0, 3], "agent": "lanefollow", "max_steps": 30, "progress": False}
TIMING = ("wall_s", "cpu_s", "eval_steps_per_s_per_core")  # the only fields that may differ


@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def untimed(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in TIMING}


def test_record_on_ray_equals_local(recorded, ray_local, tmp_path):
    summary = record(out=tmp_path, **RECORD_PLAN, ray_address="")
    assert summary["recorded"] == 2 and not summary["failed"]
    local, remote = sorted(recorded.glob("*.mcap")), sorted(tmp_path.glob("*.mcap"))
    assert [f.name for f in remote] == [f.name for f in local]
    for a, b in zip(local, remote, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    assert not list(tmp_path.glob(".ray-run-*"))  # the shared-folder marker is gone


def test_evaluate_on_ray_equals_local(ray_local, tmp_path):
    local = evaluate(out=tmp_path / "local", workers=1, **EVAL)
    remote = evaluate(out=tmp_path / "ray", ray_address="", **EVAL)
    assert cluster._initialised_for is None  # the agent was loaded in Ray's workers, not here
    assert untimed(remote) == untimed(local)
    # Lines are appended as episodes finish: compare them by episode.
    lines = {ln["key"]: untimed(ln) for ln in read_lines(tmp_path / "local" / "episodes.jsonl")}
    ray_lines = {ln["key"]: untimed(ln) for ln in read_lines(tmp_path / "ray" / "episodes.jsonl")}
    assert ray_lines == lines and len(lines) == 2
    saved = [json.loads((tmp_path / d / "summary.json").read_text()) for d in ("local", "ray")]
    assert untimed(saved[1]) == untimed(saved[0])


def test_without_ray_the_option_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as if not installed
    for argv in (["record", "--town", "02", "--episodes", "1", "--out", str(tmp_path / "r"), "--ray"],
                 ["evaluate", "--town", "02", "--agent", "lanefollow", "--out", str(tmp_path / "e"),
                  "--ray", "127.0.0.1:6379"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err == "error: --ray needs Ray: pip install 'bid-sim[cluster]'", err
    assert not (tmp_path / "r").exists() and not (tmp_path / "e").exists()  # no work started
