"""What a model's hazard outputs see, measured on recordings it never trained on (`bid probe`).

Training reports how often the hazard head sees the pedestrian, the vehicle and the red light
in the path on its validation episodes, which are Town01's under the training weathers. The
closed loop runs in Town02 under the test weathers, where the BID met pedestrians its
outputs read 0 for (docs/experiments.md). Record the expert there (`bid record --town 02
--weathers test`: the expert's frames, its path and the actors in /scene, nothing trained on)
and probe: every frame's outputs against the same targets training uses
(`recordings.open_every_frame`), overall and per command, weather, density and whether the
ego stands or moves, so that one can tell a detector that fails in a new town or light from
one that fails at a kind of junction, or only while the scene moves past.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bid_model.checkpoint import load_model
from bid_model.config import KINDS, MOVING_MPS, PATH_KINDS, PROBE_SOURCES
from bid_model.data import COMMAND_NAMES, command_one_hot
from bid_model.hazards import AT_LINE_M, HAZARD_AHEAD_M, NEAR_M, SEEN_NEARNESS
from bid_model.recordings import open_every_frame
from bid_model.train import (
    check_hazard_ahead,
    hazard_detection,
    near_and_none,
    ranking_auc,
    second_targets,
)
from bid_sim.ego import DT_S
from bid_sim.errors import BidError

# Nearness thresholds the shares are also given at ("at"): a detector that sees more at 0.2 may
# see wrongly more too, and a brake can start higher (SEEN_NEARNESS is where the brakes start).
THRESHOLDS = (0.2, 0.3, 0.4, 0.5, 0.6)
# The close band read apart: the closed loop's pedestrian contacts were seen at 5-8 m and then
# lost or read far in the last metres (docs/experiments.md), which the share within NEAR_M hides.
CLOSE_M = 4.0
# SC's presence logits (--sc-presence) are also read at these thresholds: one trained at a
# positive weight w says yes where it judges the odds above 1 / (1 + w); a lower threshold is
# what a larger w would have said, were the logit calibrated, a higher one a smaller w (what
# `bid evaluate --sc-logit` reads the pedestrian's at).
LOGIT_THRESHOLDS = (2.0, 1.0, 0.5, 0.0, -0.5, -1.0, -2.0)
# Walk-ins (`walk_ins`): the shipped BID's pedestrian contacts in Town02 were all pedestrians who
# entered its path 0.3-1.9 s before, mostly 5-8 m ahead of a moving ego (docs/experiments.md).
# A share "within NEAR_M" counts the frames after she is in; these count how early she is seen.
ENTRY_M = 12.0  # she enters the path this near or nearer
ENTRY_CLEAR_S = 1.0  # with no pedestrian in the path (within HAZARD_AHEAD_M) this long before
LEADS_S = (0.0, 0.5, 1.0, 1.5, 2.0)  # read this long before she enters
CLEAR_AHEAD_S = 3.0  # a moving frame with no one in the path now nor this long after: none to see


def _median_m(nearness: torch.Tensor) -> float | None:
    """The median distance (m) these nearness values stand for; None for none."""
    return float((1.0 - nearness.float().clamp(max=1.0)).median()) * HAZARD_AHEAD_M if len(nearness) else None


def _group(pred: torch.Tensor, target: torch.Tensor) -> dict[str, dict[str, Any]]:
    """hazard_detection of these rows, with how many frames each share is of, the shares seen
    near and wrongly at each of THRESHOLDS, how far the near ones seen are read (`read_m`, the
    median, beside their true `true_m`), and the same for the frames with one within CLOSE_M
    (`close_frames`, `seen_close`, `read_close_m`, `true_close_m`)."""
    found = hazard_detection(pred, target)
    near, none = near_and_none(target)
    close = target >= 1.0 - CLOSE_M / HAZARD_AHEAD_M
    seen = pred >= SEEN_NEARNESS

    def share(k: int, rows: torch.Tensor, threshold: float) -> float | None:
        return float((pred[rows[:, k], k] >= threshold).float().mean()) if rows[:, k].any() else None

    def read(k: int, rows: torch.Tensor) -> dict[str, float | None]:
        both = rows[:, k] & seen[:, k]
        return {"read": _median_m(pred[both, k]), "true": _median_m(target[both, k])}

    groups = {}
    for k, kind in enumerate(found):
        far, by_close = read(k, near), read(k, close)
        groups[kind] = {**found[kind], "near_frames": int(near[:, k].sum()), "none_frames": int(none[:, k].sum()),
                        "at": {f"{t:g}": {"seen_near": share(k, near, t), "seen_none": share(k, none, t)}
                               for t in THRESHOLDS},
                        "read_m": far["read"], "true_m": far["true"], "close_frames": int(close[:, k].sum()),
                        "seen_close": share(k, close, SEEN_NEARNESS), "read_close_m": by_close["read"],
                        "true_close_m": by_close["true"]}
    return groups


def _stop_line(target: torch.Tensor, speed_mps: np.ndarray, green_m: np.ndarray) -> np.ndarray:
    """Per frame: "standing at a red line" (a red or amber light's stop line AT_LINE_M or
    nearer), "standing at a green line" (hazards.green_distance), else "elsewhere". The expert
    stands at lines almost only at red; a light output that learnt the place reads the green
    ones red too."""
    standing = speed_mps < MOVING_MPS
    light = KINDS.index("red_light")
    red = (target[:, light] >= 1.0 - AT_LINE_M / HAZARD_AHEAD_M).numpy() if target.shape[1] > light else False
    return np.where(standing & red, "standing at a red line",
                    np.where(standing & (green_m <= AT_LINE_M), "standing at a green line", "elsewhere"))


def _logits(logit: torch.Tensor, target: torch.Tensor) -> dict[str, dict[str, Any]]:
    """Per kind of SC's presence logits (B, K) against the nearness targets: their `auc` (frames
    with one in the path within NEAR_M against those with none) and, at each of
    LOGIT_THRESHOLDS, the shares of those two kinds of frame the logit says yes to."""
    near, none = near_and_none(target)
    out = {}
    for k, kind in enumerate(KINDS[:logit.shape[1]]):
        yes, no = logit[near[:, k], k].numpy(), logit[none[:, k], k].numpy()
        out[kind] = {"auc": ranking_auc(yes, no) if len(yes) and len(no) else None,
                     "at": {f"{t:g}": {"seen_near": float((yes > t).mean()) if len(yes) else None,
                                       "seen_none": float((no > t).mean()) if len(no) else None}
                            for t in LOGIT_THRESHOLDS}}
    return out


def walk_ins(now: np.ndarray, episode: np.ndarray, step: np.ndarray, speed_mps: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(entries, clear) over every frame of recordings in (episode, step) order, from `now`, the
    metres to the nearest pedestrian in the path where she is (hazards.path_hazards without a
    look-ahead; HAZARD_AHEAD_M: none). `entries`: the frames where one enters the path ENTRY_M
    or nearer ahead of an ego moving at MOVING_MPS or faster, with no pedestrian in it for the
    ENTRY_CLEAR_S before (all recorded). `clear`: a bool per frame, the ego moving and no
    pedestrian in the path from then to CLEAR_AHEAD_S after (all recorded)."""
    back, ahead = round(ENTRY_CLEAR_S / DT_S), round(CLEAR_AHEAD_S / DT_S)
    none = now >= HAZARD_AHEAD_M
    moving = speed_mps >= MOVING_MPS
    entries, clear = [], np.zeros(len(now), dtype=bool)
    for e in np.unique(episode):
        rows = np.flatnonzero(episode == e)
        steps, gone = step[rows], none[rows]
        for j, r in enumerate(rows):
            lo = np.searchsorted(steps, steps[j] - back)
            whole_before = lo < j and steps[lo] == steps[j] - back and steps[j] - steps[lo] == j - lo
            if (now[r] <= ENTRY_M and moving[r] and whole_before and gone[lo:j].all()):
                entries.append(r)
            hi = np.searchsorted(steps, steps[j] + ahead, side="right")
            whole_after = hi - 1 - j == ahead and steps[hi - 1] == steps[j] + ahead
            clear[r] = moving[r] and whole_after and gone[j:hi].all()
    return np.array(entries, dtype=np.int64), clear


