"""Closed-loop benchmark runs on real SUMO: files, resume, parallel == serial, agents by
name or module:Class, bad input."""

import json
import shutil

import pytest

from bid_sim.cli import main
from bid_sim.evaluate import (
    compare,
    config_diff,
    evaluate,
    failure_cause,
    load_agent,
    outcome_tables,
    outcomes,
    p_text,
    paired_table,
    read_lines,
    sign_test_p,
    summary_markdown,
)

RUN = {"town": "02", "densities": ("none",), "weathers": ("WetSunset",), "seeds": 1, "routes": [0, 3],
       "agent": "bid_sim.agents:LaneFollower", "progress": False}


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    return out, evaluate(out=out, workers=1, **RUN)


def test_files_and_summary(serial):
    out, summary = serial
    lines = read_lines(out / "episodes.jsonl")
    assert [ln["key"] for ln in lines] == ["none/WetSunset/r00/s0", "none/WetSunset/r03/s0"]
    for ln in lines:
        assert {"SR", "SSR", "RC", "IP", "DS", "CV", "CP", "CL", "TL", "OL", "RD", "ABD"} <= set(ln["metrics"])
        assert ln["status"] in ("completed", "blocked", "route_deviation", "timeout")
        for inf in ln["infractions"]:
            assert {"kind", "time_s", "x_m", "y_m"} <= set(inf)
    s = json.loads((out / "summary.json").read_text())
    for key in ("SR", "SR_std", "SSR", "RC", "IP", "DS", "CV", "CV_per_km", "TL", "episodes"):
        assert key in s["all"], key
    assert set(s["by_density"]) == {"none"} and set(s["by_weather"]) == {"WetSunset"}
    assert s["all"]["episodes"] == 2
    md = (out / "summary.md").read_text()
    assert "| SR | SSR | TL |" in md and "## By density" in md
    assert "## What failed them first" in md and "## Where the time went" in md
    assert sum(s["outcomes"]["all"]["standing_s"].values()) <= s["outcomes"]["all"]["time_s"]
    assert s["outcomes"]["all"]["episodes"] == 2 and sum(s["outcomes"]["all"]["ended"].values()) == 2
    assert summary["eval_steps_per_s_per_core"] > 0


def _line(density, status, sr, *contacts, standing=None):
    return {"density": density, "status": status, "metrics": {"SR": sr}, "time_s": 100.0,
            **({"standing_s": standing} if standing else {}),
            "infractions": [{"kind": "red_light", "time_s": 1.0}]
            + [{"kind": kind, "time_s": t} for kind, t in contacts]}


def test_what_failed_an_episode_first():
    assert failure_cause(_line("normal", "completed", 100.0)) is None
    # the earliest collision, whatever order the infractions are in
    assert failure_cause(_line("normal", "completed", 0.0, ("collision_layout", 9.0),
                               ("collision_pedestrian", 4.0))) == "pedestrian"
    assert failure_cause(_line("normal", "route_deviation", 0.0, ("collision_vehicle", 30.0))) == "vehicle"
    # no collision: how it ended; a red light alone spoils no NoCrash success
    assert failure_cause(_line("crowded", "blocked", 0.0)) == "blocked"
    assert failure_cause(_line("crowded", "gave_up", 0.0)) == "other"
    lines = [_line("normal", "completed", 100.0), _line("normal", "timeout", 0.0),
             _line("crowded", "completed", 0.0, ("collision_vehicle", 2.0)), _line("crowded", "gave_up", 0.0)]
    out = outcomes(lines, ["crowded", "normal"])
    assert list(out["by_density"]) == ["crowded", "normal"]
    normal = out["by_density"]["normal"]
    assert normal["episodes"] == 2 and normal["failed"] == 1
    assert normal["ended"]["completed"] == 1 and normal["ended"]["timeout"] == 1
    assert normal["first_failure"]["timeout"] == 1
    crowded = out["by_density"]["crowded"]
    assert crowded["ended"]["other"] == 1 and crowded["first_failure"] == {
        "vehicle": 1, "pedestrian": 0, "layout": 0, "route_deviation": 0, "timeout": 0, "blocked": 0, "other": 1}
    assert out["all"]["failed"] == 3 and out["all"]["episodes"] == 4
    assert out["all"]["standing_from"] == 0 and "Where the time went" not in outcome_tables(out)


