"""BID model speed: `paper` forward+backward samples/s (CPU, and CUDA bf16 when a GPU is
visible), `small` training samples/s on the CPU, `small` inference latency per frame on one
core (target ≤ 15 ms), and parameter counts per area. About two minutes on 2 cores.

    .venv/bin/python benchmarks/bench_model.py [--json] [--quick] [--gpu-only] [--gpu-batches 64,100]
    python3 benchmarks/bench_model.py --gpu-profile   # where the `paper` step's GPU time goes
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch
import torch.nn.functional as F
from torch.utils.flop_counter import FlopCounterMode

from bid_model.checkpoint import load_model
from bid_model.config import preset
from bid_model.data import command_one_hot
from bid_model.losses import l1_loss
from bid_model.model import BID, compile_each_area, grid_hw


def _inputs(model: BID, batch: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    h, w = model.config.input_hw
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    prev = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    command = command_one_hot(torch.randint(1, 7, (batch,), generator=g))
    x = (frame, prev, command)
    if model.config.speed_input or model.config.sc_fine:  # the small preset sees the speed; a fine SC is read by it
        x += (torch.rand(batch, generator=g) * 10.0,)
    return tuple(t.to(device) for t in x)


class TrainStep:
    """One training step of preset `name` (forward + backward + AdamW) on fixed inputs."""

    def __init__(self, name: str, batch: int, device: torch.device, channels_last: bool = False,
                 compiled: bool = False):
        torch.manual_seed(0)
        self.run, self.device, self.batch, self.compiled = preset(name), device, batch, compiled
        self.model = BID(self.run.model).to(device).train()
        if channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=self.run.train.lr)
        if compiled:
            compile_each_area(self.model)
        self.x = _inputs(self.model, batch, device)
        self.target = torch.zeros(batch, 2, device=device)

    def __call__(self) -> None:
        with torch.autocast("cuda", torch.bfloat16, enabled=self.device.type == "cuda"):
            pred = self.model(*self.x)
        loss = l1_loss(pred, self.target, self.run.train)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()

    def seconds(self, iters: int) -> list[float]:
        """Wall seconds of each of `iters` timed steps, after warm-up steps (allocations, kernel
        choice, compilation)."""
        times = []
        cuda = self.device.type == "cuda"
        for _ in range(iters + (3 if self.compiled else 1)):
            if cuda:
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            self()
            if cuda:
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        return times[-iters:]


def train_samples_per_s(name: str, batch: int, iters: int, device: torch.device,
                        channels_last: bool = False, compiled: bool = False) -> float:
    """Forward + backward + AdamW step, samples per second (best of `iters` timed steps)."""
    step = TrainStep(name, batch, device, channels_last, compiled)
    return batch / min(step.seconds(iters))


def step_flops(name: str, device: torch.device) -> float:
    """FLOP of one sample's forward + backward (torch.utils.flop_counter, batch 2)."""
    step = TrainStep(name, 2, device)
    counter = FlopCounterMode(display=False)
    with counter:
        step()
    return counter.get_total_flops() / 2


# Kernel families of a CUDA profile, matched in order on the kernel's name (inductor's kernels
# first: their names list the operations they fused, "convolution_backward" among them).
KERNEL_FAMILIES = (
    ("fused reduction (norm statistics)", ("triton_red", "triton_per")),
    ("fused pointwise", ("triton_poi",)),
    ("conv forward", ("fprop",)), ("conv input grad", ("dgrad",)), ("conv weight grad", ("wgrad",)),
    ("conv, other", ("convolution",)),
    ("layout change", ("nchwtonhwc", "nhwctonchw", "transpose")),
    ("attention", ("flash", "fmha", "attention")),
    ("matrix product", ("gemm", "nvjet", "cutlass", "xmma")),
    ("optimiser", ("multi_tensor", "adam")),
)


def kernel_family(kernel: str) -> str:
    low = kernel.lower()
    return next((family for family, keys in KERNEL_FAMILIES if any(k in low for k in keys)), "other")