def _lead_rows(entries: np.ndarray, episode: np.ndarray, step: np.ndarray) -> dict[str, np.ndarray]:
    """Per lead of LEADS_S, the frame that long before each entry (-1 where not recorded)."""
    out = {}
    for lead in LEADS_S:
        want = step[entries] - round(lead / DT_S)
        rows = np.full(len(entries), -1, dtype=np.int64)
        for i, (r, s) in enumerate(zip(entries, want, strict=True)):
            j = r - (step[r] - s)
            if 0 <= j and episode[j] == episode[r] and step[j] == s:
                rows[i] = j
        out[f"{lead:g}"] = rows
    return out


def _walk_in_result(read: dict[int, float], entries: np.ndarray, leads: dict[str, np.ndarray], now: np.ndarray,
                    speed_mps: np.ndarray, clear_rows: np.ndarray, files: list[str], episode: np.ndarray,
                    step: np.ndarray) -> dict[str, Any]:
    """The walk-ins' figures from `read`, the pedestrian reading (nearness) of each frame the
    model ran on: per lead, how many entries have that frame and the share of them seen
    (SEEN_NEARNESS or more); the share of the sampled `clear_rows` seen (wrongly); and each
    entry (its recording, step, metres, speed and readings)."""
    def seen(rows: np.ndarray) -> float | None:
        return float(np.mean([read[int(r)] >= SEEN_NEARNESS for r in rows])) if len(rows) else None

    return {"entries": len(entries),
            "leads": {lead: {"frames": int((rows >= 0).sum()), "seen": seen(rows[rows >= 0])}
                      for lead, rows in leads.items()},
            "clear_frames": len(clear_rows), "clear_seen": seen(clear_rows),
            "median_m": float(np.median(now[entries])) if len(entries) else None,
            "median_mps": float(np.median(speed_mps[entries])) if len(entries) else None,
            "list": [{"recording": files[int(episode[r])], "step": int(step[r]), "m": round(float(now[r]), 1),
                      "mps": round(float(speed_mps[r]), 1),
                      "read": {lead: (None if rows[i] < 0 else round(read[int(rows[i])], 3))
                               for lead, rows in leads.items()}}
                     for i, r in enumerate(entries)]}


