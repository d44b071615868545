"""`bid probe`: a model's hazard outputs measured on every frame of recordings it never saw."""

import itertools
import json

import numpy as np
import pytest
import torch

from bid_model.checkpoint import load_checkpoint, load_model
from bid_model.config import MOVING_MPS, PATH_KINDS
from bid_model.data import COMMAND_NAMES, command_one_hot
from bid_model.hazards import HAZARD_AHEAD_M, NEAR_M, SEEN_NEARNESS
from bid_model.probe import (
    CLOSE_M,
    _group,
    _lead_rows,
    _walk_in_result,
    probe_hazards,
    probe_table,
    walk_ins,
)
from bid_model.recordings import open_every_frame, open_recordings
from bid_model.train import hazard_detection
from bid_sim.cli import main as bid
from bid_sim.errors import BidError


@pytest.fixture(scope="module")
def hazard_run(recorded, tmp_path_factory):
    out = tmp_path_factory.mktemp("probe")
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--out", str(out / "plain")]) == 0
    assert bid([*base, "--init", str(out / "plain" / "last.pt"), "--hazard", "1", "--out", str(out / "hz")]) == 0
    return out


@pytest.fixture(scope="module")
def sc_run(recorded, tmp_path_factory):
    """last.pt of a tiny model trained with SC and its presence logits."""
    out = tmp_path_factory.mktemp("probe_sc") / "pr"
    assert bid(["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8",
                "--quiet", "--hazard", "1", "--hazard-sc", "--sc-presence", "--out", str(out)]) == 0
    return out / "last.pt"


def test_every_frame_is_every_recorded_frame_in_order_with_the_training_targets(recorded):
    every, facts = open_every_frame(recorded, (32, 96))
    train, val, _ = open_recordings(recorded, (32, 96), 0.5, 0, hazard=True)
    assert len(every) == len(train.index.step) and every.rows.tolist() == list(range(len(every)))
    assert [f["weather"] for f in facts] == ["ClearNoon", "HardRainNoon"]
    assert np.array_equal(every.hazard, train.hazard)
    for i in (0, len(every) - 1):
        sample = every[i]
        assert sample["step"] == int(train.index.step[i]) and sample["speed_mps"] == float(train.index.speed[i])
    j = int(val.rows[0])
    assert torch.equal(every[j]["frame"], val[0]["frame"]) and torch.equal(every[j]["prev_frame"], val[0]["prev_frame"])


def test_probe_can_count_pedestrians_where_they_will_be(recorded, hazard_run, one_thread, monkeypatch):
    """`bid probe --hazard-ahead S`: the targets `bid train --hazard-ahead S` fits (hazards'
    tests show what they count), so a sighting of a pedestrian about to walk into the path
    counts as right."""
    from bid_model import recordings

    asked = []
    real = recordings.index_hazards
    monkeypatch.setattr(recordings, "index_hazards",
                        lambda *a, **kw: asked.append(kw.get("ped_ahead_s")) or real(*a, **kw))
    ahead, _ = open_every_frame(recorded, (32, 96), hazard_ahead_s=1.5)
    train, _, _ = open_recordings(recorded, (32, 96), 0.5, 0, hazard=True, hazard_ahead_s=1.5)
    assert np.array_equal(ahead.hazard, train.hazard) and asked == [1.5, 1.5]
    checkpoint = hazard_run / "hz" / "last.pt"
    plain = probe_hazards(checkpoint, recorded, every=2)
    later = probe_hazards(checkpoint, recorded, every=2, hazard_ahead_s=1.5)
    # The walk-ins are counted where the pedestrians are, whatever the look-ahead.
    assert asked[2:] == [0.0, 1.5, 0.0]
    assert later["walk_ins"] == plain["walk_ins"]
    assert later["hazard_ahead_s"] == 1.5 and "hazard_ahead_s" not in plain
    ped = PATH_KINDS.index("pedestrian")
    near = ahead.hazard[::2, ped] >= 1 - NEAR_M / HAZARD_AHEAD_M
    assert later["all"]["pedestrian"]["near_frames"] == int(near.sum())
    assert later["all"]["vehicle"] == plain["all"]["vehicle"]
    assert "pedestrians also where they will be within 1.5 s" in probe_table(later)
    with pytest.raises(BidError, match="--hazard-ahead is in seconds"):
        probe_hazards(checkpoint, recorded, hazard_ahead_s=-1)


