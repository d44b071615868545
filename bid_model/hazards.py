"""What stands in the ego's path: the targets of the auxiliary hazard head (`bid train --hazard`).

The shipped BID could not tell a pedestrian in its path from one beside it (docs/experiments.md,
"The shipped BID probed"): it drove into crossings the expert held at. The recordings know the
answer: `/scene` holds every actor's box, and the ego's own poses later in the episode hold the
path it drove. For each frame, the path is the next HAZARD_AHEAD_M metres of that trajectory
(straight on along the last heading past the episode's end), a corridor the ego's half width
plus CORRIDOR_MARGIN_M either side of it; an actor whose footprint enters the corridor is in the
path, at the arc length where it first does, from the ego's front bumper. A frame's targets are
the distances to the nearest pedestrian and the nearest vehicle in the path, capped at
HAZARD_AHEAD_M (nothing in the path within it), and (light_distance) to the stop line of a red
or amber light on the route, from the frame's recorded /ego/state.

Footprints are three discs along an actor's length (one for a pedestrian, whose box is square):
a stadium as wide as the box, close enough for a 4.6 m car beside a 3.5 m lane.

With `ped_ahead_s` (`bid train --hazard-ahead S`) a pedestrian also counts where it will be: one
that the recording shows in the path ahead of the ego within S seconds (looked at every
AHEAD_STEP_S) is in the path now, at the distance from the ego's front to where it will be. A
pedestrian about to step off the kerb, or walking across the street a turn leads into, is
what the expert brakes for (within 3 s); by where it is now it enters the targets only as it
steps into the corridor.

The fourth target (`crossing_distances`, `bid train --hazard-crossing`) is the distance from the
ego's front to where its path enters the nearest pedestrian crossing that has a pedestrian on it
(or walking onto it within ONTO_S), not counting one walking away from the path beside the
corridor, nor a crossing the front is already on. Those waiting for their green stand at its
end, within 0.1 m of it but not on it: they do not count until they walk. It is where the
expert stops for a pedestrian crossing (2 m before it): the BID's first pedestrian contacts in
Town02 were all on crossings, most just after it moved off on green with people still on
the stripes (docs/experiments.md).
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import Polygon

from bid_model.config import PATH_KINDS
from bid_sim.errors import BidError
from bid_sim.parallel import map_parallel
from bid_sim.recording import read_facts, read_snapshots
from bid_sim.snapshot import GREEN, RED, YELLOW, Actors, Snapshot

log = logging.getLogger(__name__)

HAZARD_AHEAD_M = 25.0  # how far along the path to look: about 2 s at Town01's 11 m/s, and a stop
CORRIDOR_MARGIN_M = 0.4  # beyond the ego's half width: a pedestrian on the kerb is not in the path
PATH_STEP_M = 0.5  # spacing of the path's sample points
# The hazard head's nearness (1 - distance / HAZARD_AHEAD_M) from which an actor counts as seen
# in the path, within 20 of the 25 m: where `bid evaluate --hazard-brake` / `--vehicle-brake` start.
SEEN_NEARNESS = 0.2
NEAR_M = 10.0  # an actor in the path this close must be seen (the validation's detection rate)
AHEAD_STEP_S = 0.5  # with ped_ahead_s, where pedestrians will be is looked at this often
_VERSION = "hazard-v1"  # part of the cache key: bump when the definition changes
ONTO_S = 1.0  # a pedestrian walking onto a crossing within this long is on it already
WALKING_MPS = 0.3  # slower is standing
# A standing ego's front this near a light's stop line, or past it, stands at the line (train
# --hazard-green-weight, bid probe's "stop line"): the expert stands 0.5-1.5 m before a red one.
AT_LINE_M = 3.0
AWAY_M = 0.5  # beyond the corridor by this, a pedestrian walking away from the path is no one's
_CROSSING_VERSION = "crossing-v2"
_BUMPER_VERSION = "bumper-v1"
BUMPER_MAX_CURVATURE = 0.25  # 1/m: a tighter turn than Town02's (radius 4 m) is yaw-rate noise
BUMPER_MOVING_MPS = 0.5  # slower, the yaw rate over the speed says little: the arc is straight on


def nearness_m(nearness: float) -> float:
    """The distance (m) along the path that a hazard nearness (1 − distance / HAZARD_AHEAD_M, as
    recordings.hazard_nearness gives it) stands for; a reading above 1 is touching."""
    return (1.0 - min(nearness, 1.0)) * HAZARD_AHEAD_M


def _path_points(xy: np.ndarray, s: np.ndarray, s0: float) -> np.ndarray:
    """(Q, 2) points of the trajectory (xy at arc lengths s, strictly increasing) from s0 on."""
    q = s0 + np.arange(0.0, HAZARD_AHEAD_M + PATH_STEP_M / 2, PATH_STEP_M)
    return np.stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])], axis=1)


def _discs(actors: Actors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (3A, 2), radii (3A,), actor of each disc (3A,)): three discs along each box."""
    n = len(actors)
    length, width = actors.size[:, 0], actors.size[:, 1]
    half_gap = np.maximum(length / 2 - width / 2, 0.0)
    heading = np.stack([np.cos(actors.yaw_rad), np.sin(actors.yaw_rad)], axis=1)
    offsets = np.array([-1.0, 0.0, 1.0])
    centres = actors.xy[:, None, :] + offsets[None, :, None] * (half_gap[:, None, None] * heading[:, None, :])
    return (centres.reshape(-1, 2), np.repeat(width / 2, 3), np.repeat(np.arange(n), 3))


