"""BID model speed: `paper` forward+backward samples/s (CPU, and CUDA bf16 when a GPU is
visible), `small` training samples/s on the CPU, `small` inference latency per frame on one
core (target ≤ 15 ms), and parameter counts per area. About two minutes on 2 cores.

    .venv/bin/python benchmarks/bench_model.py [--json] [--quick] [--gpu-only] [--gpu-batches 64,100]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from bid_model.config import preset
from bid_model.data import command_one_hot
from bid_model.model import BID
from bid_model.train import compile_each_area, l1_loss


def _inputs(model: BID, batch: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    h, w = model.config.frame_hw
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    prev = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    command = command_one_hot(torch.randint(1, 7, (batch,), generator=g))
    x = (frame, prev, command)
    if model.config.speed_input:  # the small preset sees the measured speed
        x += (torch.rand(batch, generator=g) * 10.0,)
    return tuple(t.to(device) for t in x)


def train_samples_per_s(name: str, batch: int, iters: int, device: torch.device,
                        channels_last: bool = False, compiled: bool = False) -> float:
    """Forward + backward + AdamW step, samples per second (best of `iters` timed steps)."""
    torch.manual_seed(0)
    run = preset(name)
    model = BID(run.model).to(device).train()
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(model.parameters(), lr=run.train.lr)
    if compiled:
        compile_each_area(model)
    x = _inputs(model, batch, device)
    target = torch.zeros(batch, 2, device=device)
    times = []
    warm_up = 3 if compiled else 1  # allocations, kernel choice, compilation
    for i in range(iters + warm_up):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        with torch.autocast("cuda", torch.bfloat16, enabled=device.type == "cuda"):
            pred = model(*x)
        loss = l1_loss(pred, target, run.train)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= warm_up:
            times.append(time.perf_counter() - t0)
    return batch / min(times)


def gpu_figures(quick: bool, batches: list[int]) -> dict[str, object]:
    """`paper` training on the GPU under bf16 autocast: samples/s per batch size with the
    default (NCHW) and channels-last memory formats, then channels-last with each area
    compiled (`bid train --compile`) at the paper's batch."""
    gpu = torch.device("cuda")
    out: dict[str, object] = {"gpu": torch.cuda.get_device_name(gpu)}
    torch.backends.cudnn.benchmark = True
    iters = 3 if quick else 10
    for batch in batches:
        for fmt, cl in (("nchw", False), ("channels_last", True)):
            torch.cuda.reset_peak_memory_stats()
            out[f"paper_bf16_b{batch}_{fmt}_samples_per_s"] = round(
                train_samples_per_s("paper", batch, iters, gpu, channels_last=cl), 1)
            out[f"paper_bf16_b{batch}_{fmt}_peak_gib"] = round(
                torch.cuda.max_memory_allocated() / 2**30, 1)
    batch = preset("paper").train.batch_size
    key = f"paper_bf16_b{batch}_channels_last_compiled_samples_per_s"
    try:
        out[key] = round(train_samples_per_s("paper", batch, iters, gpu, channels_last=True,
                                             compiled=True), 1)
    except Exception as e:  # compilation needs a C compiler and Triton; report, don't fail
        out[key] = f"failed: {type(e).__name__}: {e}"[:200]
    return out


def latency_ms(name: str, iters: int) -> dict[str, float]:
    """Inference on one frame pair, one CPU thread: median and best ms per frame."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        model = BID(preset(name).model).eval()
        x = _inputs(model, 1, torch.device("cpu"))
        times = []
        with torch.inference_mode():
            for _ in range(5):
                model(*x)
            for _ in range(iters):
                t0 = time.perf_counter()
                model(*x)
                times.append((time.perf_counter() - t0) * 1e3)
    finally:
        torch.set_num_threads(threads)
    return {"median": statistics.median(times), "best": min(times)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON dict")
    p.add_argument("--quick", action="store_true", help="fewer iterations (a smoke check)")
    p.add_argument("--gpu-only", action="store_true", help="only the GPU figures")
    p.add_argument("--gpu-batches", default="64,100,128,256",
                   help="batch sizes of the GPU sweep (default 64,100,128,256)")
    args = p.parse_args()
    quick = args.quick
    batches = [int(b) for b in args.gpu_batches.split(",")]
    cpu = torch.device("cpu")
    threads = torch.get_num_threads()
    # Other programs slow torch's OpenMP threads a lot (see bid_model.train.default_threads):
    # the load average says whether the figures were taken on a quiet machine.
    result: dict[str, object] = {"torch": str(torch.__version__), "cpu_threads": threads,
                                 "load_avg_1min_before": round(os.getloadavg()[0], 2)}
    if args.gpu_only:
        if not torch.cuda.is_available():
            raise SystemExit("error: --gpu-only but no CUDA GPU is visible; drop --gpu-only")
        result.update(gpu_figures(quick, batches))
        print(json.dumps(result, indent=1))
        return
    lat = latency_ms("small", 20 if quick else 200)
    result["small_latency_ms_1core"] = round(lat["median"], 2)
    result["small_latency_ms_1core_best"] = round(lat["best"], 2)
    result["small_train_samples_per_s_cpu"] = round(
        train_samples_per_s("small", 32, 2 if quick else 4, cpu), 1)
    torch.set_num_threads(1)
    result["small_train_samples_per_s_cpu_1thread"] = round(
        train_samples_per_s("small", 32, 2 if quick else 4, cpu), 1)
    torch.set_num_threads(threads)
    result["paper_fwd_bwd_samples_per_s_cpu"] = round(
        train_samples_per_s("paper", 1, 1 if quick else 2, cpu), 3)
    if torch.cuda.is_available():
        result.update(gpu_figures(quick, batches))
    result["load_avg_1min_after"] = round(os.getloadavg()[0], 2)
    result["parameters"] = {name: BID(preset(name).model).parameter_counts()
                            for name in ("paper", "small")}
    if args.json:
        print(json.dumps(result, indent=1))
        return
    for key, value in result.items():
        if key != "parameters":
            print(f"{key:40s} {value}")
    for name, counts in result["parameters"].items():
        total = sum(counts.values())
        print(f"{name} parameters: {total / 1e6:.2f} M  "
              + "  ".join(f"{a} {n / 1e6:.3f}M" for a, n in counts.items()))


if __name__ == "__main__":
    main()