def test_probe_counts_what_the_outputs_see_overall_and_per_group(recorded, hazard_run, one_thread):
    checkpoint = hazard_run / "hz" / "last.pt"
    result = probe_hazards(checkpoint, recorded, every=2)
    data, _ = open_every_frame(recorded, (32, 96))
    rows = list(range(0, len(data), 2))
    assert result["frames"] == len(rows) and result["recordings"] == 2 and result["towns"] == ["Town02"]
    # The same figures as the training's measure on the same frames, the model run by hand.
    model, _ = load_model(checkpoint)
    items = [data[i] for i in rows]
    with torch.no_grad():
        pred = model(torch.stack([it["frame"] for it in items]), torch.stack([it["prev_frame"] for it in items]),
                     command_one_hot([it["command"] for it in items]), hazard=True)[1]
    target = torch.stack([it["hazard"] for it in items])
    want = hazard_detection(pred, target)
    for kind in ("pedestrian", "vehicle", "red_light"):
        got = result["all"][kind]
        for key in ("seen_near", "seen_none", "auc"):
            assert got[key] == (None if want[kind][key] is None else pytest.approx(want[kind][key]))
        k = ("pedestrian", "vehicle", "red_light").index(kind)
        assert got["none_frames"] == int((target[:, k] <= 0).sum())
        # At the brakes' threshold the same as above; higher, never more seen, right or wrong.
        assert got["at"]["0.2"] == {"seen_near": got["seen_near"], "seen_none": got["seen_none"]}
        for lower, higher in itertools.pairwise(got["at"].values()):
            for key in ("seen_near", "seen_none"):
                assert higher[key] is None or higher[key] <= lower[key]
        # How far the ones seen are read, and the close band apart: the same medians by hand.
        for rows, count, seen_key, read_key, true_key in (
                (target[:, k] >= 1 - NEAR_M / HAZARD_AHEAD_M, "near_frames", "seen_near", "read_m", "true_m"),
                (target[:, k] >= 1 - CLOSE_M / HAZARD_AHEAD_M, "close_frames", "seen_close", "read_close_m",
                 "true_close_m")):
            assert got[count] == int(rows.sum())
            both = rows & (pred[:, k] >= SEEN_NEARNESS)
            if both.any():
                assert got[read_key] == pytest.approx(float((1 - pred[both, k].clamp(max=1)).median()) * HAZARD_AHEAD_M)
                assert got[true_key] == pytest.approx(float((1 - target[both, k]).median()) * HAZARD_AHEAD_M)
                assert got[true_key] <= (NEAR_M if count == "near_frames" else CLOSE_M) + 1e-6
            else:
                assert got[read_key] is None and got[true_key] is None
            assert got[seen_key] == (None if not rows.any() else pytest.approx(float(both.sum() / rows.sum())))
        assert got["close_frames"] <= got["near_frames"]
        # Each grouping splits the frames: its groups' counts add up to all of them.
        for name, groups in result["by"].items():
            for count in ("near_frames", "none_frames", "close_frames"):
                assert sum(g[kind][count] for g in groups.values()) == got[count], name
    assert set(result["by"]["weather"]) == {"ClearNoon", "HardRainNoon"}
    assert set(result["by"]["command"]) == {COMMAND_NAMES[it["command"]] for it in items}
    # Standing or moving: split at MOVING_MPS of the recorded speed (the episodes hold both).
    moving = torch.tensor([float(it["speed_mps"]) >= MOVING_MPS for it in items])
    assert set(result["by"]["ego"]) == {"moving", "standing"}
    red = target[:, 2]
    assert result["by"]["ego"]["moving"]["red_light"]["none_frames"] == int((red[moving] <= 0).sum())
    assert result["by"]["ego"]["standing"]["red_light"]["none_frames"] == int((red[~moving] <= 0).sum())
    # Where the ego stands: at a red line, at a green one, elsewhere (moving counts as elsewhere).
    assert set(result["by"]["stop line"]) <= {"standing at a red line", "standing at a green line", "elsewhere"}
    assert "elsewhere" in result["by"]["stop line"]
    # The walk-ins, from where the pedestrians are (walk_ins' own test shows what counts).
    index = data.index
    entries, clear = walk_ins((1 - data.hazard[:, 0].astype(np.float64)) * HAZARD_AHEAD_M, index.episode,
                              index.step, index.speed)
    walked = result["walk_ins"]
    assert walked["entries"] == len(entries) == len(walked["list"])
    assert walked["clear_frames"] == int(clear[::2].sum())
    table = probe_table(result)
    assert "## pedestrian" in table and "| weather HardRainNoon |" in table
    assert "## pedestrians walking in" in table and "| before she enters, s | 0 | 0.5 | 1 | 1.5 | 2 |" in table
    assert "| all frames, nearness ≥ | 0.2 | 0.3 | 0.4 | 0.5 | 0.6 |" in table
    assert f"| seen: read m (true) | within {CLOSE_M:g} m | seen % | seen: read m (true) |" in table