def _nearest_in_path(actors: Actors, path: np.ndarray, half_width: float, front_m: float) -> float:
    """Distance from the ego's front along `path` to the first actor in its corridor (HAZARD_AHEAD_M: none)."""
    if len(actors) == 0:
        return HAZARD_AHEAD_M
    near = np.linalg.norm(actors.xy - path[0], axis=1) < HAZARD_AHEAD_M + 10.0
    if not near.any():
        return HAZARD_AHEAD_M
    sub = Actors(tuple(i for i, k in zip(actors.ids, near, strict=True) if k), actors.xy[near],
                 actors.yaw_rad[near], actors.speed_mps[near], actors.size[near], actors.colour[near])
    centres, radii, _ = _discs(sub)
    gap = np.linalg.norm(centres[:, None, :] - path[None, :, :], axis=2) - radii[:, None]  # (3A, Q)
    inside = (gap < half_width).any(axis=0)  # (Q,) path points with an actor in the corridor
    if not inside.any():
        return HAZARD_AHEAD_M
    s = float(np.argmax(inside)) * PATH_STEP_M
    return float(np.clip(s - front_m, 0.0, HAZARD_AHEAD_M))


def light_distance(state: dict) -> float:
    """Metres from the ego's front to the stop line of the red or amber light on its route, from
    a recorded /ego/state (HAZARD_AHEAD_M: none, or farther): the hazard head's third target."""
    dist = state.get("next_light_dist_m")
    if state.get("next_light_state") not in (RED, YELLOW) or dist is None:
        return HAZARD_AHEAD_M
    return float(np.clip(dist, 0.0, HAZARD_AHEAD_M))


def green_distance(state: dict) -> float:
    """Metres from the ego's front to the stop line of the green light on its route, from a
    recorded /ego/state (negative: the front is past it; HAZARD_AHEAD_M: none, or farther). Not a
    target: where the ego stands at a green line the red-light target is none, and the light
    output read red there (`bid train --hazard-green-weight`, docs/experiments.md)."""
    dist = state.get("next_light_dist_m")
    if state.get("next_light_state") != GREEN or dist is None:
        return HAZARD_AHEAD_M
    return float(min(dist, HAZARD_AHEAD_M))


def _trajectory(snaps: list[Snapshot]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xy (T, 2), arc length s (T,), and both extended straight on past the end along the last
    heading, strictly increasing for np.interp) of an episode's ego poses."""
    xy = np.array([(s.ego.x_m, s.ego.y_m) for s in snaps], dtype=np.float64)
    s_all = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    last = snaps[-1].ego
    tail = xy[-1] + 2 * HAZARD_AHEAD_M * np.array([np.cos(last.yaw_rad), np.sin(last.yaw_rad)])
    xy_ext, s_ext = np.vstack([xy, tail]), np.r_[s_all, s_all[-1] + 2 * HAZARD_AHEAD_M]
    # np.interp needs strictly increasing arc lengths: a standing ego repeats its pose.
    keep = np.r_[True, np.diff(s_ext) > 1e-6]
    return xy, s_all, xy_ext[keep], s_ext[keep]


