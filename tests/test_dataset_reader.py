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


def test_recordings_of_several_towns_are_named_by_their_folder(recorded, tmp_path):
    # Each town's recorder numbers its episodes from 0, so the names alone repeat.
    src = sorted(recorded.glob("*.mcap"))
    for town, f in zip(("town01", "town02"), src, strict=True):
        (tmp_path / town).mkdir()
        shutil.copy(f, tmp_path / town / "ep00000.mcap")
    _, _, desc = open_recordings(tmp_path, (48, 144), 0.5, 0, cache=False)
    assert desc["recordings"] == 2 and desc["val_episodes"][0] in ("town01/ep00000.mcap", "town02/ep00000.mcap")


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


def _fake_index(speed, accel, episode):
    import numpy as np

    from bid_model.recordings import _Index

    n = len(speed)
    episode = np.asarray(episode)
    step = np.concatenate([np.arange((episode == e).sum()) for e in np.unique(episode)])
    return _Index([], [], episode, step, np.arange(n), np.full(n, 4), np.asarray(speed, np.float32),
                  np.zeros(n, np.float32), np.asarray(accel, np.float32), None)


def test_balance_thins_standing_keeps_the_lead_up_to_a_start_and_repeats_starts():
    import numpy as np

    from bid_model.recordings import GO_LOOKAHEAD, balance_rows

    # Episode 0: 40 standing (braking) frames, then 5 moving off, then 15 cruising.
    # Episode 1: 30 standing frames to its end (never starts).
    speed = [0.0] * 40 + [0.5, 1.0, 1.5, 1.8, 1.9] + [8.0] * 15 + [0.0] * 30
    accel = [-0.1] * 40 + [1.0] * 5 + [0.0] * 15 + [-0.1] * 30
    episode = [0] * 60 + [1] * 30
    ix = _fake_index(speed, accel, episode)
    rows, still = balance_rows(ix, np.arange(90), stop_keep=0.25, start_repeat=3)
    assert list(rows) == sorted(rows)
    counts = np.bincount(rows, minlength=90)
    assert (counts[40:45] == 3).all() and (counts[45:60] == 1).all()  # starts ×3, cruising once
    # Of each start's three rows, the two repeats are shown standing still.
    assert list(still[rows == 41]) == [False, True, True] and still.sum() == 10
    assert (counts[40 - GO_LOOKAHEAD:40] == 1).all()  # the lead-up to the start is all kept
    assert list(np.flatnonzero(counts[:40 - GO_LOOKAHEAD])) == list(range(0, 40 - GO_LOOKAHEAD, 4))
    assert list(np.flatnonzero(counts[60:])) == list(range(0, 30, 4))  # no lead-up across episodes
    same, none_still = balance_rows(ix, np.arange(90), 1.0, 1)
    assert list(same) == list(range(90)) and not none_still.any()  # off: unchanged
    with pytest.raises(BidError):
        balance_rows(ix, np.arange(90), 0.0, 1)


def test_yields_are_kept_and_repeated_but_not_stops_at_a_red_light():
    import numpy as np

    from bid_model.recordings import balance_rows, light_stops, yield_frames

    # Episode 0: 20 frames standing at a red light, then moving off. Episode 1: moving off,
    # braking at 1 m/s and standing 20 frames for a pedestrian (no light), then moving off.
    speed = [0.0] * 20 + [1.0] * 5 + [8.0] * 5 + [1.0] * 5 + [1.0] * 3 + [0.0] * 20 + [1.0] * 2
    accel = [-1.0] * 20 + [0.5] * 5 + [0.0] * 5 + [0.5] * 5 + [-0.6] * 3 + [-1.0] * 20 + [0.5] * 2
    ix = _fake_index(speed, accel, [0] * 30 + [1] * 30)
    rows0, _ = balance_rows(ix, np.arange(60), 0.25, 3)
    ix.light_stop = np.array([True] * 20 + [False] * 40)
    assert list(np.flatnonzero(yield_frames(ix))) == list(range(35, 58))
    assert list(balance_rows(ix, np.arange(60), 0.25, 3)[0]) == list(rows0)  # off: unchanged
    rows, still = balance_rows(ix, np.arange(60), 0.25, 3, hold_repeat=4)
    counts = np.bincount(rows, minlength=60)
    assert (counts[35:58] == 4).all()  # every yield frame, standing ones too: none thinned out
    assert list(counts[:20]) == list(np.bincount(rows0, minlength=60)[:20])  # the red light: as before
    assert not still[np.isin(rows, np.arange(35, 58))].any()  # shown as recorded
    with pytest.raises(BidError, match="hold_repeat"):
        balance_rows(ix, np.arange(60), 0.25, 3, hold_repeat=0)
    ix.light_stop = None  # recordings without light states: nothing counts as a yield
    assert not yield_frames(ix).any()
    assert light_stops({"next_light_state": 0, "next_light_dist_m": 12.0})  # red, near
    assert light_stops({"next_light_state": 1, "next_light_dist_m": 39.0})  # amber, near
    assert not light_stops({"next_light_state": 0, "next_light_dist_m": 80.0})  # red, far
    assert not light_stops({"next_light_state": 2, "next_light_dist_m": 5.0})  # green
    assert not light_stops({"next_light_state": 0, "next_light_dist_m": None})  # none on the route


