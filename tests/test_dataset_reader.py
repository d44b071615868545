"""The training reader over recordings (bid_model.recordings): contract samples, episode
split, frame t-1, the decoded-frame cache, unfinished and corrupt files."""

import shutil

import pytest
import torch
from conftest import RECORD_PLAN, RECORD_STEPS

from bid_model.data import check_sample
from bid_model.recordings import open_recordings
from bid_sim.errors import BidError

STEPS = RECORD_STEPS
PLAN = RECORD_PLAN


def test_reader_gives_contract_samples_split_by_episode(recorded, caplog):
    (recorded / "late.mcap.partial").write_bytes(b"x")
    try:
        train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0)
    finally:
        (recorded / "late.mcap.partial").unlink()
    assert "late.mcap.partial" in caplog.text and desc["skipped_partial"]
    assert len(train) + len(val) == 2 * STEPS and len(train) == len(val) == STEPS
    assert {train[i]["episode"] for i in range(len(train))}.isdisjoint({val[i]["episode"] for i in range(len(val))})
    s = train[3]
    check_sample(s, (48, 144))
    # frame t-1 is the previous step's frame; at the first step it is the frame itself.
    t_prev = train[2]["frame"]
    assert torch.equal(s["prev_frame"], t_prev)
    assert torch.equal(train[0]["prev_frame"], train[0]["frame"])
    nocache, _, d2 = open_recordings(recorded, (48, 144), 0.5, 0, cache=False)
    assert d2["cache"] is None and torch.equal(nocache[3]["frame"], s["frame"])



def test_corrupt_recording_is_named(recorded, tmp_path):
    src = sorted(recorded.glob("*.mcap"))[0]
    shutil.copy(src, tmp_path / "good.mcap")
    data = src.read_bytes()
    (tmp_path / "bad.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(BidError, match=r"bad\.mcap is truncated or corrupt"):
        open_recordings(tmp_path, (48, 144), 0.5, 0)


def test_empty_or_missing_folder(tmp_path):
    with pytest.raises(BidError, match="no finished recordings"):
        open_recordings(tmp_path, (48, 144), 0.5, 0)
    with pytest.raises(BidError, match="does not exist"):
        open_recordings(tmp_path / "nope", (48, 144), 0.5, 0)
