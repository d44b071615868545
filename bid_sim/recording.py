"""Episode recordings in MCAP: the writer used while driving, the reader used by training,
re-rendering and viewing, and salvage of a file whose writer was killed.

One file per episode, written as NAME.mcap.partial and renamed to NAME.mcap when the
episode ends cleanly. Topics (DESIGN.md section 8), one message each per 0.1 s step with
log_time = step × 100 ms:

| topic          | encoding | schema                   | content                                  |
|----------------|----------|--------------------------|------------------------------------------|
| /camera/rgb    | protobuf | foxglove.CompressedImage | JPEG of the 900×300 frame                |
| /ego/control   | json     | bid.Control              | steer, accel, throttle, brake            |
| /ego/state     | json     | bid.EgoState             | the snapshot's EgoView, time, step       |
| /nav/command   | json     | bid.Command              | command id (CARLA RoadOption) and name   |
| /scene         | protobuf | foxglove.SceneUpdate     | ego, vehicles, pedestrians as boxes,     |
|                |          |                          | signal heads coloured by state           |
| /tf            | protobuf | foxglove.FrameTransform  | world -> ego                             |

Foxglove's well-known protobuf schemas make a recording open in Foxglove as it is (Image
panel: /camera/rgb; 3D panel: /scene, /tf). Exact values needed to re-render a step (yaw,
colour index, speed, light codes) ride in the scene entities' metadata, so a snapshot read
back renders to the same pixels. Episode facts are an MCAP metadata record "episode"
written first; the outcome is a metadata record "result" written last.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from bid_sim.ego import Control
from bid_sim.errors import BidError
from bid_sim.render.geometry import SHIRTS, VEHICLE_COLOURS
from bid_sim.routes import COMMAND_NAMES
from bid_sim.snapshot import GREEN, OFF, RED, YELLOW, Actors, EgoView, Snapshot

STEP_NS = 100_000_000
PARTIAL = ".partial"
JPEG_QUALITY = 90
CHUNK_BYTES = 256 * 1024  # a few frames: a crash loses well under a second
_LIGHT_RGBA = {RED: (1.0, 0.1, 0.1, 1.0), YELLOW: (1.0, 0.8, 0.1, 1.0), GREEN: (0.1, 0.9, 0.3, 1.0),
               OFF: (0.2, 0.2, 0.2, 1.0)}

_JSON_SCHEMAS = {
    "bid.Control": {"type": "object", "properties": {
        "steer": {"type": "number", "description": "[-1, 1], +1 full right"},
        "accel": {"type": "number", "description": "[-1, 1], < 0 brakes"},
        "throttle": {"type": "number"}, "brake": {"type": "number"}}},
    "bid.EgoState": {"type": "object", "properties": {
        "time_s": {"type": "number"}, "step": {"type": "integer"},
        **{f.name: {"type": "string" if f.type in (str, "str") else "number"} for f in dataclasses.fields(EgoView)},
        "next_light_state": {"type": "integer"}, "next_light_dist_m": {"type": "number"}}},
    "bid.Command": {"type": "object", "properties": {
        "id": {"type": "integer", "description": "CARLA RoadOption: 1 LEFT, 2 RIGHT, 3 STRAIGHT, "
                                                 "4 LANEFOLLOW, 5 CHANGELANELEFT, 6 CHANGELANERIGHT"},
        "name": {"type": "string"}}},
}


def partial_path(path: Path) -> Path:
    return path.with_name(path.name + PARTIAL)


def _stamp(step: int) -> Timestamp:
    ns = step * STEP_NS
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _quat(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _finite_json(v: float) -> float | None:
    return v if math.isfinite(v) else None


class EpisodeWriter:
    """Writes one episode; also the recorder run_episode calls each step (``write``).

    ``finish(result)`` completes the file and renames it into place; ``abort()`` closes it
    and leaves the .partial (salvageable with ``recover``).
    """

    def __init__(self, path: str | os.PathLike, facts: dict[str, str], signal_xyz: np.ndarray,
                 jpeg_quality: int = JPEG_QUALITY):
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.signal_xyz = np.asarray(signal_xyz, dtype=np.float64).reshape(-1, 3)
        self.jpeg_quality = int(jpeg_quality)
        self.frames = 0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self.partial.open("wb")
        except OSError as e:
            raise BidError(f"cannot write {self.partial} ({e.strerror}); pick a writable --out folder") from e
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="bid-sim")
        self._channels: dict[str, int] = {}
        for topic, msg in (("/camera/rgb", CompressedImage), ("/scene", SceneUpdate), ("/tf", FrameTransform)):
            sid = register_schema(self._writer, msg)
            self._channels[topic] = self._writer.register_channel(topic, "protobuf", sid)
        for topic, name in (("/ego/control", "bid.Control"), ("/ego/state", "bid.EgoState"),
                            ("/nav/command", "bid.Command")):
            sid = self._writer.register_schema(name, "jsonschema", json.dumps(_JSON_SCHEMAS[name]).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        self._writer.add_metadata("episode", {k: str(v) for k, v in facts.items()})

    # The recorder protocol of run_episode.
    def write(self, snap: Snapshot, frame: np.ndarray | None, control: Control) -> None:
        t = snap.step * STEP_NS
        stamp = _stamp(snap.step)
        try:
            if frame is not None:
                ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR),
                                       [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
                if not ok:
                    raise BidError(f"JPEG encoding failed at step {snap.step}")
                self._put("/camera/rgb", CompressedImage(timestamp=stamp, frame_id="ego", data=jpg.tobytes(),
                                                         format="jpeg").SerializeToString(), t)
                self.frames += 1
            c = control
            self._put_json("/ego/control", {"steer": float(c.steer), "accel": float(c.accel),
                                            "throttle": float(c.throttle), "brake": float(c.brake)}, t)
            state = {"time_s": snap.time_s, "step": snap.step, **dataclasses.asdict(snap.ego),
                     "next_light_state": int(snap.next_light_state),
                     "next_light_dist_m": _finite_json(float(snap.next_light_dist_m))}
            self._put_json("/ego/state", state, t)
            cmd = int(snap.ego.command)
            self._put_json("/nav/command", {"id": cmd, "name": COMMAND_NAMES.get(cmd, "UNKNOWN")}, t)
            self._put("/scene", self._scene(snap, stamp).SerializeToString(), t)
            e = snap.ego
            tf = FrameTransform(timestamp=stamp, parent_frame_id="world", child_frame_id="ego",
                                translation=Vector3(x=e.x_m, y=e.y_m, z=0.0), rotation=_quat(e.yaw_rad))
            self._put("/tf", tf.SerializeToString(), t)
        except OSError as e:
            raise BidError(f"writing {self.partial} failed ({e.strerror}); free disk space or pick "
                           "another --out, then re-run: finished episodes are kept") from e

    def _put(self, topic: str, data: bytes, t: int) -> None:
        self._writer.add_message(self._channels[topic], log_time=t, data=data, publish_time=t)

    def _put_json(self, topic: str, obj: dict, t: int) -> None:
        self._put(topic, json.dumps(obj, separators=(",", ":")).encode(), t)

    def _scene(self, snap: Snapshot, stamp: Timestamp) -> SceneUpdate:
        """Boxes of the ego, vehicles and pedestrians, and the signal heads coloured by state
        (fields set in place: much faster than building nested messages)."""
        update = SceneUpdate()
        e = snap.ego
        _add_box(update, "ego", stamp, e.x_m, e.y_m, e.yaw_rad, (e.length_m, e.width_m, e.height_m),
                 (0.95, 0.95, 0.95, 1.0), ())
        for kind, actors in (("vehicle", snap.vehicles), ("pedestrian", snap.pedestrians)):
            palette = VEHICLE_COLOURS if kind == "vehicle" else SHIRTS
            xy, yaw, size, speed = actors.xy.tolist(), actors.yaw_rad.tolist(), actors.size.tolist(), actors.speed_mps.tolist()
            for i, aid in enumerate(actors.ids):
                ci = int(actors.colour[i])
                rgb = palette[ci % len(palette)] / 255.0
                _add_box(update, f"{kind}/{aid}", stamp, xy[i][0], xy[i][1], yaw[i], size[i], (*rgb, 1.0),
                         (("kind", kind), ("yaw", repr(yaw[i])), ("colour", str(ci)), ("speed_mps", repr(speed[i]))))
        states = np.asarray(snap.light_states, dtype=np.uint8)
        lights = update.entities.add()
        lights.timestamp.CopyFrom(stamp)
        lights.frame_id, lights.id = "world", "signals"
        kv = lights.metadata.add()
        kv.key, kv.value = "states", "".join(str(int(v)) for v in states)
        for (x, y, z), st in zip(self.signal_xyz.tolist(), states.tolist(), strict=False):
            c = lights.cubes.add()
            p = c.pose.position
            p.x, p.y, p.z = x, y, z
            c.pose.orientation.w = 1.0
            c.size.x, c.size.y, c.size.z = 0.4, 0.4, 1.0
            col = c.color
            col.r, col.g, col.b, col.a = _LIGHT_RGBA.get(st, _LIGHT_RGBA[OFF])
        return update

    def finish(self, result: dict | None = None) -> Path:
        """Completes the file (summary, index) and renames it into place."""
        try:
            if result is not None:
                self._writer.add_metadata("result", {k: v if isinstance(v, str) else json.dumps(v)
                                                     for k, v in result.items()})
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.partial, self.path)
        except OSError as e:
            raise BidError(f"finishing {self.path} failed ({e.strerror}); free disk space or pick "
                           "another --out, then re-run: finished episodes are kept") from e
        return self.path

    def abort(self) -> None:
        """Closes the file as it is: the .partial stays for `bid recover`."""
        try:
            self._file.close()
        except OSError:
            pass


def _add_box(update: SceneUpdate, eid: str, stamp: Timestamp, x: float, y: float, yaw: float, size,
             rgba, meta) -> None:
    length, width, height = size
    ent = update.entities.add()
    ent.timestamp.CopyFrom(stamp)
    ent.frame_id, ent.id = "world", eid
    cube = ent.cubes.add()
    p = cube.pose.position
    p.x, p.y, p.z = x, y, height / 2.0
    q = cube.pose.orientation
    q.z, q.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)
    cube.size.x, cube.size.y, cube.size.z = length, width, height
    col = cube.color
    col.r, col.g, col.b, col.a = (float(v) for v in rgba)
    for k, v in meta:
        kv = ent.metadata.add()
        kv.key, kv.value = k, v


# ----------------------------------------------------------------------------- reading

@dataclass
class Episode:
    """What a recording holds, per step with a camera frame (arrays are parallel)."""

    path: Path
    facts: dict[str, str]
    result: dict[str, str] | None
    steps: np.ndarray  # (N,) int
    jpeg: list[bytes]  # (N,) JPEG frames (empty when read with frames=False)
    steer: np.ndarray  # (N,) float32
    accel: np.ndarray
    speed_mps: np.ndarray
    command: np.ndarray  # (N,) int64, 1..6
    states: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.steps)


def _open_reader(path: Path):
    if not path.exists():
        raise BidError(f"{path} does not exist")
    if path.name.endswith(PARTIAL):
        raise BidError(f"{path} is an unfinished recording; salvage it with `bid recover {path}`")
    f = path.open("rb")
    try:
        reader = make_reader(f)
        reader.get_summary()
    except (McapError, ValueError, EOFError, OSError, KeyError, AssertionError) as e:
        f.close()
        raise BidError(f"{path} is truncated or corrupt ({type(e).__name__}); salvage it with "
                       f"`bid recover {path}` or delete it") from e
    return f, reader


def _metadata(reader) -> dict[str, dict[str, str]]:
    return {m.name: dict(m.metadata) for m in reader.iter_metadata()}


def read_episode(path: str | os.PathLike, frames: bool = True) -> Episode:
    """Reads a finished recording (BidError naming the file if it is unfinished or corrupt)."""
    path = Path(path)
    f, reader = _open_reader(path)
    try:
        meta = _metadata(reader)
        topics = ["/ego/control", "/ego/state", "/nav/command"] + (["/camera/rgb"] if frames else [])
        by_step: dict[int, dict] = {}
        for _schema, channel, msg in reader.iter_messages(topics=topics):
            step = msg.log_time // STEP_NS
            rec = by_step.setdefault(step, {})
            if channel.topic == "/camera/rgb":
                rec["jpeg"] = CompressedImage.FromString(msg.data).data
            else:
                rec[channel.topic] = json.loads(msg.data)
    except (McapError, ValueError, EOFError, KeyError, AssertionError) as e:
        raise BidError(f"{path} is corrupt ({type(e).__name__}: {e}); salvage it with `bid recover {path}` "
                       "or delete it") from e
    finally:
        f.close()
    if "episode" not in meta:
        raise BidError(f"{path} has no 'episode' metadata: not a bid-sim recording")
    steps = sorted(s for s, r in by_step.items() if ("jpeg" in r or not frames) and "/ego/control" in r
                   and "/ego/state" in r and "/nav/command" in r)
    recs = [by_step[s] for s in steps]
    return Episode(
        path=path, facts=meta["episode"], result=meta.get("result"),
        steps=np.array(steps, dtype=np.int64),
        jpeg=[r["jpeg"] for r in recs] if frames else [],
        steer=np.array([r["/ego/control"]["steer"] for r in recs], dtype=np.float32),
        accel=np.array([r["/ego/control"]["accel"] for r in recs], dtype=np.float32),
        speed_mps=np.array([r["/ego/state"]["speed_mps"] for r in recs], dtype=np.float32),
        command=np.array([r["/nav/command"]["id"] for r in recs], dtype=np.int64),
        states=[r["/ego/state"] for r in recs],
    )


def decode_jpeg(data: bytes) -> np.ndarray:
    """RGB uint8 frame from JPEG bytes."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise BidError("a camera frame is not a decodable JPEG")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_facts(path: str | os.PathLike) -> dict[str, str]:
    """The episode facts of a finished recording (town, weather, ...)."""
    path = Path(path)
    f, reader = _open_reader(path)
    try:
        meta = _metadata(reader)
    finally:
        f.close()
    if "episode" not in meta:
        raise BidError(f"{path} has no 'episode' metadata: not a bid-sim recording")
    return meta["episode"]