def test_where_the_time_went_adds_up_the_episodes_that_kept_it():
    lines = [_line("crowded", "completed", 100.0, standing={"light": 20.0, "vehicle": 5.0, "pedestrian": 1.0,
                                                            "nothing": 4.0}),
             _line("crowded", "timeout", 0.0, standing={"light": 10.0, "vehicle": 0.0, "pedestrian": 0.0,
                                                        "nothing": 50.0}),
             _line("crowded", "timeout", 0.0)]  # written before standing_s was kept
    out = outcomes(lines, ["crowded"])
    crowded = out["by_density"]["crowded"]
    assert crowded["standing_from"] == 2 and crowded["time_s"] == 200.0
    assert crowded["standing_s"] == {"light": 30.0, "vehicle": 5.0, "pedestrian": 1.0, "nothing": 54.0}
    table = outcome_tables(out)
    assert "## Where the time went" in table
    assert "| crowded | 2 | 200 | 90 (45 %) | 30 | 5 | 1 | 54 |" in table


def test_parallel_and_resumed_runs_match_serial(serial, tmp_path):
    out, summary = serial
    par = evaluate(out=tmp_path / "par", workers=2, **RUN)
    assert par["all"] == summary["all"]
    # A run killed after its first episode resumes with the second only.
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    lines = (out / "episodes.jsonl").read_text().splitlines()
    (resumed / "episodes.jsonl").write_text(lines[0] + "\n")
    (resumed / "config.json").write_text((out / "config.json").read_text())
    again = evaluate(out=resumed, workers=1, **RUN)
    assert again["all"] == summary["all"]
    assert len(read_lines(resumed / "episodes.jsonl")) == 2


def test_other_configuration_is_refused_but_more_seeds_extend_a_run(serial, tmp_path, capsys):
    out, _ = serial
    more = tmp_path / "more"
    shutil.copytree(out, more)

    def run(folder, seeds: str, routes: str = "0,3") -> int:
        return main(["evaluate", "--town", "02", "--density", "none", "--weathers", "WetSunset", "--routes", routes,
                     "--agent", "bid_sim.agents:LaneFollower", "--workers", "1", "--json", "--seeds", seeds,
                     "--out", str(folder)])

    assert run(more, "2") == 0
    lines = (more / "episodes.jsonl").read_text().splitlines()
    assert lines[:2] == (out / "episodes.jsonl").read_text().splitlines()  # seed 0's, kept as they were
    assert [json.loads(ln)["seed"] for ln in lines[2:]] == [1, 1]
    assert json.loads((more / "config.json").read_text())["seeds"] == 2
    capsys.readouterr()
    assert run(more, "1") == 2  # fewer seeds than done: refused
    assert "another configuration (seeds differ)" in capsys.readouterr().err
    assert run(out, "2", routes="0") == 2  # more seeds, but another change too
    assert "another configuration (seeds, routes differ)" in capsys.readouterr().err


def test_a_moved_checkpoint_resumes_another_one_does_not():
    """The same checkpoint bytes at another path (the repository cloned elsewhere) resume a
    results folder; other bytes at the same path, or another option, do not."""
    old = {"town": "Town02", "seeds": 1, "checkpoint": "/a/bid_small.pt", "checkpoint_sha256": "e2bb",
           "options": {"vehicle_hold": 5.0}, "software": "bid-sim 0.1.0"}
    assert config_diff(old, {**old, "checkpoint": "/b/bid_small.pt", "software": "bid-sim 0.2.0"}) == []
    assert config_diff(old, {**old, "checkpoint_sha256": "ffff"}) == ["checkpoint_sha256"]
    assert config_diff(old, {**old, "checkpoint": "/b/x.pt", "checkpoint_sha256": "ffff"}) \
        == ["checkpoint", "checkpoint_sha256"]
    assert config_diff(old, {**old, "checkpoint": "/b/x.pt", "options": None}) == ["options"]
    none = {**old, "checkpoint": None, "checkpoint_sha256": None}
    assert config_diff(none, {**none, "checkpoint": "/a/bid_small.pt"}) == ["checkpoint"]


