"""Data contract of the BID model ("Brain-inspired driving", BID), the frame resize and a
synthetic dataset.

Dataset contract. Training reads any `torch.utils.data.Dataset` whose items are dicts:

| key          | type                              | meaning                                   |
|--------------|-----------------------------------|-------------------------------------------|
| `frame`      | uint8 tensor (3, H, W)            | RGB frame t, left | centre | right camera, |
|              |                                   | resized by `prepare_frame` to the preset's |
|              |                                   | `frame_hw`                                |
| `prev_frame` | uint8 tensor (3, H, W)            | frame t−1 of the same episode (frame t at  |
|              |                                   | an episode's first step)                   |
| `command`    | int64 (tensor or int), 1..6       | CARLA RoadOption: 1 LEFT, 2 RIGHT,         |
|              |                                   | 3 STRAIGHT, 4 LANEFOLLOW, 5/6 CHANGELANE   |
|              |                                   | LEFT/RIGHT                                 |
| `speed_mps`  | float32 (tensor or float)         | measured ego speed                         |
| `steer`      | float32 in [−1, 1], +1 full right | expert label                               |
| `accel`      | float32 in [−1, 1], >0 throttle   | expert label                               |
| `episode`    | int                               | episode index (splits, sequence plots)     |
| `step`       | int                               | step within the episode (0.1 s each)       |
| `future_speed` | float32 tensor (K,)             | optional: the speed at each of the K       |
|              |                                   | horizons of `forecast_s`, m/s (the speed   |
|              |                                   | forecast's targets; needed by --forecast)  |
| `hazard`     | float32 tensor (3,) or (4,)       | optional: nearness of the nearest          |
|              |                                   | pedestrian and vehicle in the ego's path   |
|              |                                   | and of a red light's stop line (and of a   |
|              |                                   | crossing with a pedestrian on it), 1 −     |
|              |                                   | distance / 25 m, 0 for none (the hazard    |
|              |                                   | head's targets; needed by --hazard, the    |
|              |                                   | fourth by --hazard-crossing)               |

Train and validation sets are split by episode (`split_episodes`), never by frame, so that
neighbouring, nearly identical frames do not leak into validation. `check_sample` validates
one item against the contract. `prepare_frame` is the one resize used by training and by
closed-loop driving, so both see identical pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset, Subset

from bid_sim.errors import BidError

RIG_HW = (300, 900)  # the renderer's frame: three 300×300 cameras side by side
N_COMMANDS = 6
COMMAND_NAMES = {1: "LEFT", 2: "RIGHT", 3: "STRAIGHT", 4: "LANEFOLLOW",
                 5: "CHANGELANELEFT", 6: "CHANGELANERIGHT"}
SAMPLE_KEYS = ("frame", "prev_frame", "command", "speed_mps", "steer", "accel", "episode", "step")


def resize_frame(frame: np.ndarray, frame_hw: tuple[int, int]) -> np.ndarray:
    """An (H, W, 3) uint8 RGB frame resized to `frame_hw` = (rows, cols), area-averaged."""
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise BidError(f"a frame must be an RGB uint8 array (rows, cols, 3), got "
                       f"{frame.dtype} {tuple(frame.shape)}")
    h, w = frame_hw
    if frame.shape[:2] == (h, w):
        return frame
    # INTER_AREA averages the pixels a target pixel covers: no aliasing when shrinking.
    return cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA)


def prepare_frame(frame: np.ndarray, frame_hw: tuple[int, int]) -> torch.Tensor:
    """The model's input for one rendered frame: resized, as a uint8 tensor (3, rows, cols)."""
    return torch.from_numpy(np.ascontiguousarray(resize_frame(frame, frame_hw).transpose(2, 0, 1)))


def command_one_hot(command: torch.Tensor | Sequence[int] | int,
                    n_commands: int = N_COMMANDS) -> torch.Tensor:
    """One-hot (B, 6) float of RoadOption numbers 1..6; a command out of range is a BidError."""
    c = torch.as_tensor(command, dtype=torch.int64).reshape(-1)
    bad = (c < 1) | (c > n_commands)
    if bool(bad.any()):
        raise BidError(f"navigation command {int(c[bad][0])} out of range; commands are CARLA "
                       f"RoadOption numbers 1..{n_commands} ({', '.join(f'{k} {v}' for k, v in COMMAND_NAMES.items())})")
    return torch.nn.functional.one_hot(c - 1, n_commands).float()


def check_sample(sample: dict[str, Any], frame_hw: tuple[int, int]) -> None:
    """Raise BidError naming what is wrong if `sample` breaks the dataset contract."""
    missing = [k for k in SAMPLE_KEYS if k not in sample]
    if missing:
        raise BidError(f"dataset items lack {', '.join(missing)}; see the contract in bid_model/data.py")
    for key in ("frame", "prev_frame"):
        x = sample[key]
        if not isinstance(x, torch.Tensor) or x.dtype != torch.uint8 or x.ndim != 3:
            raise BidError(f"dataset item {key!r} must be a uint8 tensor (3, rows, cols)")
        if tuple(x.shape) != (3, *frame_hw):
            raise BidError(f"dataset {key!r} is {tuple(x.shape[1:])} (rows, cols) but the preset "
                           f"expects {tuple(frame_hw)}; resize with bid_model.data.prepare_frame")
    command_one_hot(sample["command"])
    for key in ("steer", "accel"):
        v = float(sample[key])
        if not -1.0 <= v <= 1.0:
            raise BidError(f"dataset {key!r} = {v} is outside [-1, 1]")


