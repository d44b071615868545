"""`bid view`: frames for a person to look at, as a PNG (one frame, or one frame under
several weathers stacked) or an MP4 (a drive).

Snapshots come from a real episode (SUMO traffic, the chosen scripted agent driving).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from bid_sim.errors import BidError
from bid_sim.render.pool import RenderPool
from bid_sim.snapshot import Snapshot
from bid_sim.towns import resolve_town
from bid_sim.weather import WEATHERS, check_weather

VIDEO_FPS = 10  # one frame per 0.1 s simulation step: real time


class _Collect:
    def __init__(self, keep) -> None:
        self.keep = keep
        self.snaps: list[Snapshot] = []

    def write(self, snap: Snapshot, frame, control) -> None:
        if self.keep(snap.step):
            self.snaps.append(snap)


def episode_snapshots(town: str, route: int, density: str, seed: int, agent, steps: int,
                      keep=lambda step: True) -> list[Snapshot]:
    """Snapshots of the first `steps` steps of an episode (fewer if it ends sooner)."""
    from bid_sim.episode import run_episode

    rec = _Collect(keep)
    run_episode(town, route, "ClearNoon", density, seed, agent, recorder=rec, max_steps=steps)
    return rec.snaps


def label(frame: np.ndarray, text: str) -> np.ndarray:
    """A copy of the frame with a caption in its top-left corner."""
    out = frame.copy()
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.5
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    cv2.rectangle(out, (4, 4), (12 + w, 12 + h + base), (0, 0, 0), -1)
    cv2.putText(out, text, (8, 8 + h), font, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_png(frame: np.ndarray, path: str | os.PathLike) -> None:
    """An RGB frame as a PNG (written next to the target, then moved into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    if not ok:
        raise BidError(f"could not encode {path} as PNG")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)