def test_results_name_the_net_and_another_crossing_width_is_refused(serial, tmp_path, town_with_crossings, capsys):
    """Results of Town02 and of a Town02 folder with 4 m crossings do not mix in one --out;
    results written before config.json named the net still resume; a summary names crossings
    other than netconvert's 4 m."""
    from bid_sim import towns

    out, summary = serial
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["town_net"] == towns.net_tag(towns.resolve_town("02"))
    assert (cfg["crossing_width_m"], cfg["zebra_width_m"]) == (2.0, 4.0)
    assert summary_markdown(summary).startswith("# Town02 · 2 m crossings painted 4 m wide · agent")
    argv = ["evaluate", "--density", "none", "--weathers", "WetSunset", "--routes", "0,3",
            "--agent", "bid_sim.agents:LaneFollower", "--workers", "1", "--json", "--seeds", "1"]
    old = tmp_path / "old"
    shutil.copytree(out, old)
    (old / "config.json").write_text(json.dumps({k: v for k, v in cfg.items()
                                                 if k not in ("town_net", "crossing_width_m", "zebra_width_m")}))
    assert main([*argv, "--town", "02", "--out", str(old)]) == 0
    wide = town_with_crossings("02", 4.0)
    capsys.readouterr()
    assert main([*argv, "--town", str(wide.folder), "--out", str(out)]) == 2
    assert "another configuration (town_net, crossing_width_m, zebra_width_m differ)" in capsys.readouterr().err
    for width, zebra, title in ((4.0, None, "# Town02 · agent"), (2.0, None, "# Town02 · 2 m crossings · agent")):
        other = {**summary, "config": {**summary["config"], "crossing_width_m": width, "zebra_width_m": zebra}}
        assert summary_markdown(other).startswith(title)


def test_compare(serial, tmp_path, capsys):
    out, _ = serial
    assert main(["evaluate", "--compare", str(out), str(out)]) == 0
    table = capsys.readouterr().out
    assert "| all | SR |" in table
    assert table.splitlines()[0].count("(bid_sim.agents:LaneFollower)") == 2
    # a run from before standing_s was kept shows — in the standing rows
    old = tmp_path / "old"
    shutil.copytree(out, old)
    summary = json.loads((old / "summary.json").read_text())
    for group in (summary["outcomes"]["all"], *summary["outcomes"]["by_density"].values()):
        for key in ("standing_s", "standing_from", "time_s"):
            del group[key]
    (old / "summary.json").write_text(json.dumps(summary))
    assert main(["evaluate", "--compare", str(out), str(old)]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if "| standing, nothing near s |" in line]
    assert len(rows) == 2 and all(r.endswith(" | — |") and "| — | — |" not in r for r in rows)
    assert main(["evaluate", "--compare", str(tmp_path / "none")]) == 2


def test_compare_pairs_the_episodes_both_ran(serial, tmp_path):
    """Episode by episode against the first folder: the same keys, success against success, the
    sign test of the split and the mean DS difference; nothing paired across towns."""
    out, _ = serial
    lines = read_lines(out / "episodes.jsonl")
    same = paired_table(str(out), str(out))
    wins = sum(ln["metrics"]["SR"] >= 100.0 for ln in lines)
    assert f"| 2 | {wins} | {2 - wins} | 0 | 0 | 1.00 | +0.0 ± 0.0 |" in same
    flipped = tmp_path / "flipped"
    shutil.copytree(out, flipped)
    first = lines[0]
    succeeded = first["metrics"]["SR"] >= 100.0
    first = {**first, "status": "timeout" if succeeded else "completed",
             "metrics": {**first["metrics"], "SR": 0.0 if succeeded else 100.0,
                         "DS": first["metrics"]["DS"] - 10.0}}
    (flipped / "episodes.jsonl").write_text(json.dumps(first) + "\n")  # and the second not run
    table = paired_table(str(out), str(flipped))
    split = "| 1 | 0 | 0 | 1 | 0 |" if succeeded else "| 1 | 0 | 0 | 0 | 1 |"
    assert f"{split} 1.00 | -10.0 ± 0.0 |" in table
    before = failure_cause(lines[0]) or "success"
    assert f"| {first['key']} | {before} | {failure_cause(first) or 'success'} |" in table
    assert "## Episode by episode: flipped against " in compare([str(out), str(flipped)])
    other_town = tmp_path / "other_town"
    shutil.copytree(out, other_town)
    cfg = json.loads((other_town / "config.json").read_text())
    (other_town / "config.json").write_text(json.dumps({**cfg, "town": "Town01"}))
    assert paired_table(str(out), str(other_town)) == ""


