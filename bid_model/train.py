"""Training of the BID model: `bid train`, or `python -m bid_model.train` (also under
`torchrun --nproc-per-node=N -m bid_model.train ...` for DDP).

L1 loss on (steer, accel) weighted λ_s = λ_a = 0.5; AdamW with weight decay on weights only;
the lr halves at the (scaled) milestones. A run folder holds config.json (resolved config,
git hash, software versions), dataset.json, metrics.csv, last.pt and best.pt (atomic, with
optimiser and scheduler state for --resume) and the plots mae.png and steering.png.
Each epoch reseeds from (seed, epoch), so a resumed run repeats an uninterrupted one exactly.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib.metadata
import io
import json
import logging
import math
import os
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm import tqdm

from bid_model.checkpoint import check_preset, git_hash, load_checkpoint, save_checkpoint
from bid_model.config import RunConfig, TrainConfig, preset, with_variant
from bid_model.data import check_sample, command_one_hot, synthetic_split
from bid_model.model import BID
from bid_model.plots import plot_metrics, plot_sequence
from bid_sim.errors import BidError

log = logging.getLogger(__name__)

DEFAULT_DATA = Path("data/town01")
PLOT_EVERY_S = 60.0  # plots are redrawn at most this often, and after the last epoch
METRIC_COLUMNS = ("epoch", "train_loss", "val_loss", "val_mae_steer", "val_mae_accel",
                  "const_mae_steer", "const_mae_accel", "lr", "samples_per_s", "time_s")


# --- pieces ----------------------------------------------------------------------------------


def make_optimizer(model: nn.Module, tc: TrainConfig) -> torch.optim.AdamW:
    """AdamW decaying only weight matrices and kernels: not biases, norms or embeddings."""
    decay, keep = [], []
    for name, p in model.named_parameters():
        if p.requires_grad:
            (decay if p.ndim >= 2 and not name.endswith("embed") else keep).append(p)
    return torch.optim.AdamW([{"params": decay, "weight_decay": tc.weight_decay},
                              {"params": keep, "weight_decay": 0.0}], lr=tc.lr)


def l1_loss(pred: torch.Tensor, target: torch.Tensor, tc: TrainConfig) -> torch.Tensor:
    """λ_s·|Δsteer| + λ_a·|Δaccel|, averaged over the batch."""
    err = (pred.float() - target).abs().mean(0)
    return tc.lambda_steer * err[0] + tc.lambda_accel * err[1]


def batch_inputs(batch: dict[str, Any], device: torch.device
                 ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
    """((frame_t, frame_prev, command one-hot, speed), target (B, 2)) on `device`."""
    inputs = (batch["frame"].to(device, non_blocking=True),
              batch["prev_frame"].to(device, non_blocking=True),
              command_one_hot(batch["command"]).to(device, non_blocking=True),
              torch.as_tensor(batch["speed_mps"], dtype=torch.float32).to(device))
    target = torch.stack([torch.as_tensor(batch["steer"]), torch.as_tensor(batch["accel"])], 1)
    return inputs, target.float().to(device, non_blocking=True)


def open_data(config: RunConfig, data: Path | None, synthetic: bool
              ) -> tuple[Dataset, Dataset, dict[str, Any]]:
    """(train, validation, description): generated data, or the recordings in `data`."""
    tc, hw = config.train, config.model.frame_hw
    if synthetic:
        return synthetic_split(tc.synthetic_samples, hw, tc.val_fraction, tc.seed)
    folder = Path(data if data is not None else DEFAULT_DATA)
    hint = "record some with `make record TOWN=01`, or train on generated data with --synthetic"
    if not folder.is_dir():
        raise BidError(f"no recordings: {folder} does not exist; {hint}")
    if not any(folder.rglob("*.mcap")):
        raise BidError(f"no recordings in {folder} (no .mcap files); {hint}")
    try:
        from bid_model.recordings import open_recordings
    except ModuleNotFoundError as e:
        if e.name != "bid_model.recordings":
            raise
        raise BidError("this version has no recording reader (bid_model/recordings.py); "
                       "train on --synthetic") from e
    train_set, val_set, description = open_recordings(folder, hw, tc.val_fraction, tc.seed)
    if len(train_set) == 0:
        raise BidError(f"no recordings in {folder} gave training samples; {hint}")
    return train_set, val_set, description


@dataclasses.dataclass(frozen=True)
class Dist:
    """This process's place in a torchrun job (rank 0 of 1 when run alone)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> Dist:
    """Join the torchrun process group if WORLD_SIZE > 1 (NCCL on GPUs, Gloo on CPUs)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return Dist()
    dist = Dist(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
    if not torch.distributed.is_initialized():
        cuda = device != "cpu" and torch.cuda.is_available()
        if cuda:
            torch.cuda.set_device(dist.local_rank)
        torch.distributed.init_process_group("nccl" if cuda else "gloo")
    return dist


def pick_device(name: str, dist: Dist) -> torch.device:
    """'auto' is CUDA when a GPU is visible, else the CPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise BidError("--device cuda but no CUDA GPU is visible; use --device cpu")
        return torch.device("cuda", dist.local_rank)
    if name != "cpu":
        raise BidError(f"unknown device {name!r}; use auto, cpu or cuda")
    return torch.device("cpu")