def split_episodes(episodes: Sequence[int], val_fraction: float,
                   seed: int) -> tuple[list[int], list[int]]:
    """Episode ids split into (train, validation), a seeded choice of whole episodes.

    With two or more episodes both sides get at least one.
    """
    ids = sorted(set(episodes))
    if len(ids) < 2:
        return ids, []
    n_val = min(len(ids) - 1, max(1, round(val_fraction * len(ids))))
    order = np.random.default_rng(seed).permutation(len(ids))
    val = sorted(ids[i] for i in order[:n_val])
    return [e for e in ids if e not in set(val)], val


class SyntheticDriving(Dataset):
    """Generated frames whose labels are a learnable function of the pixels.

    Each episode moves one bright square smoothly across the three cameras: steer follows its
    horizontal position (plus a nudge from the command), accel its height (high = far =
    throttle), speed its height too. Frame t−1 is the square one step earlier, so motion is
    real. Item `i` depends only on (seed, i): no state, same data in every worker. With
    `forecast_steps`, items hold "future_speed": the speed that many steps on (held at the
    episode's last step).
    """

    def __init__(self, n: int, frame_hw: tuple[int, int], seed: int = 0, episode_len: int = 20,
                 forecast_steps: tuple[int, ...] = ()):
        self.n, self.frame_hw, self.seed, self.episode_len = n, tuple(frame_hw), seed, episode_len
        self.forecast_steps = tuple(forecast_steps)

    def __len__(self) -> int:
        return self.n

    def _episode(self, episode: int) -> tuple[np.random.Generator, float, float, int]:
        rng = np.random.default_rng((self.seed, episode))
        phase_x, phase_y = rng.uniform(0, 2 * math.pi, 2)
        command = int(rng.choice([1, 2, 3, 4, 4, 4, 5, 6]))
        return rng, float(phase_x), float(phase_y), command

    def _position(self, phase_x: float, phase_y: float, step: int) -> tuple[float, float]:
        t = 2 * math.pi * step / self.episode_len
        return 0.5 + 0.4 * math.sin(phase_x + t), 0.5 + 0.3 * math.sin(phase_y + 0.5 * t)

    @staticmethod
    def _speed(y: float) -> float:
        return 6.0 + 8.0 * (0.5 - y)

    def _render(self, episode: int, step: int, x: float, y: float) -> np.ndarray:
        h, w = self.frame_hw
        rng = np.random.default_rng((self.seed, episode, step, 1))
        img = rng.integers(0, 60, size=(h, w, 3), dtype=np.uint8)
        s = max(2, h // 5)
        cx, cy = int(x * (w - s)), int(y * (h - s))
        img[cy:cy + s, cx:cx + s] = (250, 240, 200)
        return img

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not 0 <= i < self.n:
            raise IndexError(i)
        episode, step = divmod(i, self.episode_len)
        _, px, py, command = self._episode(episode)
        x, y = self._position(px, py, step)
        frame = self._render(episode, step, x, y)
        prev = frame if step == 0 else self._render(episode, step - 1, *self._position(px, py, step - 1))
        nudge = {1: -0.3, 2: 0.3, 5: -0.15, 6: 0.15}.get(command, 0.0)
        steer = float(np.clip(1.6 * (x - 0.5) + nudge, -1, 1))
        accel = float(np.clip(2.4 * (0.5 - y), -1, 1))
        sample = {
            "frame": torch.from_numpy(frame.transpose(2, 0, 1).copy()),
            "prev_frame": torch.from_numpy(prev.transpose(2, 0, 1).copy()),
            "command": torch.tensor(command, dtype=torch.int64),
            "speed_mps": torch.tensor(self._speed(y), dtype=torch.float32),
            "steer": torch.tensor(steer, dtype=torch.float32),
            "accel": torch.tensor(accel, dtype=torch.float32),
            "episode": episode,
            "step": step,
        }
        if self.forecast_steps:
            last = self.episode_len - 1
            sample["future_speed"] = torch.tensor(
                [self._speed(self._position(px, py, min(step + k, last))[1]) for k in self.forecast_steps],
                dtype=torch.float32)
        return sample


def synthetic_split(n: int, frame_hw: tuple[int, int], val_fraction: float, seed: int,
                    forecast_steps: tuple[int, ...] = ()) -> tuple[Dataset, Dataset, dict[str, Any]]:
    """(train, validation, description) of a SyntheticDriving set, split by episode."""
    data = SyntheticDriving(n, frame_hw, seed, forecast_steps=forecast_steps)
    episodes = [i // data.episode_len for i in range(n)]
    train_eps, val_eps = split_episodes(episodes, val_fraction, seed)
    val_set = set(val_eps)
    train_idx = [i for i, e in enumerate(episodes) if e not in val_set]
    val_idx = [i for i, e in enumerate(episodes) if e in val_set]
    description = {"kind": "synthetic", "samples": n, "frame_hw": list(frame_hw), "seed": seed,
                   "episode_len": data.episode_len, "train_episodes": len(train_eps),
                   "val_episodes": len(val_eps), "train_samples": len(train_idx),
                   "val_samples": len(val_idx)}
    return Subset(data, train_idx), Subset(data, val_idx), description