def probe_hazards(checkpoint: str | os.PathLike, folder: str | os.PathLike, every: int = 1,
                  batch_size: int = 64, threads: int | None = None, second: bool = False,
                  source: str = "merged", hazard_ahead_s: float = 0.0) -> dict[str, Any]:
    """The hazard outputs of `checkpoint` on every `every`-th frame of the recordings in
    `folder`: per kind, `seen_near` (of the frames with one in the path within NEAR_M, the share
    read at SEEN_NEARNESS or more, where the brakes start), `seen_none` (of those with none within
    HAZARD_AHEAD_M, the share read as one all the same), `auc`, the frame counts, and how far
    the ones seen are read against how far they are, also within CLOSE_M apart (`_group`); for all
    frames ("all") and grouped by command, weather, density, "ego" (standing, or moving at
    MOVING_MPS or faster) and "stop line" (standing at a red line, at a green one, elsewhere:
    `_stop_line`). `second`: the second head's outputs (model.move_off_head; beside SC's, as the
    first head's are) in place of the first head's, against its own targets (with `bid train
    --second-bumper` its vehicle the nearer of the path's and the one ahead of the bumper).
    `source` (config.PROBE_SOURCES): the reading driving uses ("merged"), or with SC the head's
    alone (its pedestrian gated by its presence logit, as driving reads it), SC's alone (gated
    by its logits with --sc-presence; then also `logits`, _logits of SC's logits over all
    frames) or the fine SC's alone (config.sc_fine; gated by its logits, and `logits` too),
    while the ego stands too. `hazard_ahead_s`: a pedestrian counts in the path also where the
    recording shows her in it within that many seconds (`bid train --hazard-ahead`), so a
    sighting of one about to walk in is right, not wrong. `walk_ins`: how early the pedestrian
    reading of `source` sees the ones who walk into a moving ego's path (`walk_ins`: counted
    where they are, whatever `hazard_ahead_s`; the frames before each entry are read too, even
    those `every` skips)."""
    if every < 1:
        raise BidError(f"every is a frame step, 1 or more; got {every}")
    check_hazard_ahead(hazard_ahead_s)
    if source not in PROBE_SOURCES:
        raise BidError(f"source is one of {', '.join(PROBE_SOURCES)}; got {source!r}")
    apart = source != "merged"
    if apart and second:
        raise BidError("--source reads the first head or SC apart, --second-head the second head: drop one")
    if threads:
        torch.set_num_threads(threads)
    model, config = load_model(checkpoint)
    if not config.model.hazard:
        raise BidError(f"{checkpoint} has no hazard head to probe; train one with --hazard")
    if second and not config.model.move_off_head:
        raise BidError(f"{checkpoint} has no second head to probe (bid train --move-off-head); drop --second-head")
    if apart and not config.model.hazard_sc:
        raise BidError(f"{checkpoint} has no SC (--hazard-sc): its reading is its head's alone; drop --source")
    if source == "SC_fine" and not config.model.sc_fine:
        raise BidError(f"{checkpoint} has no fine SC (bid graft --fine-sc); probe --source SC or merged")
    bumper_m = config.train.second_bumper_m if second else 0.0
    data, facts = open_every_frame(folder, config.model.input_hw, crossing=config.model.hazard_crossing,
                                   bumper_m=bumper_m, hazard_ahead_s=hazard_ahead_s)
    rows = np.arange(0, len(data), every)
    index = data.index
    now = data.hazard[:, 0] if hazard_ahead_s == 0 else open_every_frame(
        folder, config.model.input_hw, crossing=config.model.hazard_crossing)[0].hazard[:, 0]
    now = (1.0 - np.asarray(now, dtype=np.float64)) * HAZARD_AHEAD_M
    entries, clear = walk_ins(now, index.episode, index.step, index.speed)
    leads = _lead_rows(entries, index.episode, index.step)
    run = np.union1d(rows, np.concatenate([r[r >= 0] for r in leads.values()] + [rows[:0]]))
    preds, logits, targets, commands, episodes, speeds, greens = [], [], [], [], [], [], []
    with torch.inference_mode():
        for start in range(0, len(run), batch_size):
            items = [data[int(i)] for i in run[start:start + batch_size]]
            command = [it["command"] for it in items]
            speed = torch.tensor([it["speed_mps"] for it in items], dtype=torch.float32)
            out = model(torch.stack([it["frame"] for it in items]), torch.stack([it["prev_frame"] for it in items]),
                        command_one_hot(command), speed, hazard=True, hazard_apart=apart,
                        **({"move_off": True} if second else {}))
            pred = out[-1].float()
            if source == "head":
                pred = model.gate_head(pred[:, :model.head_columns()])
            elif source in ("SC", "SC_fine"):
                fine = source == "SC_fine"
                if fine or config.model.sc_presence:
                    logits.append(model.sc_columns(pred, fine)[:, len(PATH_KINDS):])
                pred = model.sc_near(pred, fine)
            preds.append(pred)
            near = torch.stack([it["hazard"] for it in items])
            if bumper_m > 0:
                near = second_targets({"vehicle_bumper": torch.tensor([it["vehicle_bumper"] for it in items])}, near)
            targets.append(near)
            commands += command
            episodes += [it["episode"] for it in items]
            speeds += [float(it["speed_mps"]) for it in items]
            greens += [float(it.get("green_m", HAZARD_AHEAD_M)) for it in items]
    # The sampled frames' figures; the lead frames only the walk-ins read.
    sampled = np.isin(run, rows)
    read = dict(zip(run.tolist(), torch.cat(preds)[:, 0].tolist(), strict=True))
    walked = _walk_in_result(read, entries, leads, now, index.speed, rows[clear[rows]],
                             [Path(f).name for f in index.files], index.episode, index.step)
    keep = torch.from_numpy(sampled)
    pred, every_target = torch.cat(preds)[keep], torch.cat(targets)[keep]
    speed, green = np.array(speeds)[sampled], np.array(greens)[sampled]
    target = every_target[:, :pred.shape[1]]
    groups: dict[str, np.ndarray] = {
        "command": np.array([COMMAND_NAMES[c] for c in commands])[sampled],
        "weather": np.array([facts[e].get("weather", "?") for e in episodes])[sampled],
        "density": np.array([facts[e].get("density", "?") for e in episodes])[sampled],
        "ego": np.where(speed >= MOVING_MPS, "moving", "standing"),
        "stop line": _stop_line(every_target, speed, green),
    }
    by: dict[str, dict[str, Any]] = {}
    for name, labels in groups.items():
        by[name] = {}
        for value in sorted(set(labels)):
            rows_of = torch.from_numpy(labels == value)
            by[name][value] = _group(pred[rows_of], target[rows_of])
    towns = sorted({f.get("town", "?") for f in facts})
    return {"checkpoint": str(checkpoint), **({"head": "second"} if second else {}),
            **({"source": source} if apart else {}),
            **({"logits": _logits(torch.cat(logits)[keep], target)} if logits else {}),
            **({"bumper_m": bumper_m} if bumper_m > 0 else {}),
            **({"hazard_ahead_s": hazard_ahead_s} if hazard_ahead_s > 0 else {}),
            "folder": str(folder), "towns": towns, "recordings": len(facts),
            "frames": len(rows), "every": every, "all": _group(pred, target), "by": by, "walk_ins": walked}