def test_sign_test():
    assert sign_test_p(0, 0) == 1.0 and sign_test_p(10, 10) == 1.0
    assert sign_test_p(0, 5) == pytest.approx(2 / 32) and sign_test_p(5, 0) == sign_test_p(0, 5)
    assert sign_test_p(1, 9) == pytest.approx(2 * 11 / 1024)
    # 17 against 3: p = 2 (1 + 20 + 190 + 1140) / 2^20, printed with its digits, not as 0.00
    assert p_text(sign_test_p(17, 3)) == "0.0026" and p_text(0.61) == "0.61" and p_text(1.0) == "1.00"


@pytest.mark.parametrize(("agent", "words"), [("pilot", "unknown agent 'pilot'"),
                                               ("nosuch.module:Agent", "cannot load agent"),
                                               ("bid_sim.agents:Nope", "cannot load agent")])
def test_bad_agents(agent, words, tmp_path, capsys):
    assert main(["evaluate", "--town", "02", "--agent", agent, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err


def test_missing_checkpoint(tmp_path, capsys):
    assert main(["evaluate", "--town", "02", "--agent", "expert", "--checkpoint", str(tmp_path / "x.pt"),
                 "--out", str(tmp_path / "r")]) == 2
    assert "checkpoint" in capsys.readouterr().err


def test_named_agents_load():
    assert type(load_agent("lanefollow")).__name__ == "LaneFollower"
    assert type(load_agent("bid_sim.agents:LaneFollower")).__name__ == "LaneFollower"


def test_tables_lay_runs_out_like_the_paper(serial, tmp_path, capsys):
    out, summary = serial
    md = tmp_path / "tables.md"
    assert main(["tables", str(out), "--out", str(md)]) == 0  # the run folder itself
    text = md.read_text()
    assert text in capsys.readouterr().out
    row = next(ln for ln in text.splitlines() if ln.startswith(f"| {out.name} ("))
    sr = f"{summary['by_density']['none']['SR']:.1f} ± {summary['by_density']['none']['SR_std']:.1f}"
    assert row.split(" | ")[1] == sr and row.split(" | ")[4] == "—"  # none SR; no normal runs
    assert "| paper BID (CARLA Town02) | 100 | 100 |" in text
    assert "| run | town | DS | SR | IP | PA | ABD | IRL | CWO | CWP | CWV |" in text
    assert main(["tables", str(tmp_path / "empty")]) == 2


def test_video_of_the_first_episodes_only(tmp_path):
    run = {**RUN, "routes": [0, 3], "max_steps": 8}
    evaluate(out=tmp_path / "v", workers=1, video=1, **run)
    assert [p.name for p in (tmp_path / "v" / "videos").glob("*.mp4")] == ["none_WetSunset_r00_s0.mp4"]


class BrokenOnRoute3:
    """A user's agent with a bug that shows on one route only."""

    def __init__(self):
        from bid_sim.agents import LaneFollower

        self.inner = LaneFollower()

    def reset(self, info):
        self.route_index = info.route_index
        self.inner.reset(info)

    def act(self, obs):
        if self.route_index == 3:
            raise ZeroDivisionError("division by zero\nsecond line")
        return self.inner.act(obs)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_episode_ends_the_run_with_one_line_and_keeps_the_others(workers, tmp_path, capsys):
    out = tmp_path / "r"
    args = ["evaluate", "--town", "02", "--density", "none", "--weathers", "WetSunset", "--seeds", "1",
            "--routes", "3,0", "--agent", "test_evaluate:BrokenOnRoute3", "--max-steps", "20",
            "--workers", str(workers), "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress bar
    assert err == (f"error: episode none/WetSunset/r03/s0 failed (ZeroDivisionError: division by zero); the finished "
                   f"ones (1) are kept in {out / 'episodes.jsonl'}; rerun the same command to retry the rest")
    assert [ln["key"] for ln in read_lines(out / "episodes.jsonl")] == ["none/WetSunset/r00/s0"]
    assert not (out / "summary.json").exists()
