"""The renderer: Snapshot -> (300, 900, 3) uint8 RGB frame, left | centre | right camera.

Per frame and camera: copy the weather's sky/terrain background, fill the ground layers
(one batched fillPoly per layer), apply the ground's distance fog and wet sheen (one
multiply-add per camera), then draw walls, signals, vehicles and pedestrians far to near
(painter's algorithm). Objects are ordered among themselves by distance; against a wall
they follow the wall's plane (an object on the camera's side of a wall is drawn after it,
one behind it before it), which distance alone gets wrong for long facades. Last, the rain
layer. Only geometry within the weather's view range and the cameras' horizontal field of
view is considered, found with vectorised distance and angle tests before any face is built,
so the cost follows what the ego can see, not the size of the town.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from bid_sim.errors import BidError
from bid_sim.render.camera import (
    MARGIN_PX,
    NEAR_M,
    ONE,
    SHIFT,
    CameraRig,
    camera_poses,
    clip_near,
    project,
)
from bid_sim.render.geometry import (
    FACES_PER_HEAD,
    GROUND_COLOURS,
    GROUND_LAYERS,
    LAMP_RADIUS_M,
    TERRAIN_COLOUR,
    Faces,
    StaticScene,
    concat,
    pedestrian_faces,
    static_scene,
    vehicle_faces,
)
from bid_sim.render.presets import WeatherPreset, preset
from bid_sim.snapshot import GREEN, RED, YELLOW, Snapshot
from bid_sim.town_map import TownMap

STAGES = ("transform", "clip", "sort", "fill", "effects")
OUT_OF_TOWN_M = 150.0
CELL_M = 10.0  # grid cell of the static-geometry cache  # an ego this far outside the town's bounds is an error
RAIN_LAYERS = 8
LAMP_COLOURS = {RED: (255, 46, 32), YELLOW: (255, 196, 30), GREEN: (50, 255, 120)}
LAMP_OFF = (52, 48, 44)
_LAMP_CODES = np.array([RED, YELLOW, GREEN])  # top to bottom, as in geometry's lamp_centres
_LAMP_RGB = np.array([LAMP_COLOURS[c] for c in (RED, YELLOW, GREEN)], dtype=np.int64)
_EPS = 1e-3
HEAD_RADIUS_M = 0.5  # a signal head (pole, housing, lamps) fits in this disc around head_xy
PED_RADIUS_M = 0.3  # a pedestrian's figure fits in this disc
_HEAD_FACE_RANGE = np.arange(FACES_PER_HEAD)[None, :]


@dataclass(frozen=True)
class _Background:
    canvas: np.ndarray  # sky above the horizon, terrain below (one camera's canvas)
    ground_row0: int  # first canvas row below the horizon
    ground_mul: np.ndarray  # (rows, W, 3) uint8: per-row fog/wet multiplier × 255
    ground_add: np.ndarray  # (rows, W, 3) uint8: per-row fog and sky-sheen colour
    rain: tuple[np.ndarray, ...]  # frame-sized streak layers, added to the frame


def _background(rig: CameraRig, w: WeatherPreset, seed: int) -> _Background:
    hc, wc, _ = rig.canvas_shape
    f, cy = rig.focal_px, rig.cy
    rows = np.arange(hc, dtype=np.float64)
    canvas = np.empty((hc, wc, 3), dtype=np.uint8)
    top, hor = np.array(w.sky_top, float), np.array(w.sky_horizon, float)
    row0 = math.floor(cy) + 1
    t = np.clip(rows[:row0] / max(cy, 1.0), 0.0, 1.0) ** 1.6
    canvas[:row0] = np.round(top + (hor - top) * t[:, None])[:, None, :].astype(np.uint8)
    canvas[row0:] = np.array(TERRAIN_COLOUR, np.uint8)
    # Ground rows: distance along the flat ground for each row below the horizon.
    below = rows[row0:] - cy
    dist = f * rig.height_m / below
    fog = w.fog(dist)
    grazing = np.arctan(below / f)  # angle below the horizon
    fresnel = 0.04 + 0.96 * (1.0 - np.sin(grazing)) ** 5
    sheen = np.clip(w.wet * 0.75 * fresnel, 0.0, 0.9)
    dark = 1.0 - 0.3 * w.wet
    # Flat ground: sun from above plus light from the whole sky, so it keeps some
    # brightness and less of the sun's colour than walls facing a low sun do.
    sun_lit = (w.ambient + w.diffuse * max(0.0, w.sun_vector()[2])) / (w.ambient + w.diffuse)
    tint = np.array(w.ground_tint) * (0.5 + 0.5 * np.array(w.light)) * max(0.72, sun_lit)
    mul = ((1 - fog) * (1 - sheen) * dark)[:, None] * tint[None, :]
    add = (sheen * (1 - fog))[:, None] * hor[None, :] + fog[:, None] * hor[None, :]
    ground_mul = np.broadcast_to(np.clip(np.round(mul * 255), 0, 255).astype(np.uint8)[:, None, :],
                                 (hc - row0, wc, 3)).copy()
    ground_add = np.broadcast_to(np.clip(np.round(add), 0, 255).astype(np.uint8)[:, None, :],
                                 (hc - row0, wc, 3)).copy()
    rain = tuple(_rain_layer(rig, w, seed * RAIN_LAYERS + k) for k in range(RAIN_LAYERS)) if w.rain > 0 else ()
    return _Background(canvas, row0, ground_mul, ground_add, rain)


def _rain_layer(rig: CameraRig, w: WeatherPreset, seed: int) -> np.ndarray:
    """Slanted light streaks (additive), denser and brighter the harder it rains."""
    h, wd, _ = rig.frame_shape
    rng = np.random.default_rng(seed)
    layer = np.zeros((h, wd), np.uint8)
    n = int(w.rain * 0.012 * h * wd / 10)
    x = rng.uniform(0, wd, n)
    y = rng.uniform(-20, h, n)
    length = rng.uniform(6, 22, n) * (0.6 + 0.4 * w.rain)
    bright = rng.uniform(18, 46, n) * (0.5 + 0.5 * w.rain)
    for xi, yi, li, bi in zip(x, y, length, bright, strict=True):
        cv2.line(layer, (int(xi), int(yi)), (int(xi - 0.18 * li), int(yi + li)), int(bi), 1, cv2.LINE_AA)
    return cv2.merge([layer, layer, layer])


class Renderer:
    """Renders Snapshots of one town with one camera rig under one weather.

    ``render`` is pure: the same snapshot, weather and seed give the same pixels. The seed
    only picks the rain streak pattern (with the snapshot's step). A Renderer keeps scratch
    canvases, so give each thread or process its own.
    """

    def __init__(self, town_map: TownMap, rig: CameraRig | None = None,
                 weather: str | WeatherPreset = "ClearNoon", seed: int = 0):
        self.town_map = town_map
        self.rig = rig or CameraRig()
        self.weather = preset(weather)
        self.seed = int(seed)
        self.scene: StaticScene = static_scene(town_map)
        self.view_m = self.weather.fog_full_m + 5.0
        rig = self.rig
        bg = _background(rig, self.weather, self.seed)
        n_cam = len(rig.yaws_deg)
        # One canvas for all cameras side by side, each with its margin; drawn through views.
        self._bg = bg
        self._bg_all = np.tile(bg.canvas, (1, n_cam, 1))
        self._mul_all = np.tile(bg.ground_mul, (1, n_cam, 1))
        self._add_all = np.tile(bg.ground_add, (1, n_cam, 1))
        self._canvas = np.empty_like(self._bg_all)
        self._cells: dict[tuple[int, int], _Cell] = {}
        wc = rig.canvas_shape[1]
        self._views = [self._canvas[:, c * wc:(c + 1) * wc] for c in range(n_cam)]
        h, w = rig.height_px, rig.width_px
        self._crops = [v[MARGIN_PX:MARGIN_PX + h, MARGIN_PX:MARGIN_PX + w] for v in self._views]
        self._sun = self.weather.sun_vector()
        self._light = np.array(self.weather.light)
        self._fog_colour = np.array(self.weather.sky_horizon, dtype=np.float64)
        self._ground_cols = [tuple(int(v) for v in c) for c in GROUND_COLOURS]
        half = math.atan((rig.width_px / 2.0 + MARGIN_PX) / rig.focal_px)
        vhalf = math.atan((rig.height_px / 2.0 + MARGIN_PX) / rig.focal_px)
        self._side = (math.cos(half), math.sin(half))
        self._tan_h, self._tan_v = math.tan(half), math.tan(vhalf)
        # The cameras' horizontal fields of view merged into intervals of azimuth (relative
        # to the ego's heading): their middles, and cos, sin and the wrap term of half widths.
        spans = _merge_spans([(math.radians(y) - half, math.radians(y) + half) for y in rig.yaws_deg])
        self._fov_all = any(b - a >= 2 * math.pi for a, b in spans)
        self._fov_mid = [0.5 * (a + b) for a, b in spans]
        self._fov_trig = []
        for a, b in spans:
            hw = 0.5 * (b - a)
            wide = math.sin(math.pi - hw) ** 2 if hw >= math.pi / 2 else 1.0
            self._fov_trig.append((math.cos(hw), math.sin(hw), wide))

    # ------------------------------------------------------------------ public

    def render(self, snapshot: Snapshot, timings: dict[str, float] | None = None) -> np.ndarray:
        """The (H, W × cameras, 3) uint8 RGB frame for a snapshot."""
        self._check(snapshot)
        clock = _Clock(timings)
        rig = self.rig
        ego = snapshot.ego
        poses = camera_poses(rig, ego.x_m, ego.y_m, ego.yaw_rad)
        eye = np.array([poses[0].x, poses[0].y, poses[0].z])
        fwd = np.array([p.fwd for p in poses])  # (C, 2)
        right = np.array([p.right for p in poses])
        faces, obj_xy, obj_rad, lamps = self._gather(snapshot, eye, ego.yaw_rad)
        shaded = self._shade(faces, eye)
        clock.lap("transform")
        keys, lamp_keys = self._keys(faces, obj_xy, obj_rad, lamps, eye)
        cols = shaded.astype(np.int32).tolist()
        clock.lap("sort")
        np.copyto(self._canvas, self._bg_all)
        clock.lap("effects")
        self._draw_ground(eye, fwd, right, clock)
        bg = self._bg
        roi = self._canvas[bg.ground_row0:]
        cv2.multiply(roi, self._mul_all, dst=roi, scale=1.0 / 255.0)
        cv2.add(roi, self._add_all, dst=roi)
        clock.lap("effects")
        self._draw_faces(faces, keys, cols, lamps, lamp_keys, eye, fwd, right, clock)
        frame = np.concatenate(self._crops, axis=1)
        if bg.rain:
            k = (self.seed * 1_000_003 + snapshot.step * 7919) % len(bg.rain)
            cv2.add(frame, bg.rain[k], dst=frame)
        clock.lap("effects")
        return frame

    # ------------------------------------------------------------------ checks

    def _check(self, snap: Snapshot) -> None:
        e = snap.ego
        if not all(math.isfinite(v) for v in (e.x_m, e.y_m, e.yaw_rad)):
            raise BidError(f"snapshot step {snap.step}: the ego pose is not finite "
                           f"(x={e.x_m}, y={e.y_m}, yaw={e.yaw_rad}); fix the state that produced it")
        x0, y0, x1, y1 = self.scene.bounds
        m = OUT_OF_TOWN_M
        if not (x0 - m <= e.x_m <= x1 + m and y0 - m <= e.y_m <= y1 + m):
            raise BidError(f"snapshot step {snap.step}: the ego at ({e.x_m:.1f}, {e.y_m:.1f}) m is "
                           f"outside {self.town_map.name} (x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}); "
                           "render it with its own town's map")
        for kind, actors in (("vehicle", snap.vehicles), ("pedestrian", snap.pedestrians)):
            if len(actors) == 0:
                continue
            if math.isfinite(float(actors.xy.sum() + actors.yaw_rad.sum() + actors.size.sum())):
                continue  # the common case, in three reductions
            ok = np.isfinite(actors.xy).all(axis=1) & np.isfinite(actors.yaw_rad) & np.isfinite(actors.size).all(axis=1)
            if not ok.all():
                i = int(np.argmin(ok))
                raise BidError(f"snapshot step {snap.step}: {kind} {actors.ids[i]!r} has a non-finite "
                               "position, yaw or size; fix the state that produced it")
        if len(snap.light_states) != len(self.scene.head_xy):
            raise BidError(f"snapshot has {len(snap.light_states)} light states but "
                           f"{self.town_map.name} has {len(self.scene.head_xy)} signal heads; "
                           "render it with its own town's map")

    # ------------------------------------------------------------------ gathering

    def _gather(self, snap: Snapshot, eye: np.ndarray, yaw: float) -> tuple[Faces, np.ndarray, np.ndarray, _Lamps]:
        """Faces within view range, in some camera's horizontal field of view and facing the
        eye: walls, signals, vehicles, pedestrians.

        Objects (signal heads, then vehicles, then pedestrians) are numbered; obj_xy and
        obj_rad give each one's centre and footprint radius, for ordering against walls.
        """
        sc = self.scene
        r2 = self.view_m ** 2
        eye2 = eye[:2]
        cell = self._near_static(eye[0], eye[1])
        axes = [(math.cos(yaw + a), math.sin(yaw + a)) for a in self._fov_mid]
        rel = cell.wall_xy - eye2
        d2 = rel[:, 0] ** 2 + rel[:, 1] ** 2
        keep = (d2 < cell.wall_reach2) & (cell.wall_normal @ eye2 > cell.wall_plane)  # in range, facing
        keep &= self._in_view(rel, d2, cell.wall_radius, axes)
        parts = [cell.walls.take(np.flatnonzero(keep))]
        obj_xy, obj_rad = [], []
        lamps = _Lamps.none()
        n_obj = 0
        if len(cell.heads):
            rel = sc.head_xy[cell.heads] - eye2
            d2 = rel[:, 0] ** 2 + rel[:, 1] ** 2
            heads = cell.heads[(d2 < r2) & self._in_view(rel, d2, HEAD_RADIUS_M, axes)]
            n_obj = len(heads)
            if n_obj:
                sel = (heads[:, None] * FACES_PER_HEAD + _HEAD_FACE_RANGE).ravel()
                part = sc.signal_faces.take(sel)
                part.obj[:] = np.repeat(np.arange(n_obj), FACES_PER_HEAD)  # renumbered: near heads
                parts.append(part)
                hxy = sc.head_xy[heads]
                obj_xy.append(hxy)
                obj_rad.append(np.full(n_obj, 0.4))
                # Lamps face their approach; from behind a head shows only its housing.
                fv = sc.head_facing[heads]
                j = np.flatnonzero(((eye2 - hxy) * fv).sum(axis=1) > 0)
                if len(j):
                    states = np.asarray(snap.light_states)[heads[j]]
                    lamps = _Lamps(np.repeat(j, 3), sc.lamp_centres[heads[j]].reshape(-1, 3),
                                   (_LAMP_CODES[None, :] == states[:, None]).ravel(),
                                   np.tile(_LAMP_RGB, (len(j), 1)))
        for kind, actors in (("v", snap.vehicles), ("p", snap.pedestrians)):
            if len(actors) == 0:
                continue
            rel = actors.xy - eye2
            d2 = rel[:, 0] ** 2 + rel[:, 1] ** 2
            rad = 0.5 * np.hypot(actors.size[:, 0], actors.size[:, 1]) if kind == "v" else PED_RADIUS_M
            m = np.flatnonzero((d2 < r2) & self._in_view(rel, d2, rad, axes))
            if len(m) == 0:
                continue
            xy = actors.xy[m]
            if kind == "v":
                parts.append(vehicle_faces(xy, actors.yaw_rad[m], actors.size[m], actors.colour[m], n_obj))
                obj_rad.append(rad[m])
            else:
                parts.append(pedestrian_faces(xy, actors.size[m], actors.colour[m], eye, n_obj))
                obj_rad.append(np.full(len(m), PED_RADIUS_M))
            obj_xy.append(xy)
            n_obj += len(m)
        faces = concat(parts)
        if n_obj:  # back faces of objects (closed boxes or billboards); walls are culled above
            q0 = faces.quads[:, 0]
            nm = faces.normals
            vis = ((eye[0] - q0[:, 0]) * nm[:, 0] + (eye[1] - q0[:, 1]) * nm[:, 1]
                   + (eye[2] - q0[:, 2]) * nm[:, 2]) > 0
            faces = faces.take(np.flatnonzero(vis))
        oxy = np.concatenate(obj_xy) if obj_xy else np.zeros((0, 2))
        orad = np.concatenate(obj_rad) if obj_rad else np.zeros(0)
        return faces, oxy, orad, lamps

    def _in_view(self, rel: np.ndarray, d2: np.ndarray, rad: np.ndarray | float,
                 axes: list[tuple[float, float]]) -> np.ndarray:
        """Which discs (centre at rel from the eye, squared distance d2, radius rad) reach into
        the cameras' horizontal field of view (canvas margins included).

        The cameras' fields of view are merged into intervals of azimuth (one for the usual
        contiguous rig), each with its axis and half width H. A disc at distance d subtends
        ±asin(r/d), so it is in an interval when the angle to the axis is below H + asin(r/d);
        for H + asin(r/d) < π that is rel·axis > cos(H)·√(d² − r²) − sin(H)·r. Only the
        vertical side planes are tested, so nothing in view is ever dropped.
        """
        if self._fov_all:
            return np.ones(len(d2), bool)
        r2 = rad * rad
        s = np.sqrt(np.maximum(d2 - r2, 0.0))
        out = np.zeros(len(d2), bool)
        for (ax, ay), (ch, sh, wide) in zip(axes, self._fov_trig, strict=True):
            out |= rel[:, 0] * ax + rel[:, 1] * ay > ch * s - sh * rad
            out |= r2 >= d2 * wide  # the disc's angular radius reaches past ±π
        return out

    def _near_static(self, x: float, y: float) -> _Cell:
        """Walls, signal heads and ground rings that may be in view range from anywhere in
        the eye's grid cell (ascending indices), cached per cell: the exact range test then
        runs on these few, and its result does not depend on the cache."""
        key = (math.floor(x / CELL_M), math.floor(y / CELL_M))
        hit = self._cells.get(key)
        if hit is None:
            sc = self.scene
            cx, cy = (key[0] + 0.5) * CELL_M, (key[1] + 0.5) * CELL_M
            reach = self.view_m + CELL_M * 0.7072  # the cell's half diagonal
            wc, rc, hc = sc.wall_centre, sc.ring_centre, sc.head_xy
            walls = np.flatnonzero((wc[:, 0] - cx) ** 2 + (wc[:, 1] - cy) ** 2 < (reach + sc.wall_radius) ** 2)
            rings = np.flatnonzero((rc[:, 0] - cx) ** 2 + (rc[:, 1] - cy) ** 2 < (reach + sc.ring_radius) ** 2)
            heads = np.flatnonzero((hc[:, 0] - cx) ** 2 + (hc[:, 1] - cy) ** 2 < reach ** 2)
            wf = sc.walls.take(walls)
            normal = np.ascontiguousarray(wf.normals[:, :2])
            if len(self._cells) >= 64:
                self._cells.clear()
            hit = self._cells[key] = _Cell(
                wf, wc[walls, :2].copy(), sc.wall_radius[walls], (self.view_m + sc.wall_radius[walls]) ** 2,
                normal, (normal * wf.quads[:, 0, :2]).sum(axis=1), heads, rings)
        return hit

    def _shade(self, faces: Faces, eye: np.ndarray) -> np.ndarray:
        """Face colours lit by the sun and fogged by distance: (F, 3) float."""
        w = self.weather
        lam = w.ambient + w.diffuse * np.clip(faces.normals @ self._sun, 0.0, None)
        col = faces.colours * lam[:, None] * self._light[None, :]
        if len(faces.quads):
            c = faces.centre
            d = np.sqrt((c[:, 0] - eye[0]) ** 2 + (c[:, 1] - eye[1]) ** 2 + (c[:, 2] - eye[2]) ** 2)
            fog = w.fog(d)[:, None]
            col = col * (1 - fog) + self._fog_colour[None, :] * fog
        return np.clip(col, 0, 255)

    # ------------------------------------------------------------------ ordering

    def _keys(self, faces: Faces, obj_xy: np.ndarray, obj_rad: np.ndarray, lamps: _Lamps,
              eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Painter's keys (larger = farther = drawn first), shared by all cameras.

        Walls use their distance; an object uses its own, moved behind every wall it is
        behind (on the wall's back side and overlapping it in azimuth from the eye) and in
        front of every wall it is in front of. Azimuth is the same for all cameras, which
        share the eye, so one ordering serves them all.
        """
        is_wall = faces.obj < 0
        wi = np.flatnonzero(is_wall)
        oi = np.flatnonzero(~is_wall)
        wq = faces.quads[wi]
        wc = faces.centre[wi]
        wall_d = np.hypot(wc[:, 0] - eye[0], wc[:, 1] - eye[1])
        rel = obj_xy - eye[None, :2]
        obj_d = np.hypot(rel[:, 0], rel[:, 1])
        key_obj = obj_d.copy()
        if len(obj_xy) and len(wi):
            obj_az = np.arctan2(rel[:, 1], rel[:, 0])
            obj_half = np.arcsin(np.clip(obj_rad / np.maximum(obj_d, 1e-6), 0.0, 1.0))
            a0 = np.arctan2(wq[:, 0, 1] - eye[1], wq[:, 0, 0] - eye[0])
            span = _wrap(np.arctan2(wq[:, 1, 1] - eye[1], wq[:, 1, 0] - eye[0]) - a0)
            w_mid = a0 + 0.5 * span
            w_half = 0.5 * np.abs(span)
            ov = np.abs(_wrap(obj_az[:, None] - w_mid[None, :])) < obj_half[:, None] + w_half[None, :]
            if ov.any():
                wn = faces.normals[wi, :2]
                side = obj_xy @ wn.T - (wq[:, 0, :2] * wn).sum(axis=1)  # (O, W): < 0 behind the wall
                lower = np.where(ov & (side < 0), wall_d[None, :], -np.inf).max(axis=1)
                upper = np.where(ov & (side >= 0), wall_d[None, :], np.inf).min(axis=1)
                key_obj = np.minimum(np.maximum(key_obj, lower + _EPS), upper - _EPS)
        keys = np.empty(len(faces.obj))
        keys[wi] = wall_d
        keys[oi] = key_obj[faces.obj[oi]] - faces.sub[oi] * 1e-5
        lamp_keys = key_obj[lamps.obj] - 1e-3 if len(lamps.obj) else np.zeros(0)
        return keys, lamp_keys

    # ------------------------------------------------------------------ ground

    def _draw_ground(self, eye: np.ndarray, fwd: np.ndarray, right: np.ndarray, clock: _Clock) -> None:
        """Ground layers of all cameras: one batched fillPoly per camera and layer (a layer's
        rings never overlap, and later layers are drawn over earlier ones)."""
        sc = self.scene
        ex, ey, ez = eye
        cand = self._near_static(ex, ey).rings
        cen = sc.ring_centre[cand]
        near = cand[(cen[:, 0] - ex) ** 2 + (cen[:, 1] - ey) ** 2 < (self.view_m + sc.ring_radius[cand]) ** 2]
        if len(near) == 0:
            return
        rel = sc.ring_centre[near] - eye[None, :2]
        x = rel @ right.T  # (R, C)
        z = rel @ fwd.T
        rad = sc.ring_radius[near][:, None]
        cs, sn = self._side
        keep = (z > NEAR_M - rad) & (x * cs - z * sn < rad) & (-x * cs - z * sn < rad)
        cam_i, ring_i = np.nonzero(keep.T)  # camera-major, rings (sorted by layer) within
        sel = near[ring_i]
        starts = sc.ring_start[sel]
        lengths = sc.ring_start[sel + 1] - starts
        offs = np.zeros(len(sel) + 1, np.int64)
        np.cumsum(lengths, out=offs[1:])
        vidx = np.repeat(starts - offs[:-1], lengths) + np.arange(offs[-1])
        v = sc.ring_verts.take(vidx, axis=0) - eye[None, :2]
        vc = np.repeat(cam_i, lengths)
        r_, f_ = right.take(vc, axis=0), fwd.take(vc, axis=0)
        cam = np.empty((len(v), 3))
        cam[:, 0] = v[:, 0] * r_[:, 0] + v[:, 1] * r_[:, 1]
        cam[:, 1] = ez
        cam[:, 2] = v[:, 0] * f_[:, 0] + v[:, 1] * f_[:, 1]
        clock.lap("transform")
        pts, offs = clip_near(cam, offs)
        proj = project(self.rig, pts)
        # Rings wholly behind the near plane come back empty; the others keep >= 3 corners.
        left = np.flatnonzero(offs[1:] > offs[:-1])
        pieces = [proj[i:j] for i, j in zip(offs.take(left).tolist(), offs.take(left + 1).tolist(), strict=True)]
        n_layers = len(GROUND_LAYERS)
        group = (cam_i * n_layers + sc.ring_layer[sel]).take(left)
        bounds = np.searchsorted(group, np.arange(len(self._views) * n_layers + 1)).tolist()
        clock.lap("clip")
        fill = cv2.fillPoly
        for c, view in enumerate(self._views):
            for k in range(n_layers):
                g = c * n_layers + k
                if bounds[g] < bounds[g + 1]:
                    fill(view, pieces[bounds[g]:bounds[g + 1]], self._ground_cols[k], cv2.LINE_8, SHIFT)
        clock.lap("fill")

    # ------------------------------------------------------------------ objects

    def _draw_faces(self, faces: Faces, keys: np.ndarray, cols: list, lamps: _Lamps,
                    lamp_keys: np.ndarray, eye: np.ndarray, fwd: np.ndarray, right: np.ndarray,
                    clock: _Clock) -> None:
        """Walls, signals and actors of all cameras, far to near per camera."""
        rig = self.rig
        rel = faces.quads[..., :2] - eye[None, None, :2]  # (F, 4, 2)
        xs = np.einsum("fkd,cd->cfk", rel, right)  # (C, F, 4)
        zs = np.einsum("fkd,cd->cfk", rel, fwd)
        ys = eye[2] - faces.quads[..., 2]  # (F, 4): the same for every camera
        th, tv = self._tan_h, self._tan_v
        clock.lap("transform")
        # A face is culled when all four corners are outside one plane of the view volume.
        out = _all4(zs < NEAR_M) | _all4(xs - th * zs > 0) | _all4(-xs - th * zs > 0) \
            | _all4(ys - tv * zs > 0) | _all4(-ys - tv * zs > 0)
        cam_i, face_i = np.nonzero(~out)
        cam = np.empty((len(face_i), 4, 3))
        flat = cam_i * len(ys) + face_i
        cam[..., 0] = xs.reshape(-1, 4).take(flat, axis=0)
        cam[..., 1] = ys.take(face_i, axis=0)
        cam[..., 2] = zs.reshape(-1, 4).take(flat, axis=0)
        zv = cam[..., 2]
        unsafe = np.flatnonzero(_any4(zv < NEAR_M))
        raw = cam.take(unsafe, axis=0).reshape(-1, 3)
        cam[unsafe, :, 2] = NEAR_M  # placeholders, replaced by the clipped polygons below
        pts: list = list(project(rig, cam))
        if len(unsafe):
            clipped, offs = clip_near(raw, np.arange(0, len(raw) + 1, 4))
            for i, p in zip(unsafe.tolist(), _split(project(rig, clipped), offs), strict=True):
                pts[i] = p if len(p) >= 3 else None
        # Lamps: in front of a camera and on its screen.
        lrel = lamps.pos[:, :2] - eye[None, :2]
        lx, lz = lrel @ right.T, lrel @ fwd.T  # (L, C)
        ly = (eye[2] - lamps.pos[:, 2])[:, None]
        lamp_i, lamp_c = np.nonzero((lz > NEAR_M) & (np.abs(lx) < th * lz + 1.0) & (np.abs(ly) < tv * lz + 1.0))
        clock.lap("clip")
        n = len(face_i)
        order = np.lexsort((-np.concatenate([keys[face_i], lamp_keys[lamp_i]]), np.concatenate([cam_i, lamp_c])))
        clock.lap("sort")
        discs = self._lamp_discs(lx[lamp_i, lamp_c], ly[lamp_i, 0], lz[lamp_i, lamp_c], lamps, lamp_i)
        views = self._views
        cams, fids, lcams = cam_i.tolist(), face_i.tolist(), lamp_c.tolist()
        fill, circle = cv2.fillConvexPoly, cv2.circle
        for i in order.tolist():
            if i < n:
                p = pts[i]
                if p is not None:
                    fill(views[cams[i]], p, cols[fids[i]], cv2.LINE_8, SHIFT)
            else:
                for centre, rad, col in discs[i - n]:
                    circle(views[lcams[i - n]], centre, rad, col, -1, cv2.LINE_AA, SHIFT)
        clock.lap("fill")

    def _lamp_discs(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, lamps: _Lamps,
                    k: np.ndarray) -> list[list[tuple[tuple[int, int], int, tuple[int, ...]]]]:
        """Each visible lamp (camera coordinates x, y, z; lamps' rows k) as discs to draw:
        (centre, radius, colour) in fixed point. An unlit lamp is one dark disc, left out
        when below 0.7 px; a lit one gets a halo so it stays legible far away."""
        if len(z) == 0:
            return []
        f = self.rig.focal_px
        rad = LAMP_RADIUS_M * f / z
        u = np.round((self.rig.cx + f * x / z) * ONE).astype(np.int64).tolist()
        v = np.round((self.rig.cy + f * y / z) * ONE).astype(np.int64).tolist()
        fog = self.weather.fog(z)
        on = lamps.on[k]
        glow = np.where(on, 0.4, 1.0) * fog  # lit lamps shine through haze
        base = np.where(on[:, None], lamps.colour[k], np.array(LAMP_OFF)[None, :])
        col = (base * (1 - glow[:, None]) + self._fog_colour[None, :] * glow[:, None]).astype(np.int64)
        halo = (0.55 * col + 0.45 * 40).astype(np.int64).tolist()
        col = col.tolist()
        lit_rad = np.maximum(rad, 1.6)
        r_lit = np.round(lit_rad * ONE).astype(np.int64).tolist()
        r_halo = np.round(2.2 * lit_rad * ONE).astype(np.int64).tolist()
        r_off = np.round(np.maximum(rad, 0.7) * ONE).astype(np.int64).tolist()
        out = []
        for j, (lit, big) in enumerate(zip(on.tolist(), (rad >= 0.7).tolist(), strict=True)):
            c = (u[j], v[j])
            if lit:
                out.append([(c, r_halo[j], tuple(halo[j])), (c, r_lit[j], tuple(col[j]))])
            else:
                out.append([(c, r_off[j], tuple(col[j]))] if big else [])
        return out