def _path_of(t: int, xy: np.ndarray, s_all: np.ndarray, xy_ext: np.ndarray, s_ext: np.ndarray) -> np.ndarray:
    path = _path_points(xy_ext, s_ext, s_all[t])
    path[0] = xy[t]  # the ego itself, not the first pose after a standstill's jitter
    return path


def path_hazards(snaps: list[Snapshot], ped_ahead_s: float = 0.0) -> np.ndarray:
    """(T, 2) float32: per snapshot (one episode, in step order) the distance in metres from
    the ego's front to the nearest pedestrian and vehicle in its path (HAZARD_AHEAD_M: none);
    with `ped_ahead_s`, pedestrians also where they will be in the path ahead of the ego within
    that many seconds (see the module's docstring)."""
    out = np.full((len(snaps), len(PATH_KINDS)), HAZARD_AHEAD_M, dtype=np.float32)
    if not snaps:
        return out
    traj = _trajectory(snaps)
    s_all = traj[1]
    for t, snap in enumerate(snaps):
        path = _path_of(t, *traj)
        half_width = snap.ego.width_m / 2 + CORRIDOR_MARGIN_M
        front = snap.ego.length_m / 2
        out[t] = (_nearest_in_path(snap.pedestrians, path, half_width, front),
                  _nearest_in_path(snap.vehicles, path, half_width, front))
    if ped_ahead_s > 0:
        # Where the path ahead of the ego at a later snapshot u meets a pedestrian then is that
        # snapshot's own target; counted from the front at t, it is the distance driven on top.
        times = np.array([s.time_s for s in snaps])
        offsets = AHEAD_STEP_S * np.arange(1, int(ped_ahead_s / AHEAD_STEP_S + 1e-9) + 1)
        now = out[:, 0].copy()
        for t in range(len(snaps)):
            for u in np.searchsorted(times, times[t] + offsets - 1e-6):
                if u >= len(snaps):
                    break
                if now[u] < HAZARD_AHEAD_M:
                    out[t, 0] = min(out[t, 0], s_all[u] - s_all[t] + now[u], HAZARD_AHEAD_M)
    return out


def _arc(x: float, y: float, yaw: float, curvature: float, length_m: float) -> np.ndarray:
    """(Q, 2) points every PATH_STEP_M along a circular arc of `curvature` (1/m, + left) from
    (x, y) at heading `yaw`, `length_m` long (a straight line at curvature 0)."""
    s = np.arange(0.0, length_m + PATH_STEP_M / 2, PATH_STEP_M)
    if abs(curvature) < 1e-6:
        return np.stack([x + s * np.cos(yaw), y + s * np.sin(yaw)], axis=1)
    turned = yaw + curvature * s
    return np.stack([x + (np.sin(turned) - np.sin(yaw)) / curvature,
                     y - (np.cos(turned) - np.cos(yaw)) / curvature], axis=1)


def bumper_vehicles(snaps: list[Snapshot], ahead_m: float) -> np.ndarray:
    """(T,) float32: per snapshot (one episode, in step order) the distance in metres from the
    ego's front to the nearest vehicle in the corridor along the arc its heading and turn now
    lead along, within `ahead_m` of the front (HAZARD_AHEAD_M: none; see the module's docstring).
    The turn is the yaw rate since the previous snapshot over the speed (none at the first,
    nor below BUMPER_MOVING_MPS), at most BUMPER_MAX_CURVATURE."""
    out = np.full(len(snaps), HAZARD_AHEAD_M, dtype=np.float32)
    for t, snap in enumerate(snaps):
        ego = snap.ego
        curvature = 0.0
        if t > 0 and ego.speed_mps >= BUMPER_MOVING_MPS:
            dt = snap.time_s - snaps[t - 1].time_s
            if dt > 0:
                turn = (ego.yaw_rad - snaps[t - 1].ego.yaw_rad + np.pi) % (2 * np.pi) - np.pi
                curvature = float(np.clip(turn / dt / ego.speed_mps, -BUMPER_MAX_CURVATURE, BUMPER_MAX_CURVATURE))
        front = ego.length_m / 2
        arc = _arc(ego.x_m, ego.y_m, ego.yaw_rad, curvature, front + ahead_m)
        dist = _nearest_in_path(snap.vehicles, arc, ego.width_m / 2 + CORRIDOR_MARGIN_M, front)
        out[t] = dist if dist <= ahead_m else HAZARD_AHEAD_M
    return out