def test_balance_drops_standing_frames_at_full_lock():
    import numpy as np

    from bid_model.recordings import balance_rows

    # A car stranded off its route: standing, the expert at full lock; then it drives, steering.
    speed = [0.0] * 20 + [5.0] * 10
    accel = [-1.0] * 20 + [0.3] * 10
    ix = _fake_index(speed, accel, [0] * 30)
    ix.steer[:] = -1.0
    ix.steer[5:8] = 0.2  # standing, a little steer: kept
    rows, _ = balance_rows(ix, np.arange(30), 1.0, 1)
    assert list(rows) == [5, 6, 7, *range(20, 30)]  # steering while moving is kept


def test_hard_steering_and_braking_frames_are_repeated_while_moving():
    import numpy as np

    from bid_model.recordings import balance_rows

    # Cruising, then a bend: braking into it, steering through it; then standing at full lock.
    speed = [10.0] * 10 + [9.0] * 5 + [6.0] * 5 + [0.0] * 5
    accel = [0.1] * 10 + [-0.5] * 5 + [0.0] * 5 + [-1.0] * 5
    ix = _fake_index(speed, accel, [0] * 25)
    ix.steer[15:20] = 0.8
    ix.steer[20:25] = 0.3  # standing: the wheel turns nothing, not a hard frame
    rows, still = balance_rows(ix, np.arange(25), 1.0, 1, hard_repeat=3)
    counts = np.bincount(rows, minlength=25)
    assert list(counts) == [1] * 10 + [3] * 10 + [1] * 5 and not still.any()
    assert list(balance_rows(ix, np.arange(25), 1.0, 1)[0]) == list(range(25))  # off: unchanged
    steering_only = np.bincount(balance_rows(ix, np.arange(25), 1.0, 1, hard_repeat=3, hard_brake=False)[0])
    assert list(steering_only) == [1] * 15 + [3] * 5 + [1] * 5  # braking into the bend: once
    with pytest.raises(BidError, match="hard_repeat"):
        balance_rows(ix, np.arange(25), 1.0, 1, hard_repeat=0)


def test_a_standstills_faint_throttle_is_a_hold_not_a_start():
    import numpy as np

    from bid_model.recordings import balance_rows, hold_creep

    # 20 frames standing in a queue, the expert closing up at +0.05; then moving off at +0.8
    # (5 frames), and a slow roll at +0.05 (moving: not a standstill, its label kept).
    speed = [0.0] * 20 + [0.5, 1.0, 1.5, 1.8, 1.9] + [1.0] * 5
    accel = [0.05] * 20 + [0.8] * 5 + [0.05] * 5
    ix = _fake_index(speed, accel, [0] * 30)
    every_throttle = np.bincount(balance_rows(ix, np.arange(30), 0.25, 3)[0], minlength=30)
    assert (every_throttle[:30] == 3).all()  # without: all 30 are starts, each trained on thrice
    rows, still = balance_rows(ix, np.arange(30), 0.25, 3, start_accel=0.3)
    counts = np.bincount(rows, minlength=30)
    assert (counts[20:25] == 3).all() and (counts[25:] == 1).all()  # only the real start repeated
    assert list(np.flatnonzero(counts[:10])) == [0, 4, 8] and (counts[10:20] == 1).all()  # thinned, lead-up kept
    assert still.sum() == 10
    labels = hold_creep(ix, None, 0.3)
    assert list(labels[:20]) == [0.0] * 20 and np.allclose(labels[20:], accel[20:])
    assert np.allclose(ix.accel, accel)  # the recorded labels untouched
    braking = np.full(30, -0.2, np.float32)  # labels already lowered (anticipate_braking): kept
    assert (hold_creep(ix, braking, 0.3) == braking).all()
    with pytest.raises(BidError, match="moves off"):
        balance_rows(ix, np.arange(30), 1.0, 1, start_accel=1.0)