def _autocast(device: torch.device):
    # bf16 autocast on GPUs (no loss scaling needed); the CPUs here have no fast bf16.
    return torch.autocast("cuda", dtype=torch.bfloat16, enabled=device.type == "cuda")


def _all_sum(values: Iterable[float], dist: Dist, device: torch.device) -> list[float]:
    t = torch.tensor(list(values), dtype=torch.float64, device=device)
    if dist.world > 1:
        torch.distributed.all_reduce(t)
    return t.tolist()


def _write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_metrics(history: list[dict[str, Any]], path: Path) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, METRIC_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in history:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    _write_text_atomic(path, buf.getvalue())


# --- one epoch ----------------------------------------------------------------------------


def train_epoch(net: nn.Module, loader: DataLoader, opt: torch.optim.Optimizer, tc: TrainConfig,
                device: torch.device, bar_desc: str | None) -> tuple[float, int]:
    """One pass over `loader`; (sum of batch losses × batch sizes, samples) of this process."""
    net.train()
    loss_sum = torch.zeros((), dtype=torch.float64, device=device)
    samples, t0 = 0, time.perf_counter()
    bar = tqdm(loader, desc=bar_desc, unit="batch", disable=bar_desc is None, leave=False,
               dynamic_ncols=True, mininterval=1.0)
    for i, batch in enumerate(bar):
        inputs, target = batch_inputs(batch, device)
        with _autocast(device):
            pred = net(*inputs)
        loss = l1_loss(pred, target, tc)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_sum += loss.detach() * len(target)
        samples += len(target)
        if bar_desc is not None and i % 5 == 0:
            bar.set_postfix(loss=f"{float(loss.detach()):.4f}",
                            samples_s=f"{samples / (time.perf_counter() - t0):.0f}")
    bar.close()
    return float(loss_sum), samples


@torch.no_grad()
def evaluate(model: BID, loader: DataLoader, tc: TrainConfig, device: torch.device
             ) -> dict[str, Any]:
    """Loss and MAE on `loader`, the best constant's MAE, and every prediction (for plots)."""
    model.eval()
    preds, targets, episodes, steps = [], [], [], []
    for batch in loader:
        inputs, target = batch_inputs(batch, device)
        with _autocast(device):
            preds.append(model(*inputs).float().cpu())
        targets.append(target.cpu())
        episodes.append(torch.as_tensor(batch["episode"]))
        steps.append(torch.as_tensor(batch["step"]))
    pred, target = torch.cat(preds), torch.cat(targets)
    mae = (pred - target).abs().mean(0)
    # The median minimises the L1 error of a constant: the baseline a model must beat.
    const = (target - target.median(0).values).abs().mean(0)
    return {"val_loss": float(tc.lambda_steer * mae[0] + tc.lambda_accel * mae[1]),
            "val_mae_steer": float(mae[0]), "val_mae_accel": float(mae[1]),
            "const_mae_steer": float(const[0]), "const_mae_accel": float(const[1]),
            "pred": pred.numpy(), "target": target.numpy(),
            "episode": torch.cat(episodes).numpy(), "step": torch.cat(steps).numpy()}


def _plot(history: list[dict[str, Any]], val: dict[str, Any] | None, out: Path) -> None:
    plot_metrics(history, out / "mae.png")
    if val is None:
        return
    # The longest validation episode, in time order.
    ids, counts = np.unique(val["episode"], return_counts=True)
    episode = int(ids[np.argmax(counts)])
    idx = np.flatnonzero(val["episode"] == episode)
    idx = idx[np.argsort(val["step"][idx], kind="stable")]
    plot_sequence(val["step"][idx], val["pred"][idx], val["target"][idx], episode,
                  out / "steering.png")


# --- the run ----------------------------------------------------------------------------------