def read_snapshots(path: str | os.PathLike) -> Iterator[tuple[Snapshot, Control]]:
    """The scene state of every step (enough to re-render it) with the control taken."""
    path = Path(path)
    f, reader = _open_reader(path)
    try:
        pending: dict[int, dict] = {}
        for _schema, channel, msg in reader.iter_messages(topics=["/ego/state", "/scene", "/ego/control"]):
            step = msg.log_time // STEP_NS
            rec = pending.setdefault(step, {})
            rec[channel.topic] = msg.data
            if len(rec) == 3:
                del pending[step]
                yield _snapshot(rec), Control(**{k: v for k, v in json.loads(rec["/ego/control"]).items()
                                                 if k in ("steer", "accel")})
    except (McapError, ValueError, EOFError, KeyError, AssertionError) as e:
        raise BidError(f"{path} is corrupt ({type(e).__name__}: {e}); salvage it with `bid recover {path}`") from e
    finally:
        f.close()


def _snapshot(rec: dict[str, bytes]) -> Snapshot:
    state = json.loads(rec["/ego/state"])
    ego = EgoView(**{f.name: state[f.name] for f in dataclasses.fields(EgoView)})
    scene = SceneUpdate.FromString(rec["/scene"])
    rows: dict[str, list] = {"vehicle": [], "pedestrian": []}
    lights = np.zeros(0, np.uint8)
    for ent in scene.entities:
        meta = {kv.key: kv.value for kv in ent.metadata}
        if ent.id == "signals":
            lights = np.array([int(c) for c in meta.get("states", "")], dtype=np.uint8)
        elif "kind" in meta:
            cube = ent.cubes[0]
            p, s = cube.pose.position, cube.size
            rows[meta["kind"]].append((ent.id.split("/", 1)[1], p.x, p.y, float(meta["yaw"]),
                                       float(meta["speed_mps"]), (s.x, s.y, s.z), int(meta["colour"])))
    return Snapshot(time_s=state["time_s"], step=state["step"], ego=ego, vehicles=_actors(rows["vehicle"]),
                    pedestrians=_actors(rows["pedestrian"]), light_states=lights,
                    next_light_state=state.get("next_light_state", OFF),
                    next_light_dist_m=state.get("next_light_dist_m") or float("inf"))