def write_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = VIDEO_FPS) -> int:
    """RGB frames as an MP4 (MPEG-4 part 2, plays everywhere); returns the frame count."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.mp4")
    writer = None
    n = 0
    try:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
                if not writer.isOpened():
                    raise BidError(f"OpenCV cannot write MP4 to {path}; write a .png instead")
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            n += 1
    finally:
        if writer is not None:
            writer.release()
    if n == 0:
        tmp.unlink(missing_ok=True)
        raise BidError("no frames to write: the episode ended before its first step")
    os.replace(tmp, path)
    return n


def view(town: str, route: int, density: str, seed: int, weather: str, out: str, agent,
         step: int = 50, steps: int = 200, workers: int = 1) -> str:
    """Writes `out` (.png: the frame at `step`; .mp4: the first `steps` frames) and returns a
    one-line summary. weather may be 'all' (PNG only): the six weathers stacked."""
    suffix = Path(out).suffix.lower()
    if suffix not in (".png", ".mp4"):
        raise BidError(f"--out {out!r}: write a .png (one frame) or an .mp4 (a drive)")
    weathers = list(WEATHERS) if weather == "all" else [check_weather(weather)]
    t = resolve_town(town)
    if suffix == ".png":
        snaps = episode_snapshots(town, route, density, seed, agent, step + 1, keep=lambda s: s == step)
        if not snaps:
            raise BidError(f"the episode ended before step {step}; pick an earlier --step")
        rows = []
        for w in weathers:
            with RenderPool(t, w, workers=1, seed=seed) as pool:
                frame = next(pool.map(snaps))
            rows.append(label(frame, f"{t.name} {w} step {step}") if len(weathers) > 1 else frame)
        write_png(np.vstack(rows), out)
        return f"wrote {out}: {len(weathers)} frame(s) of {rows[0].shape[1]}x{rows[0].shape[0]} px"
    if len(weathers) > 1:
        raise BidError("--weather all makes a PNG; pick one weather for an MP4")
    snaps = episode_snapshots(town, route, density, seed, agent, steps)
    with RenderPool(t, weathers[0], workers=workers, seed=seed) as pool:
        n = write_mp4(pool.map(snaps), out)
    return f"wrote {out}: {n} frames at {VIDEO_FPS} fps ({n / VIDEO_FPS:.1f} s)"


def rerender(src: str | os.PathLike, weather: str, out: str | os.PathLike, workers: int = 1,
             seed: int | None = None) -> str:
    """Re-renders a recording (or a folder of them) from its scene states under another
    weather, into a new recording with the same steps, controls and states."""
    from bid_sim.recording import EpisodeWriter, read_facts, read_snapshots
    from bid_sim.town_map import load_town_map

    check_weather(weather)
    src, out = Path(src), Path(out)
    if src.is_dir():
        files = sorted(src.glob("*.mcap"))
        if not files:
            raise BidError(f"{src} holds no finished recordings (*.mcap)")
        pairs = [(f, out / f.name.replace(read_facts(f)["weather"], weather)) for f in files]
    else:
        if out.suffix != ".mcap":
            raise BidError(f"--out {out}: give a .mcap file (or a folder when re-rendering a folder)")
        pairs = [(src, out)]
    frames = 0
    for f, dst in pairs:
        facts = read_facts(f)
        # town_source: the --town the recording was made with (01, 02, 05 or a folder).
        town = resolve_town(facts.get("town_source") or facts["town"].removeprefix("Town"))
        heads = [h.position for h in load_town_map(town).signal_heads]
        ep_seed = int(facts.get("seed", 0)) if seed is None else seed
        writer = EpisodeWriter(dst, {**facts, "weather": weather, "rendered_from": f.name}, heads)
        try:
            steps = list(read_snapshots(f))
            with RenderPool(town, weather, workers=workers, seed=ep_seed) as pool:
                for (snap, control), frame in zip(steps, pool.map(s for s, _ in steps), strict=True):
                    writer.write(snap, frame, control)
        except BaseException:
            writer.abort()
            raise
        writer.finish({"status": "rerendered", "steps": len(steps)})
        frames += writer.frames
    return f"re-rendered {len(pairs)} recording(s), {frames} frames under {weather} -> {out}"


def view_recording(path: str | os.PathLike, out: str, step: int | None = None, sheet: int = 6) -> str:
    """A recording's frames as recorded: an MP4 of all, a PNG of one step, or (PNG without a
    step) a contact sheet of `sheet` frames spread over the episode, captioned."""
    from bid_sim.recording import decode_jpeg, read_episode
    from bid_sim.routes import COMMAND_NAMES

    suffix = Path(out).suffix.lower()
    if suffix not in (".png", ".mp4"):
        raise BidError(f"--out {out!r}: write a .png (one frame or a contact sheet) or an .mp4")
    ep = read_episode(path)
    if len(ep) == 0:
        raise BidError(f"{path} holds no camera frames")
    if suffix == ".mp4":
        n = write_mp4((decode_jpeg(j) for j in ep.jpeg), out)
        return f"wrote {out}: {n} frames at {VIDEO_FPS} fps ({n / VIDEO_FPS:.1f} s)"
    if step is not None:
        hit = np.flatnonzero(ep.steps == step)
        if len(hit) == 0:
            raise BidError(f"{path} has steps {ep.steps[0]}..{ep.steps[-1]}; step {step} is not among them")
        idx = [int(hit[0])]
    else:
        idx = sorted({round(v) for v in np.linspace(0, len(ep) - 1, min(sheet, len(ep)))})
    rows = [label(decode_jpeg(ep.jpeg[i]), f"{ep.facts.get('town', '')} {ep.facts.get('weather', '')} step "
                  f"{ep.steps[i]}  {COMMAND_NAMES.get(int(ep.command[i]), '?')}  speed {ep.speed_mps[i]:.1f} m/s  "
                  f"steer {ep.steer[i]:+.2f}  accel {ep.accel[i]:+.2f}") for i in idx]
    write_png(np.vstack(rows), out)
    return f"wrote {out}: {len(rows)} frame(s) from {Path(path).name}"
