"""Checkpoints of the BID model: atomic writes, and loading with the config they were saved with.

A checkpoint is a dict: `config` (RunConfig.to_dict), `model` (state dict), `optimizer`,
`scheduler`, `epoch` (epochs finished), `history` (metrics rows), `best_val_loss`,
`git_hash`, `version`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
from pathlib import Path
from typing import Any

import torch

from bid_model.config import RunConfig
from bid_model.model import BID
from bid_sim.errors import BidError


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write `payload` to `path` atomically: a crash leaves the old file or the new one."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        torch.save(payload, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict at `path`; a missing or unreadable file is a BidError."""
    path = Path(path)
    if not path.is_file():
        raise BidError(f"no checkpoint at {path}; train one with `bid train` or pass its path")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for a damaged file
        raise BidError(f"cannot read checkpoint {path} ({type(e).__name__}); is it a `bid train` "
                       "checkpoint (last.pt / best.pt)?") from e
    if not isinstance(ckpt, dict) or "config" not in ckpt or "model" not in ckpt:
        raise BidError(f"{path} is not a `bid train` checkpoint (no config or model inside)")
    return ckpt


def load_model(path: str | Path, preset: str | None = None,
               device: str | torch.device = "cpu") -> tuple[BID, RunConfig]:
    """The model of checkpoint `path` in eval mode, and its config.

    With `preset`, a checkpoint trained with another preset is a BidError.
    """
    ckpt = load_checkpoint(path)
    config = RunConfig.from_dict(ckpt["config"])
    check_preset(config, preset, path)
    model = BID(config.model)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as e:
        raise BidError(f"checkpoint {path} does not fit the {config.preset!r} "
                       f"{config.model.variant!r} model it names; was it written by another "
                       "version of bid_model?") from e
    return model.to(device).eval(), config


SHIPPED_KEYS = ("config", "model", "epoch", "history", "best_val_loss", "git_hash", "version", "init")


def export_checkpoint(run: str | Path, out: str | Path, which: str = "best.pt",
                      recipe: str | None = None) -> dict[str, Any]:
    """A small checkpoint to ship or share, from run folder `run`: the model and how it came to
    be (config, metrics history, git hash, the run's dataset.json, `recipe`), without the
    optimiser and scheduler state; `out` with a `.json` card beside it. Returns the card."""
    run, out = Path(run), Path(out)
    ckpt = load_checkpoint(run / which)
    dataset_path = run / "dataset.json"
    dataset = json.loads(dataset_path.read_text()) if dataset_path.is_file() else None
    payload = {k: ckpt[k] for k in SHIPPED_KEYS if k in ckpt}
    payload["dataset"] = json.dumps(dataset)  # a string: weights_only loading takes plain types
    payload["recipe"] = recipe or ""
    best = min(payload.get("history") or [{}], key=lambda r: r.get("val_loss", math.inf))
    card = {"checkpoint": out.name, "from": str(run / which), "epoch": payload.get("epoch"),
            "git_hash": payload.get("git_hash"), "version": payload.get("version"), "recipe": recipe,
            "config": payload["config"], "best_epoch": best, "dataset": dataset, "init": payload.get("init")}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out, payload)
    out.with_suffix(".json").write_text(json.dumps(card, indent=1, default=str) + "\n")
    return card


# Auxiliary heads (training signals driving never reads): model config field → (its value
# without the head, the head's weight prefix, its loss weight in the train config).
# Checkpoints that differ only in them average into one without the heads they do not all have.
# The hazard prefix covers hazard_head., hazard_sc., hazard_crossing. and hazard_move_off.
AUX_HEADS = {"forecast_s": ((), "forecast_head.", "lambda_forecast"),
             "hazard": (False, "hazard_", "lambda_hazard")}
