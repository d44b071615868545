"""The driving loss of `bid train`, apart from the trainer so that it imports without the
simulator: a GPU node that times training steps of the network needs neither SUMO nor the
recordings' libraries (benchmarks/bench_model.py --gpu-profile; `bid train` itself still
imports them)."""

from __future__ import annotations

import torch

from bid_model.config import TrainConfig


def l1_loss(pred: torch.Tensor, target: torch.Tensor, tc: TrainConfig) -> torch.Tensor:
    """λ_s·|Δsteer| + λ_a·|Δaccel|, averaged over the batch.

    With tc.accel_quantile τ ≠ 0.5 the accel term is the pinball loss 2·max(τ·r, (τ−1)·r),
    r = label − prediction, whose minimiser is the τ-quantile of the labels rather than their
    median (τ = 0.5 is |r|): with τ < 0.5, accelerating past a label costs more than braking
    past it.
    """
    diff = target - pred.float()
    steer = diff[:, 0].abs().mean()
    tau = tc.accel_quantile
    r = diff[:, 1]
    accel = r.abs().mean() if tau == 0.5 else 2.0 * torch.maximum(tau * r, (tau - 1.0) * r).mean()
    return tc.lambda_steer * steer + tc.lambda_accel * accel