def gpu_profile(batch: int, steps: int = 3) -> dict[str, object]:
    """Where one compiled channels-last `paper` training step's GPU time goes: milliseconds per
    step by kernel family and for the 20 costliest kernels, against the wall time per step."""
    from torch.profiler import ProfilerActivity, profile

    step = TrainStep("paper", batch, torch.device("cuda"), channels_last=True, compiled=True)
    wall_s = min(step.seconds(5))
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step()
        torch.cuda.synchronize()
    kernels = []
    for event in prof.key_averages():
        us = getattr(event, "self_device_time_total", None)
        if us is None:
            us = getattr(event, "self_cuda_time_total", 0.0)
        if us > 0:
            kernels.append((event.key, us / 1e3 / steps, event.count // steps))
    kernels.sort(key=lambda k: -k[1])
    families: dict[str, float] = {}
    for name, ms, _ in kernels:
        families[kernel_family(name)] = families.get(kernel_family(name), 0.0) + ms
    return {"wall_ms_per_step": round(wall_s * 1e3, 2),
            "kernel_ms_per_step": round(sum(k[1] for k in kernels), 2),
            "families_ms": {f: round(ms, 2) for f, ms in sorted(families.items(), key=lambda i: -i[1])},
            "top_kernels": [(name[:110], round(ms, 2), n) for name, ms, n in kernels[:20]]}


def conv_ceiling(batch: int, iters: int = 10) -> dict[str, object]:
    """The `paper` preset's 3×3 convolutions alone (forward + both gradients, bf16,
    channels-last, the shapes and strides of every recurrent step): milliseconds per step at
    `batch` and the rate they reach, TFLOP/s. The step can go no faster than these."""
    run = preset("paper").model
    g = grid_hw(run.frame_hw)
    cuda = torch.device("cuda")
    total_ms, total_flop, rows = 0.0, 0.0, {}
    inputs_of = {"V2": g["V1"], "V4": g["V2"], "IT": g["V4"]}
    for i, (area, times) in enumerate(zip(("V2", "V4", "IT"), run.times, strict=True)):
        ch = run.widths[i + 1] * run.expansion
        weight = torch.randn(ch, ch, 3, 3, device=cuda, dtype=torch.bfloat16, requires_grad=True)
        weight = weight.to(memory_format=torch.channels_last)
        for stride, hw in ((2, inputs_of[area]), (1, g[area])):
            x = torch.randn(batch, ch, *hw, device=cuda, dtype=torch.bfloat16)
            x = x.to(memory_format=torch.channels_last).requires_grad_(True)
            out = F.conv2d(x, weight, None, stride, 1)
            grad = torch.randn_like(out)
            times_ms = []
            for _ in range(iters + 2):
                torch.cuda.synchronize()
                t0 = time.perf_counter()
                out = F.conv2d(x, weight, None, stride, 1)
                out.backward(grad)
                torch.cuda.synchronize()
                times_ms.append((time.perf_counter() - t0) * 1e3)
            ms = min(times_ms[2:])
            flop = 3 * 2 * ch * ch * 9 * out.shape[2] * out.shape[3] * batch
            steps = 1 if stride == 2 else times - 1
            rows[f"{area}_stride{stride}"] = {"ms": round(ms, 2), "tflops": round(flop / ms / 1e9, 1),
                                             "per_step_calls": steps}
            total_ms += ms * steps
            total_flop += flop * steps
    return {"convs_3x3_ms_per_step": round(total_ms, 2),
            "convs_3x3_tflops": round(total_flop / total_ms / 1e9, 1), "by_conv": rows}


def gpu_figures(quick: bool, batches: list[int]) -> dict[str, object]:
    """`paper` training on the GPU under bf16 autocast: samples/s per batch size with the
    default (NCHW) and channels-last memory formats, and channels-last with each area
    compiled (`bid train --compile`)."""
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
        key = f"paper_bf16_b{batch}_channels_last_compiled_samples_per_s"
        try:
            out[key] = round(train_samples_per_s("paper", batch, iters, gpu, channels_last=True,
                                                 compiled=True), 1)
        except Exception as e:  # compilation needs a C compiler and Triton; report, don't fail
            out[key] = f"failed: {type(e).__name__}: {e}"[:200]
    return out


def latency_ms(name: str, iters: int, checkpoint: str | None = None) -> dict[str, float]:
    """Inference on one frame pair, one CPU thread: median and best ms per frame; with
    `checkpoint` its model, as driving runs it (the hazard outputs too), not preset `name`'s."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        model = BID(preset(name).model).eval() if checkpoint is None else load_model(checkpoint)[0]
        x = _inputs(model, 1, torch.device("cpu"))
        hazard = {"hazard": True} if checkpoint is not None and model.config.hazard else {}
        times = []
        with torch.inference_mode():
            for _ in range(5):
                model(*x, **hazard)
            for _ in range(iters):
                t0 = time.perf_counter()
                model(*x, **hazard)
                times.append((time.perf_counter() - t0) * 1e3)
    finally:
        torch.set_num_threads(threads)
    return {"median": statistics.median(times), "best": min(times)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON dict")
    p.add_argument("--quick", action="store_true", help="fewer iterations (a smoke check)")
    p.add_argument("--gpu-only", action="store_true", help="only the GPU figures")
    p.add_argument("--checkpoint", action="append", default=[], metavar="CKPT",
                   help="also the inference latency of this checkpoint's model, hazard outputs "
                        "included (repeatable; e.g. checkpoints/bid_small.pt)")
    p.add_argument("--gpu-batches", default="64,100,128,256",
                   help="batch sizes of the GPU sweep (default 64,100,128,256)")
    p.add_argument("--gpu-profile", action="store_true",
                   help="only where the compiled `paper` step's GPU time goes, at the first of "
                        "--gpu-batches, and the rate of its 3×3 convolutions alone")
    args = p.parse_args()
    quick = args.quick
    batches = [int(b) for b in args.gpu_batches.split(",")]
    cpu = torch.device("cpu")
    threads = torch.get_num_threads()
    # Other programs slow torch's OpenMP threads a lot (see bid_model.train.default_threads):
    # the load average says whether the figures were taken on a quiet machine.
    result: dict[str, object] = {"torch": str(torch.__version__), "cpu_threads": threads,
                                 "load_avg_1min_before": round(os.getloadavg()[0], 2)}
    if (args.gpu_only or args.gpu_profile) and not torch.cuda.is_available():
        raise SystemExit("error: --gpu-only and --gpu-profile need a visible CUDA GPU; drop them")
    if args.gpu_profile:
        torch.backends.cudnn.benchmark = True
        gpu = torch.device("cuda")
        result.update(gpu=torch.cuda.get_device_name(gpu), paper_gflop_per_sample=round(
            step_flops("paper", gpu) / 1e9, 1), batch=batches[0])
        print(json.dumps(result), flush=True)  # each part as it comes: compiling takes minutes
        result.update(conv_ceiling(batches[0]))
        print(json.dumps(result), flush=True)
        result.update(gpu_profile(batches[0]))
        result["samples_per_s"] = round(batches[0] / result["wall_ms_per_step"] * 1e3, 1)
        result["tflops"] = round(result["paper_gflop_per_sample"] * result["samples_per_s"] / 1e3, 1)
        print(json.dumps(result, indent=1))
        return
    if args.gpu_only:
        result.update(gpu_figures(quick, batches))
        print(json.dumps(result, indent=1))
        return
    lat = latency_ms("small", 20 if quick else 200)
    result["small_latency_ms_1core"] = round(lat["median"], 2)
    result["small_latency_ms_1core_best"] = round(lat["best"], 2)
    for path in args.checkpoint:
        result[f"latency_ms_1core {path}"] = round(latency_ms("small", 20 if quick else 200, path)["median"], 2)
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
