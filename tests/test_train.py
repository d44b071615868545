"""Training on generated tiny data: the run folder, resume = uninterrupted run, bad input."""

import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from bid_model.agent import BIDAgent
from bid_model.augment import photometric
from bid_model.checkpoint import average_checkpoints, load_checkpoint, load_model, save_checkpoint
from bid_model.config import RunConfig, model_config_from_dict, tiny, with_variant
from bid_model.data import SyntheticDriving, synthetic_split
from bid_model.model import BID
from bid_model.recordings import RecordingDataset
from bid_model.train import (
    METRIC_COLUMNS,
    EpisodeShardSampler,
    KeptAccel,
    KeptHazard,
    batch_inputs,
    busy_cores,
    hazard_loss,
    item_episodes,
    load_shared_weights,
    second_boost,
    second_targets,
    train,
    warm_start_crossing,
    warm_start_move_off,
)
from bid_sim.cli import _drive_options, build_parser
from bid_sim.cli import main as bid
from bid_sim.errors import BidError

pytestmark = pytest.mark.usefixtures("one_thread")


def quick_run(epochs: int) -> RunConfig:
    """The tiny preset on 60 generated samples."""
    run = tiny()
    return RunConfig(run.model, dataclasses.replace(run.train.with_epochs(epochs),
                                                    synthetic_samples=60))


def test_bid_train_writes_the_run_folder(tmp_path, capsys):
    out = tmp_path / "run"
    rc = bid(["train", "--preset", "tiny", "--synthetic", "--epochs", "2", "--out", str(out),
              "--quiet"])
    assert rc == 0
    assert str(out) in capsys.readouterr().out
    for name in ("config.json", "dataset.json", "metrics.csv", "last.pt", "best.pt", "mae.png",
                 "steering.png"):
        assert (out / name).is_file(), name
    assert not list(out.glob("*.tmp"))
    config = json.loads((out / "config.json").read_text())
    assert config["model"]["preset"] == "tiny" and config["train"]["epochs"] == 2
    assert len(config["git_hash"]) >= 7
    assert json.loads((out / "dataset.json").read_text())["kind"] == "synthetic"
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [r["epoch"] for r in rows] == ["1", "2"]
    assert tuple(rows[0]) == METRIC_COLUMNS
    assert all(float(r["samples_per_s"]) > 0 and float(r["val_mae_steer"]) >= 0 for r in rows)
    assert float(rows[1]["lr"]) < float(rows[0]["lr"])  # the scaled milestone at epoch 1
    for png in ("mae.png", "steering.png"):
        assert cv2.imread(str(out / png)).shape[2] == 3
    ckpt = load_checkpoint(out / "last.pt")
    assert ckpt["epoch"] == 2 and {"optimizer", "scheduler", "git_hash"} <= set(ckpt)
    model, run = load_model(out / "best.pt", preset="tiny")
    assert run.preset == "tiny" and not model.training


@pytest.mark.parametrize("augment", [0.0, 0.8])
def test_resume_continues_exactly(tmp_path, augment):
    run = quick_run(3)
    run = RunConfig(run.model, dataclasses.replace(run.train, augment=augment))
    straight = train(tmp_path / "a", run, synthetic=True, progress=False)
    first = train(tmp_path / "b", run, synthetic=True, progress=False, stop_after=1)
    assert len(first) == 1
    resumed = train(tmp_path / "b", synthetic=True, resume=True, progress=False)
    assert len(resumed) == 3
    for a, b in zip(straight, resumed, strict=True):
        for key in ("train_loss", "val_loss", "val_mae_steer", "val_mae_accel", "lr"):
            assert a[key] == b[key], (a["epoch"], key)
    sa = load_checkpoint(tmp_path / "a" / "last.pt")["model"]
    sb = load_checkpoint(tmp_path / "b" / "last.pt")["model"]
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert train(tmp_path / "b", synthetic=True, resume=True, progress=False) == resumed


def test_bad_input_gives_one_clear_line(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        (["train", "--preset", "tiny", "--data", str(tmp_path / "missing")], "no recordings"),
        (["train", "--preset", "tiny", "--data", str(empty), "--out", str(tmp_path / "r")],
         "no recordings in"),
        (["train", "--preset", "tiny", "--synthetic", "--resume", "--out", str(tmp_path / "r")],
         "nothing to resume"),
        (["train", "--resume"], "--out DIR or --name"),
        (["train", "--resume", "--no-hard-brake", "--out", str(tmp_path / "r")], "drop --hard-brake"),
        (["train", "--preset", "tiny", "--synthetic", "--brake-lookahead", "0"], "--brake-lookahead must be at least 1"),
        (["train", "--preset", "tiny", "--synthetic", "--epochs", "0"], "--epochs"),
        (["train", "--preset", "tiny", "--synthetic", "--augment", "1.5"], "--augment"),
        (["train", "--preset", "tiny", "--synthetic", "--device", "cpu", "--compile",
          "--out", str(tmp_path / "c")], "--compile is for CUDA"),
        (["gradcam", "--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path)],
         "no checkpoint"),
    ]
    for argv, message in cases:
        assert bid(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and message in err and "\n" not in err, (argv, err)
    assert not (tmp_path / "c").exists()  # refused before the run folder is made


def test_hard_frame_flags_reach_the_training_config():
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.train import config_from_args

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)

    def config(*flags):
        return config_from_args(parser.parse_args(["--preset", "tiny", *flags])).train

    assert config().hard_repeat == 1 and config().hard_brake
    steering_only = config("--hard-repeat", "3", "--no-hard-brake")
    assert steering_only.hard_repeat == 3 and not steering_only.hard_brake
    assert config().brake_lookahead == 1 and config("--brake-lookahead", "10").brake_lookahead == 10


def test_photometric_augmentation_changes_both_frames_alike():
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (64, 3, 8, 12), dtype=torch.uint8, generator=g)
    prev = torch.randint(0, 256, (64, 3, 8, 12), dtype=torch.uint8, generator=g)
    a, b = photometric(frame, prev, 0.5, torch.Generator().manual_seed(1))
    assert a.dtype == torch.uint8 and a.shape == frame.shape
    changed = (a != frame).flatten(1).any(1)
    assert changed.equal((b != prev).flatten(1).any(1))  # both frames of a sample, or neither
    assert 16 < int(changed.sum()) < 48
    again = photometric(frame, prev, 0.5, torch.Generator().manual_seed(1))
    assert a.equal(again[0]) and b.equal(again[1])
    same, same_too = photometric(frame, frame, 1.0, torch.Generator().manual_seed(2))
    assert same.equal(same_too) and not same.equal(frame)  # no motion made where there was none
    untouched = photometric(frame, prev, 0.0)
    assert untouched[0] is frame and untouched[1] is prev
    with pytest.raises(ValueError, match="two"):
        photometric(frame, prev[:3], 1.0)


def test_checkpoint_from_another_preset_is_refused(tmp_path, capsys):
    out = tmp_path / "run"
    train(out, quick_run(1), synthetic=True, progress=False)
    with pytest.raises(BidError, match="'tiny' preset, not 'small'"):
        load_model(out / "last.pt", preset="small")
    with pytest.raises(BidError, match="'tiny' preset, not 'small'"):
        train(out, synthetic=True, resume=True, expect_preset="small", progress=False)
    with pytest.raises(BidError, match="already holds a run"):
        train(out, quick_run(1), synthetic=True, progress=False)
    assert bid(["train", "--preset", "small", "--synthetic", "--resume", "--out", str(out)]) == 2
    assert "preset" in capsys.readouterr().err
    assert bid(["train", "--synthetic", "--resume", "--epochs", "5", "--out", str(out)]) == 2
    assert "drop --epochs" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(BidError, match="cannot read"):
        load_model(tmp_path / "junk.pt")


def test_episode_shards_are_whole_episodes_and_their_union_is_the_global_batch():
    """Process r of 2 trains on whole episodes of its own; batch k of one process with
    shards=2 is the union of the two processes' batches k; all yield as many batches."""
    episodes = np.repeat(np.arange(7), [20, 15, 30, 5, 20, 25, 10])

    def batches(rank: int, world: int, epoch: int) -> list[list[int]]:
        sampler = EpisodeShardSampler(episodes, 16, 2, rank, world, seed=3)
        sampler.set_epoch(epoch)
        out = list(sampler)
        assert len(out) == len(sampler)
        return out

    for epoch in (0, 1):
        one, r0, r1 = batches(0, 1, epoch), batches(0, 2, epoch), batches(1, 2, epoch)
        assert len(one) == len(r0) == len(r1) >= 6
        assert {len(b) for b in one} == {16} and {len(b) for b in r0 + r1} == {8}
        assert all(u == a + b for u, a, b in zip(one, r0, r1, strict=True))
        assert not set(episodes[np.concatenate(r0)]) & set(episodes[np.concatenate(r1)])
        assert len(set(np.concatenate(one))) == 16 * len(one)  # no item twice
    assert batches(0, 1, 0) != batches(0, 1, 1)  # another order each epoch, the same on a rerun
    assert batches(0, 1, 1) == one
    with pytest.raises(BidError, match="3 data shards cannot be split over 2"):
        EpisodeShardSampler(episodes, 16, 3, 0, 2)
    with pytest.raises(BidError, match="7 training episodes cannot be shared by 8"):
        EpisodeShardSampler(episodes, 16, 8, 0, 8)


def test_item_episodes_of_generated_data_and_recordings():
    train_set, _, _ = synthetic_split(100, (32, 96), 0.2, seed=0)
    expected = [train_set[i]["episode"] for i in range(len(train_set))]
    assert item_episodes(train_set).tolist() == expected
    index = SimpleNamespace(episode=np.array([0, 0, 1, 1, 1, 2]))
    rows = np.array([5, 2, 2, 0])  # a RecordingDataset's rows may repeat (balance_rows)
    assert item_episodes(RecordingDataset(index, rows, (32, 96), None)).tolist() == [2, 1, 1, 0]


@pytest.mark.skipif(shutil.which("torchrun", path=os.path.dirname(sys.executable)) is None,
                    reason="torchrun not installed")
def test_torchrun_ddp_equals_one_process_with_the_same_global_batch(tmp_path):
    """Two Gloo processes on whole episodes of their own end with the weights, batch norm
    statistics and areas' mean activations of one process that sees the same global
    batches (shards=2): 2 epochs of 5 steps of 2 × 8 samples.

    At the paper's lr: at the tiny preset's 10× larger one, Adam turns float rounding
    (sums in another order) in near-zero gradients into whole steps, and even two
    single-process runs that differ only in how batch norm sums drift apart by ~1e-3.
    """
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [torchrun, "--standalone", "--nproc-per-node=2", "-m", "bid_model.train", "--preset",
         "tiny", "--synthetic", "--samples", "100", "--epochs", "2", "--lr", "2e-4",
         "--device", "cpu", "--out", str(tmp_path / "ddp"), "--quiet"],
        capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((tmp_path / "ddp" / "config.json").read_text())["world_size"] == 2
    run = tiny()
    run = RunConfig(run.model, dataclasses.replace(run.train.with_epochs(2), lr=2e-4,
                                                   synthetic_samples=100))
    single = train(tmp_path / "one", run, synthetic=True, device="cpu", shards=2, progress=False)
    ddp = load_checkpoint(tmp_path / "ddp" / "last.pt")
    assert ddp["epoch"] == 2 and ddp["config"] == run.to_dict()
    for a, b in zip(ddp["history"], single, strict=True):
        for key in ("train_loss", "val_loss", "val_mae_steer", "val_mae_accel"):
            assert a[key] == pytest.approx(b[key], rel=1e-4), (a["epoch"], key)
    one = load_checkpoint(tmp_path / "one" / "last.pt")["model"]
    assert ddp["model"].keys() == one.keys()
    for key, w in one.items():
        torch.testing.assert_close(ddp["model"][key], w, rtol=1e-4, atol=1e-4, msg=key)