def _percent(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def _metres(read: float | None, true: float | None) -> str:
    return "—" if read is None else f"{read:.1f} ({true:.1f})"


def probe_table(result: dict[str, Any]) -> str:
    """The probe's figures as markdown: one table per kind, a row per group."""
    head = {"head": " (its head alone)", "SC": " (SC alone)", "SC_fine": " (the fine SC alone)"}.get(result.get("source"), "")
    head += " (its second head)" if result.get("head") == "second" else ""
    if result.get("bumper_m"):
        head += f" (vehicles also within {result['bumper_m']:g} m ahead of the bumper)"
    if result.get("hazard_ahead_s"):
        head += f" (pedestrians also where they will be within {result['hazard_ahead_s']:g} s)"
    lines = [f"# Hazard outputs of {result['checkpoint']}{head} on {result['folder']} "
             f"({', '.join(result['towns'])}; {result['recordings']} recordings, {result['frames']} frames"
             f"{'' if result['every'] == 1 else ', one in ' + str(result['every'])})", ""]
    for kind in (k for k in KINDS if k in result["all"]):
        lines += [f"## {kind}", "",
                  f"| group | frames with one within {NEAR_M:g} m | seen % | frames with none | seen wrongly % | AUC "
                  f"| seen: read m (true) | within {CLOSE_M:g} m | seen % | seen: read m (true) |",
                  "|---" * 10 + "|"]
        rows = [("all", result["all"])] + [(f"{name} {value}", group) for name, values in result["by"].items()
                                            for value, group in values.items()]
        for label, group in rows:
            g = group[kind]
            auc = "—" if g["auc"] is None else f"{g['auc']:.3f}"
            lines.append(f"| {label} | {g['near_frames']} | {_percent(g['seen_near'])} | {g['none_frames']} | "
                         f"{_percent(g['seen_none'])} | {auc} | {_metres(g['read_m'], g['true_m'])} | "
                         f"{g['close_frames']} | {_percent(g['seen_close'])} | "
                         f"{_metres(g['read_close_m'], g['true_close_m'])} |")
        at = result["all"][kind]["at"]
        lines += ["", "| all frames, nearness ≥ | " + " | ".join(at) + " |", "|---" * (len(at) + 1) + "|",
                  "| seen % | " + " | ".join(_percent(a["seen_near"]) for a in at.values()) + " |",
                  "| seen wrongly % | " + " | ".join(_percent(a["seen_none"]) for a in at.values()) + " |", ""]
        if kind in result.get("logits", {}):
            logit = result["logits"][kind]
            auc = "—" if logit["auc"] is None else f"{logit['auc']:.3f}"
            lines += [f"| all frames, SC's logit (AUC {auc}) > | " + " | ".join(logit["at"]) + " |",
                      "|---" * (len(logit["at"]) + 1) + "|",
                      "| seen % | " + " | ".join(_percent(a["seen_near"]) for a in logit["at"].values()) + " |",
                      "| seen wrongly % | " + " | ".join(_percent(a["seen_none"]) for a in logit["at"].values())
                      + " |", ""]
    walked = result.get("walk_ins")
    if walked:
        leads = walked["leads"]
        median = ("" if walked["median_m"] is None else
                  f" (median {walked['median_m']:.1f} m ahead at {walked['median_mps']:.1f} m/s)")
        lines += ["## pedestrians walking in", "",
                  f"{walked['entries']} times a pedestrian entered the path {ENTRY_M:g} m or nearer ahead of the moving "
                  f"ego{median}, with none in it for the {ENTRY_CLEAR_S:g} s before. The pedestrian reading "
                  f"(nearness ≥ {SEEN_NEARNESS:g}) that long before:", "",
                  "| before she enters, s | " + " | ".join(leads) + " |", "|---" * (len(leads) + 1) + "|",
                  "| entries recorded that long | " + " | ".join(str(a["frames"]) for a in leads.values()) + " |",
                  "| seen % | " + " | ".join(_percent(a["seen"]) for a in leads.values()) + " |", "",
                  f"Moving, with no pedestrian in the path then nor for the {CLEAR_AHEAD_S:g} s after: "
                  f"{walked['clear_frames']} frames, seen wrongly {_percent(walked['clear_seen'])} %.", ""]
    return "\n".join(lines)


def write_probe(result: dict[str, Any], out: str | os.PathLike) -> Path:
    """The probe as `out`.json and `out`.md."""
    import json

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    out.with_suffix(".md").write_text(probe_table(result) + "\n")
    return out
