"""Training samples from a folder of recordings (bid_sim.recording), in the dataset contract
of bid_model.data.

`open_recordings` indexes every finished recording (`*.mcap`, recursively; unfinished
`.mcap.partial` files are skipped with a warning, a corrupt file is a BidError naming it),
splits whole episodes into training and validation, and by default decodes and resizes
every frame once into a memory-mapped cache next to the data (decoding in worker
processes, one recording each), so that epochs read frames without decoding JPEG. The
cache is keyed by the recordings' names, sizes and times and by the frame size, and is
rebuilt when any of them changes. Without the cache, frames stay as JPEG in memory and are
decoded in __getitem__ (in DataLoader workers when there are any).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from bid_model.config import PATH_KINDS
from bid_model.data import resize_frame, split_episodes
from bid_model.hazards import (
    HAZARD_AHEAD_M,
    green_distance,
    index_bumper,
    index_crossings,
    index_hazards,
    light_distance,
)
from bid_sim.errors import BidError
from bid_sim.parallel import map_parallel, require_main_process
from bid_sim.recording import PARTIAL, decode_jpeg, read_episode
from bid_sim.snapshot import RED, YELLOW

log = logging.getLogger(__name__)
CACHE_DIR = ".bid_cache"


@dataclass
class _Index:
    """Every sample of the folder, in (file, step) order; arrays are parallel."""

    files: list[Path]
    facts: list[dict[str, str]]
    episode: np.ndarray  # (N,) file index
    step: np.ndarray
    prev: np.ndarray  # (N,) sample index of frame t-1 (itself at an episode's start or after a gap)
    command: np.ndarray
    speed: np.ndarray
    steer: np.ndarray
    accel: np.ndarray
    jpeg: list[bytes] | None  # kept only without the cache
    # (N,) bool: a red or amber light on the route within LIGHT_STOP_M (None: not known, none)
    light_stop: np.ndarray | None = None
    # (N,) float32: metres to the stop line of a red or amber light on the route (hazards.light_distance)
    light_dist: np.ndarray | None = None
    # (N,) float32: metres to the stop line of a green light on the route (hazards.green_distance)
    green_dist: np.ndarray | None = None


def find_recordings(folder: str | os.PathLike) -> tuple[list[Path], list[Path]]:
    """(finished recordings, unfinished .partial files) under `folder`, sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BidError(f"no recordings: {folder} does not exist; record some with `make record TOWN=01`")
    files = sorted(p for p in folder.rglob("*.mcap") if CACHE_DIR not in p.parts)
    partial = sorted(folder.rglob(f"*.mcap{PARTIAL}"))
    return files, partial


def _index(files: list[Path], keep_jpeg: bool) -> _Index:
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("episode", "step", "prev", "command", "speed", "steer", "accel",
                                                         "light_stop", "light_dist", "green_dist")}
    facts, jpeg = [], [] if keep_jpeg else None
    n = 0
    for e, f in enumerate(files):
        ep = read_episode(f, frames=keep_jpeg)
        facts.append(ep.facts)
        m = len(ep)
        if m == 0:
            continue
        idx = np.arange(n, n + m)
        cont = np.r_[False, np.diff(ep.steps) == 1]  # frame t-1 exists right before
        cols["prev"].append(np.where(cont, idx - 1, idx))
        cols["episode"].append(np.full(m, e))
        cols["step"].append(ep.steps)
        cols["command"].append(ep.command)
        cols["speed"].append(ep.speed_mps)
        cols["steer"].append(ep.steer)
        cols["accel"].append(ep.accel)
        cols["light_stop"].append(np.array([light_stops(st) for st in ep.states], dtype=bool))
        cols["light_dist"].append(np.array([light_distance(st) for st in ep.states], dtype=np.float32))
        cols["green_dist"].append(np.array([green_distance(st) for st in ep.states], dtype=np.float32))
        if jpeg is not None:
            jpeg.extend(ep.jpeg)
        n += m
    arr = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in cols.items()}
    return _Index(files, facts, arr["episode"].astype(np.int64), arr["step"].astype(np.int64),
                  arr["prev"].astype(np.int64), arr["command"].astype(np.int64), arr["speed"].astype(np.float32),
                  arr["steer"].astype(np.float32), arr["accel"].astype(np.float32), jpeg,
                  arr["light_stop"].astype(bool), arr["light_dist"].astype(np.float32),
                  arr["green_dist"].astype(np.float32))