def train(out: Path, config: RunConfig | None = None, *, data: Path | None = None,
          synthetic: bool = False, resume: bool = False, expect_preset: str | None = None,
          device: str = "auto", workers: int | None = None, stop_after: int | None = None,
          progress: bool = True) -> list[dict[str, Any]]:
    """Train into run folder `out`; returns the metrics rows of all epochs so far.

    With `resume`, continue from out/last.pt with its saved config (`config`, if given, must
    equal it; `expect_preset` must match it). `stop_after` ends this call after that many
    epochs (the run stays resumable). `data` is a folder of recordings, unless `synthetic`.
    """
    out = Path(out)
    ckpt = None
    if resume:
        if not (out / "last.pt").is_file():
            raise BidError(f"nothing to resume in {out}: no last.pt; start a run without --resume")
        ckpt = load_checkpoint(out / "last.pt")
        saved = RunConfig.from_dict(ckpt["config"])
        check_preset(saved, expect_preset or (config.preset if config else None), out / "last.pt")
        if config is not None and config != saved:
            raise BidError(f"--resume continues {out} with its saved config; start a new run "
                           "to change it")
        config = saved
    elif (out / "last.pt").exists():
        raise BidError(f"{out} already holds a run; pass --resume to continue it, or choose "
                       "another --out / --name")
    if config is None:
        raise BidError("no config: pass a preset or --resume an existing run")
    tc = config.train

    dist = init_distributed(device)
    dev = pick_device(device, dist)
    train_set, val_set, description = open_data(config, data, synthetic)
    check_sample(train_set[0], config.model.frame_hw)

    torch.manual_seed(tc.seed)
    model = BID(config.model).to(dev)
    opt = make_optimizer(model, tc)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, list(tc.milestones), tc.lr_gamma)
    start, history, best = 0, [], math.inf
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start, history, best = ckpt["epoch"], list(ckpt["history"]), ckpt["best_val_loss"]

    meta = {"git_hash": git_hash(), "version": _version(), "torch": str(torch.__version__)}
    if dist.main:
        out.mkdir(parents=True, exist_ok=True)
        _write_text_atomic(out / "config.json", json.dumps(
            {**config.to_dict(), **meta, "device": str(dev), "world_size": dist.world},
            indent=1) + "\n")
        _write_text_atomic(out / "dataset.json",
                           json.dumps(description, indent=1, default=str) + "\n")

    net: nn.Module = model
    if dist.world > 1:
        net = nn.parallel.DistributedDataParallel(
            model, device_ids=[dev.index] if dev.type == "cuda" else None)
    n_workers = tc.workers if workers is None else workers
    batch = max(1, tc.batch_size // dist.world)  # the global batch stays tc.batch_size
    sampler = DistributedSampler(train_set, dist.world, dist.rank, shuffle=True, seed=tc.seed)
    loader = DataLoader(train_set, batch, sampler=sampler, num_workers=n_workers,
                        pin_memory=dev.type == "cuda",
                        # a last batch of 1 would break batch norm
                        drop_last=len(sampler) > batch)
    val_loader = DataLoader(val_set, max(batch, 64), shuffle=False, num_workers=n_workers)

    end = tc.epochs if stop_after is None else min(tc.epochs, start + stop_after)
    last_plot = -math.inf
    for epoch in range(start, end):
        sampler.set_epoch(epoch)
        torch.manual_seed(tc.seed * 1_000_003 + epoch)  # dropout & workers: same on resume
        lr = opt.param_groups[0]["lr"]
        t0 = time.perf_counter()
        desc = f"epoch {epoch + 1}/{tc.epochs}" if progress and dist.main else None
        loss_sum, samples = _all_sum(train_epoch(net, loader, opt, tc, dev, desc), dist, dev)
        train_s = time.perf_counter() - t0
        sched.step()
        if not dist.main:
            torch.distributed.barrier()
            continue
        val = evaluate(model, val_loader, tc, dev) if len(val_set) else None
        row = {"epoch": epoch + 1, "train_loss": loss_sum / max(samples, 1)}
        nan = math.nan
        row.update({k: (val[k] if val else nan) for k in METRIC_COLUMNS[2:7]})
        row.update(lr=lr, samples_per_s=samples / train_s, time_s=time.perf_counter() - t0)
        history.append(row)
        score = row["val_loss"] if val else row["train_loss"]
        payload = {"config": config.to_dict(), "model": model.state_dict(),
                   "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                   "epoch": epoch + 1, "history": history, "best_val_loss": min(best, score),
                   **meta}
        save_checkpoint(out / "last.pt", payload)
        if score < best:
            best = score
            save_checkpoint(out / "best.pt", payload)
        _write_metrics(history, out / "metrics.csv")
        if epoch + 1 == end or time.monotonic() - last_plot > PLOT_EVERY_S:
            _plot(history, val, out)
            last_plot = time.monotonic()
        log.info("epoch %d/%d: train %.4f, val %.4f (MAE steer %.4f, accel %.4f), %.0f samples/s",
                 epoch + 1, tc.epochs, row["train_loss"], row["val_loss"], row["val_mae_steer"],
                 row["val_mae_accel"], row["samples_per_s"])
        if dist.world > 1:
            torch.distributed.barrier()
    return history


def _version() -> str:
    try:
        return importlib.metadata.version("bid-sim")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# --- command line (shared by `bid train` and `python -m bid_model.train`) -----------------


def config_from_args(args: argparse.Namespace) -> RunConfig | None:
    """The run config the flags ask for; None with --resume (the saved config is used)."""
    flags = {"--variant": args.variant, "--epochs": args.epochs, "--batch-size": args.batch_size,
             "--lr": args.lr, "--seed": args.seed, "--samples": args.samples,
             "--speed-input": args.speed_input or None}
    if args.resume:
        given = [k for k, v in flags.items() if v is not None]
        if given:
            raise BidError(f"--resume continues a run with its saved config; drop {', '.join(given)}")
        return None
    run = preset(args.preset or "small")
    model, tc = run.model, run.train
    if args.variant:
        model = with_variant(model, args.variant)
    if args.speed_input:
        model = dataclasses.replace(model, speed_input=True)
    if args.epochs is not None:
        tc = tc.with_epochs(args.epochs)
    for flag, value, field, ok in (("--batch-size", args.batch_size, "batch_size", 2),
                                   ("--samples", args.samples, "synthetic_samples", 4),
                                   ("--seed", args.seed, "seed", 0)):
        if value is not None:
            if value < ok:
                raise BidError(f"{flag} must be at least {ok}, got {value}")
            tc = dataclasses.replace(tc, **{field: value})
    if args.lr is not None:
        if not args.lr > 0:
            raise BidError(f"--lr must be positive, got {args.lr}")
        tc = dataclasses.replace(tc, lr=args.lr)
    return RunConfig(model, tc)


def run_dir(args: argparse.Namespace, config: RunConfig | None) -> Path:
    """--out, or runs/--name, or runs/PRESET-VARIANT-TIME for a new run."""
    if args.out:
        return Path(args.out)
    if args.name:
        return Path("runs") / args.name
    if config is None:
        raise BidError("--resume needs the run folder: pass --out DIR or --name NAME")
    return Path("runs") / f"{config.preset}-{config.model.variant}-{time.strftime('%Y%m%d-%H%M%S')}"


def default_threads(workers: int) -> int:
    """Torch threads for training: the cores that neither data loaders nor other programs use.

    OpenMP threads that outnumber the free cores wait for each other at every parallel
    region: measured on 2 cores next to one busy process, one thread trained the tiny preset
    3-5× faster than two. So count one core per loader process and the 1-minute load average.
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    busy = round(os.getloadavg()[0]) if hasattr(os, "getloadavg") else 0
    threads = max(1, (cores or 1) - workers - busy)
    log.info("torch threads: %d (%s cores, %d loaders, load %d); set --threads to override",
             threads, cores, workers, busy)
    return threads


def run_from_args(args: argparse.Namespace) -> int:
    """`bid train`: train, then print where the run is and how it ended."""
    config = config_from_args(args)
    out = run_dir(args, config)
    if args.workers is not None and args.workers < 0:
        raise BidError(f"--workers must be 0 or more, got {args.workers}")
    if args.threads is not None and args.threads < 1:
        raise BidError(f"--threads must be at least 1, got {args.threads}")
    workers = args.workers if args.workers is not None else (config.train.workers if config else 0)
    if args.threads or "OMP_NUM_THREADS" not in os.environ:  # torchrun sets it per process
        torch.set_num_threads(args.threads or default_threads(workers))
    history = train(out, config, data=Path(args.data), synthetic=args.synthetic,
                    resume=args.resume, expect_preset=args.preset, device=args.device,
                    workers=args.workers, progress=not args.quiet)
    if int(os.environ.get("RANK", "0")) == 0:
        if history:
            r = history[-1]
            print(f"{out}: epoch {r['epoch']}, train loss {r['train_loss']:.4f}, validation MAE "
                  f"steer {r['val_mae_steer']:.4f} accel {r['val_mae_accel']:.4f} (best "
                  f"constant {r['const_mae_steer']:.4f}, {r['const_mae_accel']:.4f})")
        else:
            print(f"{out}: nothing left to train")
    return 0


def main(argv: list[str] | None = None) -> int:
    from bid_model.cli import add_train_arguments

    parser = argparse.ArgumentParser(prog="python -m bid_model.train",
                                     description="Train the BID model (torchrun-ready).")
    add_train_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        return run_from_args(args)
    except BidError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    finally:
        if torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())
