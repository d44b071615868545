"""Training of the BID model: `bid train`, or `python -m bid_model.train`, also under torchrun
for DDP (Gloo on CPUs, NCCL on GPUs), N processes on one machine:

    torchrun --standalone --nproc-per-node=N -m bid_model.train --preset small --data data/town01

or on several machines, the same command on each (HOST: one of them, reachable from all):

    torchrun --nnodes=2 --nproc-per-node=N --rdzv-backend=c10d --rdzv-endpoint=HOST:29400 --rdzv-id=RUN -m bid_model.train --preset small --data data/town01 --out runs/RUN

Every process needs the data at the same path; process 0 writes the run folder (--resume
reads it in every process: keep it on a shared filesystem). The global batch stays the
preset's, each process trains on whole episodes of its own, and a job of N processes ends
where one process with shards=N does (see train).

L1 loss on (steer, accel) weighted λ_s = λ_a = 0.5 (accel's with `--accel-quantile` a pinball
loss, see l1_loss), plus with `--forecast W` W times the L1 error of the speed forecast
(BID.forward_forecast) and with `--hazard W` W times the L1 error of the hazard head
(BID.forward_hazard, bid_model.hazards; with `--hazard-sc` plus that of SC's pedestrian and
vehicle outputs, each fitted alone though driving reads the nearer); AdamW with weight decay on weights only;
the lr halves at the (scaled) milestones. A run folder holds config.json (resolved config,
git hash, software versions), dataset.json, metrics.csv, last.pt and best.pt (atomic, with
optimiser and scheduler state for --resume) and the plots mae.png and steering.png.
Each epoch reseeds from (seed, epoch), so a resumed run repeats an uninterrupted one exactly.
"""

from __future__ import annotations

import argparse
import copy
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
from torch.utils.data import DataLoader, Dataset, Sampler, Subset
from tqdm import tqdm

from bid_model.augment import mirror, photometric, shift
from bid_model.checkpoint import check_preset, git_hash, load_checkpoint, save_checkpoint
from bid_model.config import (
    FORECAST_S,
    INIT_FIELDS,
    KINDS,
    MOVING_MPS,
    PATH_KINDS,
    READ_FIELDS,
    RESIZE_FIELDS,
    RunConfig,
    TrainConfig,
    preset,
    with_variant,
)
from bid_model.data import SyntheticDriving, check_sample, command_one_hot, synthetic_split
from bid_model.hazards import AT_LINE_M, HAZARD_AHEAD_M, NEAR_M, SEEN_NEARNESS
from bid_model.losses import l1_loss
from bid_model.model import (
    BID,
    SPEED_SCALE_MPS,
    compile_each_area,
    hazard_kinds,
    resize_grid_tokens,
)
from bid_model.plots import plot_metrics, plot_sequence
from bid_sim.errors import BidError
from bid_sim.routes import LEFT, RIGHT
from bid_sim.world import DT_S

log = logging.getLogger(__name__)

DEFAULT_DATA = Path("data/town01")
MAX_HAZARD_AHEAD_S = 5.0  # --hazard-ahead: pedestrians farther in the future are guesses
MAX_BUMPER_M = HAZARD_AHEAD_M  # --second-bumper: the head says no farther
PRESENCE_GAIN = 10.0  # warm_start_presence: the new logit per unit of nearness past SEEN_NEARNESS
PLOT_EVERY_S = 60.0  # plots are redrawn at most this often, and after the last epoch
METRIC_COLUMNS = ("epoch", "train_loss", "val_loss", "val_mae_steer", "val_mae_accel",
                  "const_mae_steer", "const_mae_accel", "val_mae_forecast_mps", "val_mae_hazard_m", "val_ped_seen_near", "val_ped_seen_none",
                  "val_ped_auc", "val_light_seen_near", "val_light_seen_none", "lr", "samples_per_s", "time_s")


# --- pieces ----------------------------------------------------------------------------------


def check_hazard_ahead(seconds: float) -> None:
    """BidError unless `seconds` is a --hazard-ahead look-ahead, 0 to MAX_HAZARD_AHEAD_S."""
    if not 0 <= seconds <= MAX_HAZARD_AHEAD_S:
        raise BidError(f"--hazard-ahead is in seconds, 0 to {MAX_HAZARD_AHEAD_S:g}; got {seconds}")


def make_optimizer(model: nn.Module, tc: TrainConfig) -> torch.optim.AdamW:
    """AdamW decaying only weight matrices and kernels: not biases, norms or embeddings."""
    decay, keep = [], []
    for name, p in model.named_parameters():
        if p.requires_grad:
            (decay if p.ndim >= 2 and not name.endswith("embed") else keep).append(p)
    return torch.optim.AdamW([{"params": decay, "weight_decay": tc.weight_decay},
                              {"params": keep, "weight_decay": 0.0}], lr=tc.lr)


def freeze_all_but(model: BID, names: tuple[str, ...]) -> None:
    """Train only the parts `names` of `model` (BID.parts: areas, forecast, hazard, ...): every
    other parameter stops requiring a gradient, so a head can be fitted to a trunk that stays
    exactly as it was (`bid train --init CKPT --train-only hazard`)."""
    parts = model.parts()
    unknown = [name for name in names if name not in parts]
    if unknown:
        raise BidError(f"--train-only {','.join(unknown)}: this {model.config.variant} model has no such part; "
                       f"it has {', '.join(parts)}")
    keep = {id(p) for name in names for p in parts[name].parameters()}
    for p in model.parameters():
        p.requires_grad_(id(p) in keep)


def set_train_mode(model: BID, tc: TrainConfig) -> None:
    """model.train(), or with tc.train_only only those parts: the frozen ones stay in eval mode,
    their batch norms' statistics and mean activations (for lesions) untouched."""
    if not tc.train_only:
        model.train()
        return
    model.eval()
    parts = model.parts()
    for name in tc.train_only:
        parts[name].train()


def _frozen_copy(module: nn.Module, state: dict[str, torch.Tensor], prefix: str) -> nn.Module:
    """A frozen copy of `module` holding the weights `state` (a checkpoint's) keeps under `prefix`."""
    reference = copy.deepcopy(module).eval().requires_grad_(False)
    own = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    missing, unexpected = reference.load_state_dict(own, strict=False)
    # A head with a presence logit (model.PresenceHazardHead) kept to a plain head's outputs: the
    # logit is not among the outputs kept.
    if unexpected or any(not k.startswith("presence.") for k in missing):
        raise RuntimeError(f"the reference {prefix[:-1]} does not fit: missing {missing}, unexpected {unexpected}")
    return reference