def light_stops(state: dict) -> bool:
    """Whether a recorded /ego/state has a red or amber light on the route within LIGHT_STOP_M."""
    dist = state.get("next_light_dist_m")
    return state.get("next_light_state") in (RED, YELLOW) and dist is not None and dist < LIGHT_STOP_M


def _cache_key(files: list[Path], frame_hw: tuple[int, int]) -> str:
    h = hashlib.sha1(f"{frame_hw}".encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def _decode_file(args: tuple[str, str, int, int, tuple[int, int]]) -> int:
    """Worker: decodes one recording's frames into its rows of the cache file."""
    import cv2

    cv2.setNumThreads(1)
    path, cache, start, total, (h, w) = args
    ep = read_episode(path)
    mm = np.memmap(cache, dtype=np.uint8, mode="r+", shape=(total, 3, h, w))
    for i, data in enumerate(ep.jpeg):
        mm[start + i] = resize_frame(decode_jpeg(data), (h, w)).transpose(2, 0, 1)
    mm.flush()
    del mm
    return len(ep.jpeg)


def build_cache(index: _Index, folder: Path, frame_hw: tuple[int, int], workers: int | None = None) -> Path:
    """The memory-mapped (N, 3, H, W) uint8 frame cache of an index (built if missing)."""
    h, w = frame_hw
    total = len(index.step)
    cache_dir = folder / CACHE_DIR
    path = cache_dir / f"frames-{h}x{w}-{_cache_key(index.files, frame_hw)}.u8"
    if path.exists() and path.stat().st_size == total * 3 * h * w:
        return path
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    counts = np.bincount(index.episode, minlength=len(index.files))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    jobs = [(str(f), str(tmp), int(s), total, (h, w)) for f, s, c in zip(index.files, starts, counts, strict=True) if c]
    workers = workers or max(1, min(os.cpu_count() or 1, len(jobs)))
    if workers > 1 and len(jobs) > 1:
        require_main_process()  # before writing a cache-sized file
    try:
        cache_dir.mkdir(exist_ok=True)
        for old in cache_dir.glob(f"frames-{h}x{w}-*.u8"):
            old.unlink()
        np.memmap(tmp, dtype=np.uint8, mode="w+", shape=(max(total, 1), 3, h, w)).flush()
    except OSError as e:
        raise BidError(f"cannot write the frame cache in {cache_dir} ({e.strerror}); free disk space "
                       "or train with --no-cache") from e
    log.info("caching %d frames of %d recordings at %dx%d with %d workers", total, len(jobs), h, w, workers)
    try:
        done = map_parallel(_decode_file, jobs, workers)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if sum(done) != total:
        tmp.unlink(missing_ok=True)
        raise BidError(f"recordings in {folder} changed while caching; run again")
    os.replace(tmp, path)
    return path


class RecordingDataset(Dataset):
    """Samples (bid_model.data contract) of chosen rows of an index."""

    def __init__(self, index: _Index, rows: np.ndarray, frame_hw: tuple[int, int], cache: Path | None,
                 still: np.ndarray | None = None, motionless: np.ndarray | None = None,
                 accel: np.ndarray | None = None, forecast: np.ndarray | None = None,
                 hazard: np.ndarray | None = None, bumper: np.ndarray | None = None):
        self.index, self.rows, self.frame_hw = index, np.asarray(rows, dtype=np.int64), tuple(frame_hw)
        # (N, K) speeds ahead per index row, the targets of the speed forecast (future_speeds).
        self.forecast = forecast
        # (N, 2) nearness of the nearest pedestrian and vehicle in the path per index row, the
        # targets of the hazard head (hazard_nearness).
        self.hazard = hazard
        # (N,) nearness of the nearest vehicle in the path or ahead of the bumper per index row,
        # the second head's vehicle target with `bid train --second-bumper` (bumper_targets).
        self.bumper = bumper
        # Accel labels per index row, where they are not the recorded ones (anticipate_braking).
        self.accel_labels = None if accel is None else np.asarray(accel, dtype=np.float32)
        # Rows shown standing still: frame t−1 = frame t and speed 0 (see balance_rows).
        self.still = np.zeros(len(self.rows), dtype=bool) if still is None else np.asarray(still, dtype=bool)
        # Rows shown without motion, at their speed: frame t−1 = frame t (see motion_dropout).
        self.motionless = (np.zeros(len(self.rows), dtype=bool) if motionless is None
                           else np.asarray(motionless, dtype=bool))
        self.cache = cache
        self._mm: np.ndarray | None = None  # opened lazily: once per DataLoader worker

    def __len__(self) -> int:
        return len(self.rows)

    def _frame(self, j: int) -> torch.Tensor:
        if self.cache is not None:
            if self._mm is None:
                h, w = self.frame_hw
                self._mm = np.memmap(self.cache, dtype=np.uint8, mode="r", shape=(len(self.index.step), 3, h, w))
            return torch.from_numpy(np.array(self._mm[j]))
        assert self.index.jpeg is not None
        img = resize_frame(decode_jpeg(self.index.jpeg[j]), self.frame_hw)
        return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))

    def __getitem__(self, i: int) -> dict[str, Any]:
        ix = self.index
        accel = ix.accel if self.accel_labels is None else self.accel_labels
        j = int(self.rows[i])
        frame = self._frame(j)
        still = bool(self.still[i])
        same = still or bool(self.motionless[i])
        sample = {"frame": frame, "prev_frame": frame if same else self._frame(int(ix.prev[j])),
                  "command": int(ix.command[j]), "speed_mps": 0.0 if still else float(ix.speed[j]),
                  "steer": float(ix.steer[j]),
                  "accel": float(accel[j]), "episode": int(ix.episode[j]), "step": int(ix.step[j])}
        if self.forecast is not None:
            sample["future_speed"] = torch.from_numpy(self.forecast[j])
        if self.hazard is not None:
            sample["hazard"] = torch.from_numpy(self.hazard[j])
            if ix.green_dist is not None:  # not a target: for --hazard-green-weight and `bid probe`
                sample["green_m"] = float(ix.green_dist[j])
        if self.bumper is not None:
            sample["vehicle_bumper"] = float(self.bumper[j])
        return sample

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_mm"] = None  # each worker process maps the file itself
        return state