def test_bid_probe_prints_and_writes_the_tables_and_refuses_bad_input(recorded, hazard_run, tmp_path, capsys,
                                                                      one_thread):
    checkpoint = str(hazard_run / "hz" / "last.pt")
    out = tmp_path / "probe" / "town02"
    assert bid(["probe", "--checkpoint", checkpoint, "--data", str(recorded), "--every", "3", "--threads", "1",
                "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "## red_light" in printed and out.with_suffix(".md").read_text().strip() in printed
    assert json.loads(out.with_suffix(".json").read_text())["every"] == 3
    for args, says in ((["--checkpoint", str(hazard_run / "plain" / "last.pt"), "--data", str(recorded)],
                        "no hazard head to probe"),
                       (["--checkpoint", checkpoint, "--data", str(tmp_path / "none")], "does not exist"),
                       (["--checkpoint", checkpoint, "--data", str(recorded), "--every", "0"], "every is a frame step")):
        assert bid(["probe", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    with pytest.raises(BidError, match="no hazard head"):
        probe_hazards(hazard_run / "plain" / "last.pt", recorded)


def test_probe_second_head_reads_the_second_head(recorded, tmp_path, one_thread, two_heads):
    """--second-head probes the second head (bid train --move-off-head): a copy of the first
    head reads as it does, a changed one otherwise; a checkpoint without one is refused."""
    from pathlib import Path

    from bid_model.checkpoint import save_checkpoint

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "bid_small.pt"
    _, two = two_heads()
    first = probe_hazards(tmp_path / "two.pt", recorded, every=9)
    second = probe_hazards(tmp_path / "two.pt", recorded, every=9, second=True)
    assert second.pop("head") == "second" and second == first
    two["model"]["hazard_move_off.2.bias"] += torch.tensor([0.0, 0.9, 0.0])  # sees a vehicle everywhere
    save_checkpoint(tmp_path / "two.pt", two)
    changed = probe_hazards(tmp_path / "two.pt", recorded, every=9, second=True)
    assert changed["all"]["vehicle"]["seen_none"] == 1.0 and changed["all"]["pedestrian"] == first["all"]["pedestrian"]
    assert "(its second head)" in probe_table(changed)
    # Fitted with --second-bumper, the second head is probed against its own vehicle target: the
    # nearer of the path's and the one ahead of the bumper; the pedestrian's as the first head's.
    two["config"]["train"]["second_bumper_m"] = 8.0
    save_checkpoint(tmp_path / "two.pt", two)
    bumped = probe_hazards(tmp_path / "two.pt", recorded, every=9, second=True)
    assert bumped["bumper_m"] == 8.0 and "within 8 m ahead of the bumper" in probe_table(bumped)
    assert bumped["all"]["vehicle"]["none_frames"] <= changed["all"]["vehicle"]["none_frames"]
    assert bumped["all"]["vehicle"]["near_frames"] >= changed["all"]["vehicle"]["near_frames"]
    assert bumped["all"]["pedestrian"] == changed["all"]["pedestrian"]
    assert "bumper_m" not in probe_hazards(tmp_path / "two.pt", recorded, every=9)
    with pytest.raises(BidError, match="no second head to probe"):
        probe_hazards(shipped, recorded, every=9, second=True)


def test_probe_reads_how_far_the_seen_ones_are_and_the_close_ones_apart():
    def nearness(metres):
        return 0.0 if metres is None else 1.0 - metres / HAZARD_AHEAD_M

    # Pedestrians at 2, 3, 3.5 and 8 m and none; the head reads 5, 6, nothing, 9 m and nothing.
    true_m, read_m = (2.0, 3.0, 3.5, 8.0, None), (5.0, 6.0, None, 9.0, None)
    target = torch.tensor([[nearness(t), 0.0, 0.0] for t in true_m])
    pred = torch.tensor([[nearness(r), 0.0, 0.0] for r in read_m])
    got = _group(pred, target)["pedestrian"]
    assert (got["near_frames"], got["close_frames"], got["none_frames"]) == (4, 3, 1)
    assert got["seen_near"] == pytest.approx(3 / 4) and got["seen_close"] == pytest.approx(2 / 3)
    # Medians of the seen ones (torch's: the lower middle of an even count).
    assert got["read_m"] == pytest.approx(6.0) and got["true_m"] == pytest.approx(3.0)
    assert got["read_close_m"] == pytest.approx(5.0) and got["true_close_m"] == pytest.approx(2.0)
    vehicle = _group(pred, target)["vehicle"]
    assert vehicle["close_frames"] == 0 and vehicle["seen_close"] is None and vehicle["read_close_m"] is None
    table = probe_table({"checkpoint": "c.pt", "folder": "d", "towns": ["Town02"], "recordings": 1, "frames": 5,
                         "every": 1, "all": _group(pred, target), "by": {}})
    assert "| all | 4 | 75.0 | 1 | 0.0 | 0.875 | 6.0 (3.0) | 3 | 66.7 | 5.0 (2.0) |" in table


def test_probe_source_reads_the_head_and_sc_apart(recorded, hazard_run, sc_run, capsys, one_thread):
    """--source head / SC: with SC, the head's reading and SC's alone, each as driving reads it
    (gated by its presence logit), against the same targets; SC's logits also at lower
    thresholds. The merged reading, the larger of the two, sees at least what either sees."""
    from bid_model.train import ranking_auc

    checkpoint = sc_run
    merged, head, sc = (probe_hazards(checkpoint, recorded, every=2, source=s) for s in ("merged", "head", "SC"))
    assert "source" not in merged and "logits" not in merged and "logits" not in head
    assert (head["source"], sc["source"]) == ("head", "SC")
    assert set(head["all"]) == {"pedestrian", "vehicle", "red_light"} and set(sc["all"]) == {"pedestrian", "vehicle"}
    # By hand: the model's apart columns, the head's and SC's readings out of them.
    model, _ = load_model(checkpoint)
    data, _ = open_every_frame(recorded, (32, 96))
    items = [data[i] for i in range(0, len(data), 2)]
    with torch.no_grad():
        apart = model(torch.stack([it["frame"] for it in items]), torch.stack([it["prev_frame"] for it in items]),
                      command_one_hot([it["command"] for it in items]), hazard=True, hazard_apart=True)[1]
    target = torch.stack([it["hazard"] for it in items])
    for got, pred in ((head, model.gate_head(apart[:, :3])), (sc, model.sc_near(apart))):
        want = hazard_detection(pred, target[:, :pred.shape[1]])
        for kind in want:
            for key in ("seen_near", "seen_none", "auc"):
                assert got["all"][kind][key] == (None if want[kind][key] is None else pytest.approx(want[kind][key]))
        assert set(got["by"]["stop line"]) == set(merged["by"]["stop line"])
    for kind in ("pedestrian", "vehicle"):
        for key in ("seen_near", "seen_none"):
            if merged["all"][kind][key] is not None:
                assert merged["all"][kind][key] >= max(head["all"][kind][key], sc["all"][kind][key]) - 1e-9
    near = target >= 1 - NEAR_M / HAZARD_AHEAD_M
    for k, kind in enumerate(("pedestrian", "vehicle")):
        logit = sc["logits"][kind]
        yes, no = apart[near[:, k], 5 + k].numpy(), apart[target[:, k] <= 0, 5 + k].numpy()
        assert logit["auc"] == (pytest.approx(ranking_auc(yes, no)) if len(yes) and len(no) else None)
        # A lower threshold says yes at least as often; at 0 at least as often as the gated nearness is seen.
        for lower, higher in itertools.pairwise(reversed(list(logit["at"].values()))):
            for key in ("seen_near", "seen_none"):
                assert lower[key] is None or higher[key] <= lower[key]
        for key in ("seen_near", "seen_none"):
            assert sc["all"][kind][key] is None or sc["all"][kind][key] <= logit["at"]["0"][key]
    printed = probe_table(sc)
    assert "(SC alone)" in printed and "## red_light" not in printed and "SC's logit (AUC" in printed
    assert "(its head alone)" in probe_table(head)
    # Refused: a model without SC, SC apart with the second head, an unknown source.
    plain = str(hazard_run / "hz" / "last.pt")
    for args, says in (([plain, "--source", "SC"], "has no SC"),
                       ([str(checkpoint), "--source", "head", "--second-head"], "drop one")):
        assert bid(["probe", "--checkpoint", args[0], "--data", str(recorded), *args[1:]]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    with pytest.raises(BidError, match="source is one of"):
        probe_hazards(checkpoint, recorded, source="sc")


def test_graft_puts_a_second_sc_beside_the_first_and_probe_reads_it_apart(recorded, hazard_run, sc_run, tmp_path,
                                                                          capsys, one_thread):
    """`bid graft CKPT --fine-sc DONOR`: CKPT's weights as they were, DONOR's SC beside them as the
    fine SC. Grafted onto itself (SC with presence at 1×), the fine SC reads what SC reads: `bid
    probe --source SC_fine` gives SC's figures, and the merged reading is the base's. Refused: no
    SC to graft onto, a donor without presence logits, a second graft, --source SC_fine without one.
    `bid train --train-only SC_fine` fine-tunes the fine SC alone."""
    out = tmp_path / "grafted.pt"
    assert bid(["graft", str(sc_run), "--fine-sc", str(sc_run), "--out", str(out)]) == 0
    assert "at 1x the cortex's resolution (input" in capsys.readouterr().out
    grafted, base = load_checkpoint(out), load_checkpoint(sc_run)
    assert grafted["config"]["model"]["sc_fine"] == 1 and grafted["graft"]["fine_sc"] == str(sc_run)
    assert "optimizer" not in grafted
    assert all(torch.equal(grafted["model"][k], v) for k, v in base["model"].items())
    sc_keys = [k for k in base["model"] if k.startswith("hazard_sc.")]
    assert sc_keys and all(torch.equal(grafted["model"]["hazard_sc_fine." + k.removeprefix("hazard_sc.")],
                                       base["model"][k]) for k in sc_keys)
    sc, fine = probe_hazards(sc_run, recorded, every=2, source="SC"), probe_hazards(out, recorded, every=2, source="SC_fine")
    assert fine["source"] == "SC_fine" and "(the fine SC alone)" in probe_table(fine)
    assert (fine["all"], fine["by"], fine["logits"]) == (sc["all"], sc["by"], sc["logits"])
    merged, merged_base = probe_hazards(out, recorded, every=2), probe_hazards(sc_run, recorded, every=2)
    assert (merged["all"], merged["by"]) == (merged_base["all"], merged_base["by"])
    plain = str(hazard_run / "hz" / "last.pt")
    for args, says in (([plain, "--fine-sc", str(sc_run)], "no SC (--hazard-sc)"),
                       ([str(sc_run), "--fine-sc", plain], "no SC with presence logits"),
                       ([str(out), "--fine-sc", str(sc_run)], "a fine SC already")):
        assert bid(["graft", *args, "--out", str(tmp_path / "no.pt")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    assert not (tmp_path / "no.pt").exists()
    with pytest.raises(BidError, match="has no fine SC"):
        probe_hazards(sc_run, recorded, source="SC_fine")
    # `bid train --init grafted.pt --train-only SC_fine` fits the fine SC (its presence loss) alone.
    assert bid(["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8",
                "--quiet", "--init", str(out), "--hazard", "1", "--hazard-sc", "--sc-presence", "--sc-fine", "1",
                "--train-only", "SC_fine",
                "--out", str(tmp_path / "ft")]) == 0
    for flags, says in ((["--sc-fine", "2"], "add --hazard-sc"), (["--hazard-sc", "--sc-fine", "5"], "whole factor")):
        assert bid(["train", "--preset", "tiny", "--synthetic", "--hazard", "1", *flags, "--out", str(tmp_path / "no")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    tuned = load_checkpoint(tmp_path / "ft" / "last.pt")["model"]
    changed = {k for k, v in tuned.items() if v.is_floating_point() and not torch.equal(v, grafted["model"][k])}
    assert changed and all(k.startswith("hazard_sc_fine.") for k in changed), sorted(changed)[:5]


def test_walk_ins_are_pedestrians_entering_a_moving_egos_path_near_after_a_clear_second():
    """An entry: one in the path ENTRY_M (12 m) or nearer ahead of an ego moving at MOVING_MPS
    or faster, after ENTRY_CLEAR_S (1 s, 10 recorded frames) with none in it; the frames LEADS_S
    before it are read."""
    none = HAZARD_AHEAD_M
    # Episode 0, 80 frames at 5 m/s: one walks in at step 20 (8 m) and stays to 25; another at
    # 28, only 0.3 s after, is no entry. Episode 1 stands: one at 5 m is no entry; one at 15 m
    # while it moves is too far. Episode 2 has a gap (steps 10-14 unrecorded): 16 is no entry,
    # nor is one at step 5, under a second into the episode.
    now0 = np.full(80, none)
    now0[20:26], now0[28:30] = 8.0, 7.0
    now1 = np.full(30, none)
    now1[15], now1[25] = 5.0, 15.0
    steps2 = np.r_[np.arange(10), np.arange(15, 31)]
    now2 = np.full(len(steps2), none)
    now2[np.searchsorted(steps2, 16)], now2[5] = 6.0, 6.0
    now = np.r_[now0, now1, now2]
    episode = np.r_[np.zeros(80), np.ones(30), np.full(len(steps2), 2)].astype(np.int64)
    step = np.r_[np.arange(80), np.arange(30), steps2]
    speed = np.r_[np.full(80, 5.0), np.full(25, 0.1), np.full(5, 4.0), np.full(len(steps2), 5.0)]
    entries, clear = walk_ins(now, episode, step, speed)
    assert entries.tolist() == [20]
    # Clear: moving, and none in the path from then to 3 s (30 frames) after, all recorded.
    assert np.flatnonzero(clear[:80]).tolist() == list(range(30, 50))
    assert not clear[80:110].any()  # standing, or someone ahead, or the episode ends too soon
    assert not clear[110:].any()
    # Ten frames a second: 0.5 s before is 5 frames back; 2 s before an entry at step 12 of an
    # episode that starts at 0 is not recorded (-1).
    leads = _lead_rows(np.array([20, 12]), np.zeros(80, dtype=np.int64), np.arange(80))
    assert {k: v.tolist() for k, v in leads.items()} == {"0": [20, 12], "0.5": [15, 7], "1": [10, 2],
                                                         "1.5": [5, -1], "2": [0, -1]}
    # The shares: seen at nearness SEEN_NEARNESS or more, over the entries with that frame.
    read = dict.fromkeys(range(80), 0.0) | {20: 0.5, 15: SEEN_NEARNESS, 12: 0.9, 2: 0.3, 30: 0.25}
    result = _walk_in_result(read, np.array([20, 12]), leads, np.r_[now0], np.full(80, 5.0),
                             np.array([30, 31, 32, 33]), ["a.mcap"], np.zeros(80, dtype=np.int64), np.arange(80))
    assert result["entries"] == 2 and result["clear_frames"] == 4 and result["clear_seen"] == 0.25
    assert {k: (v["frames"], v["seen"]) for k, v in result["leads"].items()} == {
        "0": (2, 1.0), "0.5": (2, 0.5), "1": (2, 0.5), "1.5": (1, 0.0), "2": (1, 0.0)}
    assert result["list"][0] == {"recording": "a.mcap", "step": 20, "m": 8.0, "mps": 5.0,
                                 "read": {"0": 0.5, "0.5": SEEN_NEARNESS, "1": 0.0, "1.5": 0.0, "2": 0.0}}
    assert result["list"][1]["read"]["2"] is None