def _actors(rows: list) -> Actors:
    if not rows:
        return Actors.empty()
    return Actors(tuple(r[0] for r in rows), np.array([(r[1], r[2]) for r in rows]), np.array([r[3] for r in rows]),
                  np.array([r[4] for r in rows]), np.array([r[5] for r in rows]), np.array([r[6] for r in rows], dtype=int))


# ----------------------------------------------------------------------------- salvage

def recover(path: str | os.PathLike) -> tuple[Path, int]:
    """Salvages a recording whose writer died: every complete record up to the damage is
    copied into a finished file (NAME.mcap for NAME.mcap.partial, else NAME.recovered.mcap)
    marked result status 'recovered'. Returns the new path and the steps kept."""
    src = Path(path)
    if not src.exists():
        raise BidError(f"{src} does not exist")
    if src.name.endswith(PARTIAL):
        dst = src.with_name(src.name[: -len(PARTIAL)])
    else:
        dst = src.with_name(src.name.removesuffix(".mcap") + ".recovered.mcap")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[Message] = []
    metadata: list[Metadata] = []
    with src.open("rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    messages.append(rec)
                elif isinstance(rec, Metadata):
                    metadata.append(rec)
        except Exception as e:  # any damage: keep what came before it
            if not messages and not metadata:
                raise BidError(f"{src} holds nothing readable ({type(e).__name__}); delete it and re-record") from e
    if not any(m.name == "episode" for m in metadata):
        raise BidError(f"{src} has no episode facts: not a bid-sim recording, or damaged at its start")
    # Keep only whole steps: every topic present.
    by_step: dict[int, set[str]] = {}
    for m in messages:
        if m.channel_id in channels:
            by_step.setdefault(m.log_time // STEP_NS, set()).add(channels[m.channel_id].topic)
    needed = {c.topic for c in channels.values()}
    whole = {s for s, t in by_step.items() if t >= needed}
    tmp = partial_path(dst).with_name(partial_path(dst).name + ".tmp")
    with tmp.open("wb") as out:
        w = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="", library="bid-sim recover")
        schema_ids = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()}
        chan_ids = {cid: w.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), c.metadata)
                    for cid, c in channels.items()}
        for md in metadata:
            if md.name != "result":
                w.add_metadata(md.name, md.metadata)
        for m in messages:
            if m.channel_id in chan_ids and m.log_time // STEP_NS in whole:
                w.add_message(chan_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        kept = len(whole)
        w.add_metadata("result", {"status": "recovered", "steps": str(kept), "source": src.name})
        w.finish()
    os.replace(tmp, dst)
    if src.name.endswith(PARTIAL):
        src.unlink()
    return dst, kept