@dataclass(frozen=True)
class _Cell:
    """The static geometry that may be in view range from one grid cell."""

    walls: Faces  # the walls, taken from the scene
    wall_xy: np.ndarray  # (W, 2) centres
    wall_radius: np.ndarray  # (W,)
    wall_reach2: np.ndarray  # (W,) (view range + radius)²: a wall nearer than this is in range
    wall_normal: np.ndarray  # (W, 2) horizontal outward normals (walls are vertical)
    wall_plane: np.ndarray  # (W,) normal · a corner: the eye sees the wall's front when normal · eye is larger
    heads: np.ndarray  # signal head indices
    rings: np.ndarray  # ground ring indices


@dataclass(frozen=True)
class _Lamps:
    obj: np.ndarray  # (L,) object index of the lamp's signal head
    pos: np.ndarray  # (L, 3) world centre
    on: np.ndarray  # (L,) lit
    colour: np.ndarray  # (L, 3) RGB when lit

    @staticmethod
    def none() -> _Lamps:
        return _Lamps(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, bool), np.zeros((0, 3), np.int64))


def _merge_spans(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Overlapping or touching intervals merged (angles in radians, not wrapped)."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    if len(out) > 1 and out[0][0] + 2 * math.pi <= out[-1][1]:  # the last wraps round into the first
        out = [*out[1:-1], (out[-1][0], max(out[-1][1], out[0][1] + 2 * math.pi))]
    return out


def _split(a: np.ndarray, offs: np.ndarray) -> list[np.ndarray]:
    """a[offs[i]:offs[i + 1]] for each i (views; much cheaper than np.split)."""
    o = offs.tolist()
    return [a[i:j] for i, j in itertools.pairwise(o)]


def _all4(m: np.ndarray) -> np.ndarray:
    """All of the last axis (of size 4) of a bool array: its four bytes read as one uint32,
    one operation instead of three."""
    return np.ascontiguousarray(m).view(np.uint32)[..., 0] == 0x01010101


def _any4(m: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(m).view(np.uint32)[..., 0] != 0


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


class _Clock:
    """Adds the CPU time since the last lap to a stage (no-op without a timings dict)."""

    def __init__(self, timings: dict[str, float] | None):
        self.t = timings
        self.last = time.process_time() if timings is not None else 0.0

    def lap(self, stage: str) -> None:
        if self.t is None:
            return
        now = time.process_time()
        self.t[stage] = self.t.get(stage, 0.0) + now - self.last
        self.last = now