def _entry(polygon, path: np.ndarray) -> int | None:
    """Index of the first point of `path` inside `polygon` (None: it never enters)."""
    inside = shapely.contains_xy(polygon, path[:, 0], path[:, 1])
    return int(np.argmax(inside)) if inside.any() else None


def crossing_distances(snaps: list[Snapshot], crossings: list[Polygon]) -> np.ndarray:
    """(T,) float32: per snapshot (one episode, in step order) the distance in metres from the
    ego's front to where its path enters the nearest crossing with a pedestrian on it
    (HAZARD_AHEAD_M: none within reach; see the module's docstring). `crossings`: the town's
    crossing polygons (TownMap.crossings)."""
    out = np.full(len(snaps), HAZARD_AHEAD_M, dtype=np.float32)
    if not snaps or not crossings:
        return out
    for c in crossings:
        shapely.prepare(c)
    centres = np.array([(c.centroid.x, c.centroid.y) for c in crossings])
    reach = np.array([np.hypot(b[2] - b[0], b[3] - b[1]) / 2 for b in (c.bounds for c in crossings)])
    traj = _trajectory(snaps)
    for t, snap in enumerate(snaps):
        peds = snap.pedestrians
        if len(peds) == 0:
            continue
        ego_xy = traj[0][t]
        near = np.flatnonzero(np.hypot(*(centres - ego_xy).T) < HAZARD_AHEAD_M + reach + snap.ego.length_m)
        if not len(near):
            continue
        path = _path_of(t, *traj)
        front = snap.ego.length_m / 2
        half_width = snap.ego.width_m / 2 + CORRIDOR_MARGIN_M
        heading = np.stack([np.cos(peds.yaw_rad), np.sin(peds.yaw_rad)], axis=1)
        walking = peds.speed_mps > WALKING_MPS
        soon = peds.xy + ONTO_S * peds.speed_mps[:, None] * heading
        for c in near:
            i = _entry(crossings[c], path)
            if i is None or i == 0 or i * PATH_STEP_M - front < 0:
                continue  # not on the path, or the front is on it already
            on = shapely.contains_xy(crossings[c], peds.xy[:, 0], peds.xy[:, 1])
            on |= walking & shapely.contains_xy(crossings[c], soon[:, 0], soon[:, 1])
            if not on.any():
                continue
            # Beside the corridor and walking away from the path (across where it enters): no one's.
            tangent = path[min(i + 1, len(path) - 1)] - path[i - 1]
            normal = np.array([-tangent[1], tangent[0]]) / max(np.linalg.norm(tangent), 1e-9)
            lateral = (peds.xy - path[i]) @ normal
            away = walking & (lateral * (heading @ normal) > 0) & (np.abs(lateral) > half_width + AWAY_M)
            if (on & ~away).any():
                out[t] = min(out[t], float(np.clip(i * PATH_STEP_M - front, 0.0, HAZARD_AHEAD_M)))
    return out


def town_crossings(path: str | os.PathLike) -> list[Polygon]:
    """The crossing polygons of the town a recording was made in (its facts' town)."""
    from bid_sim.town_map import load_town_map
    from bid_sim.towns import resolve_town

    facts = read_facts(path)
    spec = facts.get("town_source") or facts.get("town")
    if not spec:
        raise BidError(f"{path} names no town: record it again with `bid record`")
    return [Polygon(ring) for ring in load_town_map(resolve_town(spec)).crossings]


