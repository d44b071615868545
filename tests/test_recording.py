"""Recordings: written by real episodes (SUMO, renderer), read back with the mcap library,
deterministic, resumable, re-renderable, salvageable."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import RECORD_PLAN, RECORD_STEPS
from mcap.reader import make_reader

from bid_sim.cli import main
from bid_sim.errors import BidError
from bid_sim.record import record
from bid_sim.recording import decode_jpeg, read_episode, read_snapshots, recover
from bid_sim.render import Renderer
from bid_sim.town_map import load_town_map

STEPS = RECORD_STEPS
PLAN = RECORD_PLAN


def files(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.mcap"))


def test_every_topic_is_there_with_foxglove_schemas(recorded):
    paths = files(recorded)
    assert [p.name for p in paths] == ["ep00000_ClearNoon_normal.mcap", "ep00001_HardRainNoon_normal.mcap"]
    assert not list(recorded.glob("*.partial"))
    with paths[0].open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        texts = {}
        for _s, ch, msg in reader.iter_messages(topics=["/ego/control", "/nav/command", "/ego/state"]):
            texts.setdefault(ch.topic, json.loads(msg.data))
    assert set(topics) == {"/camera/rgb", "/ego/control", "/ego/state", "/nav/command", "/scene", "/tf"}
    assert {t: (schemas[t].name, topics[t].message_encoding) for t in topics} == {
        "/camera/rgb": ("foxglove.CompressedImage", "protobuf"),
        "/scene": ("foxglove.SceneUpdate", "protobuf"),
        "/tf": ("foxglove.FrameTransform", "protobuf"),
        "/ego/control": ("bid.Control", "json"),
        "/ego/state": ("bid.EgoState", "json"),
        "/nav/command": ("bid.Command", "json"),
    }
    assert set(counts.values()) == {STEPS}
    assert meta["episode"]["town"] == "Town02" and meta["episode"]["weather"] == "ClearNoon"
    assert meta["episode"]["density"] == "normal" and meta["episode"]["agent"] == "lanefollow"
    assert meta["result"]["status"] == "timeout"
    assert set(texts["/ego/control"]) == {"steer", "accel", "throttle", "brake"}
    assert texts["/nav/command"]["name"] in ("LANEFOLLOW", "LEFT", "RIGHT", "STRAIGHT")
    assert {"x_m", "y_m", "yaw_rad", "speed_mps", "command", "step"} <= set(texts["/ego/state"])


def test_frames_decode_and_match_a_fresh_render(recorded, town02):
    path = files(recorded)[0]
    ep = read_episode(path)
    assert len(ep) == STEPS and ep.steps.tolist() == list(range(STEPS))
    renderer = Renderer(load_town_map(town02), weather="ClearNoon", seed=int(ep.facts["seed"]))
    for i, (snap, control) in enumerate(read_snapshots(path)):
        frame = decode_jpeg(ep.jpeg[i])
        assert frame.shape == (300, 900, 3)
        fresh = renderer.render(snap)
        assert np.abs(frame.astype(int) - fresh.astype(int)).mean() < 3.0  # JPEG q90 only
        assert control.steer == pytest.approx(float(ep.steer[i]))
        assert len(snap.vehicles) == len(snap.vehicles.ids)


def test_recording_is_deterministic(recorded, tmp_path):
    summary = record(out=tmp_path, **{**PLAN, "episodes": 1})
    assert summary["recorded"] == 1
    assert (tmp_path / "ep00000_ClearNoon_normal.mcap").read_bytes() == files(recorded)[0].read_bytes()


def test_rerun_resumes(recorded, tmp_path):
    for f in files(recorded):
        shutil.copy(f, tmp_path / f.name)
    (tmp_path / "ep00001_HardRainNoon_normal.mcap").unlink()
    (tmp_path / "ep00001_HardRainNoon_normal.mcap.partial").write_bytes(b"junk")  # a crashed try
    before = (tmp_path / "ep00000_ClearNoon_normal.mcap").stat().st_mtime_ns
    summary = record(out=tmp_path, **PLAN)
    assert summary["skipped"] == 1 and summary["recorded"] == 1
    assert (tmp_path / "ep00000_ClearNoon_normal.mcap").stat().st_mtime_ns == before
    assert not list(tmp_path.glob("*.partial"))
    assert read_episode(tmp_path / "ep00001_HardRainNoon_normal.mcap").jpeg


def test_rerender_under_another_weather(recorded, tmp_path, capsys):
    src = files(recorded)[0]
    out = tmp_path / "wet.mcap"
    assert main(["render", str(src), "--weather", "WetSunset", "--out", str(out)]) == 0
    a, b = read_episode(src), read_episode(out)
    assert b.facts["weather"] == "WetSunset" and b.facts["rendered_from"] == src.name
    np.testing.assert_array_equal(a.steps, b.steps)
    np.testing.assert_array_equal(a.steer, b.steer)
    fa, fb = decode_jpeg(a.jpeg[5]), decode_jpeg(b.jpeg[5])
    assert np.abs(fa.astype(int) - fb.astype(int)).mean() > 10  # another look
    assert main(["render", str(src), "--weather", "Foggy", "--out", str(out)]) == 2
    assert "unknown weather" in capsys.readouterr().err


def test_view_from_a_recording(recorded, tmp_path):
    src = files(recorded)[0]
    assert main(["view", str(src), "--out", str(tmp_path / "sheet.png")]) == 0
    assert main(["view", str(src), "--step", "4", "--out", str(tmp_path / "one.png")]) == 0
    assert main(["view", str(src), "--out", str(tmp_path / "all.mp4")]) == 0
    assert (tmp_path / "all.mp4").stat().st_size > 10_000


def test_recover_salvages_a_truncated_recording(recorded, tmp_path):
    data = files(recorded)[1].read_bytes()
    part = tmp_path / "ep.mcap.partial"
    part.write_bytes(data[: int(len(data) * 0.7)])
    path, steps = recover(part)
    assert path == tmp_path / "ep.mcap" and not part.exists()
    assert 0 < steps < STEPS
    ep = read_episode(path)
    assert len(ep) == steps and ep.result["status"] == "recovered"
    assert ep.steps.tolist() == list(range(steps))


def test_corrupt_and_partial_recordings_are_named(recorded, tmp_path):
    data = files(recorded)[0].read_bytes()
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(BidError, match=r"bad\.mcap is truncated or corrupt.*bid recover"):
        read_episode(bad)
    (tmp_path / "x.mcap.partial").write_bytes(data[:1000])
    with pytest.raises(BidError, match="unfinished"):
        read_episode(tmp_path / "x.mcap.partial")


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    for argv, words in ((["--town", "07"], "unknown town"), (["--weathers", "Foggy"], "unknown weather"),
                        (["--densities", "rush"], "unknown density"), (["--episodes", "0"], "--episodes")):
        assert main(["record", *argv, "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["record", "--town", "02", "--out", str(blocker / "sub")]) == 2
    assert "writable" in capsys.readouterr().err


def test_record_bends_takes_routes_round_a_corner(tmp_path):
    from bid_sim.recording import read_facts
    from bid_sim.routes import RouteSpec, plan_spec, road_graph
    from bid_sim.towns import resolve_town

    out = tmp_path / "bends"
    assert main(["record", "--town", "02", "--episodes", "2", "--densities", "none", "--weathers", "ClearNoon",
                 "--max-steps", "3", "--workers", "1", "--bends", "--out", str(out), "--json"]) == 0
    graph = road_graph(resolve_town("02").net_file)
    assert len(files(out)) == 2
    for f in files(out):
        start, goal = read_facts(f)["route"].split("->")
        (a, pa), (b, pb) = start.split("@"), goal.split("@")
        route = plan_spec(graph, RouteSpec(a, float(pa), b, float(pb)))
        assert any(s <= 250.0 for s, _ in route.road_bends())


def test_record_stop_line_gap_is_recorded_and_kept_to(tmp_path, capsys):
    """bid record --stop-line-gap: the expert stands that far before a red light's line
    (tests/test_expert.py); the recordings say so, and a folder is finished only with the same
    gap; another agent, or a gap out of range, is refused."""
    from bid_sim.recording import read_facts

    def rec(out, *flags):
        return main(["record", "--town", "02", "--episodes", "1", "--densities", "none", "--weathers", "ClearNoon",
                     "--max-steps", "3", "--workers", "1", *flags, "--out", str(out), "--json"])

    assert rec(tmp_path / "gap", "--stop-line-gap", "2.5") == 0
    capsys.readouterr()
    assert read_facts(files(tmp_path / "gap")[0])["stop_line_gap_m"] == "2.5"
    assert rec(tmp_path / "gap") == 2
    assert "stop_line_gap_m '2.5' here, 'none' planned" in capsys.readouterr().err
    for flags, says in ((("--stop-line-gap", "6"), "--stop-line-gap is a distance from 0 to 5 m; got 6.0"),
                        (("--stop-line-gap", "2.5", "--agent", "lanefollow"), "--stop-line-gap is where the expert stops")):
        assert rec(tmp_path / "x", *flags) == 2, flags
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err


def test_a_rerun_into_a_folder_of_another_recording_is_refused(recorded, tmp_path, town_with_crossings):
    """Rerunning finishes an interrupted recording; the same folder with another --seed,
    --perturb or --agent is refused before anything is written, the files left as they were."""
    for f in files(recorded):
        shutil.copy(f, tmp_path / f.name)
    before = {f.name: f.read_bytes() for f in files(tmp_path)}
    same = {**RECORD_PLAN, "out": tmp_path}
    assert record(**same)["skipped"] == 2
    for change, named in (({"seed": 4}, "seed"), ({"perturb": 0.2}, "perturb"), ({"agent": "expert"}, "agent")):
        with pytest.raises(BidError, match=f"belongs to another recording.*{named} .* planned.*another --out"):
            record(**{**same, **change})
    assert {f.name: f.read_bytes() for f in files(tmp_path)} == before
    from bid_sim import towns
    from bid_sim.recording import read_facts

    facts = read_facts(files(tmp_path)[0])
    assert facts["town_net"] == towns.net_tag(towns.resolve_town("02"))
    assert (facts["crossing_width_m"], facts["zebra_width_m"]) == ("2", "4")
    wide = town_with_crossings("02", 4.0)  # the same town with 4 m crossings: another net, refused
    with pytest.raises(BidError, match="2 m crossings painted 4 m wide here, 4 m crossings planned"):
        record(**{**same, "town": str(wide.folder)})


def test_record_from_a_town_folder_writes_into_out(tmp_path, monkeypatch):
    """--out is where a user town's episodes go, as for a numbered town (it was once ignored
    for folders, which all went to data/<folder name>)."""
    from bid_sim import towns

    monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
    mine = tmp_path / "mytown"
    mine.mkdir()
    shutil.copy(towns.resolve_town("02").net_file, mine / "city.net.xml")
    out = tmp_path / "o"
    monkeypatch.chdir(tmp_path)
    assert main(["record", "--town", str(mine), "--episodes", "1", "--densities", "none", "--weathers",
                 "ClearNoon", "--max-steps", "3", "--workers", "1", "--out", str(out), "--json"]) == 0
    assert len(files(out)) == 1 and not (tmp_path / "data").exists()


def test_kill_mid_episode_keeps_finished_ones(recorded, tmp_path):
    """kill -9 while recording: finished episodes stay intact, the partial is salvageable,
    and a re-run completes the rest."""
    for f in files(recorded):
        shutil.copy(f, tmp_path / f.name)
    (tmp_path / "ep00001_HardRainNoon_normal.mcap").unlink()
    cmd = [sys.executable, "-m", "bid_sim.cli", "record", "--town", "02", "--episodes", "2",
           "--weathers", "ClearNoon,HardRainNoon", "--densities", "normal", "--seed", "3", "--workers", "1",
           "--agent", "lanefollow", "--max-steps", "2000", "--out", str(tmp_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    part = tmp_path / "ep00001_HardRainNoon_normal.mcap.partial"
    deadline = time.time() + 60
    while time.time() < deadline and (not part.exists() or part.stat().st_size < 400_000):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert part.exists(), "the recording never got going"
    assert read_episode(tmp_path / "ep00000_ClearNoon_normal.mcap").jpeg  # untouched
    path, steps = recover(part)
    assert steps > 0 and len(read_episode(path)) == steps