def test_a_torchrun_process_exits_with_its_code_and_its_output_written():
    """Under torchrun (WORLD_SIZE > 1) the process ends without finalizing the interpreter
    (train.exit_process), its buffered output and log lines written first."""
    script = ("import logging, os, sys; os.environ['WORLD_SIZE'] = '2'; from bid_model.train import exit_process; "
              "logging.basicConfig(level=logging.INFO, format='%(message)s'); logging.info('logged'); "
              "print('printed', end=''); exit_process(3)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # stdout buffered, as in a pipe
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert (proc.returncode, proc.stdout, proc.stderr.strip()) == (3, "printed", "logged")


def test_init_starts_from_a_checkpoints_weights(tmp_path, capsys):
    first = quick_run(1)
    train(tmp_path / "a", first, synthetic=True, progress=False)
    start = load_checkpoint(tmp_path / "a" / "last.pt")["model"]
    # A learning rate too small to move anything: the fine-tuned weights are the start's.
    still = RunConfig(first.model, dataclasses.replace(first.train, lr=1e-20, weight_decay=0.0))
    train(tmp_path / "b", still, synthetic=True, progress=False, init=tmp_path / "a" / "last.pt")
    tuned = load_checkpoint(tmp_path / "b" / "last.pt")
    weights = [name for name, _ in BID(first.model).named_parameters()]  # not the running statistics
    assert weights and all(torch.allclose(start[k], tuned["model"][k]) for k in weights)
    assert tuned["init"]["path"] == str(tmp_path / "a" / "last.pt")
    # From scratch, the same run ends elsewhere.
    train(tmp_path / "c", still, synthetic=True, progress=False)
    scratch = load_checkpoint(tmp_path / "c" / "last.pt")["model"]
    assert not all(torch.allclose(start[k], scratch[k]) for k in weights)
    other = RunConfig(dataclasses.replace(first.model, speed_input=True), first.train)
    with pytest.raises(BidError, match="different model \\(speed_input"):
        train(tmp_path / "d", other, synthetic=True, progress=False, init=tmp_path / "a" / "last.pt")
    assert bid(["train", "--preset", "tiny", "--synthetic", "--out", str(tmp_path / "e"),
                "--init", str(tmp_path / "missing.pt")]) == 2
    assert "no checkpoint at" in capsys.readouterr().err


def test_train_only_fits_the_parts_named_and_leaves_the_rest_as_it_was(tmp_path, capsys):
    """--train-only CPC after --init: CPC's weights move; every other tensor, the frozen areas'
    batch-norm statistics and mean activations included, stays exactly the start's."""
    first = quick_run(1)
    train(tmp_path / "a", first, synthetic=True, progress=False)
    start = load_checkpoint(tmp_path / "a" / "last.pt")["model"]
    head_only = RunConfig(first.model, dataclasses.replace(first.train, train_only=("CPC",)))
    train(tmp_path / "b", head_only, synthetic=True, progress=False, init=tmp_path / "a" / "last.pt")
    tuned = load_checkpoint(tmp_path / "b" / "last.pt")
    assert list(tuned["config"]["train"]["train_only"]) == ["CPC"]
    moved = {k for k in start if not torch.equal(start[k], tuned["model"][k])}
    assert moved and all(k.startswith("areas.CPC.") or k == "mean_CPC" for k in moved)
    assert any(k.startswith("areas.CPC.") and k.endswith("weight") for k in moved)
    assert any(k.startswith("areas.V2.") and "running_mean" in k for k in start)  # there were some to keep
    # A part the model lacks, or none: one line, before any run folder is written.
    for flag, says in (("hazard", "no such part; it has V1, V2"), (",", "names the parts to train")):
        assert bid(["train", "--preset", "tiny", "--synthetic", "--train-only", flag,
                    "--out", str(tmp_path / "c")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err
    assert not (tmp_path / "c").exists()


def test_keep_accel_fits_cpc_to_the_steering_labels_and_holds_its_accel(tmp_path, capsys):
    """--keep-accel: the accel labels are the --init control head's own on the same features;
    CPC fitted alone to them moves its steering and keeps its accel, a resumed run included."""
    first = quick_run(1)
    train(tmp_path / "a", first, synthetic=True, progress=False)
    init = tmp_path / "a" / "last.pt"
    model, _ = load_model(init)
    data = SyntheticDriving(8, first.model.frame_hw, seed=3)
    inputs, _ = batch_inputs(default_collate([data[i] for i in range(8)]), torch.device("cpu"))

    def control(m):
        m.eval()
        with torch.no_grad():
            return m(*inputs)

    kept = KeptAccel(model, load_checkpoint(init)["model"])
    before = control(model)
    labels = torch.tensor([[0.5, 0.9]] * 8)
    target = kept.target(labels)  # the init's own accel, the steering label as given
    assert torch.equal(target[:, 0], labels[:, 0]) and torch.allclose(target[:, 1], before[:, 1])

    lively = dataclasses.replace(first.train.with_epochs(2), train_only=("CPC",), lr=5e-3)
    keep = RunConfig(first.model, dataclasses.replace(lively, keep_accel=True))
    train(tmp_path / "keep", keep, synthetic=True, progress=False, init=init)
    train(tmp_path / "free", RunConfig(first.model, lively), synthetic=True, progress=False, init=init)
    after = {name: control(load_model(tmp_path / name / "last.pt")[0]) for name in ("keep", "free")}
    drift = {name: float((out[:, 1] - before[:, 1]).abs().mean()) for name, out in after.items()}
    assert float((after["keep"][:, 0] - before[:, 0]).abs().mean()) > 1e-3  # the steering learnt
    assert drift["keep"] < 0.5 * drift["free"], drift
    assert load_checkpoint(tmp_path / "keep" / "last.pt")["config"]["train"]["keep_accel"] is True
    # Resumed, the reference is the run's --init checkpoint again: as uninterrupted.
    train(tmp_path / "half", keep, synthetic=True, progress=False, init=init, stop_after=1)
    train(tmp_path / "half", synthetic=True, resume=True, progress=False)
    straight, resumed = (load_checkpoint(tmp_path / n / "last.pt")["model"] for n in ("keep", "half"))
    assert all(torch.equal(straight[k], resumed[k]) for k in straight)
    # Without CPC alone, or without a checkpoint to keep: one line each.
    for flags, says in ((("--keep-accel", "--init", str(init)), "add --train-only CPC"),
                        (("--keep-accel", "--train-only", "CPC"), "add --init CHECKPOINT")):
        assert bid(["train", "--preset", "tiny", "--synthetic", *flags, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    assert not (tmp_path / "x").exists()


def test_init_starts_another_variant_from_the_areas_they_share(tmp_path, capsys):
    """The paper's ablations can start from a trained BID: the areas a variant keeps carry over,
    the ones it lacks are dropped, and its own new ones (the MT → MPC tokens) start afresh."""
    first = quick_run(1)
    train(tmp_path / "full", first, synthetic=True, progress=False)
    start = load_checkpoint(tmp_path / "full" / "last.pt")["model"]
    still = dataclasses.replace(first.train, lr=1e-20, weight_decay=0.0)
    dorsal = RunConfig(with_variant(first.model, "dorsal"), still)
    train(tmp_path / "dorsal", dorsal, synthetic=True, progress=False, init=tmp_path / "full" / "last.pt")
    tuned = load_checkpoint(tmp_path / "dorsal" / "last.pt")
    weights = [name for name, _ in BID(dorsal.model).named_parameters()]
    kept = [k for k in weights if k in start]
    assert any(k.startswith("areas.MT.") for k in kept) and any(k.startswith("areas.MPC.") for k in kept)
    assert all(torch.allclose(start[k], tuned["model"][k]) for k in kept)
    assert not any(k.startswith(("areas.DPC.", "areas.OFC.")) for k in tuned["model"])
    assert {k for k in weights if k not in start} == {k for k in tuned["init"]["fresh"] if k in weights}
    assert tuned["init"]["fresh"] and all(k.startswith("dorsal_tokens.") or k.startswith("mean_")
                                          for k in tuned["init"]["fresh"])
    assert "starts" in capsys.readouterr().out
    # Anything beyond the variant still has to match.
    other = RunConfig(dataclasses.replace(dorsal.model, speed_input=not dorsal.model.speed_input), still)
    with pytest.raises(BidError, match="different model"):
        train(tmp_path / "x", other, synthetic=True, progress=False, init=tmp_path / "full" / "last.pt")


def test_init_starts_a_larger_input_from_a_checkpoint(tmp_path, capsys):
    """`--frame-hw` with `--init`: the convolutions carry over as they are, and the token grids'
    positional embeddings are resized to the new IT grid (a 1×3 grid becomes 2×6), bilinearly."""
    first = quick_run(1)
    train(tmp_path / "a", first, synthetic=True, progress=False)
    start = load_checkpoint(tmp_path / "a" / "last.pt")["model"]
    assert BID(first.model).grid_hw()["IT"] == (1, 3)
    still = dataclasses.replace(first.train, lr=1e-20, weight_decay=0.0)
    larger = RunConfig(dataclasses.replace(first.model, frame_hw=(64, 192)), still)
    train(tmp_path / "b", larger, synthetic=True, progress=False, init=tmp_path / "a" / "last.pt")
    tuned = load_checkpoint(tmp_path / "b" / "last.pt")
    weights = [name for name, _ in BID(larger.model).named_parameters()]
    grids = [k for k in weights if k.endswith("pos_embed")]
    assert grids == ["areas.VPC.pos_embed", "areas.DPC.tokens.pos_embed"]
    assert all(torch.allclose(start[k], tuned["model"][k]) for k in weights if k not in grids)
    for k in grids:
        old = start[k].reshape(1, 3, -1)
        new = tuned["model"][k].reshape(2, 6, -1)
        assert torch.allclose(new[0], new[1])  # one row of tokens spread over two
        # The edges keep the edge tokens; each old token spreads over two columns' worth.
        assert torch.allclose(new[:, 0], old[0, 0].expand(2, -1), atol=1e-6)
        assert torch.allclose(new[:, -1], old[0, -1].expand(2, -1), atol=1e-6)
        assert torch.allclose(new[0].mean(0), old[0].mean(0), atol=1e-6)
        assert not torch.allclose(new[0, 0], new[0, -1])
    assert all(k.startswith("mean_") for k in tuned["init"]["fresh"])
    assert "frame_hw differ" in capsys.readouterr().out
    assert bid(["train", "--preset", "tiny", "--synthetic", "--frame-hw", "64", "--out",
                str(tmp_path / "c")]) == 2
    assert "--frame-hw is ROWSxCOLS" in capsys.readouterr().err


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="needs Linux /proc/stat")
def test_busy_cores_counts_a_running_process_at_once(tmp_path):
    """Training picks its torch threads from the cores busy right now, not the load average
    (which still counts a recording that has just ended): a spinning process counts."""
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 5: pass"])
    try:
        time.sleep(0.5)
        assert busy_cores(1.0) >= 0.6
    finally:
        spin.kill()
        spin.wait()
    frozen = tmp_path / "stat"
    frozen.write_text("cpu  100 0 50 1000 5 0 0 0 0 0\n")
    assert busy_cores(0.01, stat=str(frozen)) == 0.0  # no ticks passed: nothing busy, no division by zero
    assert busy_cores(0.01, stat=str(tmp_path / "missing")) is None  # the caller falls back to the load average


def test_bid_average_is_the_weighted_mean_of_two_fine_tunings(tmp_path, capsys):
    first = quick_run(1)
    train(tmp_path / "a", first, synthetic=True, progress=False)
    train(tmp_path / "b", RunConfig(first.model, dataclasses.replace(first.train, seed=1)), synthetic=True,
          progress=False)
    a, b = (load_checkpoint(tmp_path / n / "last.pt")["model"] for n in "ab")
    out = tmp_path / "soup" / "last.pt"
    assert bid(["average", str(tmp_path / "a" / "last.pt"), str(tmp_path / "b" / "last.pt"),
                "--weights", "1,3", "--out", str(out)]) == 0
    soup = load_checkpoint(out)
    floats = [k for k, v in a.items() if v.is_floating_point()]
    assert floats and any(not torch.equal(a[k], b[k]) for k in floats)
    for k in floats:
        torch.testing.assert_close(soup["model"][k], 0.25 * a[k] + 0.75 * b[k], msg=k)
    assert all(torch.equal(soup["model"][k], a[k]) for k in a if k not in floats)  # batch counts
    assert [s["weight"] for s in soup["init"]["average"]] == [0.25, 0.75]
    model, _ = load_model(out, preset="tiny")
    h, w = first.model.frame_hw
    frames = torch.randint(0, 255, (2, 3, h, w), dtype=torch.uint8)
    speed = torch.full((2,), 5.0) if first.model.speed_input else None
    steer_accel = model(frames, frames, torch.eye(6)[[3, 0]], speed)
    assert steer_accel.shape == (2, 2) and torch.isfinite(steer_accel).all()
    assert bid(["export", str(out.parent), "--which", "last.pt", "--out", str(tmp_path / "soup.pt")]) == 0
    # Another network, a lone checkpoint or bad weights: one line, exit 2.
    other = RunConfig(dataclasses.replace(first.model, speed_input=True), first.train)
    train(tmp_path / "c", other, synthetic=True, progress=False)
    capsys.readouterr()
    for argv, says in (([str(tmp_path / "a" / "last.pt"), str(tmp_path / "c" / "last.pt")], "another network"),
                       ([str(tmp_path / "a" / "last.pt")], "two or more"),
                       ([str(tmp_path / "a" / "last.pt"), str(tmp_path / "b" / "last.pt"), "--weights", "1"],
                        "--weights needs 2 numbers")):
        assert bid(["average", *argv, "--out", str(tmp_path / "x.pt")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not (tmp_path / "x.pt").exists()


def test_speed_forecast_trains_the_network_and_driving_ignores_it(tmp_path, capsys, monkeypatch):
    """--forecast adds a head that forecasts the speed ahead; its loss reaches the shared
    network, the metrics report its error, and the control output stays what it was."""
    plain = quick_run(1)
    forecast = RunConfig(dataclasses.replace(plain.model, forecast_s=(1.0, 2.0)),
                         dataclasses.replace(plain.train, lambda_forecast=0.5))
    train(tmp_path / "plain", plain, synthetic=True, progress=False)
    history = train(tmp_path / "fc", forecast, synthetic=True, progress=False,
                    init=tmp_path / "plain" / "last.pt")
    assert history[-1]["val_mae_forecast_mps"] > 0
    rows = list(csv.DictReader((tmp_path / "fc" / "metrics.csv").open()))
    assert float(rows[-1]["val_mae_forecast_mps"]) == pytest.approx(history[-1]["val_mae_forecast_mps"], rel=1e-4)
    tuned = load_checkpoint(tmp_path / "fc" / "last.pt")
    assert {k for k in tuned["init"]["fresh"] if not k.startswith("mean_")} == {
        k for k in tuned["model"] if k.startswith("forecast_head.")}
    assert "forecast_s differ" in capsys.readouterr().out
    # The same fine-tuning without the forecast's loss ends elsewhere in the shared network.
    again = RunConfig(plain.model, plain.train)
    train(tmp_path / "again", again, synthetic=True, progress=False, init=tmp_path / "plain" / "last.pt")
    other = load_checkpoint(tmp_path / "again" / "last.pt")["model"]
    assert not torch.allclose(other["areas.V1.conv1.0.weight"], tuned["model"]["areas.V1.conv1.0.weight"])
    # Driving reads (steer, accel) alone; forecast=True adds the speeds ahead, in m/s.
    model, _ = load_model(tmp_path / "fc" / "last.pt", preset="tiny")
    sample = synthetic_split(4, (32, 96), 0.0, 0)[0][0]
    inputs = (sample["frame"][None], sample["prev_frame"][None], torch.eye(6)[[3]])
    with torch.no_grad():
        control = model(*inputs)
        both, ahead = model(*inputs, forecast=True)
    assert control.shape == (1, 2) and torch.equal(control, both) and ahead.shape == (1, 2)
    with pytest.raises(BidError, match="no speed forecast"):
        BID(plain.model).forward_forecast({"MPC": torch.zeros(1, 3, 16)})
    half = RunConfig(forecast.model, plain.train)
    with pytest.raises(BidError, match="--forecast WEIGHT"):
        train(tmp_path / "half", half, synthetic=True, progress=False)
    # Data without the speeds ahead gets one clear line, not a KeyError mid-epoch.
    monkeypatch.setattr("bid_model.train.open_data", lambda config, data, synthetic: synthetic_split(
        20, config.model.frame_hw, 0.2, 0))
    with pytest.raises(BidError, match="'future_speed'"):
        train(tmp_path / "nofc", forecast, synthetic=True, progress=False)


def test_forecast_flag_sets_head_and_weight_together(tmp_path, capsys):
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.config import FORECAST_S
    from bid_model.train import config_from_args

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--forecast", "0.5"]))
    assert run.model.forecast_s == FORECAST_S and run.train.lambda_forecast == 0.5
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--forecast", "0"]))
    assert run.model.forecast_s == () and run.train.lambda_forecast == 0.0
    assert bid(["train", "--preset", "tiny", "--synthetic", "--forecast", "-1",
                "--out", str(tmp_path / "x")]) == 2
    assert "--forecast is the weight" in capsys.readouterr().err


def test_speed_noise_scales_each_speed_by_a_log_normal_factor_and_reaches_training(tmp_path, capsys):
    """--speed-noise σ trains on speed × exp(σ·N(0,1)): standstill stays 0, the log-ratio has
    spread σ, and a run with it ends elsewhere than one without."""
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.train import config_from_args, noisy_speed

    speed = torch.full((20000,), 5.0)
    speed[:100] = 0.0
    torch.manual_seed(0)
    noisy = noisy_speed(speed, 0.3)
    assert torch.equal(noisy[:100], speed[:100])
    log_ratio = (noisy[100:] / speed[100:]).log()
    assert abs(float(log_ratio.mean())) < 0.01 and float(log_ratio.std()) == pytest.approx(0.3, rel=0.05)
    assert noisy_speed(speed, 0.0) is speed

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert config_from_args(parser.parse_args(["--preset", "small"])).train.speed_noise == 0.0
    assert config_from_args(parser.parse_args(["--preset", "small", "--speed-noise", "0.3"])).train.speed_noise == 0.3
    for flags, says in ((["--preset", "small", "--speed-noise", "-1"], "--speed-noise is the σ"),
                        (["--preset", "tiny", "--speed-noise", "0.3"], "--speed-noise needs a speed input")):
        assert bid(["train", *flags, "--synthetic", "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    assert not (tmp_path / "x").exists()

    base = quick_run(1)
    exact = RunConfig(dataclasses.replace(base.model, speed_input=True), base.train)
    noised = RunConfig(exact.model, dataclasses.replace(exact.train, speed_noise=0.5))
    train(tmp_path / "exact", exact, synthetic=True, progress=False)
    train(tmp_path / "noised", noised, synthetic=True, progress=False)
    a = load_checkpoint(tmp_path / "exact" / "last.pt")["model"]["speed_token.weight"]
    b = load_checkpoint(tmp_path / "noised" / "last.pt")["model"]["speed_token.weight"]
    assert not torch.allclose(a, b)


def test_accel_quantile_fits_that_quantile_of_the_labels_and_half_is_l1(tmp_path, capsys):
    """--accel-quantile τ: a constant fitted by the loss lands on the labels' τ-quantile for
    accel and their median for steer; τ = 0.5 is the plain L1 loss."""
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.train import config_from_args, l1_loss

    gen = torch.Generator().manual_seed(0)
    labels = torch.stack([torch.rand(4000, generator=gen) * 2 - 1, torch.rand(4000, generator=gen) * 2 - 1], 1)
    l1 = tiny().train
    pred = torch.zeros(4000, 2) + 0.1
    assert float(l1_loss(pred, labels, l1)) == pytest.approx(
        float(0.5 * (labels - pred).abs().mean(0).sum()), rel=1e-6)
    tc = dataclasses.replace(l1, accel_quantile=0.2)
    const = torch.zeros(2, requires_grad=True)
    opt = torch.optim.SGD([const], lr=0.02)
    for _ in range(600):
        opt.zero_grad()
        l1_loss(const.expand(4000, 2), labels, tc).backward()
        opt.step()
    const = const.detach()
    assert float(const[1]) == pytest.approx(float(labels[:, 1].quantile(0.2)), abs=0.03)
    assert float(const[0]) == pytest.approx(float(labels[:, 0].median()), abs=0.03)

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert config_from_args(parser.parse_args(["--preset", "tiny"])).train.accel_quantile == 0.5
    assert config_from_args(parser.parse_args(["--preset", "tiny", "--accel-quantile", "0.3"])).train.accel_quantile == 0.3
    assert bid(["train", "--preset", "tiny", "--synthetic", "--accel-quantile", "1",
                "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--accel-quantile is a quantile" in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_hold_and_start_repeat_reach_the_config_and_a_bad_one_is_one_line(tmp_path, capsys):
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.train import config_from_args

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert config_from_args(parser.parse_args(["--preset", "tiny"])).train.hold_repeat == 1
    assert config_from_args(parser.parse_args(["--preset", "tiny", "--hold-repeat", "6"])).train.hold_repeat == 6
    assert config_from_args(parser.parse_args([])).train.start_repeat == 3  # the small preset's
    assert config_from_args(parser.parse_args(["--start-repeat", "8"])).train.start_repeat == 8
    assert bid(["train", "--preset", "tiny", "--synthetic", "--start-repeat", "0", "--out", str(tmp_path / "z")]) == 2
    assert "--start-repeat must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "z").exists()
    assert config_from_args(parser.parse_args([])).train.start_accel == 0.0
    assert config_from_args(parser.parse_args(["--start-accel", "0.3"])).train.start_accel == 0.3
    assert bid(["train", "--preset", "tiny", "--synthetic", "--start-accel", "1", "--out", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--start-accel is a throttle" in err and "\n" not in err
    assert not (tmp_path / "w").exists()
    assert bid(["train", "--preset", "tiny", "--synthetic", "--hold-repeat", "0", "--out", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--hold-repeat must be at least 1" in err and "\n" not in err
    assert not (tmp_path / "y").exists()


def test_hazard_head_trains_on_recordings_and_driving_ignores_it(recorded, tmp_path, capsys):
    """--hazard adds a head for what stands in the path, learnt from the recordings' /scene:
    started from a run without it, only the head is fresh; its loss reaches the shared
    network; the metrics report its error in metres; (steer, accel) stay what they were; it
    averages with a run without the head into one without it."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--out", str(tmp_path / "plain")]) == 0
    start = ["--init", str(tmp_path / "plain" / "last.pt")]
    assert bid([*base, *start, "--hazard", "1", "--out", str(tmp_path / "hz")]) == 0
    assert bid([*base, *start, "--out", str(tmp_path / "again")]) == 0
    capsys.readouterr()
    tuned = load_checkpoint(tmp_path / "hz" / "last.pt")
    assert tuned["config"]["model"]["hazard"] and tuned["config"]["train"]["lambda_hazard"] == 1.0
    assert {k for k in tuned["init"]["fresh"] if not k.startswith("mean_")} == {
        k for k in tuned["model"] if k.startswith("hazard_head.")}
    other = load_checkpoint(tmp_path / "again" / "last.pt")["model"]
    assert not torch.allclose(other["areas.V1.conv1.0.weight"], tuned["model"]["areas.V1.conv1.0.weight"])
    rows = list(csv.DictReader((tmp_path / "hz" / "metrics.csv").open()))
    assert 0 <= float(rows[-1]["val_mae_hazard_m"]) <= 25.0
    assert rows[-1]["val_ped_seen_none"] == "" or 0 <= float(rows[-1]["val_ped_seen_none"]) <= 1
    assert json.loads((tmp_path / "hz" / "dataset.json").read_text())["hazard_frames"] is not None
    model, _ = load_model(tmp_path / "hz" / "last.pt", preset="tiny")
    x = torch.zeros(1, 3, 32, 96, dtype=torch.uint8)
    with torch.no_grad():
        control = model(x, x, torch.eye(6)[[3]])
        both, near = model(x, x, torch.eye(6)[[3]], hazard=True)
    assert torch.equal(control, both) and near.shape == (1, 3)  # pedestrian, vehicle, red light
    with pytest.raises(BidError, match="no hazard head"):
        load_model(tmp_path / "plain" / "last.pt", preset="tiny")[0](x, x, torch.eye(6)[[3]], hazard=True)
    # Averaged with the run without it: the head is left out, the rest is the mean.
    assert bid(["average", str(tmp_path / "hz" / "last.pt"), str(tmp_path / "again" / "last.pt"),
                "--out", str(tmp_path / "avg.pt")]) == 0
    avg = load_checkpoint(tmp_path / "avg.pt")
    assert not avg["config"]["model"]["hazard"] and avg["config"]["train"]["lambda_hazard"] == 0.0
    assert not any(k.startswith("hazard_head.") for k in avg["model"])
    key = "areas.V1.conv1.0.weight"
    assert torch.allclose(avg["model"][key], (tuned["model"][key] + other[key]) / 2)
    load_model(tmp_path / "avg.pt", preset="tiny")  # a network like any other
    # --keep-heads: the head comes from the one run that has it, the trunk is the mean as before.
    assert bid(["average", str(tmp_path / "again" / "last.pt"), str(tmp_path / "hz" / "last.pt"),
                "--weights", "3,1", "--keep-heads", "--out", str(tmp_path / "kept.pt")]) == 0
    kept = load_checkpoint(tmp_path / "kept.pt")
    assert kept["config"]["model"]["hazard"] and kept["config"]["train"]["lambda_hazard"] == 1.0
    heads = [k for k in tuned["model"] if k.startswith("hazard_head.")]
    assert heads and all(torch.equal(kept["model"][k], tuned["model"][k]) for k in heads)
    assert torch.allclose(kept["model"][key], 0.75 * other[key] + 0.25 * tuned["model"][key])
    model, _ = load_model(tmp_path / "kept.pt", preset="tiny")
    assert model(x, x, torch.eye(6)[[3]], hazard=True)[1].shape == (1, 3)
    # Heads of different shapes are not averaged: left out, or refused with --keep-heads.
    for name, horizons in (("f1.pt", [1.0]), ("f2.pt", [1.0, 2.0])):
        save_checkpoint(tmp_path / name, {**tuned, "config": {**tuned["config"], "model": {
            **tuned["config"]["model"], "forecast_s": horizons}}})
    pair = [str(tmp_path / "f1.pt"), str(tmp_path / "f2.pt")]
    assert bid(["average", *pair, "--out", str(tmp_path / "f.pt")]) == 0
    assert not load_checkpoint(tmp_path / "f.pt")["config"]["model"]["forecast_s"]
    capsys.readouterr()
    assert bid(["average", *pair, "--keep-heads", "--out", str(tmp_path / "g.pt")]) == 2
    assert "forecast_s heads of different shapes" in capsys.readouterr().err
    assert not (tmp_path / "g.pt").exists()


def test_hazard_detection_counts_what_the_head_sees_near_and_where_there_is_nothing():
    from bid_model.train import hazard_detection

    # Targets (pedestrian, vehicle) nearness: 0.8 is 5 m off, 0.5 12.5 m, 0 nothing within 25 m.
    target = torch.tensor([[0.8, 0.0], [0.8, 0.0], [0.5, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    pred = torch.tensor([[0.7, 0.0], [0.1, 0.3], [0.0, 0.0], [0.25, 0.0], [0.0, 0.0], [0.0, 0.0]])
    d = hazard_detection(pred, target)
    # AUC: of the 2 × 3 (near, none) pairs, 0.7 outranks all three nones, 0.1 two and ties none.
    assert d["pedestrian"] == {"seen_near": 0.5, "seen_none": pytest.approx(1 / 3), "auc": pytest.approx(5 / 6)}
    assert d["vehicle"] == {"seen_near": None, "seen_none": pytest.approx(1 / 6), "auc": None}


def test_ranking_auc_counts_ties_half():
    import numpy as np

    from bid_model.train import ranking_auc

    assert ranking_auc(np.array([0.9, 0.8]), np.array([0.1, 0.2, 0.3])) == 1.0
    assert ranking_auc(np.array([0.1]), np.array([0.9])) == 0.0
    assert ranking_auc(np.zeros(4), np.zeros(7)) == 0.5
    assert ranking_auc(np.array([0.0, 0.5]), np.array([0.0, 0.0])) == pytest.approx(0.75)


def test_hazard_pos_weight_makes_a_rare_hazard_worth_reporting():
    """Pedestrians in the path in 20 % of frames: plain L1 fits "none" (the median), with
    the frames that have one weighted 8 times a constant fitted by the loss reports it."""
    from bid_model.train import hazard_loss

    target = torch.tensor([[0.6, 0.0]] * 2 + [[0.0, 0.0]] * 8)

    def fitted(pos_weight: float) -> float:
        c = torch.zeros(1, 2, requires_grad=True)
        opt = torch.optim.SGD([c], lr=0.01)
        for _ in range(400):
            opt.zero_grad()
            hazard_loss(c.expand_as(target), target, pos_weight).backward()
            opt.step()
        return float(c.detach()[0, 0])

    assert fitted(1.0) == pytest.approx(0.0, abs=0.02)
    assert fitted(8.0) == pytest.approx(0.6, abs=0.02)
    # Weight 1 is the plain mean absolute error.
    pred = torch.rand(10, 2)
    assert hazard_loss(pred, target) == pytest.approx(float((pred - target).abs().mean()))


def test_hazard_turn_weight_weighs_pedestrians_met_turning():
    """--hazard-turn-weight: a pedestrian in the path while the command is LEFT or RIGHT weighs
    that much more, on top of --hazard-pos-weight; one met going straight, a vehicle met
    turning and a turn with nobody in the path weigh as before."""
    from bid_model.data import command_one_hot
    from bid_model.train import hazard_loss

    target = torch.tensor([[0.6, 0.0], [0.6, 0.0], [0.0, 0.5], [0.0, 0.0]])
    command = command_one_hot([2, 3, 1, 1])  # RIGHT, STRAIGHT, LEFT, LEFT
    pred = torch.zeros(4, 2)
    # Entries' weights: pedestrian column 2·3, 2, 1, 1; vehicle column 1, 1, 2, 1.
    want = (0.6 * 6 + 0.6 * 2 + 0.5 * 2) / (6 + 2 + 1 + 1 + 1 + 1 + 2 + 1)
    assert hazard_loss(pred, target, 2.0, 3.0, command) == pytest.approx(want)
    assert hazard_loss(pred, target, 2.0, 1.0, command) == pytest.approx(hazard_loss(pred, target, 2.0))
    # Fitted as a constant per turning row, the pedestrian met turning is reported only when weighed up.
    many = torch.tensor([[0.6, 0.0]] * 2 + [[0.0, 0.0]] * 8)
    turning = command_one_hot([2] * 10)

    def fitted(turn_weight: float) -> float:
        c = torch.zeros(1, 2, requires_grad=True)
        opt = torch.optim.SGD([c], lr=0.01)
        for _ in range(400):
            opt.zero_grad()
            hazard_loss(c.expand_as(many), many, 1.0, turn_weight, turning).backward()
            opt.step()
        return float(c.detach()[0, 0])

    assert fitted(1.0) == pytest.approx(0.0, abs=0.02)
    assert fitted(8.0) == pytest.approx(0.6, abs=0.02)


def test_hazard_moving_weight_weighs_pedestrians_in_the_path_of_a_moving_ego():
    """--hazard-moving-weight: a pedestrian in the path while the ego moves (0.3 m/s or
    faster) weighs that much more, on top of the other weights; one met standing, a vehicle met
    moving and a moving ego with nobody in the path weigh as before."""
    from bid_model.config import MOVING_MPS
    from bid_model.train import hazard_loss, hazard_weights, presence_loss

    target = torch.tensor([[0.6, 0.0], [0.6, 0.0], [0.0, 0.5], [0.0, 0.0]])
    speed = torch.tensor([5.0, 0.0, 5.0, MOVING_MPS])
    weight = hazard_weights(target, 2.0, moving_weight=4.0, speed_mps=speed)
    assert weight.tolist() == [[8.0, 1.0], [2.0, 1.0], [1.0, 2.0], [1.0, 1.0]]
    pred = torch.zeros(4, 2)
    want = (0.6 * 8 + 0.6 * 2 + 0.5 * 2) / float(weight.sum())
    assert hazard_loss(pred, target, 2.0, moving_weight=4.0, speed_mps=speed) == pytest.approx(want)
    assert hazard_loss(pred, target, 2.0, speed_mps=speed) == pytest.approx(hazard_loss(pred, target, 2.0))
    # The presence loss weighs its cross-entropy the same way: heavier where the moving ego meets one.
    out = torch.zeros(4, 4)
    out[:, 2] = -2.0  # "no pedestrian in the path" everywhere: wrong most where one is
    assert presence_loss(out, target, 1.0, moving_weight=4.0, speed_mps=speed) > presence_loss(out, target, 1.0) + 0.1


def test_hazard_vehicle_moving_weight_weighs_vehicles_in_the_path_of_a_moving_ego():
    """--hazard-vehicle-moving-weight: a vehicle in the path while the ego moves weighs that much
    more, on top of the others; a vehicle met standing and a pedestrian met moving as before."""
    from bid_model.config import MOVING_MPS
    from bid_model.train import hazard_loss, hazard_weights, presence_loss

    target = torch.tensor([[0.0, 0.6], [0.0, 0.6], [0.5, 0.0], [0.0, 0.0]])
    speed = torch.tensor([MOVING_MPS, 0.0, 5.0, 5.0])
    weight = hazard_weights(target, 2.0, speed_mps=speed, vehicle_moving_weight=3.0)
    assert weight.tolist() == [[1.0, 6.0], [1.0, 2.0], [2.0, 1.0], [1.0, 1.0]]
    both = hazard_weights(target, 2.0, moving_weight=5.0, speed_mps=speed, vehicle_moving_weight=3.0)
    assert both.tolist() == [[1.0, 6.0], [1.0, 2.0], [10.0, 1.0], [1.0, 1.0]]
    pred = torch.zeros(4, 2)
    want = (0.6 * 6 + 0.6 * 2 + 0.5 * 2) / float(weight.sum())
    assert hazard_loss(pred, target, 2.0, speed_mps=speed, vehicle_moving_weight=3.0) == pytest.approx(want)
    out = torch.zeros(4, 4)
    out[:, 3] = -2.0  # "no vehicle in the path" everywhere: wrong most where the moving ego meets one
    assert presence_loss(out, target, 1.0, speed_mps=speed, vehicle_moving_weight=3.0) > \
        presence_loss(out, target, 1.0) + 0.1


def test_hazard_green_weight_weighs_the_red_light_entry_of_a_standing_ego_at_a_green_line(recorded):
    """--hazard-green-weight: the red-light entry (none there) of a frame where the ego stands at
    a green light's stop line (AT_LINE_M or nearer, or past it) weighs that much more; moving,
    farther off, or the other kinds weigh as before, and SC's two-kind loss is untouched. The
    recordings' samples carry the distance (hazards.green_distance of their /ego/state)."""
    from bid_model.hazards import AT_LINE_M, HAZARD_AHEAD_M, green_distance
    from bid_model.recordings import open_every_frame
    from bid_model.train import hazard_loss, hazard_weights, presence_loss
    from bid_sim.recording import read_episode
    from bid_sim.snapshot import GREEN, RED

    target = torch.zeros(4, 3)
    speed = torch.tensor([0.0, 0.0, 5.0, 0.0])
    green_m = torch.tensor([0.8, -0.3, 1.0, AT_LINE_M + 0.5])
    weight = hazard_weights(target, 2.0, speed_mps=speed, green_weight=4.0, green_m=green_m)
    assert weight.tolist() == [[1.0, 1.0, 4.0], [1.0, 1.0, 4.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    pred = torch.zeros(4, 3)
    pred[0, 2] = 0.5  # a red light read at the green line
    assert float(hazard_loss(pred, target, green_weight=4.0, green_m=green_m, speed_mps=speed)) == \
        pytest.approx(4 * 0.5 / float(weight.sum()))
    two = torch.zeros(4, 4)
    assert presence_loss(two, target[:, :2], 1.0, speed_mps=speed, green_weight=4.0, green_m=green_m) == \
        pytest.approx(float(presence_loss(two, target[:, :2], 1.0, speed_mps=speed)))
    assert green_distance({"next_light_state": GREEN, "next_light_dist_m": -0.3}) == pytest.approx(-0.3)
    assert green_distance({"next_light_state": RED, "next_light_dist_m": 1.0}) == HAZARD_AHEAD_M
    assert green_distance({"next_light_state": GREEN, "next_light_dist_m": 60.0}) == HAZARD_AHEAD_M
    data, _ = open_every_frame(recorded, (32, 96))
    first = read_episode(data.index.files[0], frames=False)
    want = {int(step): green_distance(state) for step, state in zip(first.steps, first.states, strict=True)}
    items = [data[i] for i in range(0, len(data), 7) if int(data.index.episode[i]) == 0]
    assert items and all(it["green_m"] == pytest.approx(want[it["step"]]) for it in items)


def test_hazard_flag_needs_recordings_and_a_sound_weight(tmp_path, capsys):
    import argparse

    from bid_model.cli import add_train_arguments
    from bid_model.train import config_from_args

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5"]))
    assert run.model.hazard and run.train.lambda_hazard == 0.5 and run.train.hazard_pos_weight == 1.0
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5", "--hazard-pos-weight", "8"]))
    assert run.train.hazard_pos_weight == 8.0 and run.train.hazard_ahead_s == 0.0
    assert run.train.hazard_turn_weight == 1.0
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5", "--hazard-turn-weight", "3"]))
    assert run.train.hazard_turn_weight == 3.0 and run.train.hazard_moving_weight == 1.0
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5", "--hazard-moving-weight", "6"]))
    assert run.train.hazard_moving_weight == 6.0 and run.train.hazard_vehicle_moving_weight == 1.0
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5",
                                              "--hazard-vehicle-moving-weight", "4"]))
    assert run.train.hazard_vehicle_moving_weight == 4.0 and run.train.hazard_moving_weight == 1.0
    run = config_from_args(parser.parse_args(["--preset", "tiny", "--hazard", "0.5", "--hazard-ahead", "1.5"]))
    assert run.train.hazard_ahead_s == 1.5
    for flags, says in ((["--synthetic", "--hazard", "0.5"], "--hazard learns from recordings"),
                        (["--hazard", "1", "--hazard-ahead", "-1"], "in seconds, 0 to 5"),
                        (["--hazard-ahead", "1"], "add --hazard WEIGHT"),
                        (["--shift", "40"], "a quarter of the input's"),
                        (["--synthetic", "--hazard", "-1"], "--hazard is the weight"),
                        (["--hazard", "1", "--hazard-pos-weight", "0.5"], "1 or more"),
                        (["--hazard-pos-weight", "8"], "add --hazard WEIGHT"),
                        (["--hazard", "1", "--hazard-turn-weight", "0"], "1 or more"),
                        (["--hazard", "1", "--hazard-turn-weight", "inf"], "1 or more"),
                        (["--hazard", "1", "--hazard-pos-weight", "nan"], "1 or more"),
                        (["--hazard-turn-weight", "3"], "add --hazard WEIGHT"),
                        (["--hazard", "1", "--hazard-moving-weight", "0.5"], "1 or more"),
                        (["--hazard-moving-weight", "3"], "add --hazard WEIGHT"),
                        (["--hazard", "1", "--hazard-vehicle-moving-weight", "0"], "1 or more"),
                        (["--hazard-vehicle-moving-weight", "3"], "add --hazard WEIGHT")):
        assert bid(["train", "--preset", "tiny", *flags, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err
    assert not (tmp_path / "x" / "last.pt").exists()
    half = tiny()
    half = RunConfig(dataclasses.replace(half.model, hazard=True), half.train)
    with pytest.raises(BidError, match="--hazard WEIGHT"):
        train(tmp_path / "half", half, synthetic=True, progress=False)


def test_attending_hazard_head_fits_alone_on_a_trained_trunk_and_reads_v2(recorded, tmp_path, capsys):
    """--hazard --hazard-attend --train-only hazard from a run without a head: only the new head
    moves; it says (pedestrian, vehicle, red light) and reads V2's grid, not MPC's mean alone."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--out", str(tmp_path / "plain")]) == 0
    assert bid([*base, "--init", str(tmp_path / "plain" / "last.pt"), "--hazard", "1", "--hazard-attend",
                "--train-only", "hazard", "--out", str(tmp_path / "hz")]) == 0
    start = load_checkpoint(tmp_path / "plain" / "last.pt")["model"]
    tuned = load_checkpoint(tmp_path / "hz" / "last.pt")
    assert tuned["config"]["model"]["hazard_attend"]
    assert all(torch.equal(v, tuned["model"][k]) for k, v in start.items())
    assert any(k.startswith("hazard_head.project.V2") for k in tuned["model"])
    model, _ = load_model(tmp_path / "hz" / "last.pt", preset="tiny")
    x = torch.zeros(1, 3, 32, 96, dtype=torch.uint8)
    feats = model.forward_features(x, x, torch.eye(6)[[3]])
    feats["V2"] = feats["V2"].detach().requires_grad_(True)
    with torch.no_grad():  # every hidden unit read, so that the check is of the wiring alone
        model.hazard_head.out_weight.fill_(1.0)
        model.hazard_head.hidden.bias.fill_(1.0)
    near = model.forward_hazard(feats)
    assert near.shape == (1, 3)
    near.sum().backward()
    assert feats["V2"].grad.abs().sum() > 0
    assert bid(["train", "--preset", "tiny", "--synthetic", "--hazard-attend", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "add --hazard WEIGHT" in err and "\n" not in err


def test_sc_fits_alone_beside_a_trained_head_and_gives_the_pedestrian_output(recorded, tmp_path, capsys):
    """--hazard --hazard-sc --train-only SC from a run with a hazard head: only SC moves; the
    pedestrian and vehicle outputs are the larger of the head's and SC's peaks (read from the
    frames), the light's is the head's."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--hazard", "1", "--out", str(tmp_path / "hz")]) == 0
    assert bid([*base, "--init", str(tmp_path / "hz" / "last.pt"), "--hazard", "1", "--hazard-sc",
                "--train-only", "SC", "--stop-keep", "1", "--motion-drop", "0", "--mirror", "0.5",
                "--out", str(tmp_path / "sc")]) == 0
    start = load_checkpoint(tmp_path / "hz" / "last.pt")["model"]
    tuned = load_checkpoint(tmp_path / "sc" / "last.pt")
    assert tuned["config"]["model"]["hazard_sc"]
    assert tuned["config"]["train"]["stop_keep"] == 1.0 and tuned["config"]["train"]["motion_drop"] == 0.0
    assert tuned["config"]["train"]["mirror"] == 0.5
    assert all(torch.equal(v, tuned["model"][k]) for k, v in start.items())
    assert any(k.startswith("hazard_sc.retina") for k in tuned["model"])
    plain, _ = load_model(tmp_path / "hz" / "last.pt", preset="tiny")
    model, _ = load_model(tmp_path / "sc" / "last.pt", preset="tiny")
    frame = torch.randint(0, 256, (2, 3, 32, 96), dtype=torch.uint8)
    prev = torch.randint(0, 256, (2, 3, 32, 96), dtype=torch.uint8)
    cmd = torch.eye(6)[[0, 2]]
    with torch.no_grad():
        near = model(frame, prev, cmd, hazard=True)[1]
        feats = model.forward_features(frame, prev, cmd)
        before = plain(frame, prev, cmd, hazard=True)[1]
    assert near.shape == (2, 3)
    assert torch.allclose(near[:, :2], torch.maximum(before[:, :2], feats["SC"]))  # the nearer of the two
    assert torch.allclose(near[:, 2:], before[:, 2:])  # the light is the head's
    frame_f = frame.float().requires_grad_(True)
    model.forward_features(frame_f, prev, cmd)["SC"].sum().backward()
    assert frame_f.grad.abs().sum() > 0  # SC reads the frame itself, not MPC's tokens
    with torch.no_grad():  # training fits each alone: the head's three outputs, then SC's two
        apart = model(frame, prev, cmd, hazard=True, hazard_apart=True)[1]
    assert apart.shape == (2, 5) and torch.equal(apart[:, 3:], feats["SC"]) and torch.allclose(apart[:, :3], before)
    # Averaged, the run keeps SC with its head.
    average_checkpoints([tmp_path / "sc" / "last.pt", tmp_path / "sc" / "last.pt"], tmp_path / "avg.pt")
    avg = load_checkpoint(tmp_path / "avg.pt")
    assert avg["config"]["model"]["hazard_sc"] and "hazard_sc.position" in avg["model"]
    for flags, says in ((["--hazard-sc"], "add --hazard WEIGHT"),
                        (["--hazard", "1", "--stop-keep", "0"], "--stop-keep is a share"),
                        (["--hazard", "1", "--motion-drop", "1.5"], "--motion-drop is a share"),
                        (["--hazard", "1", "--mirror", "2"], "--mirror is a share")):
        assert bid(["train", "--preset", "tiny", "--data", str(recorded), *flags, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err


def hazard_outputs(checkpoint) -> tuple[torch.Tensor, torch.Tensor]:
    """A tiny checkpoint's hazard output on 4 random frames, as driving reads it and apart."""
    model, _ = load_model(checkpoint, preset="tiny")
    frame = torch.randint(0, 256, (4, 3, 32, 96), dtype=torch.uint8)
    prev = torch.randint(0, 256, (4, 3, 32, 96), dtype=torch.uint8)
    cmd = torch.eye(6)[[0, 1, 2, 3]]
    with torch.no_grad():
        return (model(frame, prev, cmd, hazard=True)[1],
                model(frame, prev, cmd, hazard=True, hazard_apart=True)[1])


def test_sc_presence_reads_a_nearness_only_where_it_says_one_is_in_the_path(recorded, tmp_path, capsys):
    """--sc-presence: SC's second map per kind is a logit that one is in the path; its nearness
    is read where that map peaks, and counts only where the logit is above 0. Started from a
    run with plain SC, everything but SC's last layer carries over; training fits the logits by
    cross-entropy and the nearness only where one is in the path."""
    from bid_model.areas import SC
    from bid_model.train import presence_loss

    sc = SC((32, 96), 6, 2, presence=True).eval()
    frame, prev = torch.randn(3, 3, 32, 96), torch.randn(3, 3, 32, 96)
    cmd = torch.eye(6)[[0, 1, 3]]
    with torch.no_grad():
        out, maps = sc(frame, prev, cmd), sc.priority_map(frame, prev, cmd).flatten(2)
    where = maps[:, 2:].argmax(dim=2)
    assert out.shape == (3, 4) and torch.equal(out[:, 2:], maps[:, 2:].amax(dim=2))
    assert torch.equal(out[:, :2], maps[:, :2].gather(2, where[:, :, None]).squeeze(2))

    # The loss: the nearness is fitted on the entries with one in the path only.
    target = torch.tensor([[0.6, 0.0], [0.0, 0.4]])
    out = torch.tensor([[0.6, 0.9, 3.0, -3.0], [0.1, 0.4, -3.0, 3.0]], requires_grad=True)
    presence_loss(out, target).backward()
    assert out.grad[0, 1] == 0 and out.grad[1, 0] == 0  # no nearness fitted where nobody is
    assert out.grad[0, 2] < 0 and out.grad[0, 3] > 0  # yes where one is, no where none is

    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--hazard", "1", "--hazard-sc", "--out", str(tmp_path / "sc")]) == 0
    assert bid([*base, "--init", str(tmp_path / "sc" / "last.pt"), "--hazard", "1", "--hazard-sc",
                "--sc-presence", "--hazard-pos-weight", "4", "--hazard-turn-weight", "2", "--train-only", "SC",
                "--out", str(tmp_path / "pr")]) == 0
    start, tuned = load_checkpoint(tmp_path / "sc" / "last.pt"), load_checkpoint(tmp_path / "pr" / "last.pt")
    assert tuned["config"]["model"]["sc_presence"] and tuned["config"]["train"]["hazard_turn_weight"] == 2.0
    assert tuned["model"]["hazard_sc.priority.2.weight"].shape[0] == 4
    assert all(torch.equal(v, tuned["model"][k]) for k, v in start["model"].items()
               if not k.startswith("hazard_sc."))  # only SC moved
    near, apart = hazard_outputs(tmp_path / "pr" / "last.pt")
    assert apart.shape == (4, 7)  # the head's three, SC's two nearnesses, SC's two logits
    gated = torch.where(apart[:, 5:] > 0, apart[:, 3:5], torch.zeros(4, 2))
    assert torch.allclose(near[:, :2], torch.maximum(apart[:, :2], gated))
    assert torch.allclose(near[:, 2:], apart[:, 2:3])
    assert bid([*base, "--hazard", "1", "--sc-presence", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "add --hazard-sc" in err and "\n" not in err

    # `bid evaluate --sc-logit T`: SC's pedestrian counts only where its logit is above T, its vehicle above 0.
    agent = BIDAgent(tmp_path / "pr" / "last.pt", hazard_brake=1.0, sc_logit=1.0)
    assert agent.model.config.sc_logit == 1.0 and agent.config.model.sc_logit == 1.0
    columns = torch.tensor([[0.0, 0.0, 0.0, 0.5, 0.75, -1.0, 0.5],
                            [0.0, 0.0, 0.0, 0.5, 0.75, 0.5, 0.5],
                            [0.0, 0.0, 0.0, 0.5, 0.75, 1.5, -1.0]])
    assert agent.model.sc_near(columns).tolist() == [[0.0, 0.75], [0.0, 0.75], [0.5, 0.0]]
    assert BIDAgent(tmp_path / "pr" / "last.pt").model.sc_near(columns).tolist() == [[0.0, 0.75], [0.5, 0.75], [0.5, 0.0]]
    for checkpoint, logit, says in ((tmp_path / "sc" / "last.pt", 1.0, "has none"),
                                    (tmp_path / "pr" / "last.pt", 11.0, "a logit from -10 to 10")):
        with pytest.raises(BidError, match=says):
            BIDAgent(checkpoint, sc_logit=logit)
    with pytest.raises(ValueError, match="needs sc_presence"):
        dataclasses.replace(load_model(tmp_path / "sc" / "last.pt")[1].model, sc_logit=1.0)
    args = build_parser().parse_args(["evaluate", "--agent", "bid", "--sc-logit", "1.5"])
    assert _drive_options(args, None) == {"sc_logit": 1.5}


def tiny_runs_and_inputs(*runs):
    """The `tiny` models of these run folders' last.pt in eval mode, and one batch of two random
    frame pairs with their commands."""
    models = [load_model(run / "last.pt", preset="tiny")[0].eval() for run in runs]
    frame = torch.randint(0, 256, (2, 3, 32, 96), dtype=torch.uint8)
    prev = torch.randint(0, 256, (2, 3, 32, 96), dtype=torch.uint8)
    return models, (frame, prev, torch.eye(6)[[0, 3]])


def test_sc_still_reads_frame_t_alone_and_starts_from_a_moving_sc(recorded, tmp_path, capsys):
    """--sc-still: SC reads frame t with its change since t−1 zeroed, so what it says does not
    depend on frame t−1 (the ego's own motion); --init from a run whose SC read the change keeps
    every weight, and training moves SC alone."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--hazard", "1", "--hazard-sc", "--out", str(tmp_path / "sc")]) == 0
    assert bid([*base, "--init", str(tmp_path / "sc" / "last.pt"), "--hazard", "1", "--hazard-sc", "--sc-still",
                "--train-only", "SC", "--out", str(tmp_path / "still")]) == 0
    start, still = load_checkpoint(tmp_path / "sc" / "last.pt"), load_checkpoint(tmp_path / "still" / "last.pt")
    assert still["config"]["model"]["sc_still"] and "fresh" not in still.get("init", {})
    assert all(torch.equal(v, still["model"][k]) for k, v in start["model"].items()
               if not k.startswith("hazard_sc."))  # only SC may move
    (model, moving), (frame, prev, cmd) = tiny_runs_and_inputs(tmp_path / "still", tmp_path / "sc")
    with torch.no_grad():
        sc = [model.forward_features(frame, p, cmd)["SC"] for p in (prev, frame)]
        sc_moving = [moving.forward_features(frame, p, cmd)["SC"] for p in (prev, frame)]
    assert torch.equal(sc[0], sc[1])  # frame t−1 changes nothing
    assert not torch.equal(sc_moving[0], sc_moving[1])  # where SC reads the change, it does
    assert bid([*base, "--hazard", "1", "--sc-still", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "add --hazard-sc" in err and "\n" not in err


def test_hazard_speedless_keeps_the_speed_from_the_hazard_head_alone(recorded, tmp_path, capsys):
    """--hazard-speedless: the hazard head reads MPC's tokens merged without the speed token, so
    what it says does not depend on the speed input, while the control head and the forecast
    still do; --init from a run whose head read the speed keeps every weight, and
    `--train-only hazard` moves the head alone. A model without a speed input is refused."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--speed-input", "--forecast", "0.5", "--hazard", "1"]
    assert bid([*base, "--out", str(tmp_path / "sped")]) == 0
    assert bid([*base, "--init", str(tmp_path / "sped" / "last.pt"), "--hazard-speedless", "--train-only", "hazard",
                "--out", str(tmp_path / "speedless")]) == 0
    start, blind = load_checkpoint(tmp_path / "sped" / "last.pt"), load_checkpoint(tmp_path / "speedless" / "last.pt")
    assert blind["config"]["model"]["hazard_speedless"] and "fresh" not in blind.get("init", {})
    assert all(torch.equal(v, blind["model"][k]) for k, v in start["model"].items()
               if not k.startswith("hazard_head."))  # only the head may move
    assert any(not torch.equal(v, blind["model"][k]) for k, v in start["model"].items() if k.startswith("hazard_head."))
    (model, sped), (frame, prev, cmd) = tiny_runs_and_inputs(tmp_path / "speedless", tmp_path / "sped")
    with torch.no_grad():
        out = [model(frame, prev, cmd, torch.tensor([v, v]), forecast=True, hazard=True) for v in (0.0, 8.0)]
        sped_out = [sped(frame, prev, cmd, torch.tensor([v, v]), forecast=True, hazard=True) for v in (0.0, 8.0)]
    assert torch.equal(out[0][2], out[1][2])  # the hazard head: the same at 0 and 8 m/s
    assert not torch.equal(sped_out[0][2], sped_out[1][2])  # with the speed token, it differs
    assert not torch.equal(out[0][0], out[1][0]) and not torch.equal(out[0][1], out[1][1])  # control, forecast
    model.set_lesions({"MPC": "zero"})
    with torch.no_grad():
        lesioned = model(frame, prev, cmd, torch.tensor([0.0, 0.0]), hazard=True)[1]
        assert torch.allclose(lesioned, model.hazard_head(torch.zeros(2, model.config.width)))
    assert bid(["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--quiet", "--hazard", "1",
                "--hazard-speedless", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--hazard-speedless keeps the speed input from the hazard head" in err and "\n" not in err


def test_a_move_off_head_starts_as_the_hazard_head_and_fits_as_a_speedless_one(recorded, tmp_path, capsys, caplog):
    """--move-off-head: a second hazard head reading MPC without the speed token. --init from a
    run without it starts it as that run's hazard head, `--train-only move_off` moves it alone,
    and it then learns exactly what --hazard-speedless teaches the first head from that start
    (the same targets, the same tokens). It is refused beside --hazard-speedless."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--speed-input", "--forecast", "0.5", "--hazard", "1"]
    assert bid([*base, "--out", str(tmp_path / "sped")]) == 0
    start = tmp_path / "sped" / "last.pt"
    caplog.set_level("INFO", logger="bid_model.train")
    assert bid([*base, "--init", str(start), "--move-off-head", "--train-only", "move_off",
                "--out", str(tmp_path / "two")]) == 0
    assert any(r.getMessage().startswith("move-off head distance MAE") for r in caplog.records)  # validated
    assert bid([*base, "--init", str(start), "--hazard-speedless", "--train-only", "hazard",
                "--out", str(tmp_path / "speedless")]) == 0
    sped, two, blind = (load_checkpoint(tmp_path / run / "last.pt") for run in ("sped", "two", "speedless"))
    assert two["config"]["model"]["move_off_head"] and "fresh" not in two.get("init", {})
    heads = [k for k in sped["model"] if k.startswith("hazard_head.")]
    model = BID(model_config_from_dict(two["config"]["model"]))
    assert warm_start_move_off(model, sped["model"], load_shared_weights(model, sped["model"])) == []
    assert all(torch.equal(model.state_dict()["hazard_move_off." + k[12:]], sped["model"][k]) for k in heads)
    assert all(torch.equal(v, two["model"][k]) for k, v in sped["model"].items())  # the first head too
    assert all(torch.equal(two["model"]["hazard_move_off." + k[12:]], blind["model"][k]) for k in heads)
    assert not all(torch.equal(two["model"]["hazard_move_off." + k[12:]], sped["model"][k]) for k in heads)
    assert bid([*base, "--move-off-head", "--hazard-speedless", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "keep one" in err and "\n" not in err


def test_a_move_off_head_reading_the_speed_fits_as_the_first_head_refitted(recorded, tmp_path, capsys):
    """--move-off-speed: the move-off head reads MPC with the speed token, so `--train-only
    move_off` from a run without it fits exactly the head `--train-only hazard` refits there:
    a second head of the first head's kind, fitted apart (here with --hazard-green-weight)."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--speed-input", "--forecast", "0.5", "--hazard", "1"]
    assert bid([*base, "--out", str(tmp_path / "sped")]) == 0
    start = str(tmp_path / "sped" / "last.pt")
    assert bid([*base, "--init", start, "--move-off-head", "--move-off-speed", "--train-only", "move_off",
                "--hazard-green-weight", "4", "--out", str(tmp_path / "two")]) == 0
    assert bid([*base, "--init", start, "--train-only", "hazard", "--hazard-green-weight", "4",
                "--out", str(tmp_path / "refit")]) == 0
    sped, two, refit = (load_checkpoint(tmp_path / run / "last.pt") for run in ("sped", "two", "refit"))
    assert two["config"]["model"]["move_off_speed"]
    heads = [k for k in sped["model"] if k.startswith("hazard_head.")]
    assert all(torch.equal(two["model"]["hazard_move_off." + k[12:]], refit["model"][k]) for k in heads)
    assert not all(torch.equal(refit["model"][k], sped["model"][k]) for k in heads)
    assert all(torch.equal(v, two["model"][k]) for k, v in sped["model"].items())  # the first head as it was
    assert bid([*base, "--move-off-speed", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "add --move-off-head" in err and "\n" not in err


def _hazard_refit(recorded, tmp_path):
    """A tiny model with a hazard head trained on `recorded` (its last.pt), the flags of a refit of
    that head alone from it, and its hazard outputs on four random frames (`near(model)`)."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--hazard", "1"]
    assert bid([*base, "--out", str(tmp_path / "start")]) == 0
    init = tmp_path / "start" / "last.pt"
    x = torch.randint(0, 255, (4, 3, 32, 96), dtype=torch.uint8)
    cmd = torch.eye(6)[[0, 1, 2, 3]]

    def near(m):
        m.eval()
        with torch.no_grad():
            return m(x, x, cmd, hazard=True)[1]

    return base, init, [*base, "--init", str(init), "--train-only", "hazard", "--lr", "3e-3"], near


def test_keep_hazard_refits_the_red_light_and_holds_the_pedestrian_and_vehicle(recorded, tmp_path, capsys):
    """--keep-hazard: the hazard head's pedestrian and vehicle targets are the --init head's own on
    the same features; refitted alone, its red light moves and the other two stay nearer the init's
    than in a refit without it. Refused without --train-only hazard or an --init."""
    base, init, refit, near = _hazard_refit(recorded, tmp_path)
    assert bid([*refit, "--keep-hazard", "--out", str(tmp_path / "keep")]) == 0
    assert bid([*refit, "--out", str(tmp_path / "free")]) == 0
    model, _ = load_model(init, preset="tiny")
    kept = KeptHazard(model, load_checkpoint(init)["model"])
    before = near(model)
    recorded_targets = torch.tensor([[0.9, 0.8, 0.7]] * 4)
    target = kept.target(recorded_targets)  # the init head's own pedestrian and vehicle, the light as given
    assert torch.allclose(target[:, :2], before[:, :2]) and torch.equal(target[:, 2], recorded_targets[:, 2])
    after = {run: near(load_model(tmp_path / run / "last.pt", preset="tiny")[0]) for run in ("keep", "free")}
    drift = {run: float((out[:, :2] - before[:, :2]).abs().mean()) for run, out in after.items()}
    assert drift["keep"] < 0.5 * drift["free"], drift
    assert float((after["keep"][:, 2] - before[:, 2]).abs().mean()) > 1e-3  # the red light refitted
    assert load_checkpoint(tmp_path / "keep" / "last.pt")["config"]["train"]["keep_hazard"] is True
    for flags, says in ((("--keep-hazard", "--init", str(init)), "add --train-only hazard"),
                        (("--keep-hazard", "--train-only", "hazard"), "add --init CHECKPOINT")):
        assert bid([*base, *flags, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err


def test_keep_hazard_kinds_holds_the_kinds_named_and_refits_the_rest(recorded, tmp_path, capsys):
    """--keep-hazard vehicle,red_light: those two targets are the --init head's own, the
    pedestrian is refitted (bid record --crossing-walkers data); with --keep-hazard-standing all
    three are the init head's where the ego stands. Kinds the head lacks, all of its kinds, or
    --keep-hazard-standing alone are refused."""
    _, init, refit, near = _hazard_refit(recorded, tmp_path)
    assert bid([*refit, "--keep-hazard", "vehicle,red_light", "--out", str(tmp_path / "keep")]) == 0
    assert bid([*refit, "--out", str(tmp_path / "free")]) == 0
    model, _ = load_model(init, preset="tiny")
    kept = KeptHazard(model, load_checkpoint(init)["model"], ("vehicle", "red_light"))
    before = near(model)
    recorded_targets = torch.tensor([[0.9, 0.8, 0.7]] * 4)
    target = kept.target(recorded_targets)
    assert torch.allclose(target[:, 1:], before[:, 1:]) and torch.equal(target[:, 0], recorded_targets[:, 0])
    # --keep-hazard-standing: where the ego stands, every kind is the init head's own.
    standing = KeptHazard(model, load_checkpoint(init)["model"], ("vehicle", "red_light"), standing=True)
    near(model)
    target = standing.target(recorded_targets, torch.tensor([0.0, 5.0, 0.1, 2.0]))
    assert torch.allclose(target[[0, 2]], before[[0, 2]])
    assert torch.equal(target[[1, 3], 0], recorded_targets[[1, 3], 0]) and torch.allclose(target[[1, 3], 1:], before[[1, 3], 1:])
    after = {run: near(load_model(tmp_path / run / "last.pt", preset="tiny")[0]) for run in ("keep", "free")}
    drift = {run: float((out[:, 1:] - before[:, 1:]).abs().mean()) for run, out in after.items()}
    assert drift["keep"] < 0.5 * drift["free"], drift
    assert float((after["keep"][:, 0] - before[:, 0]).abs().mean()) > 1e-3  # the pedestrian refitted
    train = load_checkpoint(tmp_path / "keep" / "last.pt")["config"]["train"]
    assert train["keep_hazard"] is True and tuple(train["keep_hazard_kinds"]) == ("vehicle", "red_light")
    for kinds, says in (("crossing", "keep some of this head's kinds, pedestrian, vehicle, red_light"),
                        ("pedestrian,vehicle,red_light", "leaves it nothing to learn: keep fewer")):
        assert bid([*refit, "--keep-hazard", kinds, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
    assert bid([*refit, "--keep-hazard-standing", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--keep-hazard-standing keeps the standing frames of --keep-hazard's refit: add --keep-hazard" in err


def test_head_presence_reads_the_pedestrian_only_where_its_logit_says_she_is(recorded, tmp_path, capsys):
    """--head-presence: the hazard head's last column is a logit that a pedestrian is in the path
    (at SEEN_NEARNESS or nearer); driving reads her nearness only where it is above 0. Started
    from a head without it, the logit starts as "her nearness is 0.2 or more" and everything but
    the head carries over; training fits the logit by cross-entropy and her nearness only where
    she is; the vehicle and red light can be kept (--keep-hazard vehicle,red_light)."""
    from bid_model.hazards import SEEN_NEARNESS
    from bid_model.train import head_presence_loss, warm_start_presence

    # The loss: her nearness is fitted only where she is in the path; the other kinds as ever.
    target = torch.tensor([[0.6, 0.0, 0.3], [0.1, 0.4, 0.0]])  # the second pedestrian too far to count
    out = torch.tensor([[0.5, 0.9, 0.3, -3.0], [0.5, 0.4, 0.2, 3.0]], requires_grad=True)
    head_presence_loss(out, target).backward()
    assert out.grad[0, 0] < 0 and out.grad[1, 0] == 0  # no nearness fitted where she is not
    assert out.grad[0, 3] < 0 and out.grad[1, 3] > 0  # yes where she is, no where she is not
    assert out.grad[0, 1] > 0 and out.grad[1, 2] > 0  # the vehicle and the red light fitted as hazard_loss

    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--hazard", "1", "--hazard-sc"]
    assert bid([*base, "--out", str(tmp_path / "sc")]) == 0
    start = load_checkpoint(tmp_path / "sc" / "last.pt")
    config = dataclasses.replace(model_config_from_dict(start["config"]["model"]), head_presence=True)
    model = BID(config)
    fresh = load_shared_weights(model, start["model"])
    assert fresh == ["hazard_head.presence.bias", "hazard_head.presence.weight"]
    assert warm_start_presence(model, start["model"], fresh) == []
    plain, _ = load_model(tmp_path / "sc" / "last.pt", preset="tiny")
    feats = torch.randn(64, config.width)
    with torch.no_grad():
        before, after = plain.hazard_head(feats), model.hazard_head(feats)
    assert after.shape == (64, 4) and torch.allclose(after[:, :3], before)
    assert torch.equal(after[:, 3] > 0, before[:, 0] > SEEN_NEARNESS)
    gated = model.gate_head(after)
    assert torch.equal(gated[:, 0], torch.where(before[:, 0] > SEEN_NEARNESS, after[:, 0], torch.zeros(64)))

    refit = [*base, "--init", str(tmp_path / "sc" / "last.pt"), "--head-presence", "--train-only", "hazard",
             "--lr", "3e-3", "--hazard-pos-weight", "4"]
    assert bid([*refit, "--keep-hazard", "vehicle,red_light", "--keep-hazard-standing", "--out", str(tmp_path / "hp")]) == 0
    tuned = load_checkpoint(tmp_path / "hp" / "last.pt")
    assert tuned["config"]["model"]["head_presence"] and "hazard_head.presence.weight" in tuned["model"]
    assert all(torch.equal(v, tuned["model"][k]) for k, v in start["model"].items()
               if not k.startswith("hazard_head."))  # only the head moved
    near, apart = hazard_outputs(tmp_path / "hp" / "last.pt")
    assert apart.shape == (4, 6)  # the head's three nearnesses, its pedestrian logit, SC's two
    head = torch.where(apart[:, 3] > 0, apart[:, 0], torch.zeros(4))
    assert torch.allclose(near[:, 0], torch.maximum(head, apart[:, 4]))
    assert torch.allclose(near[:, 1], torch.maximum(apart[:, 1], apart[:, 5])) and torch.allclose(near[:, 2], apart[:, 2])
    # Kept from a reference with a logit of its own, her nearness is read gated, as driving reads it:
    # where its logit says no, 0, whatever the (unfitted) nearness column holds.
    again = BID(config)
    load_shared_weights(again, tuned["model"])
    kept = KeptHazard(again, tuned["model"], ("vehicle", "red_light"), standing=True)
    with torch.no_grad():
        out = again.hazard_head(feats)
    fit = kept.target(torch.zeros(64, 3), torch.zeros(64))  # all standing: every kind the reference's
    assert torch.equal(fit, again.gate_head(out))
    assert torch.equal(fit[:, 0], torch.where(out[:, 3] > 0, out[:, 0], torch.zeros(64)))
    for flags in (["--head-presence"], ["--hazard-attend", "--head-presence"], ["--move-off-head", "--head-presence"]):
        args = ["train", "--preset", "tiny", "--data", str(recorded), "--hazard", "1", *flags, "--out", str(tmp_path / "x")]
        assert bid([*args, *(["--hazard-sc"] if flags != ["--head-presence"] else [])]) == 2
        err = capsys.readouterr().err.strip()
        assert "--head-presence is a logit beside the plain hazard head" in err and "\n" not in err, err


def test_second_bumper_fits_the_second_heads_vehicle_to_cars_ahead_of_the_bumper(recorded, tmp_path, capsys):
    """--second-bumper M: the second head's vehicle target is the nearer of the path's vehicle
    and the one within M m ahead of the bumper (recordings.bumper_targets); its other targets,
    and the first head's, stay the path's. Refused without a second head or out of range."""
    near = torch.tensor([[0.1, 0.2, 0.3], [0.0, 0.0, 0.9]])
    assert torch.equal(second_targets({}, near), near)
    bumped = second_targets({"vehicle_bumper": torch.tensor([0.7, 0.0], dtype=torch.float64)}, near)
    assert torch.equal(bumped, torch.tensor([[0.1, 0.7, 0.3], [0.0, 0.0, 0.9]])) and near[0, 1] == 0.2
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--speed-input", "--forecast", "0.5", "--hazard", "1", "--out"]
    assert bid([*base, str(tmp_path / "two"), "--move-off-head", "--second-bumper", "8"]) == 0
    run = json.loads((tmp_path / "two" / "config.json").read_text())
    assert run["train"]["second_bumper_m"] == 8.0
    frames = json.loads((tmp_path / "two" / "dataset.json").read_text())["hazard_frames"]
    assert frames["bumper_m"] == 8.0 and frames["vehicle_in_path_or_bumper"] >= frames["vehicle_in_path"]
    # --second-bumper-weight: where the bumper's car is nearer than the path's, its entry weighs more.
    boost = second_boost(near, bumped, 5.0)
    assert torch.equal(boost, torch.tensor([[1.0, 5.0, 1.0], [1.0, 1.0, 1.0]])) and second_boost(near, bumped, 1.0) is None
    pred = torch.zeros(2, 3)
    assert hazard_loss(pred, bumped, boost=boost) == pytest.approx((0.1 + 5 * 0.7 + 0.3 + 0.9) / 10)
    assert bid([*base, str(tmp_path / "w"), "--move-off-head", "--second-bumper", "8", "--second-bumper-weight",
                "5"]) == 0
    assert json.loads((tmp_path / "w" / "config.json").read_text())["train"]["second_bumper_weight"] == 5.0
    for flags, says in ((["--second-bumper", "8"], "add --move-off-head"),
                        (["--move-off-head", "--second-bumper-weight", "5"], "add --second-bumper M"),
                        (["--move-off-head", "--second-bumper", "8", "--second-bumper-weight", "0.5"], "1 or more"),
                        (["--move-off-head", "--second-bumper", "0"], "above 0 to 25"),
                        (["--move-off-head", "--second-bumper", "30"], "above 0 to 25")):
        assert bid([*base, str(tmp_path / "x"), *flags]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err


def test_hazard_crossing_is_a_fourth_output_from_a_second_sc_map_started_as_sc(recorded, tmp_path, capsys):
    """--hazard-crossing: a second SC map says how near an occupied crossing on the path is, the
    hazard output's fourth column. Started from a run with SC, it starts as that SC with its
    pedestrian map, and `--train-only crossing` moves it alone."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet"]
    assert bid([*base, "--hazard", "1", "--hazard-sc", "--out", str(tmp_path / "sc")]) == 0
    start = load_checkpoint(tmp_path / "sc" / "last.pt")
    config = RunConfig.from_dict(start["config"]).model
    model = BID(dataclasses.replace(config, hazard_crossing=True))
    fresh = load_shared_weights(model, start["model"])
    assert fresh and all(k.startswith("hazard_crossing.") for k in fresh)
    assert warm_start_crossing(model, start["model"], fresh) == []
    own = model.hazard_crossing.state_dict()
    assert torch.equal(own["retina.0.0.weight"], start["model"]["hazard_sc.retina.0.0.weight"])
    assert torch.equal(own["priority.2.weight"], start["model"]["hazard_sc.priority.2.weight"][:1])

    assert bid([*base, "--init", str(tmp_path / "sc" / "last.pt"), "--hazard", "1", "--hazard-sc",
                "--hazard-crossing", "--train-only", "crossing", "--out", str(tmp_path / "x")]) == 0
    tuned = load_checkpoint(tmp_path / "x" / "last.pt")
    assert tuned["config"]["model"]["hazard_crossing"] and "fresh" not in tuned.get("init", {})
    assert all(torch.equal(v, tuned["model"][k]) for k, v in start["model"].items())  # all else as it was
    assert not torch.equal(tuned["model"]["hazard_crossing.priority.2.weight"], own["priority.2.weight"])
    near, apart = hazard_outputs(tmp_path / "x" / "last.pt")
    assert near.shape == (4, 4) and apart.shape == (4, 6)  # the head's 3, SC's 2, the crossing map's 1
    assert torch.allclose(near[:, :2], torch.maximum(apart[:, :2], apart[:, 3:5]))
    assert torch.allclose(near[:, 2:], apart[:, [2, 5]])
    assert "crossing" in model.parameter_counts()
    assert bid([*base, "--hazard", "1", "--hazard-crossing", "--out", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err.strip()
    assert "add --hazard-sc" in err and "\n" not in err


def test_shift_moves_both_frames_alike_and_repeats_the_edges():
    from bid_model.augment import shift

    frame = torch.randint(0, 256, (6, 3, 10, 30), dtype=torch.uint8)
    prev = torch.randint(0, 256, (6, 3, 10, 30), dtype=torch.uint8)
    state = torch.get_rng_state()
    assert shift(frame, prev, 0)[0] is frame and torch.equal(state, torch.get_rng_state())
    gen = torch.Generator().manual_seed(3)
    f, p = shift(frame, prev, 2, gen)
    assert f.dtype == torch.uint8 and f.shape == frame.shape and p.shape == prev.shape
    moved = edges = 0
    for i in range(6):
        # Find the move: frame t's inside matches the original moved by (dy, dx), and t−1's by the same.
        found = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)
                 if torch.equal(f[i, :, 2:-2, 2:-2], frame[i, :, 2 - dy:8 - dy, 2 - dx:28 - dx])]
        assert len(found) == 1
        dy, dx = found[0]
        assert torch.equal(p[i, :, 2:-2, 2:-2], prev[i, :, 2 - dy:8 - dy, 2 - dx:28 - dx])
        if dy > 0:  # moved down: the top rows repeat the original's first row
            assert torch.equal(f[i, :, 0, 2:-2], frame[i, :, 0, 2 - dx:28 - dx])
            edges += 1
        moved += (dy, dx) != (0, 0)
    assert moved >= 4 and edges >= 1
    again = shift(frame, prev, 2, torch.Generator().manual_seed(3))
    assert torch.equal(again[0], f) and torch.equal(again[1], p)


def test_mirror_flips_the_world_left_to_right_with_its_commands_and_steering():
    from bid_model.augment import mirror

    frame = torch.randint(0, 256, (4, 3, 8, 24), dtype=torch.uint8)
    prev = torch.randint(0, 256, (4, 3, 8, 24), dtype=torch.uint8)
    command = torch.eye(6)[[0, 1, 4, 3]]  # LEFT, RIGHT, CHANGELANELEFT, LANEFOLLOW
    target = torch.tensor([[0.5, 0.2], [-0.3, -1.0], [0.1, 0.0], [0.0, 0.4]])
    f, p, c, t = mirror(frame, prev, command, target, 1.0)
    assert torch.equal(f, frame.flip(-1)) and torch.equal(p, prev.flip(-1))
    assert c.argmax(1).tolist() == [1, 0, 5, 3]  # RIGHT, LEFT, CHANGELANERIGHT, LANEFOLLOW
    assert torch.equal(t, target * torch.tensor([-1.0, 1.0]))
    assert all(torch.equal(a, b) for a, b in zip(mirror(f, p, c, t, 1.0), (frame, prev, command, target), strict=True))
    state = torch.get_rng_state()
    assert mirror(frame, prev, command, target, 0.0)[0] is frame
    assert torch.equal(state, torch.get_rng_state())  # no draws: runs without it train as before
    torch.manual_seed(0)
    f, _, c, t = mirror(frame, prev, command, target, 0.5)
    flipped = [bool(torch.equal(f[i], frame[i].flip(-1))) for i in range(3)]  # steer ≠ 0
    assert flipped == [bool(t[i, 0] == -target[i, 0]) for i in range(3)]


def test_sc_scale_starts_sc_afresh_on_finer_frames_and_keeps_every_other_weight(recorded, tmp_path, capsys):
    """--sc-scale 2 --init from a run whose SC read the cortex's frames: the recordings are read
    twice as fine, SC starts afresh on them and alone moves (--train-only SC), every other weight
    is the start's; the agent feeds the run frames of that size. Without SC, or out of range, it
    is refused in one line."""
    base = ["train", "--preset", "tiny", "--data", str(recorded), "--epochs", "1", "--batch-size", "8", "--quiet",
            "--hazard", "1", "--hazard-sc"]
    assert bid([*base, "--out", str(tmp_path / "sc")]) == 0
    assert bid([*base, "--init", str(tmp_path / "sc" / "last.pt"), "--sc-scale", "2", "--train-only", "SC",
                "--out", str(tmp_path / "fine")]) == 0
    start, fine = load_checkpoint(tmp_path / "sc" / "last.pt"), load_checkpoint(tmp_path / "fine" / "last.pt")
    assert fine["config"]["model"]["sc_scale"] == 2
    assert all(torch.equal(v, fine["model"][k]) for k, v in start["model"].items() if not k.startswith("hazard_sc."))
    assert fine["model"]["hazard_sc.position"].shape[2:] == (8, 24)  # tiny's 32×96 twice as fine, over 8
    assert set(fine["init"]["fresh"]) == {k for k in fine["model"] if k.startswith("hazard_sc.")}  # all of SC
    agent = BIDAgent(tmp_path / "fine" / "last.pt")
    assert agent.hw == (64, 192)
    for flags, why in ((["--hazard", "1", "--sc-scale", "2"], "add --hazard-sc"),
                       ([*base[-3:], "--sc-scale", "5"], "whole factor, 1 to 4")):
        assert bid(["train", "--preset", "tiny", "--data", str(recorded), "--quiet", *flags,
                    "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert why in err and "\n" not in err