def file_hazards(path: str | os.PathLike, ped_ahead_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(steps (T,), path_hazards (T, 2)) of one recording."""
    snaps = [snap for snap, _control in read_snapshots(path)]
    return np.array([s.step for s in snaps], dtype=np.int64), path_hazards(snaps, ped_ahead_s)


def file_crossings(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(steps (T,), crossing_distances (T, 1)) of one recording."""
    snaps = [snap for snap, _control in read_snapshots(path)]
    return (np.array([s.step for s in snaps], dtype=np.int64),
            crossing_distances(snaps, town_crossings(path))[:, None])


def file_bumper(path: str | os.PathLike, ahead_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(steps (T,), bumper_vehicles (T, 1)) of one recording."""
    snaps = [snap for snap, _control in read_snapshots(path)]
    return np.array([s.step for s in snaps], dtype=np.int64), bumper_vehicles(snaps, ahead_m)[:, None]


def _bumper_job(job: tuple[str, float]) -> tuple[np.ndarray, np.ndarray]:
    return file_bumper(*job)


def _file_job(job: tuple[str, float]) -> tuple[np.ndarray, np.ndarray]:
    return file_hazards(*job)


def _crossing_job(job: tuple[str]) -> tuple[np.ndarray, np.ndarray]:
    return file_crossings(*job)


def _key(files: list[Path], version: str) -> str:
    h = hashlib.sha1(version.encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def index_hazards(files: list[Path], episode: np.ndarray, step: np.ndarray, cache_dir: Path | None,
                  workers: int | None = None, ped_ahead_s: float = 0.0) -> np.ndarray:
    """(N, 2) float32 path_hazards (with `ped_ahead_s`) of every index row (recording `episode[i]`, `step[i]`),
    read from `cache_dir` when it holds them for these files, else computed (one worker
    process per recording) and stored there. A row without a /scene record is HAZARD_AHEAD_M."""
    version = _VERSION + (f";ahead={ped_ahead_s:g}" if ped_ahead_s else "")
    return _index(files, episode, step, cache_dir, workers, "hazards", version, len(PATH_KINDS),
                  _file_job, [(str(f), ped_ahead_s) for f in files])


def index_crossings(files: list[Path], episode: np.ndarray, step: np.ndarray, cache_dir: Path | None,
                    workers: int | None = None) -> np.ndarray:
    """(N, 1) float32 crossing_distances of every index row, cached as index_hazards' are."""
    return _index(files, episode, step, cache_dir, workers, "crossings", _CROSSING_VERSION, 1,
                  _crossing_job, [(str(f),) for f in files])


def index_bumper(files: list[Path], episode: np.ndarray, step: np.ndarray, cache_dir: Path | None,
                 ahead_m: float, workers: int | None = None) -> np.ndarray:
    """(N, 1) float32 bumper_vehicles within `ahead_m` of every index row, cached as index_hazards' are."""
    return _index(files, episode, step, cache_dir, workers, "bumper", f"{_BUMPER_VERSION};ahead={ahead_m:g}", 1,
                  _bumper_job, [(str(f), ahead_m) for f in files])


def _index(files: list[Path], episode: np.ndarray, step: np.ndarray, cache_dir: Path | None,
           workers: int | None, name: str, version: str, columns: int, job_fn, file_jobs: list[tuple]) -> np.ndarray:
    """Per-recording targets `job_fn(file_jobs[e])` → (steps, (T, columns)) laid on the index rows,
    cached in `cache_dir` as `name`-KEY.npy (one such file kept)."""
    path = cache_dir / f"{name}-{_key(files, version)}.npy" if cache_dir is not None else None
    if path is not None and path.exists():
        cached = np.load(path)
        if cached.shape == (len(step), columns):
            return cached
    out = np.full((len(step), columns), HAZARD_AHEAD_M, dtype=np.float32)
    wanted = sorted(set(np.unique(episode).tolist()))
    jobs = [file_jobs[e] for e in wanted]
    workers = workers or max(1, min(os.cpu_count() or 1, len(jobs)))
    log.info("finding the %s targets of %d recordings with %d workers", name, len(jobs), workers)
    results = map_parallel(job_fn, jobs, workers)
    for e, (steps, targets) in zip(wanted, results, strict=True):
        rows = np.flatnonzero(episode == e)
        at = np.searchsorted(steps, step[rows])
        found = (at < len(steps)) & (steps[np.minimum(at, len(steps) - 1)] == step[rows])
        out[rows[found]] = targets[at[found]]
    if path is not None:
        try:
            cache_dir.mkdir(exist_ok=True)
            tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npy")
            np.save(tmp, out)
            for old in cache_dir.glob(f"{name}-*.npy"):
                if old != path and not old.name.endswith(".tmp.npy"):
                    old.unlink()
            os.replace(tmp, path)
        except OSError as e:
            raise BidError(f"cannot write the {name} cache in {cache_dir} ({e.strerror}); free disk space "
                           "or train with --no-cache") from e
    return out
