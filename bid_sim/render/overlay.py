"""Evaluation videos: the three cameras with the command, speed, control and infraction
events drawn over them, written as MP4 while the episode runs (`bid evaluate --video`).

An agent may add its own picture under the cameras (the BID agent's Grad-CAM) by having
a method ``overlay(frame) -> np.ndarray | None`` returning an RGB image of the frame's
width.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from bid_sim.errors import BidError
from bid_sim.routes import COMMAND_NAMES

EVENT_SHOW_S = 3.0
VIDEO_FPS = 10
_FONT = cv2.FONT_HERSHEY_SIMPLEX


class VideoRecorder:
    """A recorder for run_episode (write, note) that encodes an MP4."""

    def __init__(self, path: str | os.PathLike, agent=None, fps: float = VIDEO_FPS):
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp.mp4")
        self.agent = agent
        self.fps = fps
        self.events: list[tuple[float, str]] = []
        self._writer: cv2.VideoWriter | None = None
        self.frames = 0

    def note(self, infraction) -> None:
        self.events.append((float(infraction.time_s), str(infraction.kind).replace("_", " ")))

    def write(self, snap, frame: np.ndarray | None, control) -> None:
        if frame is None:
            return
        img = annotate(frame, snap, control, [e for t, e in self.events if snap.time_s - t <= EVENT_SHOW_S])
        extra = getattr(self.agent, "overlay", None)
        below = extra(frame) if callable(extra) else None
        if below is not None:
            img = np.vstack([img, below])
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            h, w = img.shape[:2]
            self._writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
            if not self._writer.isOpened():
                raise BidError(f"OpenCV cannot write MP4 to {self.path}")
        self._writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def finish(self) -> Path | None:
        if self._writer is None:
            return None
        self._writer.release()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.release()
        self.tmp.unlink(missing_ok=True)


def annotate(frame: np.ndarray, snap, control, events: list[str]) -> np.ndarray:
    """A copy of the frame with a status line, steer/accel bars and recent events."""
    img = frame.copy()
    h, w = img.shape[:2]
    cmd = COMMAND_NAMES.get(int(snap.ego.command), "?")
    text = f"t {snap.time_s:5.1f} s  {cmd:<15} {snap.ego.speed_mps * 3.6:5.1f} km/h"
    cv2.rectangle(img, (0, 0), (w, 22), (0, 0, 0), -1)
    cv2.putText(img, text, (6, 16), _FONT, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    # Steer bar (centre = straight, right = +1) and accel bar (green throttle, red brake).
    cx, y0 = w // 2, h - 16
    cv2.rectangle(img, (cx - 100, y0), (cx + 100, y0 + 6), (40, 40, 40), -1)
    sx = int(cx + 100 * float(np.clip(control.steer, -1, 1)))
    cv2.rectangle(img, (min(cx, sx), y0), (max(cx, sx), y0 + 6), (255, 255, 255), -1)
    a = float(np.clip(control.accel, -1, 1))
    ax = int(cx + 100 * a)
    cv2.rectangle(img, (cx - 100, y0 + 8), (cx + 100, y0 + 14), (40, 40, 40), -1)
    cv2.rectangle(img, (min(cx, ax), y0 + 8), (max(cx, ax), y0 + 14), (60, 220, 90) if a >= 0 else (230, 60, 50), -1)
    for i, ev in enumerate(events[-3:]):
        y = 44 + 22 * i
        (tw, th), _ = cv2.getTextSize(ev, _FONT, 0.6, 2)
        cv2.rectangle(img, (w - tw - 16, y - th - 6), (w - 4, y + 6), (200, 30, 30), -1)
        cv2.putText(img, ev, (w - tw - 10, y), _FONT, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    return img