# Fields that shape a head beside its own (→ their value without it): heads alike agree on them too.
HEAD_SHAPE = {"forecast_s": {}, "hazard": {"hazard_light": False, "hazard_attend": False,
                                                   "hazard_sc": False, "sc_presence": False, "sc_still": False,
                                                   "hazard_crossing": False, "hazard_speedless": False,
                                                   "move_off_head": False, "move_off_speed": False,
                                                   "head_presence": False}}


def average_checkpoints(paths: list[str | Path], out: str | Path,
                        weights: list[float] | None = None, keep_heads: bool = False) -> dict[str, Any]:
    """Writes to `out` the weighted average of the weights of checkpoints of one network
    (weight-space ensembling, as WiSE-FT and model soups: fine-tunings of the same start
    average into one model that keeps what each learnt). Integer buffers (batch counts) come
    from the first. An auxiliary head (AUX_HEADS) not all of them have is left out, or with
    `keep_heads` averaged over those that have it (their weights renormalised), so that a
    head driving reads (`--hazard-brake`) survives averaging with a run without it.
    Returns the checkpoint written; its `init` names the sources and weights."""
    if len(paths) < 2:
        raise BidError("give two or more checkpoints to average")
    weights = [1.0] * len(paths) if weights is None else [float(w) for w in weights]
    if len(weights) != len(paths) or min(weights) < 0 or sum(weights) <= 0:
        raise BidError(f"--weights needs {len(paths)} numbers >= 0 with a positive sum, got {weights}")
    weights = [w / sum(weights) for w in weights]
    ckpts = [load_checkpoint(p) for p in paths]
    first = ckpts[0]
    model_cfg = dict(first["config"].get("model", {}))
    train_cfg = dict(first["config"].get("train", {}))
    heads = tuple(prefix for _, prefix, _ in AUX_HEADS.values())
    trunk = {k for k in first["model"] if not k.startswith(heads)}
    for p, c in zip(paths[1:], ckpts[1:], strict=True):
        theirs = c["config"].get("model", {})
        diff = {k for k in model_cfg.keys() | theirs.keys() if model_cfg.get(k) != theirs.get(k)}
        if diff - AUX_HEADS.keys() - {k for shape in HEAD_SHAPE.values() for k in shape} or {k for k in c["model"] if not k.startswith(heads)} != trunk:
            raise BidError(f"{p} is another network than {paths[0]} (model config or weights differ); "
                           "average only fine-tunings of one model")
    # Each head's source: the checkpoints that have it, all alike (None: the average goes without it).
    sources: dict[str, list[int] | None] = {}
    for field, (absent, prefix, lam) in AUX_HEADS.items():
        fields = {field: absent, **HEAD_SHAPE[field]}
        values = [tuple(c["config"].get("model", {}).get(f, a) for f, a in fields.items()) for c in ckpts]
        have = [i for i, v in enumerate(values) if v[0] and v[0] != absent]
        alike = bool(have) and all(values[i] == values[have[0]] for i in have)
        if alike and (len(have) == len(ckpts) or keep_heads):
            sources[prefix] = have
            model_cfg.update(zip(fields, values[have[0]], strict=True))
            train_cfg[lam] = ckpts[have[0]]["config"].get("train", {}).get(lam, 0.0)
        elif have and keep_heads:
            raise BidError(f"the checkpoints have {field} heads of different shapes "
                           f"({sorted({str(values[i][0] if len(fields) == 1 else values[i]) for i in have})}); "
                           "--keep-heads needs them alike")
        else:
            sources[prefix] = None
            model_cfg.update(fields)
            train_cfg[lam] = 0.0
    state = {}
    for c in ckpts:  # every key once, in the first order it appears in
        for key, t0 in c["model"].items():
            prefix = next((h for h in heads if key.startswith(h)), None)
            if key in state or (prefix is not None and sources[prefix] is None):
                continue
            members = list(range(len(ckpts))) if prefix is None else sources[prefix]
            if t0.is_floating_point():
                total = sum(weights[i] for i in members)
                # A head only zero-weighted checkpoints have: their plain mean.
                share = {i: weights[i] / total if total > 0 else 1 / len(members) for i in members}
                state[key] = sum(share[i] * ckpts[i]["model"][key].double() for i in members).to(t0.dtype)
            else:
                state[key] = ckpts[members[0]]["model"][key].clone()
    payload = {k: first[k] for k in SHIPPED_KEYS if k in first}
    payload["config"] = {**first["config"], "model": model_cfg, "train": train_cfg}
    payload.update(model=state, history=[], best_val_loss=math.inf, git_hash=git_hash(),
                   init={"average": [{"path": str(p), "weight": w, "epoch": c.get("epoch"), "git_hash": c.get("git_hash")}
                                     for p, w, c in zip(paths, weights, ckpts, strict=True)]})
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out, payload)
    return payload