def test_start_accel_reaches_the_training_labels_and_the_description(recorded, monkeypatch):
    import numpy as np

    import bid_model.recordings as recordings

    opened = recordings._open_index

    def closing_up(folder, cache):  # the expert moves off at full throttle: make its starts faint ones
        index, partial = opened(folder, cache)
        index.accel[(index.speed < recordings.STOPPED_MPS) & (index.accel > 0)] = 0.05
        return index, partial

    monkeypatch.setattr(recordings, "_open_index", closing_up)
    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, start_repeat=2, start_accel=0.3)
    ix = train.index
    creep = (ix.speed < recordings.STOPPED_MPS) & (ix.accel == np.float32(0.05))
    assert desc["start_accel"] == 0.3 and desc["train_creep_held"] == int(creep[train.rows].sum()) > 0
    i = int(np.flatnonzero(creep[train.rows])[0])
    assert train[i]["accel"] == 0.0 and ix.accel[train.rows[i]] == np.float32(0.05)  # recorded untouched
    plain, _, plain_desc = open_recordings(recorded, (48, 144), 0.5, 0, start_repeat=2)
    assert plain_desc["train_creep_held"] == 0 and plain_desc["start_accel"] == 0.0
    assert len(train) < len(plain)  # no longer repeated as starts
    creep_val = np.flatnonzero(creep[val.rows])
    if len(creep_val):  # validation keeps the labels as recorded
        assert val[int(creep_val[0])]["accel"] == np.float32(0.05)


def test_repeated_starts_are_shown_standing_still(recorded):
    train, _, desc = open_recordings(recorded, (48, 144), 0.5, 0, stop_keep=0.5, start_repeat=2)
    assert desc["train_shown_still"] == train.still.sum() > 0
    i = next(i for i in range(len(train)) if train.still[i] and train.index.speed[train.rows[i]] > 0)
    s, moving = train[i], train[i - 1]  # the same frame, first as recorded
    assert train.rows[i] == train.rows[i - 1] and s["speed_mps"] == 0.0 < moving["speed_mps"]
    assert torch.equal(s["prev_frame"], s["frame"]) and s["accel"] == moving["accel"] > 0


def test_reader_reads_the_light_ahead_and_counts_the_yields_it_repeats(recorded):
    import numpy as np

    from bid_model.recordings import light_stops, yield_frames
    from bid_sim.recording import read_episode

    train, _, desc = open_recordings(recorded, (48, 144), 0.5, 0, hold_repeat=3)
    ix = train.index
    first = read_episode(ix.files[0], frames=False)
    assert list(ix.light_stop[ix.episode == 0]) == [light_stops(s) for s in first.states]
    assert desc["hold_repeat"] == 3
    assert desc["train_yield_frames"] == int(yield_frames(ix)[train.rows].sum())
    plain = open_recordings(recorded, (48, 144), 0.5, 0)[0]
    assert len(train) - len(plain) >= 2 * len(np.unique(train.rows[yield_frames(ix)[train.rows]]))


def test_motion_dropout_hides_motion_but_keeps_speed(recorded):
    import numpy as np

    from bid_model.recordings import motion_dropout

    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, motion_drop=0.5)
    hidden = train.motionless
    assert desc["train_shown_motionless"] == hidden.sum() and 0.3 < hidden.mean() < 0.7
    assert not val.motionless.any()  # validation: every frame as recorded
    i = next(i for i in range(len(train)) if hidden[i] and train.index.speed[train.rows[i]] > 1.0)
    s = train[i]
    assert torch.equal(s["prev_frame"], s["frame"]) and s["speed_mps"] == pytest.approx(train.index.speed[train.rows[i]])
    j = next(j for j in range(1, len(train)) if not hidden[j] and not train.still[j]
             and train.index.speed[train.rows[j]] > 1.0)
    assert not torch.equal(train[j]["prev_frame"], train[j]["frame"])  # moving, shown as recorded
    assert np.array_equal(motion_dropout(100, 0.5, 3), motion_dropout(100, 0.5, 3))
    assert not motion_dropout(100, 0.0, 3).any()
    with pytest.raises(BidError, match="motion dropout"):
        motion_dropout(10, 1.0, 0)