STOPPED_MPS = 0.1  # below this the ego stands
START_MPS = 2.0  # below this, with throttle, it is moving off
GO_LOOKAHEAD = 10  # standing frames this close before a start are kept: the cue to go is in them
STANDING_STEER_MAX = 0.5  # standing frames that steer harder say nothing (see balance_rows)
HARD_STEER = 0.25  # |steer| from which a moving frame is a hard one (a turn, a sharp bend)
HARD_BRAKE = -0.2  # accel up to which a moving frame is a hard one (slowing for a bend, a car)
STOP_BRAKE = -0.5  # accel up to which the expert is stopping (anticipate_braking), not slowing
# A red light this close ahead explains a stop (a queue of a few cars before its line); a stop
# without one is a yield: to a pedestrian on the crossing, a car ahead, cross traffic.
LIGHT_STOP_M = 40.0


def balance_rows(index: _Index, rows: np.ndarray, stop_keep: float, start_repeat: int, hard_repeat: int = 1,
                 hard_brake: bool = True, accel: np.ndarray | None = None, hold_repeat: int = 1,
                 start_accel: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Training rows rebalanced against the stop/go imbalance of driving data, and which of
    them to show as standing still.

    Demonstrations stand still much of the time (a red light lasts up to 45 s) holding the
    brake, and move off in a handful of frames, so a network learns "keep standing" as its
    safe bet and never starts in closed loop. Worse, the frames of moving off show motion
    (frame t−1 differs), so it learns "go when already moving": at a standstill, nothing
    moves, and it never starts (the inertia problem of imitation learning). So: keep every
    round(1/stop_keep)-th standing, braking frame (by step number, deterministic) and all
    of those within GO_LOOKAHEAD steps before a start; repeat each moving-off frame (slow,
    throttle) `start_repeat` times, the repeats shown standing still (frame t−1 = frame t,
    speed 0) with the expert's throttle as the label. Standing frames that steer by more than
    STANDING_STEER_MAX are dropped: at a standstill the wheel turns nothing, and such labels
    come from a car stranded off its route (the expert at full lock, braking).

    Driving also cruises: in Town01 about one moving frame in five steers by HARD_STEER or
    more or brakes by HARD_BRAKE or more, mostly in junction turns, and one in thirteen in
    LANEFOLLOW, where a 90° bend of the town's corner has no junction. An L1 fit gives such
    rare labels little say, and the car takes the bend at cruising speed with a third of the
    lock it needs. Each of those frames (moving at START_MPS or more) is trained on
    `hard_repeat` times. With `hard_brake` False only the steering ones are: repeated braking
    teaches a fine-tuned network to brake before every bend it sees, down to a standstill in
    front of Town02's corners (DAgger round 8). `accel`: the labels trained on, where they are
    not the recorded ones (anticipate_braking); then the frames of a stop (braking by
    STOP_BRAKE or more, or braking earlier than recorded) are hard ones even without
    `hard_brake`.

    All of this favours going at low speed: moving off is repeated, standing is thinned. Yet
    where no red light explains it, standing or slow braking is a yield, mostly to
    pedestrians on the crossing of a turn, and the town sees it seldom (of data/new's 161k
    frames, 2.3k stand and 0.4k move slowly so, against 22k moving off). The BID of
    2026-11-25 moved off into them at +0.6 while the expert held −1 (docs/experiments.md).
    Those frames (yield_frames) are all kept and trained on `hold_repeat` times.

    With `start_accel` above 0 only a throttle above it moves off; a standstill with less is
    standing (thinned like the rest; see hold_creep for its label). Returns (rows, still), sorted.
    """
    if not 0.0 < stop_keep <= 1.0 or start_repeat < 1 or hard_repeat < 1 or hold_repeat < 1:
        raise BidError(f"stop_keep must be in (0, 1] and start_repeat, hard_repeat, hold_repeat >= 1, got "
                       f"{stop_keep}, {start_repeat}, {hard_repeat}, {hold_repeat}")
    rows = np.asarray(rows, dtype=np.int64)
    if not 0.0 <= start_accel < 1.0:
        raise BidError(f"the throttle that moves off must be in [0, 1), got {start_accel}")
    standing = (index.speed < STOPPED_MPS) & (index.accel <= start_accel)
    starting = (index.speed < START_MPS) & (index.accel > start_accel)
    # Standing frames that lead to a start within GO_LOOKAHEAD steps of the same episode.
    soon = np.zeros(len(index.step), dtype=bool)
    for k in range(1, GO_LOOKAHEAD + 1):
        ahead = np.r_[starting[k:], np.zeros(k, dtype=bool)]
        same = np.r_[index.episode[k:] == index.episode[:-k], np.zeros(k, dtype=bool)]
        soon |= ahead & same
    every = max(1, round(1.0 / stop_keep))
    yielding = yield_frames(index, accel) if hold_repeat > 1 else np.zeros(len(index.step), dtype=bool)
    keep = ~standing[rows] | soon[rows] | yielding[rows] | (index.step[rows] % every == 0)
    keep &= ~((index.speed[rows] < STOPPED_MPS) & (np.abs(index.steer[rows]) > STANDING_STEER_MAX))
    kept = rows[keep]
    repeats = np.repeat(kept[starting[kept]], start_repeat - 1)
    hard_repeats = np.repeat(kept[hard_frames(index, hard_brake, accel)[kept]], hard_repeat - 1)
    hold_repeats = np.repeat(kept[yielding[kept]], hold_repeat - 1)
    all_rows = np.r_[kept, hard_repeats, hold_repeats, repeats]
    still = np.r_[np.zeros(len(kept) + len(hard_repeats) + len(hold_repeats), dtype=bool),
                  np.ones(len(repeats), dtype=bool)]
    order = np.lexsort((still, all_rows))
    return all_rows[order], still[order]


def hard_frames(index: _Index, brake: bool = True, accel: np.ndarray | None = None) -> np.ndarray:
    """Which frames steer (or, with `brake`, brake) hard while moving, and with `accel` (the
    labels trained on) which stop (see balance_rows)."""
    labels = index.accel if accel is None else accel
    hard = np.abs(index.steer) >= HARD_STEER
    if brake:
        hard |= labels <= HARD_BRAKE
    if accel is not None:
        hard |= (labels <= STOP_BRAKE) | (labels < index.accel)
    return (index.speed >= START_MPS) & hard


def hold_creep(index: _Index, accel: np.ndarray | None, start_accel: float) -> np.ndarray:
    """Accel labels (`accel`, or the recorded ones) in which a standstill's faint throttle, 0 to
    `start_accel`, is 0: a hold.

    Standing in a queue, the expert (IDM) closes up on the car ahead at +0.00 to +0.06, a few
    centimetres a step. In a DAgger round, where the BID stood, that is most of its go labels
    (the crowded round of 2026-12-03: 6,620 of 9,341 standstill frames with throttle at up to
    +0.1, 1,987 above +0.3), and the control head fine-tuned on them learnt to creep into the
    car ahead at walking pace (r31cpc, docs/experiments.md). A standstill's go is a real start.
    """
    labels = (index.accel if accel is None else accel).copy()
    creep = (index.speed < STOPPED_MPS) & (labels > 0.0) & (labels <= start_accel)
    labels[creep] = 0.0
    return labels


def yield_frames(index: _Index, accel: np.ndarray | None = None) -> np.ndarray:
    """Which frames stand or move off slowly (below START_MPS) braking by HARD_BRAKE or more
    (`accel`: the labels trained on) with no red or amber light within LIGHT_STOP_M: the
    expert yielding (see balance_rows). Recordings without light states have none."""
    labels = index.accel if accel is None else accel
    if index.light_stop is None:
        return np.zeros(len(labels), dtype=bool)
    return (index.speed < START_MPS) & (labels <= HARD_BRAKE) & ~index.light_stop


def anticipate_braking(index: _Index, frames: int) -> np.ndarray:
    """Accel labels that brake as soon as the expert is about to: each frame's label is the
    lower of its own and the mean of its episode's labels over this frame and the next
    `frames` - 1 (fewer at an episode's end or a gap in its steps).

    The expert's speed control (IDM) brakes late and hard: towards a red light it keeps a
    light throttle until about 15 m before the stop line and brakes fully in the last 5 m.
    The round-7 BID, on Town02 route 0, brakes −0.1 to −0.35 where the expert brakes −1 and
    crosses the line at 4.6 m/s; in the last 2 m the light has left the top of the frame
    and it accelerates. Labels that already brake a second earlier, where the light is in
    plain view, ask for the stop where it can be seen. Only stops move earlier (a frame of the
    window brakes by STOP_BRAKE or more), not the slowing for a bend: braking for every bend
    stranded a fine-tuned network in front of Town02's corners (DAgger round 8). And only
    frames moving at START_MPS or more: a first try that also moved earlier the braking of
    standing frames and the throttle of moving off (where a pedestrian soon stops the car
    again) stood at green lights for good, braking fully, in 14 of 50 Town02 episodes in
    normal traffic. 1 gives the labels as recorded.
    """
    if frames < 1:
        raise BidError(f"the braking look-ahead must be at least 1 frame, got {frames}")
    accel = index.accel.astype(np.float64)
    total, count, lowest = accel.copy(), np.ones(len(accel)), accel.copy()
    for k in range(1, frames):
        # Row i + k is the same episode's frame k steps later (no gap in between).
        ahead = np.r_[index.step[k:] - index.step[:-k] == k, np.zeros(k, dtype=bool)]
        ahead &= np.r_[index.episode[k:] == index.episode[:-k], np.zeros(k, dtype=bool)]
        later = np.where(ahead, np.r_[accel[k:], np.zeros(k)], 0.0)
        total += later
        count += ahead
        lowest = np.minimum(lowest, np.where(ahead, later, np.inf))
    early = np.minimum(index.accel, (total / count).astype(np.float32))
    moving = index.speed >= START_MPS
    return np.where(moving & (lowest <= STOP_BRAKE), early, index.accel).astype(np.float32)


def future_speeds(index: _Index, steps: tuple[int, ...]) -> np.ndarray:
    """(N, len(steps)) float32: each frame's speed that many steps later in its episode, the
    targets of the speed forecast (BID.forward_forecast). Past the last frame of an unbroken
    run of steps (the episode's end, or a gap) it is that last frame's speed: where the
    recording stops, the car is taken to hold its speed."""
    n = len(index.step)
    if n == 0 or not steps:
        return np.zeros((n, len(steps)), dtype=np.float32)
    # Last row of each row's unbroken run: runs break where the episode or step continuity does.
    breaks = np.r_[(index.episode[1:] != index.episode[:-1]) | (np.diff(index.step) != 1), True]
    run_end = np.flatnonzero(breaks)
    rows = np.arange(n)
    last = run_end[np.searchsorted(run_end, rows)]
    return np.stack([index.speed[np.minimum(rows + k, last)] for k in steps], axis=1).astype(np.float32)


def hazard_nearness(distances_m: np.ndarray) -> np.ndarray:
    """The hazard head's targets from bid_model.hazards' distances: 1 − distance /
    HAZARD_AHEAD_M, so 1 is touching the ego's front and 0 nothing in the path within reach."""
    return (1.0 - np.clip(distances_m, 0.0, HAZARD_AHEAD_M) / HAZARD_AHEAD_M).astype(np.float32)


def motion_dropout(n: int, share: float, seed: int) -> np.ndarray:
    """Which of n training rows to show without motion (frame t−1 = frame t): a fixed random
    `share` of them, drawn from `seed`.

    Steering in the demonstrations goes on for many frames, and the car's own turning shows
    in the motion between frame t−1 and t. A network with both frames learns to copy that
    motion ("keep turning while turning") rather than read the road, and in closed loop,
    not yet turning, it never starts to (copycat / causal confusion, de Haan et al. 2019).
    Rows without motion must be steered from the road itself.
    """
    if not 0.0 <= share < 1.0:
        raise BidError(f"motion dropout must be a share in [0, 1), got {share}")
    return np.random.default_rng((seed, 0x3D0)).random(n) < share


def _open_index(folder: Path, cache: bool) -> tuple[_Index, list[Path]]:
    """(the index of the finished recordings in `folder`, the unfinished ones skipped, warned of);
    a BidError where there are none, or no frames, or a command no bid-sim recording holds."""
    files, partial = find_recordings(folder)
    for p in partial:
        log.warning("skipping unfinished recording %s (salvage it with `bid recover %s`)", p, p)
    if not files:
        raise BidError(f"no finished recordings (*.mcap) in {folder}; record some with `make record TOWN=01`")
    index = _index(files, keep_jpeg=not cache)
    if len(index.step) == 0:
        raise BidError(f"the recordings in {folder} hold no camera frames")
    bad = np.flatnonzero((index.command < 1) | (index.command > 6))
    if len(bad):
        raise BidError(f"{files[index.episode[bad[0]]]} has navigation command {index.command[bad[0]]} "
                       "out of 1..6: not a bid-sim recording, or damaged")
    return index, partial


def _hazard_targets(index: _Index, cache_dir: Path | None, hazard_ahead_s: float, crossing: bool) -> np.ndarray:
    """(N, 3) or with `crossing` (N, 4) hazard nearness per index row (see open_recordings)."""
    columns = [index_hazards(index.files, index.episode, index.step, cache_dir, ped_ahead_s=hazard_ahead_s),
               index.light_dist]
    if crossing:
        columns.append(index_crossings(index.files, index.episode, index.step, cache_dir))
    return hazard_nearness(np.column_stack(columns))


def bumper_targets(index: _Index, cache_dir: Path | None, near: np.ndarray, ahead_m: float) -> np.ndarray:
    """(N,) float32 nearness of the nearest vehicle in the path (`near`'s vehicle column) or
    within `ahead_m` ahead of the bumper along the ego's heading and turn (hazards.bumper_vehicles)."""
    ahead = hazard_nearness(index_bumper(index.files, index.episode, index.step, cache_dir, ahead_m))[:, 0]
    return np.maximum(near[:, PATH_KINDS.index("vehicle")], ahead).astype(np.float32)


def open_every_frame(folder: str | os.PathLike, frame_hw: tuple[int, int], crossing: bool = False,
                     cache: bool = True, bumper_m: float = 0.0,
                     hazard_ahead_s: float = 0.0) -> tuple[RecordingDataset, list[dict]]:
    """Every frame of the recordings in `folder`, in (file, step) order, as recorded (no split,
    no rebalancing), with the hazard targets (`open_recordings(hazard=True)`, pedestrians also
    where they will be within `hazard_ahead_s`; with `crossing` the fourth too), and the facts of
    each recording (a sample's "episode" indexes them): to measure a trained model on recordings
    it never saw, another town's or weather's. With `bumper_m` the samples hold
    "vehicle_bumper" too (`open_recordings`)."""
    folder = Path(folder)
    index, _ = _open_index(folder, cache)
    cache_path = build_cache(index, folder, tuple(frame_hw)) if cache else None
    cache_dir = folder / CACHE_DIR if cache else None
    near = _hazard_targets(index, cache_dir, hazard_ahead_s, crossing)
    bumper = bumper_targets(index, cache_dir, near, bumper_m) if bumper_m > 0 else None
    return (RecordingDataset(index, np.arange(len(index.step)), frame_hw, cache_path, hazard=near, bumper=bumper),
            list(index.facts))


def open_recordings(folder: str | os.PathLike, frame_hw: tuple[int, int], val_fraction: float, seed: int,
                    cache: bool = True, stop_keep: float = 1.0, start_repeat: int = 1,
                    motion_drop: float = 0.0, hard_repeat: int = 1, hard_brake: bool = True,
                    brake_lookahead: int = 1, forecast_steps: tuple[int, ...] = (), hold_repeat: int = 1,
                    hazard: bool = False, hazard_ahead_s: float = 0.0,
                    crossing: bool = False, start_accel: float = 0.0, bumper_m: float = 0.0
                    ) -> tuple[RecordingDataset, RecordingDataset, dict]:
    """(train, validation, description) of the recordings in `folder`, split by episode.

    The training rows are rebalanced with `balance_rows(stop_keep, start_repeat, hard_repeat, hard_brake,
    hold_repeat, start_accel)` and a share
    `motion_drop` of them shown without motion (`motion_dropout`); their accel labels brake
    `brake_lookahead` frames ahead (`anticipate_braking`) and, with `start_accel`, hold where a
    standstill's throttle is at most that (`hold_creep`). The validation set keeps every
    frame and label as recorded, so its errors stay those of real driving. With
    `forecast_steps` the samples of both also hold "future_speed", the speeds that many steps
    ahead (`future_speeds`); with `hazard`, "hazard", what stands in the path
    (`hazard_nearness` of bid_model.hazards.index_hazards, cached beside the frames) and how
    near a red light's stop line is (hazards.light_distance): (pedestrian, vehicle, red_light);
    pedestrians also where they will be within `hazard_ahead_s` (hazards.path_hazards); with
    `crossing` too a fourth, how near the next crossing with a pedestrian on it is
    (hazards.index_crossings, cached likewise); with `bumper_m` (and `hazard`) "vehicle_bumper",
    how near the nearest vehicle in the path or within `bumper_m` ahead of the bumper along
    the ego's heading and turn is (`bumper_targets`).
    """
    folder = Path(folder)
    index, partial = _open_index(folder, cache)
    files = index.files
    cache_path = build_cache(index, folder, tuple(frame_hw)) if cache else None
    train_eps, val_eps = split_episodes(range(len(files)), val_fraction, seed)
    is_val = np.isin(index.episode, val_eps)
    train_rows = np.flatnonzero(~is_val)
    accel = anticipate_braking(index, brake_lookahead) if brake_lookahead != 1 else None
    balanced, still = balance_rows(index, train_rows, stop_keep, start_repeat, hard_repeat, hard_brake, accel,
                                   hold_repeat, start_accel)
    labels = hold_creep(index, accel, start_accel) if start_accel > 0.0 else accel
    forecast = future_speeds(index, tuple(forecast_steps)) if forecast_steps else None
    cache_dir = folder / CACHE_DIR if cache else None
    near = _hazard_targets(index, cache_dir, hazard_ahead_s, crossing) if hazard else None
    bumper = bumper_targets(index, cache_dir, near, bumper_m) if near is not None and bumper_m > 0 else None
    train = RecordingDataset(index, balanced, frame_hw, cache_path, still,
                             motion_dropout(len(balanced), motion_drop, seed), labels, forecast, near, bumper)
    val = RecordingDataset(index, np.flatnonzero(is_val), frame_hw, cache_path, forecast=forecast, hazard=near,
                           bumper=bumper)
    weathers = Counter(f.get("weather", "?") for f in index.facts)
    densities = Counter(f.get("density", "?") for f in index.facts)
    towns = Counter(f.get("town", "?") for f in index.facts)
    description = {
        "folder": str(folder), "recordings": len(files), "skipped_partial": [str(p) for p in partial],
        "samples": len(index.step), "train_samples": len(train), "val_samples": len(val),
        "train_frames_before_balance": len(train_rows), "stop_keep": stop_keep, "start_repeat": start_repeat,
        "hard_repeat": hard_repeat, "hard_brake": hard_brake, "brake_lookahead": brake_lookahead,
        "forecast_steps": list(forecast_steps),
        "hazard_frames": None if near is None else {"pedestrian_in_path": int((near[:, 0] > 0).sum()),
                                                    "vehicle_in_path": int((near[:, 1] > 0).sum()),
                                                    "red_light_ahead": int((near[:, 2] > 0).sum()),
                                                    **({"crossing_occupied": int((near[:, 3] > 0).sum())}
                                                       if crossing else {}),
                                                    "pedestrians_ahead_s": hazard_ahead_s,
                                                    **({"vehicle_in_path_or_bumper": int((bumper > 0).sum()),
                                                        "bumper_m": bumper_m} if bumper is not None else {})},
        "train_labels_braking_earlier": 0 if accel is None else int((accel[balanced] < index.accel[balanced]).sum()),
        "start_accel": start_accel,
        "train_creep_held": 0 if labels is accel else int(
            (labels[balanced] != (index.accel if accel is None else accel)[balanced]).sum()),
        "train_hard_frames": int(hard_frames(index, hard_brake, accel)[balanced].sum()),
        "hold_repeat": hold_repeat, "train_yield_frames": int(yield_frames(index, accel)[balanced].sum()),
        "train_shown_still": int(still.sum()), "motion_drop": motion_drop,
        "train_shown_motionless": int(train.motionless.sum()),
        "perturbed_recordings": sum(1 for f in index.facts if float(f.get("perturb", 0) or 0) > 0),
        "late_turn_recordings": sum(1 for f in index.facts if float(f.get("perturb_turns") or 0) > 0),
        "train_episodes": len(train_eps), "val_episodes": [str(files[e].relative_to(folder)) for e in val_eps],
        "towns": dict(towns), "weathers": dict(weathers), "densities": dict(densities),
        "frame_hw": list(frame_hw), "cache": str(cache_path) if cache_path else None,
        "steer_mean_abs": float(np.abs(index.steer).mean()), "accel_mean": float(index.accel.mean()),
    }
    return train, val, json.loads(json.dumps(description))