def graft_fine_sc(base_path: str | Path, donor_path: str | Path, out: str | Path) -> dict[str, Any]:
    """Writes to `out` checkpoint `base_path` with a second SC (model config sc_fine): the SC of
    `donor_path`, a checkpoint of the same network whose SC has presence logits (`bid train
    --sc-presence`) and reads frames at its sc_scale, its weights as they are. Nothing is trained:
    each SC keeps what it learnt, and the merge reads the fine one's pedestrian beside the first's
    (BID.merge_hazard). Returns the checkpoint written; its `graft` names the sources."""
    base, donor = load_checkpoint(base_path), load_checkpoint(donor_path)
    mine, theirs = RunConfig.from_dict(base["config"]).model, RunConfig.from_dict(donor["config"]).model
    if not mine.hazard_sc or mine.sc_fine:
        raise BidError(f"{base_path} has {'a fine SC already' if mine.sc_fine else 'no SC (--hazard-sc)'}: "
                       "graft onto a checkpoint with one SC")
    if not (theirs.hazard_sc and theirs.sc_presence):
        raise BidError(f"{donor_path} has no SC with presence logits (bid train --hazard-sc --sc-presence) to graft")
    if (theirs.frame_hw, theirs.n_commands) != (mine.frame_hw, mine.n_commands):
        raise BidError(f"{donor_path} reads {theirs.frame_hw} frames and {theirs.n_commands} commands, "
                       f"{base_path} {mine.frame_hw} and {mine.n_commands}: graft between one preset's models")
    try:
        model_cfg = dataclasses.replace(mine, sc_fine=theirs.sc_scale)
    except ValueError as e:
        raise BidError(f"cannot graft {donor_path}'s SC onto {base_path}: {e}") from None
    state = {**base["model"], **{"hazard_sc_fine." + k.removeprefix("hazard_sc."): v
                                 for k, v in donor["model"].items() if k.startswith("hazard_sc.")}}
    BID(model_cfg).load_state_dict(state)  # every tensor in its place, or a RuntimeError
    payload = {k: v for k, v in base.items() if k not in ("optimizer", "scheduler")}
    payload["config"] = {**base["config"], "model": dataclasses.asdict(model_cfg)}
    payload.update(model=state, git_hash=git_hash(),
                   graft={"base": str(base_path), "base_git_hash": base.get("git_hash"),
                          "fine_sc": str(donor_path), "fine_sc_git_hash": donor.get("git_hash"),
                          "fine_sc_epoch": donor.get("epoch"), "fine_sc_config": donor["config"]})
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out, payload)
    return payload


def check_preset(config: RunConfig, preset: str | None, path: str | Path) -> None:
    """BidError if the checkpoint's preset is not the one asked for."""
    if preset is not None and preset != config.preset:
        raise BidError(f"checkpoint {path} is from the {config.preset!r} preset, not "
                       f"{preset!r}; pass --preset {config.preset} or another checkpoint")


def git_hash() -> str:
    """The commit of this source tree ("+dirty" with uncommitted changes), or "unknown"."""
    repo = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                              text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=repo, capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")
