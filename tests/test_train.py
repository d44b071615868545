"""Training on generated tiny data: the run folder, resume = uninterrupted run, bad input."""

import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import cv2
import pytest
import torch

from bid_model.checkpoint import load_checkpoint, load_model
from bid_model.config import RunConfig, tiny
from bid_model.train import METRIC_COLUMNS, train
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


def test_resume_continues_exactly(tmp_path):
    run = quick_run(3)
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
        (["train", "--preset", "tiny", "--synthetic", "--epochs", "0"], "--epochs"),
        (["gradcam", "--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path)],
         "no checkpoint"),
    ]
    for argv, message in cases:
        assert bid(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and message in err and "\n" not in err, (argv, err)


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


@pytest.mark.skipif(shutil.which("torchrun", path=os.path.dirname(sys.executable)) is None,
                    reason="torchrun not installed")
def test_torchrun_ddp_on_two_cpu_processes(tmp_path):
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [torchrun, "--standalone", "--nproc-per-node=2", "-m", "bid_model.train", "--preset",
         "tiny", "--synthetic", "--samples", "40", "--epochs", "1", "--device", "cpu",
         "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((out / "config.json").read_text())["world_size"] == 2
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert len(rows) == 1