class KeptAccel:
    """`bid train --keep-accel`: the accel label of every training sample is the one the --init
    checkpoint's control head (CPC) gives on the same features, so that CPC fitted alone
    (--train-only CPC) to new steering labels, say a DAgger round's, keeps its throttle and
    brake as they were. The last control head fitted on a DAgger round's accel labels learnt to
    creep into queues (docs/experiments.md); the steering of the same rounds is what is wanted."""

    def __init__(self, model: BID, state: dict[str, torch.Tensor]):
        cpc = model.areas["CPC"]
        self.reference = _frozen_copy(cpc, state, "areas.CPC.")
        self._tokens: torch.Tensor | None = None
        cpc.register_forward_hook(self._keep)

    def _keep(self, module: nn.Module, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        self._tokens = inputs[0]

    def target(self, target: torch.Tensor) -> torch.Tensor:
        """(steer, accel) labels with accel the reference's on the features of the last forward."""
        if self._tokens is None:
            raise RuntimeError("KeptAccel.target before a forward of the model")
        with torch.no_grad():
            accel = self.reference(self._tokens.detach())[:, 1].to(target.dtype)
        return torch.stack((target[:, 0], accel), dim=1)


class KeptHazard:
    """`bid train --keep-hazard [KINDS]`: the hazard head's targets of `kinds` (by default
    pedestrian and vehicle) are the --init checkpoint's head's own outputs on the same features,
    so that the head fitted alone (--train-only hazard) to new targets of the other kinds, say
    red lights from recordings of the expert standing 2.5 m short of the line (bid record
    --stop-line-gap), or pedestrians met on crossings (bid record --crossing-walkers), keeps
    what it says of the kept ones: refitted whole on such recordings its other outputs moved,
    its hidden layers being shared by the three (docs/experiments.md)."""

    def __init__(self, model: BID, state: dict[str, torch.Tensor],
                 kinds: tuple[str, ...] = ("pedestrian", "vehicle"), standing: bool = False):
        head = model.hazard_head
        self.reference = _frozen_copy(head, state, "hazard_head.")
        # A reference with a presence logit of its own (--head-presence) fits her nearness only where
        # she is, so its nearness elsewhere means nothing: kept, it is read as driving reads it, gated.
        self._gate = (model.gate_head if any(k.startswith("hazard_head.presence.") for k in state)
                      else None)
        self.columns = [KINDS.index(kind) for kind in kinds]
        self.standing = standing  # every kind kept where the ego stands (--keep-hazard-standing)
        self._inputs: tuple | None = None
        head.register_forward_hook(self._keep)

    def _keep(self, module: nn.Module, inputs: tuple, output: torch.Tensor) -> None:
        self._inputs = inputs

    def target(self, near: torch.Tensor, speed_mps: torch.Tensor | None = None) -> torch.Tensor:
        """The head's targets `near` (B, K+1) with the entries of the kept kinds the reference
        head's on the features of the last forward; with `standing`, all of them on the rows
        whose recorded `speed_mps` (B,) is below MOVING_MPS."""
        if self._inputs is None:
            raise RuntimeError("KeptHazard.target before a forward of the model")
        with torch.no_grad():
            own = self.reference(*(x.detach() if isinstance(x, torch.Tensor) else x for x in self._inputs))
            own = own if self._gate is None else self._gate(own)
        own = own[:, :near.shape[1]].to(near.dtype)
        near = near.clone()
        near[:, self.columns] = own[:, self.columns]
        if self.standing:
            if speed_mps is None:
                raise RuntimeError("KeptHazard.target keeps standing frames: give speed_mps")
            still = speed_mps.reshape(-1) < MOVING_MPS
            near[still] = own[still]
        return near


def forecast_loss(pred_mps: torch.Tensor, target_mps: torch.Tensor) -> torch.Tensor:
    """L1 error of the speed forecast in units of SPEED_SCALE_MPS (as the speed input),
    averaged over the batch and the horizons."""
    return ((pred_mps.float() - target_mps) / SPEED_SCALE_MPS).abs().mean()


def hazard_weights(target: torch.Tensor, pos_weight: float = 1.0, turn_weight: float = 1.0,
                   command: torch.Tensor | None = None, moving_weight: float = 1.0,
                   speed_mps: torch.Tensor | None = None, green_weight: float = 1.0,
                   green_m: torch.Tensor | None = None, vehicle_moving_weight: float = 1.0) -> torch.Tensor:
    """(B, K) weights of the hazard targets' entries: one with an actor in the path (target > 0)
    weighs `pos_weight`; with `command` (B, n one-hot) a pedestrian in the path while turning
    (LEFT, RIGHT) `turn_weight` times more again; with `speed_mps` (B,) one in the path while
    the ego moves (MOVING_MPS or faster) `moving_weight` times more again; with `green_m` ((B,),
    hazards.green_distance) and `speed_mps`, the red-light entry of a standing ego at a green
    line (AT_LINE_M or nearer) `green_weight` times: the expert stands there almost only at
    red, and the light output learnt "standing at the line" for a red light; with `speed_mps`
    a vehicle in the path while the ego moves `vehicle_moving_weight` times more again."""
    weight = torch.where(target > 0, pos_weight, 1.0)
    light = KINDS.index("red_light")
    if green_m is not None and speed_mps is not None and green_weight != 1.0 and target.shape[1] > light:
        at_green = (green_m.reshape(-1) <= AT_LINE_M) & (speed_mps.reshape(-1) < MOVING_MPS)
        weight[:, light] *= torch.where(at_green, green_weight, 1.0)
    ped = KINDS.index("pedestrian")
    if command is not None and turn_weight != 1.0:
        turning = command[:, [LEFT - 1, RIGHT - 1]].sum(dim=1) > 0  # one-hot column = command − 1
        crossing = (target[:, ped] > 0) & turning
        weight[:, ped] *= torch.where(crossing, turn_weight, 1.0)
    if speed_mps is not None and moving_weight != 1.0:
        approaching = (target[:, ped] > 0) & (speed_mps.reshape(-1) >= MOVING_MPS)
        weight[:, ped] *= torch.where(approaching, moving_weight, 1.0)
    if speed_mps is not None and vehicle_moving_weight != 1.0:
        veh = KINDS.index("vehicle")
        approaching = (target[:, veh] > 0) & (speed_mps.reshape(-1) >= MOVING_MPS)
        weight[:, veh] *= torch.where(approaching, vehicle_moving_weight, 1.0)
    return weight


def second_targets(batch: dict[str, Any], near: torch.Tensor) -> torch.Tensor:
    """The second head's targets: the first head's `near` (B, K), with `bid train --second-bumper`
    its vehicle entry the batch's "vehicle_bumper" (recordings.bumper_targets)."""
    if "vehicle_bumper" not in batch:
        return near
    veh = KINDS.index("vehicle")
    near = near.clone()
    near[:, veh] = batch["vehicle_bumper"].to(near.device, near.dtype)
    return near


def second_boost(near: torch.Tensor, second: torch.Tensor, bumper_weight: float) -> torch.Tensor | None:
    """(B, K) weights on top of hazard_weights for the second head's targets `second` against the
    first head's `near`: its vehicle entry `bumper_weight` times where the car ahead of the
    bumper is nearer than the path's (`bid train --second-bumper-weight`); None where all are 1."""
    if bumper_weight == 1.0:
        return None
    veh = KINDS.index("vehicle")
    boost = torch.ones_like(second, dtype=torch.float32)
    boost[:, veh] = torch.where(second[:, veh] > near[:, veh], bumper_weight, 1.0)
    return boost


def hazard_loss(pred: torch.Tensor, target: torch.Tensor, pos_weight: float = 1.0,
                turn_weight: float = 1.0, command: torch.Tensor | None = None,
                moving_weight: float = 1.0, speed_mps: torch.Tensor | None = None,
                green_weight: float = 1.0, green_m: torch.Tensor | None = None,
                vehicle_moving_weight: float = 1.0, boost: torch.Tensor | None = None,
                fit: torch.Tensor | None = None) -> torch.Tensor:
    """L1 error of the hazard head's nearness (recordings.hazard_nearness), averaged over the
    batch and both kinds, each entry weighted by hazard_weights. Pedestrians are in the path in
    about 6 % of frames: under plain L1 (the median) the head says "none" wherever it is less
    than sure, and with weight w it says how near one is wherever it judges the odds above
    1 / (1 + w). `turn_weight` weighs the pedestrians in the path while turning more again:
    turning, the ego meets many more waiting on the kerb beside its path than in it.
    `moving_weight` weighs those in the path of a moving ego more: the expert has mostly
    stopped before a pedestrian is near, so such frames are rare in its recordings.
    `green_weight` weighs the red-light entry of a standing ego at a green line,
    `vehicle_moving_weight` the vehicles in the path of a moving ego; `boost` (B, K), if given,
    multiplies the weights (second_boost). `fit`, if given, is what the prediction is fitted to
    in place of `target`, the weights still following `target` (KeptHazard)."""
    weight = hazard_weights(target, pos_weight, turn_weight, command, moving_weight, speed_mps,
                            green_weight, green_m, vehicle_moving_weight)
    if boost is not None:
        weight = weight * boost
    return _weighted_l1(pred.float(), target if fit is None else fit, weight)


def _weighted_l1(pred: torch.Tensor, fit: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """|pred − fit| averaged with these weights."""
    return (weight * (pred - fit).abs()).sum() / weight.sum()


def presence_loss(out: torch.Tensor, target: torch.Tensor, pos_weight: float = 1.0,
                  turn_weight: float = 1.0, command: torch.Tensor | None = None,
                  moving_weight: float = 1.0, speed_mps: torch.Tensor | None = None,
                  green_weight: float = 1.0, green_m: torch.Tensor | None = None,
                  vehicle_moving_weight: float = 1.0) -> torch.Tensor:
    """Loss of SC with presence (areas.SC; out (B, 2K): nearness, then logits) against the
    nearness targets (B, K): the logits' binary cross-entropy on "one is in the path", its
    entries weighted by hazard_weights (it says yes where it judges the odds above 1 / (1 +
    w)), plus the nearness' L1 error on the entries with one in the path only: how near one is,
    given that it is there, not a blend of "none" and "near"."""
    k = target.shape[1]
    near, logit = out[:, :k].float(), out[:, k:].float()
    present = target > 0
    weight = hazard_weights(target, pos_weight, turn_weight, command, moving_weight, speed_mps,
                            vehicle_moving_weight=vehicle_moving_weight)
    bce = nn.functional.binary_cross_entropy_with_logits(logit, present.float(), reduction="none")
    distance = (near - target).abs()[present].mean() if present.any() else near.sum() * 0.0
    return (weight * bce).sum() / weight.sum() + distance


def head_presence_loss(out: torch.Tensor, target: torch.Tensor, pos_weight: float = 1.0,
                       turn_weight: float = 1.0, command: torch.Tensor | None = None,
                       moving_weight: float = 1.0, speed_mps: torch.Tensor | None = None,
                       green_weight: float = 1.0, green_m: torch.Tensor | None = None,
                       vehicle_moving_weight: float = 1.0, fit: torch.Tensor | None = None) -> torch.Tensor:
    """Loss of the hazard head with a pedestrian presence logit (model.PresenceHazardHead; out
    (B, K+1): the nearness per kind, then the logit) against the nearness targets (B, K): the
    other kinds' weighted L1 as hazard_loss; the logit's binary cross-entropy on "a pedestrian
    in the path at SEEN_NEARNESS or nearer", weighted by hazard_weights' pedestrian column; and
    the pedestrian's nearness' L1 error on the rows where she is, only. `fit`, if given, is what
    is fitted in place of `target` (KeptHazard), the weights still following `target`."""
    k = target.shape[1]
    fit = target if fit is None else fit
    weight = hazard_weights(target, pos_weight, turn_weight, command, moving_weight, speed_mps,
                            green_weight, green_m, vehicle_moving_weight)
    out = out.float()
    others = _weighted_l1(out[:, 1:k], fit[:, 1:], weight[:, 1:])
    present = fit[:, 0] >= SEEN_NEARNESS
    bce = nn.functional.binary_cross_entropy_with_logits(out[:, k], present.float(), reduction="none")
    presence = (weight[:, 0] * bce).sum() / weight[:, 0].sum()
    distance = (out[:, 0] - fit[:, 0]).abs()[present].mean() if present.any() else out[:, 0].sum() * 0.0
    return others + presence + distance


def near_and_none(target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Masks over nearness targets (B, K): one in the path within NEAR_M, and none within
    HAZARD_AHEAD_M: the two kinds of frame a hazard output is judged on."""
    return target >= 1.0 - NEAR_M / HAZARD_AHEAD_M, target <= 0.0


def hazard_detection(pred: torch.Tensor, target: torch.Tensor) -> dict[str, dict[str, float | None]]:
    """Per kind (KINDS, as many as the head has) of its nearness (B, K) against its targets: `seen_near`,
    the share of frames with one in the path within NEAR_M that the head sees (nearness ≥
    SEEN_NEARNESS, where --hazard-brake starts), and `seen_none`, the share of frames with none
    within HAZARD_AHEAD_M where it sees one all the same (None where no frame is of that kind)."""
    seen = pred.float() >= SEEN_NEARNESS
    near, none = near_and_none(target)

    def share(k: int, rows: torch.Tensor) -> float | None:
        return float(seen[rows[:, k], k].float().mean()) if rows[:, k].any() else None

    def auc(k: int) -> float | None:
        if not (near[:, k].any() and none[:, k].any()):
            return None
        return ranking_auc(pred[near[:, k], k].float().numpy(), pred[none[:, k], k].float().numpy())

    return {kind: {"seen_near": share(k, near), "seen_none": share(k, none), "auc": auc(k)}
            for k, kind in enumerate(KINDS[:pred.shape[1]])}


def ranking_auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """The chance that a positive's score outranks a negative's, ties counting half (the area
    under the ROC curve, by the Mann–Whitney U statistic): whether a head ranks frames with a
    hazard above those without, whatever threshold it is read at."""
    scores = np.concatenate([positive, negative])
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    below = np.cumsum(counts) - counts  # scores lower than each distinct one
    ranks = (below + (counts + 1) / 2)[inverse]  # 1-based, ties averaged
    n1, n0 = len(positive), len(negative)
    return float((ranks[:n1].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def _split_outputs(out: torch.Tensor | tuple[torch.Tensor, ...], tc: TrainConfig
                   ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """(control, forecast or None, hazard or None, move-off head's or None) of
    BID.forward(forecast=..., hazard=..., move_off=...)."""
    if isinstance(out, torch.Tensor):
        return out, None, None, None
    rest = list(out[1:])
    ahead = rest.pop(0) if tc.lambda_forecast > 0 else None
    hazard = rest.pop(0) if tc.lambda_hazard > 0 else None
    return out[0], ahead, hazard, (rest.pop(0) if rest else None)


def forecast_steps(config: RunConfig) -> tuple[int, ...]:
    """The model's forecast horizons in simulation steps."""
    return tuple(round(t / DT_S) for t in config.model.forecast_s)


def batch_inputs(batch: dict[str, Any], device: torch.device
                 ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
    """((frame_t, frame_prev, command one-hot, speed), target (B, 2)) on `device`."""
    inputs = (batch["frame"].to(device, non_blocking=True),
              batch["prev_frame"].to(device, non_blocking=True),
              command_one_hot(batch["command"]).to(device, non_blocking=True),
              torch.as_tensor(batch["speed_mps"], dtype=torch.float32).to(device))
    target = torch.stack([torch.as_tensor(batch["steer"]), torch.as_tensor(batch["accel"])], 1)
    return inputs, target.float().to(device, non_blocking=True)


def noisy_speed(speed_mps: torch.Tensor, sigma: float) -> torch.Tensor:
    """The speed input as trained with `--speed-noise`: each sample's speed times
    exp(sigma·N(0, 1)), from torch's generator (reseeded per epoch). A standstill stays 0.

    The probe of docs/experiments.md ("Why it runs into things") found the network brakes by
    speed rather than by distance; a speed it cannot quite trust leaves the frames to judge the
    gap by.
    """
    if sigma <= 0:
        return speed_mps
    return speed_mps * torch.exp(sigma * torch.randn(speed_mps.shape, device=speed_mps.device))


def open_data(config: RunConfig, data: Path | None, synthetic: bool
              ) -> tuple[Dataset, Dataset, dict[str, Any]]:
    """(train, validation, description): generated data, or the recordings in `data`."""
    tc, hw, ahead = config.train, config.model.input_hw, forecast_steps(config)
    if synthetic:
        if tc.lambda_hazard > 0:
            raise BidError("--hazard learns from recordings (their /scene); drop it, or train on --data")
        return synthetic_split(tc.synthetic_samples, hw, tc.val_fraction, tc.seed, ahead)
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
    train_set, val_set, description = open_recordings(folder, hw, tc.val_fraction, tc.seed,
                                                      stop_keep=tc.stop_keep, start_repeat=tc.start_repeat,
                                                      motion_drop=tc.motion_drop, hard_repeat=tc.hard_repeat,
                                                      hard_brake=tc.hard_brake,
                                                      brake_lookahead=tc.brake_lookahead,
                                                      forecast_steps=ahead, hold_repeat=tc.hold_repeat,
                                                      hazard=tc.lambda_hazard > 0,
                                                      hazard_ahead_s=tc.hazard_ahead_s,
                                                      crossing=config.model.hazard_crossing,
                                                      bumper_m=tc.second_bumper_m,
                                                      start_accel=tc.start_accel)
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


def item_episodes(dataset: Dataset) -> np.ndarray:
    """The episode of every item of a training set, as an (N,) int array: recordings
    (bid_model.recordings.RecordingDataset), generated data (SyntheticDriving), Subsets of
    them; any other dataset is read item by item."""
    if isinstance(dataset, Subset):
        return item_episodes(dataset.dataset)[np.asarray(dataset.indices, dtype=np.int64)]
    if isinstance(dataset, SyntheticDriving):
        return np.arange(len(dataset)) // dataset.episode_len
    if hasattr(dataset, "index") and hasattr(dataset, "rows"):  # a RecordingDataset
        return np.asarray(dataset.index.episode)[dataset.rows]
    log.info("reading the episode of each of %d items", len(dataset))
    return np.array([int(dataset[i]["episode"]) for i in range(len(dataset))], dtype=np.int64)


class EpisodeShardSampler(Sampler[list[int]]):
    """Batches in which each process of a DDP job trains on whole episodes of its own.

    Every epoch, a permutation seeded by (seed, epoch) deals the episodes to `shards` shards,
    each episode to the shard with the fewest items so far (balanced to within one episode).
    A shard's items are shuffled, seeded by (seed, epoch, shard), and cut into batches of
    batch_size // shards items; global batch k is the union of the shards' k-th batches.
    Process `rank` of `world` (shards a multiple of world) yields as its batch k the k-th
    batches of shards rank, rank + world, ... concatenated. So one process with shards=N
    yields exactly the global batches of an N-process job, and every process yields the same
    number of batches, which DDP needs (each step waits for all processes). All shards are cut
    to the smallest one's length: up to about one episode of items per shard sits out an
    epoch, a different one each epoch. Deterministic per (seed, epoch), like a resumed run.
    """

    def __init__(self, episodes: np.ndarray, batch_size: int, shards: int = 1, rank: int = 0,
                 world: int = 1, seed: int = 0):
        if shards < 1 or shards % world:
            raise BidError(f"{shards} data shards cannot be split over {world} processes; "
                           "use a multiple of the process count")
        ids, self.episode_of = np.unique(np.asarray(episodes, dtype=np.int64), return_inverse=True)
        if len(ids) < shards:
            raise BidError(f"{len(ids)} training episodes cannot be shared by {shards} processes; "
                           "record more episodes or run fewer processes")
        self.sizes = np.bincount(self.episode_of, minlength=len(ids))
        self.batch = max(1, batch_size // shards)  # per shard
        self.shards, self.mine, self.seed, self.epoch = shards, range(rank, shards, world), seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _shards(self) -> tuple[list[np.ndarray], int]:
        """(each shard's items in order, cut to a whole number of batches; batch size)."""
        rng = np.random.default_rng((self.seed, self.epoch))
        load = np.zeros(self.shards, dtype=np.int64)
        owner = np.empty(len(self.sizes), dtype=np.int64)
        for e in rng.permutation(len(self.sizes)):
            owner[e] = s = int(np.argmin(load))  # the first of the least loaded
            load[s] += self.sizes[e]
        batch = min(self.batch, int(load.min()))
        keep = int(load.min()) // batch * batch
        items = []
        for s in range(self.shards):
            idx = np.flatnonzero(owner[self.episode_of] == s)
            items.append(np.random.default_rng((self.seed, self.epoch, s)).permutation(idx)[:keep])
        return items, batch

    def __iter__(self):
        items, b = self._shards()
        for k in range(len(items[0]) // b):
            yield np.concatenate([items[s][k * b:(k + 1) * b] for s in self.mine]).tolist()

    def __len__(self) -> int:
        items, b = self._shards()
        return len(items[0]) // b


class _AllReduceSum(torch.autograd.Function):
    """Sum over the processes; the gradient of each process's input is the sum of the
    processes' output gradients (every process's loss depends on every input)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        x = x.clone()
        torch.distributed.all_reduce(x)
        return x

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        grad = grad.clone()
        torch.distributed.all_reduce(grad)
        return grad


class CPUSyncBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics span every process of the job, over Gloo on
    CPUs (torch's nn.SyncBatchNorm runs on GPUs only): the mean and variance of the global
    batch, as one process computes them on the whole batch, and gradients through them."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and torch.distributed.is_initialized()):
            return super().forward(x)
        dims, shape = (0, 2, 3), (1, -1, 1, 1)
        count = x.new_full((1,), x.numel() // x.shape[1])
        total = _AllReduceSum.apply(torch.cat([x.sum(dims), count]))
        n = total[-1]
        mean = total[:-1] / n
        centred = x - mean.view(shape)
        var = _AllReduceSum.apply((centred * centred).sum(dims)) / n
        y = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                f = self.momentum if self.momentum is not None else 1.0 / int(self.num_batches_tracked)
                self.running_mean.mul_(1 - f).add_(mean, alpha=f)
                self.running_var.mul_(1 - f).add_(var * n / (n - 1), alpha=f)
        return y


def sync_batch_norm(module: nn.Module, device: torch.device) -> nn.Module:
    """`module` with batch norms that normalise by the statistics of the global batch (under
    DDP): nn.SyncBatchNorm on GPUs, CPUSyncBatchNorm on CPUs. Parameters and buffers are kept
    (the optimiser's stay valid); state dict keys do not change."""
    if device.type != "cpu":
        return nn.SyncBatchNorm.convert_sync_batchnorm(module)
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm2d:
            sync = CPUSyncBatchNorm(child.num_features, child.eps, child.momentum, child.affine,
                                    child.track_running_stats)
            sync._parameters, sync._buffers = child._parameters, child._buffers
            sync.train(child.training)
            module.add_module(name, sync)
        else:
            sync_batch_norm(child, device)
    return module


def _average_buffers(model: nn.Module, dist: Dist) -> None:
    """Each floating-point buffer set to its mean over the processes (see train)."""
    for b in model.buffers():
        if b.is_floating_point():
            torch.distributed.all_reduce(b)
            b.div_(dist.world)


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
                device: torch.device, bar_desc: str | None, kept: KeptAccel | None = None,
                kept_hazard: KeptHazard | None = None) -> tuple[float, int]:
    """One pass over `loader`; (sum of batch losses × batch sizes, samples) of this process.
    `kept`: the accel labels are its reference control head's (--keep-accel); `kept_hazard`: the
    hazard head's pedestrian and vehicle targets are its reference head's (--keep-hazard)."""
    base = net.module if isinstance(net, nn.parallel.DistributedDataParallel) else net
    set_train_mode(base, tc)
    apart = base.config.hazard_sc and tc.lambda_hazard > 0  # the head and SC fitted each alone
    move_off = base.config.move_off_head and tc.lambda_hazard > 0  # the second head fitted alike
    kwargs = {**({"hazard_apart": True} if apart else {}), **({"move_off": True} if move_off else {})}
    loss_sum = torch.zeros((), dtype=torch.float64, device=device)
    samples, t0 = 0, time.perf_counter()
    bar = tqdm(loader, desc=bar_desc, unit="batch", disable=bar_desc is None, leave=False,
               dynamic_ncols=True, mininterval=1.0)
    for i, batch in enumerate(bar):
        inputs, target = batch_inputs(batch, device)
        speed_mps = inputs[3]  # as recorded: the hazard weights read it, the network the noisy one
        inputs = (*inputs[:3], noisy_speed(speed_mps, tc.speed_noise))
        if tc.augment > 0:
            inputs = (*photometric(inputs[0], inputs[1], tc.augment), *inputs[2:])
        if tc.shift > 0:
            inputs = (*shift(inputs[0], inputs[1], tc.shift), *inputs[2:])
        if tc.mirror > 0:
            *flipped, target = mirror(*inputs[:3], target, tc.mirror)
            inputs = (*flipped, inputs[3])
        with _autocast(device):
            pred, ahead, hazard, second = _split_outputs(
                net(*inputs, forecast=tc.lambda_forecast > 0, hazard=tc.lambda_hazard > 0, **kwargs), tc)
        if kept is not None:
            target = kept.target(target)
        loss = l1_loss(pred, target, tc)
        if ahead is not None:
            loss = loss + tc.lambda_forecast * forecast_loss(ahead, batch["future_speed"].to(device))
        if hazard is not None:
            near = batch["hazard"].to(device)
            k, crossing = len(PATH_KINDS), base.config.hazard_crossing
            own = 2 + base.config.hazard_light  # the head's, then SC's, then the crossing map's
            head_end = base.head_columns()  # with the head's presence logit after its nearness
            green_m = batch["green_m"].to(device) if "green_m" in batch else None
            weights = (tc.hazard_pos_weight, tc.hazard_turn_weight, inputs[2], tc.hazard_moving_weight, speed_mps,
                       tc.hazard_green_weight, green_m, tc.hazard_vehicle_moving_weight)
            fit = kept_hazard.target(near[:, :own], speed_mps) if kept_hazard is not None else None
            head_loss = head_presence_loss if base.config.head_presence else hazard_loss
            loss = loss + tc.lambda_hazard * head_loss(hazard[:, :head_end], near[:, :own], *weights, fit=fit)
            if second is not None:
                near_2 = second_targets(batch, near[:, :own])
                loss = loss + tc.lambda_hazard * hazard_loss(second[:, :own], near_2, *weights,
                                                             boost=second_boost(near[:, :own], near_2,
                                                                                tc.second_bumper_weight))
            if apart:
                sc_loss = presence_loss if base.config.sc_presence else hazard_loss
                sc_end = head_end + k * (1 + base.config.sc_presence)
                loss = loss + tc.lambda_hazard * sc_loss(hazard[:, head_end:sc_end], near[:, :k], *weights)
                if base.config.sc_fine:  # the fine SC's, with presence, after SC's
                    loss = loss + tc.lambda_hazard * presence_loss(hazard[:, sc_end:sc_end + 2 * k], near[:, :k], *weights)
            if crossing:
                at = KINDS.index("crossing")
                loss = loss + tc.lambda_hazard * hazard_loss(hazard[:, -1:], near[:, at:at + 1], *weights)
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
    preds, targets, episodes, steps, forecast_err, hazard_pred, hazard_true = [], [], [], [], [], [], []
    move_off = model.config.move_off_head and tc.lambda_hazard > 0
    second_pred, second_true = [], []
    for batch in loader:
        inputs, target = batch_inputs(batch, device)
        with _autocast(device):
            pred, ahead, hazard, second = _split_outputs(
                model(*inputs, forecast=tc.lambda_forecast > 0, hazard=tc.lambda_hazard > 0,
                      **({"move_off": True} if move_off else {})), tc)
            if second is not None:
                second_pred.append(second.float().cpu())
                second_true.append(second_targets(batch, batch["hazard"][:, :second.shape[1]]))
            if ahead is not None:
                forecast_err.append((ahead.float().cpu() - batch["future_speed"]).abs())
            if hazard is not None:
                hazard_pred.append(hazard.float().cpu())
                hazard_true.append(batch["hazard"][:, :hazard.shape[1]])
            preds.append(pred.float().cpu())
        targets.append(target.cpu())
        episodes.append(torch.as_tensor(batch["episode"]))
        steps.append(torch.as_tensor(batch["step"]))
    pred, target = torch.cat(preds), torch.cat(targets)
    mae = (pred - target).abs().mean(0)
    # The median minimises the L1 error of a constant: the baseline a model must beat.
    const = (target - target.median(0).values).abs().mean(0)
    # The forecast's MAE in m/s, per horizon, beside the driving metrics (not in val_loss,
    # which stays comparable between runs with and without it).
    forecast = torch.cat(forecast_err).mean(0).tolist() if forecast_err else []
    # Likewise the hazard head's MAE in metres, (pedestrian, vehicle), and how often it sees
    # what is near (hazard_detection).
    hazard_m, detection = [], {}
    if hazard_pred:
        near_pred, near_true = torch.cat(hazard_pred), torch.cat(hazard_true)
        hazard_m = ((near_pred - near_true).abs().mean(0) * HAZARD_AHEAD_M).tolist()
        detection = hazard_detection(near_pred, near_true)
    # The move-off head's alike (in the log only: it is fitted beside, or after, the first).
    second = {}
    if second_pred:
        near_pred, near_true = torch.cat(second_pred), torch.cat(second_true)
        second = {"mae_m": ((near_pred - near_true).abs().mean(0) * HAZARD_AHEAD_M).tolist(),
                  "detection": hazard_detection(near_pred, near_true)}
    return {"val_move_off": second, "val_loss": float(tc.lambda_steer * mae[0] + tc.lambda_accel * mae[1]),
            "val_mae_steer": float(mae[0]), "val_mae_accel": float(mae[1]),
            "val_mae_forecast_mps": forecast, "val_mae_hazard_m": hazard_m, "val_hazard_detection": detection,
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


def load_shared_weights(model: nn.Module, state: dict[str, torch.Tensor]) -> list[str]:
    """Load the tensors of `state` that `model` has, with the same shape; return the names left
    as they were (areas or buffers another variant lacks, or shaped otherwise)."""
    own = model.state_dict()
    shared = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    model.load_state_dict(shared, strict=False)
    return sorted(k for k in own if k not in shared)


def warm_start_crossing(model: BID, state: dict[str, torch.Tensor], fresh: list[str]) -> list[str]:
    """A crossing map (model.hazard_crossing) that `state` lacks starts as `state`'s SC with its
    pedestrian map: a detector of pedestrians in the path is nearer an occupied crossing than
    random weights are. Returns `fresh` less the tensors so started."""
    if model.hazard_crossing is None or not any(k.startswith("hazard_crossing.") for k in fresh):
        return fresh
    own, started = model.hazard_crossing.state_dict(), []
    for name, tensor in own.items():
        theirs = state.get(f"hazard_sc.{name}")
        if theirs is None or f"hazard_crossing.{name}" not in fresh:
            continue
        if theirs.shape != tensor.shape:  # the last 1×1 layer: its first map, the pedestrians'
            if theirs.shape[1:] != tensor.shape[1:] or theirs.ndim == 0:
                continue
            theirs = theirs[:tensor.shape[0]]
        tensor.copy_(theirs)
        started.append(f"hazard_crossing.{name}")
    return sorted(set(fresh) - set(started))


def warm_start_move_off(model: BID, state: dict[str, torch.Tensor], fresh: list[str]) -> list[str]:
    """A move-off head (model.hazard_move_off) that `state` lacks starts as `state`'s hazard
    head: it learns the same nearness, only without the speed token. Returns `fresh` less the
    tensors so started."""
    if model.hazard_move_off is None:
        return fresh
    started = []
    for name, tensor in model.hazard_move_off.state_dict().items():
        theirs = state.get(f"hazard_head.{name}")
        if f"hazard_move_off.{name}" in fresh and theirs is not None and theirs.shape == tensor.shape:
            tensor.copy_(theirs)
            started.append(f"hazard_move_off.{name}")
    return sorted(set(fresh) - set(started))


def warm_start_presence(model: BID, state: dict[str, torch.Tensor], fresh: list[str]) -> list[str]:
    """A presence logit (model.PresenceHazardHead) that `state`'s head lacks starts as "the
    pedestrian's nearness is SEEN_NEARNESS or more", PRESENCE_GAIN times that margin, on the
    same hidden layer: the head with it starts reading what the head without it read wherever
    the brakes act. Returns `fresh` less the tensors so started."""
    theirs_w, theirs_b = state.get("hazard_head.2.weight"), state.get("hazard_head.2.bias")
    if not (model.config.head_presence and "hazard_head.presence.weight" in fresh) or theirs_w is None:
        return fresh
    presence = model.hazard_head.presence
    with torch.no_grad():
        presence.weight.copy_(PRESENCE_GAIN * theirs_w[:1])
        presence.bias.copy_(PRESENCE_GAIN * (theirs_b[:1] - SEEN_NEARNESS))
    return sorted(set(fresh) - {"hazard_head.presence.weight", "hazard_head.presence.bias"})


# --- the run ----------------------------------------------------------------------------------


def train(out: Path, config: RunConfig | None = None, *, data: Path | None = None,
          synthetic: bool = False, resume: bool = False, expect_preset: str | None = None,
          device: str = "auto", workers: int | None = None, stop_after: int | None = None,
          progress: bool = True, shards: int | None = None, init: Path | None = None,
          compile_areas: bool = False) -> list[dict[str, Any]]:
    """Train into run folder `out`; returns the metrics rows of all epochs so far.

    `init`: start from the weights of that checkpoint (same model config) instead of random
    ones: fine-tuning, e.g. on DAgger data (`bid record --dagger`). The optimiser starts anew.
    A checkpoint of another variant (the paper's ablations) gives the tensors both have; the
    rest start afresh and are listed in the run's config (init.fresh).

    `compile_areas` (CUDA only): each brain area through torch.compile, in place, so the
    checkpoints keep their keys and lesions keep working.

    With `resume`, continue from out/last.pt with its saved config (`config`, if given, must
    equal it; `expect_preset` must match it). `stop_after` ends this call after that many
    epochs (the run stays resumable). `data` is a folder of recordings, unless `synthetic`.

    Under torchrun (DDP) each process trains on whole episodes of its own
    (EpisodeShardSampler) and the global batch stays tc.batch_size. `shards` (default: the
    number of processes) cuts the batches as for that many processes, so one process with
    shards=N sees exactly the global batches of an N-process job, and ends with the same
    weights up to float rounding: gradients are averaged over equal shares of the global
    batch, batch norms use the statistics of the global batch (sync_batch_norm), and buffers
    stay per process during an epoch (no broadcast) and are averaged after it, which makes
    the areas' running mean activations (linear in the batch means) those of the global
    batch. Only dropout differs (masks are drawn per process): the tiny and small presets
    have none.
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
    if (config.train.lambda_forecast > 0) != bool(config.model.forecast_s):
        raise BidError("a speed forecast needs both its head (model.forecast_s) and its loss weight "
                       "(train.lambda_forecast); set both with --forecast WEIGHT")
    if (config.train.lambda_hazard > 0) != config.model.hazard:
        raise BidError("a hazard head needs both the head (model.hazard) and its loss weight "
                       "(train.lambda_hazard); set both with --hazard WEIGHT")
    start_from, diff, fresh = None, [], []
    if init is not None:
        if resume:
            raise BidError("--init starts a new run from a checkpoint's weights; --resume continues one: pick one")
        start_from = load_checkpoint(init)
        theirs = RunConfig.from_dict(start_from["config"]).model
        diff = [f.name for f in dataclasses.fields(theirs) if getattr(theirs, f.name) != getattr(config.model, f.name)]
        if set(diff) - INIT_FIELDS - RESIZE_FIELDS - READ_FIELDS:
            raise BidError(f"--init {init} holds a different model ({', '.join(diff)} differ); "
                           f"train with its preset and flags, or start from scratch")
    tc = config.train
    if tc.keep_accel and tc.train_only != ("CPC",):
        raise BidError("--keep-accel holds the control head's accel while CPC alone learns: add --train-only CPC")
    if tc.keep_accel and start_from is None and ckpt is None:
        raise BidError("--keep-accel keeps the accel of the --init checkpoint's control head: add --init CHECKPOINT")
    if tc.keep_hazard and tc.train_only != ("hazard",):
        raise BidError(f"--keep-hazard holds the hazard head's {' and '.join(tc.keep_hazard_kinds)} while it alone "
                       "learns: add --train-only hazard")
    if tc.keep_hazard:
        own = list(KINDS[:2 + config.model.hazard_light])  # the head's outputs (the crossing map is apart)
        if not tc.keep_hazard_kinds or set(tc.keep_hazard_kinds) - set(own):
            raise BidError(f"--keep-hazard {','.join(tc.keep_hazard_kinds)}: keep some of this head's kinds, "
                           f"{', '.join(own)}")
        if set(tc.keep_hazard_kinds) == set(own):
            raise BidError(f"--keep-hazard {','.join(tc.keep_hazard_kinds)} keeps every output of the head and "
                           f"leaves it nothing to learn: keep fewer")
    if tc.keep_hazard and start_from is None and ckpt is None:
        raise BidError("--keep-hazard keeps what the --init checkpoint's hazard head says: add --init CHECKPOINT")
    if tc.train_only:  # a wrong name is refused before the data is opened
        with torch.device("meta"):
            freeze_all_but(BID(config.model), tc.train_only)

    dist = init_distributed(device)
    dev = pick_device(device, dist)
    train_set, val_set, description = open_data(config, data, synthetic)
    first = train_set[0]
    check_sample(first, config.model.input_hw)
    if tc.lambda_forecast > 0 and tuple(getattr(first.get("future_speed"), "shape", ())) != (len(config.model.forecast_s),):
        raise BidError(f"--forecast needs dataset items with 'future_speed', {len(config.model.forecast_s)} speeds "
                       "ahead (see the contract in bid_model/data.py)")
    kinds = hazard_kinds(config.model)
    if tc.lambda_hazard > 0 and getattr(first.get("hazard"), "shape", (0,))[0] < kinds:
        raise BidError(f"--hazard needs dataset items with 'hazard', {kinds} nearnesses: of a pedestrian and a "
                       "vehicle in the path and a red light ahead (bid_model.recordings.hazard_nearness)")

    shards = dist.world if shards is None else shards
    torch.manual_seed(tc.seed)
    model = BID(config.model).to(dev)
    if dev.type == "cuda":
        # Channels-last convolutions skip cuDNN's layout transposes: +23 % samples/s for the
        # paper preset on an H200 (benchmarks/bench_model.py). Fixed input sizes, so let
        # cuDNN time its algorithms once.
        model = model.to(memory_format=torch.channels_last)
        torch.backends.cudnn.benchmark = True
    if compile_areas and dev.type != "cuda":
        raise BidError("--compile is for CUDA training (it was measured there); drop it on the CPU")
    if dist.world > 1:
        model = sync_batch_norm(model, dev)
    if compile_areas:
        compile_each_area(model)
    if tc.train_only:
        freeze_all_but(model, tc.train_only)
    opt = make_optimizer(model, tc)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, list(tc.milestones), tc.lr_gamma)
    start, history, best = 0, [], math.inf
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start, history, best = ckpt["epoch"], list(ckpt["history"]), ckpt["best_val_loss"]
    elif start_from is not None and diff:  # another variant or input size: the tensors both have
        state = start_from["model"]
        if "frame_hw" in diff:
            state = resize_grid_tokens(state, tuple(theirs.frame_hw), model)
        if "sc_scale" in diff:  # SC and the crossing map start afresh at their new resolution
            state = {k: v for k, v in state.items() if not k.startswith(("hazard_sc.", "hazard_crossing."))}
        fresh = load_shared_weights(model, state)
        fresh = warm_start_move_off(model, state, warm_start_crossing(model, state, fresh))
        fresh = warm_start_presence(model, state, fresh)
    elif start_from is not None:
        model.load_state_dict(start_from["model"])
    kept = kept_hazard = None
    if tc.keep_accel or tc.keep_hazard:  # the reference is the init checkpoint's, resumed or not
        if start_from is not None:
            reference = start_from["model"]
        else:
            init_path = Path(ckpt.get("init", {}).get("path", ""))
            if not init_path.is_file():
                flag = "--keep-accel" if tc.keep_accel else "--keep-hazard"
                raise BidError(f"{flag}: the run's --init checkpoint {init_path} is gone; "
                               "put it back to resume, or start a new run")
            reference = load_checkpoint(init_path)["model"]
        if tc.keep_hazard and not any(k.startswith("hazard_head.") for k in reference):
            raise BidError("--keep-hazard: the --init checkpoint has no hazard head to keep; drop --keep-hazard")
        kept = KeptAccel(model, reference) if tc.keep_accel else None
        kept_hazard = (KeptHazard(model, reference, tc.keep_hazard_kinds, tc.keep_hazard_standing)
                       if tc.keep_hazard else None)

    meta = {"git_hash": git_hash(), "version": _version(), "torch": str(torch.__version__)}
    if start_from is not None:
        meta["init"] = {"path": str(init), "epoch": start_from.get("epoch"), "git_hash": start_from.get("git_hash")}
        if fresh:
            meta["init"]["fresh"] = fresh
            if dist.main:
                print(f"--init {init}: a {theirs.variant} model ({', '.join(diff)} differ); this "
                      f"{config.model.variant} one starts {len(fresh)} tensors afresh: {', '.join(fresh)}")
    elif ckpt is not None and "init" in ckpt:
        meta["init"] = ckpt["init"]
    if dist.main:
        out.mkdir(parents=True, exist_ok=True)
        _write_text_atomic(out / "config.json", json.dumps(
            {**config.to_dict(), **meta, "device": str(dev), "world_size": dist.world,
             "shards": shards},
            indent=1) + "\n")
        _write_text_atomic(out / "dataset.json",
                           json.dumps(description, indent=1, default=str) + "\n")

    net: nn.Module = model
    if dist.world > 1:
        net = nn.parallel.DistributedDataParallel(
            model, device_ids=[dev.index] if dev.type == "cuda" else None,
            broadcast_buffers=False)  # averaged after each epoch instead (see the docstring)
    n_workers = tc.workers if workers is None else workers
    # Whole batches only (a last batch of 1 would break batch norm), the same count in every
    # process; the global batch stays tc.batch_size.
    sampler = EpisodeShardSampler(item_episodes(train_set), tc.batch_size, shards, dist.rank,
                                  dist.world, tc.seed)
    loader = DataLoader(train_set, batch_sampler=sampler, num_workers=n_workers,
                        pin_memory=dev.type == "cuda")
    val_loader = DataLoader(val_set, max(tc.batch_size // dist.world, 64), shuffle=False,
                            num_workers=n_workers)

    end = tc.epochs if stop_after is None else min(tc.epochs, start + stop_after)
    last_plot = -math.inf
    for epoch in range(start, end):
        sampler.set_epoch(epoch)
        # Dropout & workers: the same on resume, other masks in each process.
        torch.manual_seed(tc.seed * 1_000_003 + epoch + 7_919 * dist.rank)
        lr = opt.param_groups[0]["lr"]
        t0 = time.perf_counter()
        desc = f"epoch {epoch + 1}/{tc.epochs}" if progress and dist.main else None
        loss_sum, samples = _all_sum(train_epoch(net, loader, opt, tc, dev, desc, kept, kept_hazard), dist, dev)
        if dist.world > 1:
            _average_buffers(model, dist)
        train_s = time.perf_counter() - t0
        sched.step()
        if not dist.main:
            torch.distributed.barrier()
            continue
        val = evaluate(model, val_loader, tc, dev) if len(val_set) else None
        row = {"epoch": epoch + 1, "train_loss": loss_sum / max(samples, 1)}
        nan = math.nan
        row.update({k: (val[k] if val else nan) for k in METRIC_COLUMNS[2:7]})
        # The forecast's MAE over all its horizons (per horizon in the log); None (an empty
        # cell) without one.
        per_horizon = val["val_mae_forecast_mps"] if val else []
        row["val_mae_forecast_mps"] = float(np.mean(per_horizon)) if per_horizon else None
        per_kind = val["val_mae_hazard_m"] if val else []
        row["val_mae_hazard_m"] = float(np.mean(per_kind)) if per_kind else None
        detection = val["val_hazard_detection"] if val else {}
        ped, light = detection.get("pedestrian", {}), detection.get("red_light", {})
        row.update(val_ped_seen_near=ped.get("seen_near"), val_ped_seen_none=ped.get("seen_none"),
                   val_ped_auc=ped.get("auc"), val_light_seen_near=light.get("seen_near"), val_light_seen_none=light.get("seen_none"))
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
        if val and val["val_mae_forecast_mps"]:
            log.info("speed forecast MAE at %s s: %s m/s", "/".join(f"{t:g}" for t in config.model.forecast_s),
                     "/".join(f"{e:.2f}" for e in val["val_mae_forecast_mps"]))
        heads = (("hazard", val["val_mae_hazard_m"], val["val_hazard_detection"]),
                 ("move-off head", val["val_move_off"].get("mae_m"), val["val_move_off"].get("detection", {}))
                 ) if val else ()
        for head, mae_m, detection in heads:
            if not mae_m:
                continue
            log.info("%s distance MAE, pedestrian/vehicle: %s m", head, "/".join(f"{e:.2f}" for e in mae_m))
            for kind, d in detection.items():
                log.info("%s in the path: seen in %s of the frames with one within %g m, in %s of those "
                         "with none; AUC %s", kind, _percent(d["seen_near"]), NEAR_M, _percent(d["seen_none"]),
                         "-" if d["auc"] is None else f"{d['auc']:.3f}")
        if dist.world > 1:
            torch.distributed.barrier()
    return history


def _percent(share: float | None) -> str:
    return "-" if share is None else f"{100 * share:.1f} %"


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
             "--speed-input": args.speed_input, "--augment": args.augment, "--hard-repeat": args.hard_repeat,
             "--hard-brake": args.hard_brake, "--brake-lookahead": args.brake_lookahead,
             "--forecast": args.forecast, "--frame-hw": args.frame_hw, "--speed-noise": args.speed_noise,
             "--accel-quantile": args.accel_quantile, "--hold-repeat": args.hold_repeat,
             "--start-repeat": args.start_repeat, "--start-accel": args.start_accel,
             "--hazard": args.hazard, "--hazard-pos-weight": args.hazard_pos_weight,
             "--hazard-turn-weight": args.hazard_turn_weight,
             "--hazard-moving-weight": args.hazard_moving_weight, "--hazard-ahead": args.hazard_ahead,
             "--hazard-green-weight": args.hazard_green_weight,
             "--hazard-vehicle-moving-weight": args.hazard_vehicle_moving_weight,
             "--hazard-attend": args.hazard_attend, "--hazard-sc": args.hazard_sc,
             "--sc-presence": args.sc_presence, "--sc-still": args.sc_still, "--sc-scale": args.sc_scale,
             "--sc-fine": args.sc_fine,
             "--head-presence": args.head_presence,
             "--hazard-speedless": args.hazard_speedless, "--move-off-head": args.move_off_head,
             "--move-off-speed": args.move_off_speed, "--second-bumper": args.second_bumper,
             "--second-bumper-weight": args.second_bumper_weight,
             "--hazard-crossing": args.hazard_crossing,
             "--stop-keep": args.stop_keep, "--mirror": args.mirror, "--motion-drop": args.motion_drop,
             "--shift": args.shift, "--train-only": args.train_only,
             "--keep-accel": args.keep_accel or None, "--keep-hazard": args.keep_hazard or None,
             "--keep-hazard-standing": args.keep_hazard_standing or None}
    if args.resume:
        given = [k for k, v in flags.items() if v is not None]
        if given:
            raise BidError(f"--resume continues a run with its saved config; drop {', '.join(given)}")
        return None
    run = preset(args.preset or "small")
    model, tc = run.model, run.train
    if args.variant:
        model = with_variant(model, args.variant)
    if args.speed_input is not None:
        model = dataclasses.replace(model, speed_input=args.speed_input)
    if args.frame_hw is not None:
        model = dataclasses.replace(model, frame_hw=parse_frame_hw(args.frame_hw))
    if args.epochs is not None:
        tc = tc.with_epochs(args.epochs)
    for flag, value, field, ok in (("--batch-size", args.batch_size, "batch_size", 2),
                                   ("--samples", args.samples, "synthetic_samples", 4),
                                   ("--seed", args.seed, "seed", 0),
                                   ("--hard-repeat", args.hard_repeat, "hard_repeat", 1),
                                   ("--hold-repeat", args.hold_repeat, "hold_repeat", 1),
                                   ("--start-repeat", args.start_repeat, "start_repeat", 1),
                                   ("--brake-lookahead", args.brake_lookahead, "brake_lookahead", 1)):
        if value is not None:
            if value < ok:
                raise BidError(f"{flag} must be at least {ok}, got {value}")
            tc = dataclasses.replace(tc, **{field: value})
    if args.lr is not None:
        if not args.lr > 0:
            raise BidError(f"--lr must be positive, got {args.lr}")
        tc = dataclasses.replace(tc, lr=args.lr)
    if args.start_accel is not None:
        if not 0.0 <= args.start_accel < 1.0:
            raise BidError(f"--start-accel is a throttle, 0 to below 1 (0: every throttle moves off); "
                           f"got {args.start_accel}")
        tc = dataclasses.replace(tc, start_accel=args.start_accel)
    if args.augment is not None:
        if not 0.0 <= args.augment <= 1.0:
            raise BidError(f"--augment is the share of training samples to augment, 0 to 1; got {args.augment}")
        tc = dataclasses.replace(tc, augment=args.augment)
    for flag, value, field in (("--stop-keep", args.stop_keep, "stop_keep"), ("--mirror", args.mirror, "mirror"),
                               ("--motion-drop", args.motion_drop, "motion_drop")):
        if value is not None:
            if not (0.0 < value <= 1.0 if field == "stop_keep" else 0.0 <= value <= 1.0):
                raise BidError(f"{flag} is a share of training rows, {'above 0' if field == 'stop_keep' else '0'} "
                               f"to 1; got {value}")
            tc = dataclasses.replace(tc, **{field: value})
    if args.shift is not None:
        rows = model.frame_hw[0]
        if not 0 <= args.shift <= rows // 4:
            raise BidError(f"--shift is in pixels, 0 to a quarter of the input's {rows} rows; got {args.shift}")
        tc = dataclasses.replace(tc, shift=args.shift)
    if args.hard_brake is not None:
        tc = dataclasses.replace(tc, hard_brake=args.hard_brake)
    if args.accel_quantile is not None:
        if not 0.0 < args.accel_quantile < 1.0:
            raise BidError(f"--accel-quantile is a quantile, between 0 and 1 (0.5: L1); got {args.accel_quantile}")
        tc = dataclasses.replace(tc, accel_quantile=args.accel_quantile)
    if args.speed_noise is not None:
        if not 0.0 <= args.speed_noise <= 2.0:
            raise BidError(f"--speed-noise is the σ of a log-normal factor, 0 to 2; got {args.speed_noise}")
        if not model.speed_input:
            raise BidError("--speed-noise needs a speed input: drop it, or add --speed-input")
        tc = dataclasses.replace(tc, speed_noise=args.speed_noise)
    if args.forecast is not None:
        if not args.forecast >= 0:
            raise BidError(f"--forecast is the weight of the speed forecast's loss, 0 or more; got {args.forecast}")
        model = dataclasses.replace(model, forecast_s=FORECAST_S if args.forecast > 0 else ())
        tc = dataclasses.replace(tc, lambda_forecast=args.forecast)
    if args.hazard is not None:
        if not args.hazard >= 0:
            raise BidError(f"--hazard is the weight of the hazard head's loss, 0 or more; got {args.hazard}")
        model = dataclasses.replace(model, hazard=args.hazard > 0, hazard_light=args.hazard > 0)
        tc = dataclasses.replace(tc, lambda_hazard=args.hazard)
    for flag, field, weighs in (("--hazard-pos-weight", "hazard_pos_weight", "frames with an actor in the path"),
                                ("--hazard-turn-weight", "hazard_turn_weight",
                                 "pedestrians in the path while turning"),
                                ("--hazard-moving-weight", "hazard_moving_weight",
                                 "pedestrians in the path of a moving ego"),
                                ("--hazard-green-weight", "hazard_green_weight",
                                 "the red-light entry of a standing ego at a green line"),
                                ("--hazard-vehicle-moving-weight", "hazard_vehicle_moving_weight",
                                 "vehicles in the path of a moving ego")):
        weight = getattr(args, field)
        if weight is None:
            continue
        if not 1 <= weight < math.inf:
            raise BidError(f"{flag} weighs {weighs}, 1 or more; got {weight}")
        if not model.hazard:
            raise BidError(f"{flag} weighs the hazard head's loss: add --hazard WEIGHT")
        tc = dataclasses.replace(tc, **{field: weight})
    if args.hazard_ahead is not None:
        check_hazard_ahead(args.hazard_ahead)
        if not model.hazard:
            raise BidError("--hazard-ahead shapes the hazard head's targets: add --hazard WEIGHT")
        tc = dataclasses.replace(tc, hazard_ahead_s=args.hazard_ahead)
    if args.hazard_attend:
        if not model.hazard:
            raise BidError("--hazard-attend shapes the hazard head: add --hazard WEIGHT")
        model = dataclasses.replace(model, hazard_attend=True)
    if args.hazard_sc:
        if not model.hazard:
            raise BidError("--hazard-sc (SC) reads beside the hazard head: add --hazard WEIGHT")
        model = dataclasses.replace(model, hazard_sc=True)
    if args.sc_presence:
        if not model.hazard_sc:
            raise BidError("--sc-presence is a part of SC: add --hazard-sc (and --hazard WEIGHT)")
        model = dataclasses.replace(model, sc_presence=True)
    if args.head_presence:
        if not model.hazard_sc or model.hazard_attend or model.move_off_head or args.move_off_head:
            raise BidError("--head-presence is a logit beside the plain hazard head, read with SC: add --hazard-sc "
                           "(and --hazard WEIGHT), without --hazard-attend or --move-off-head")
        model = dataclasses.replace(model, head_presence=True)
    if args.sc_still:
        if not model.hazard_sc:
            raise BidError("--sc-still is how SC reads: add --hazard-sc (and --hazard WEIGHT)")
        model = dataclasses.replace(model, sc_still=True)
    if args.sc_scale is not None:
        if not model.hazard_sc:
            raise BidError("--sc-scale is SC's resolution: add --hazard-sc (and --hazard WEIGHT)")
        if not 1 <= args.sc_scale <= 4:
            raise BidError(f"--sc-scale is a whole factor, 1 to 4 (2: SC reads frames twice as fine as "
                           f"the cortex); got {args.sc_scale}")
        model = dataclasses.replace(model, sc_scale=args.sc_scale)
    if args.sc_fine is not None:
        if not model.hazard_sc:
            raise BidError("--sc-fine is a second SC beside the first: add --hazard-sc (and --hazard WEIGHT)")
        try:
            model = dataclasses.replace(model, sc_fine=args.sc_fine)
        except ValueError as e:
            raise BidError(f"--sc-fine {args.sc_fine}: {e}") from None
    if args.hazard_crossing:
        if not model.hazard_sc:
            raise BidError("--hazard-crossing is a second SC map beside SC: add --hazard-sc (and --hazard WEIGHT)")
        model = dataclasses.replace(model, hazard_crossing=True)
    if args.hazard_speedless:
        if not (model.hazard and model.speed_input):
            raise BidError("--hazard-speedless keeps the speed input from the hazard head: add --hazard WEIGHT "
                           "(the preset's model must take the speed)")
        model = dataclasses.replace(model, hazard_speedless=True)
    if args.move_off_head:
        if not (model.hazard and model.speed_input):
            raise BidError("--move-off-head is a hazard head without the speed input: add --hazard WEIGHT "
                           "(the preset's model must take the speed)")
        if model.hazard_speedless:
            raise BidError("with --hazard-speedless the hazard head already reads no speed: keep one")
        model = dataclasses.replace(model, move_off_head=True)
    if args.move_off_speed:
        if not model.move_off_head:
            raise BidError("--move-off-speed is how the move-off head reads: add --move-off-head")
        model = dataclasses.replace(model, move_off_speed=True)
    if args.second_bumper is not None:
        if not 0 < args.second_bumper <= MAX_BUMPER_M:
            raise BidError(f"--second-bumper is in metres ahead of the bumper, above 0 to {MAX_BUMPER_M:g}; "
                           f"got {args.second_bumper}")
        if not model.move_off_head:
            raise BidError("--second-bumper shapes the second head's vehicle target: add --move-off-head")
        tc = dataclasses.replace(tc, second_bumper_m=args.second_bumper)
    if args.second_bumper_weight is not None:
        if not 1 <= args.second_bumper_weight < math.inf:
            raise BidError("--second-bumper-weight weighs the cars ahead of the bumper nearer than the path's, "
                           f"1 or more; got {args.second_bumper_weight}")
        if not tc.second_bumper_m:
            raise BidError("--second-bumper-weight weighs the second head's cars ahead of the bumper: "
                           "add --second-bumper M")
        tc = dataclasses.replace(tc, second_bumper_weight=args.second_bumper_weight)
    if args.train_only is not None:
        names = tuple(name.strip() for name in args.train_only.split(",") if name.strip())
        if not names:
            raise BidError("--train-only names the parts to train, e.g. --train-only hazard or MPC,CPC")
        tc = dataclasses.replace(tc, train_only=names)
    if args.keep_accel:
        tc = dataclasses.replace(tc, keep_accel=True)
    if args.keep_hazard:
        kinds = tuple(kind.strip() for kind in args.keep_hazard.split(",") if kind.strip())
        tc = dataclasses.replace(tc, keep_hazard=True, keep_hazard_kinds=kinds)
    if args.keep_hazard_standing:
        if not args.keep_hazard:
            raise BidError("--keep-hazard-standing keeps the standing frames of --keep-hazard's refit: add --keep-hazard")
        tc = dataclasses.replace(tc, keep_hazard_standing=True)
    return RunConfig(model, tc)


def parse_frame_hw(text: str) -> tuple[int, int]:
    """`--frame-hw 96x288` → (96, 288): rows × columns of the network's input."""
    rows, sep, cols = text.lower().partition("x")
    if not (sep and rows.isdigit() and cols.isdigit() and int(rows) >= 32 and int(cols) >= 32):
        raise BidError(f"--frame-hw is ROWSxCOLS, each at least 32 (e.g. 96x288); got {text!r}")
    return int(rows), int(cols)


def run_dir(args: argparse.Namespace, config: RunConfig | None) -> Path:
    """--out, or runs/--name, or runs/PRESET-VARIANT-TIME for a new run."""
    if args.out:
        return Path(args.out)
    if args.name:
        return Path("runs") / args.name
    if config is None:
        raise BidError("--resume needs the run folder: pass --out DIR or --name NAME")
    return Path("runs") / f"{config.preset}-{config.model.variant}-{time.strftime('%Y%m%d-%H%M%S')}"


def busy_cores(interval_s: float = 0.5, stat: str = "/proc/stat") -> float | None:
    """Cores other programs keep busy now: the machine's non-idle CPU time over interval_s
    (this process sleeps meanwhile), from /proc/stat; None where that file does not exist.

    Unlike the load average, which decays over a minute, it drops as soon as a job ends:
    `make dagger` trains right after its recording workers exit.
    """
    def sample() -> tuple[int, int]:
        with open(stat) as f:
            ticks = [int(v) for v in f.readline().split()[1:9]]  # user nice system idle iowait irq softirq steal
        return sum(ticks), ticks[3] + ticks[4]

    try:
        total0, idle0 = sample()
        time.sleep(interval_s)
        total1, idle1 = sample()
    except (OSError, ValueError, IndexError):
        return None
    if total1 <= total0:
        return 0.0
    return (os.cpu_count() or 1) * (1.0 - (idle1 - idle0) / (total1 - total0))


def default_threads(workers: int) -> int:
    """Torch threads for training: the cores that neither data loaders nor other programs use.

    OpenMP threads that outnumber the free cores wait for each other at every parallel
    region: measured on 2 cores next to one busy process, one thread trained the tiny preset
    3-5× faster than two. So count one core per loader process and the cores busy right now
    (busy_cores; the 1-minute load average where /proc/stat is missing).
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    now = busy_cores()
    if now is not None:
        busy, source = round(now), f"busy now {now:.1f}"
    else:
        busy = round(os.getloadavg()[0]) if hasattr(os, "getloadavg") else 0
        source = f"load {busy}"
    threads = max(1, (cores or 1) - workers - busy)
    log.info("torch threads: %d (%s cores, %d loaders, %s); set --threads to override",
             threads, cores, workers, source)
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
                    workers=args.workers, progress=not args.quiet,
                    init=Path(args.init) if args.init else None, compile_areas=args.compile)
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


def exit_process(code: int) -> None:
    """End the process with `code`. Under torchrun, once the process group is destroyed, without
    finalizing the interpreter: Gloo's worker threads outlive destroy_process_group, and one that
    drops its last collective while Python finalizes takes the GIL from a dying interpreter and
    aborts the process (SIGABRT, "terminate called without an active exception"; about 1 run in
    25 on 2 busy cores, after every file was written: a finished run reported as failed)."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    exit_process(main())
