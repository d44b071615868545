"""`bid probe`: a model's hazard outputs measured on every frame of recordings it never saw."""

import itertools
import json

import numpy as np
import pytest
import torch

from bid_model.checkpoint import load_model
from bid_model.data import COMMAND_NAMES, command_one_hot
from bid_model.hazards import MOVING_MPS
from bid_model.probe import probe_hazards, probe_table
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
        # Each grouping splits the frames: its groups' counts add up to all of them.
        for name, groups in result["by"].items():
            assert sum(g[kind]["near_frames"] for g in groups.values()) == got["near_frames"], name
            assert sum(g[kind]["none_frames"] for g in groups.values()) == got["none_frames"], name
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
    table = probe_table(result)
    assert "## pedestrian" in table and "| weather HardRainNoon |" in table
    assert "| all frames, nearness ≥ | 0.2 | 0.3 | 0.4 | 0.5 | 0.6 |" in table


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