def test_braking_labels_move_earlier_within_an_episode_and_throttle_does_not():
    import numpy as np

    from bid_model.recordings import anticipate_braking

    # Episode 0 cruises, brakes hard for 2 frames, stands, then moves off; episode 1 follows;
    # episode 2 slows for a bend without stopping.
    accel = [0.4, 0.4, 0.4, -1.0, -1.0, -0.2, -0.2, 0.6, 0.1, 0.1, 0.3, 0.3, -0.4, -0.4]
    ix = _fake_index([5.0] * 5 + [0.0] * 2 + [1.0] + [5.0] * 6, accel, [0] * 8 + [1] * 2 + [2] * 4)
    got = anticipate_braking(ix, 3)
    # Each label of a moving frame: the lower of itself and the mean over itself and the next
    # 2 of its episode, where those brake by STOP_BRAKE or more; slowing (episode 2) and
    # frames standing or moving off (5-7) stay as recorded.
    want = [0.4, (0.8 - 1.0) / 3, (0.4 - 2.0) / 3, -1.0, -1.0, -0.2, -0.2, 0.6, 0.1, 0.1, *accel[10:]]
    assert got == pytest.approx(want, abs=1e-6)
    # The standing frame right before moving off keeps its brake; episode 1 is not pulled down
    # by episode 0's braking, nor the last frames by frames that are not there.
    assert got[6] == pytest.approx(-0.2) and got[7] == pytest.approx(0.6)
    # Moving off and stopping again right away (a pedestrian): the start keeps its throttle;
    # at cruising speed the same labels would brake earlier.
    start = _fake_index([1.0, 1.5, 1.8], [0.6, 0.6, -1.0], [0, 0, 0])
    assert anticipate_braking(start, 3)[0] == pytest.approx(0.6)
    start.speed[:] = 5.0
    assert anticipate_braking(start, 3)[0] == pytest.approx(0.2 / 3)
    assert np.array_equal(anticipate_braking(ix, 1), ix.accel)
    # A gap in the steps (frames not recorded) ends the window as an episode's end does.
    ix.step[3:8] += 5
    assert anticipate_braking(ix, 3)[1] == pytest.approx(0.4)


def test_frames_of_a_stop_are_hard_ones_when_braking_is_anticipated():
    import numpy as np

    from bid_model.recordings import anticipate_braking, balance_rows

    # Cruising, slowing for a bend, cruising, then stopping: only the stop's frames repeat.
    accel = [0.3] * 3 + [-0.3] * 2 + [0.3] * 4 + [-0.3, -0.8, -1.0]
    ix = _fake_index([6.0] * 12, accel, [0] * 12)
    early = anticipate_braking(ix, 3)
    rows, _ = balance_rows(ix, np.arange(12), 1.0, 1, hard_repeat=2, hard_brake=False, accel=early)
    assert list(np.bincount(rows)) == [1] * 8 + [2] * 4  # 8 and 9 brake earlier than recorded
    rows, _ = balance_rows(ix, np.arange(12), 1.0, 1, hard_repeat=2, hard_brake=True, accel=early)
    assert list(np.bincount(rows)) == [1] * 3 + [2] * 2 + [1] * 3 + [2] * 4
    with pytest.raises(BidError, match="look-ahead"):
        anticipate_braking(ix, 0)


def test_reader_trains_on_anticipated_braking_and_validates_on_recorded_labels(recorded):
    from bid_model.recordings import anticipate_braking

    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, brake_lookahead=10)
    early = anticipate_braking(train.index, 10)
    assert desc["brake_lookahead"] == 10
    assert desc["train_labels_braking_earlier"] == (early[train.rows] < train.index.accel[train.rows]).sum()
    assert [train[i]["accel"] for i in range(len(train))] == pytest.approx(early[train.rows].tolist())
    assert [val[i]["accel"] for i in range(len(val))] == pytest.approx(val.index.accel[val.rows].tolist())
    assert open_recordings(recorded, (48, 144), 0.5, 0)[0].accel_labels is None


def test_future_speeds_hold_the_last_speed_at_an_episodes_end_or_a_gap():
    import numpy as np

    from bid_model.recordings import future_speeds

    ix = _fake_index([1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 8.0], [0.0] * 7, [0] * 5 + [1] * 2)
    got = future_speeds(ix, (1, 3))
    assert got.dtype == np.float32 and got.shape == (7, 2)
    # Episode 0 runs to 5 m/s and ends; episode 1 is not read into it.
    assert got[:, 0].tolist() == [2.0, 3.0, 4.0, 5.0, 5.0, 8.0, 8.0]
    assert got[:, 1].tolist() == [4.0, 5.0, 5.0, 5.0, 5.0, 8.0, 8.0]
    # Frames missing after step 1 (a gap) end the run as an episode's end does.
    ix.step[2:5] += 4
    assert future_speeds(ix, (3,))[:, 0].tolist() == [2.0, 2.0, 5.0, 5.0, 5.0, 8.0, 8.0]
    assert future_speeds(ix, ()).shape == (7, 0)


def test_reader_gives_the_speeds_ahead_to_train_and_validate_the_forecast_on(recorded):
    from bid_model.recordings import future_speeds

    train, val, desc = open_recordings(recorded, (48, 144), 0.5, 0, forecast_steps=(2, 5))
    assert desc["forecast_steps"] == [2, 5]
    want = future_speeds(train.index, (2, 5))
    for data in (train, val):
        for i in (0, len(data) // 2, len(data) - 1):
            sample = data[i]
            check_sample(sample, (48, 144))
            assert sample["future_speed"].tolist() == pytest.approx(want[data.rows[i]].tolist())
    assert "future_speed" not in open_recordings(recorded, (48, 144), 0.5, 0)[0][0]
