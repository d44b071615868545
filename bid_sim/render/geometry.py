"""Scene geometry for the renderer: the town's static layers (ground polygons cut into tiles,
building walls, signal poles and housings), built once per town, and the actors' faces,
built per frame, all vectorised over many objects.

Faces are convex quads (F, 4, 3) in the world frame with an outward unit normal (F, 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon, box
from shapely.ops import substring

from bid_sim.town_map import TownMap

TILE_M = 25.0  # ground polygons are cut into tiles this size, so culling can drop most
WALL_SEGMENT_M = 6.0  # long walls are split so distance sorting stays sound
DASH_M, GAP_M = 3.0, 5.0  # dashed lane lines

# Ground layers, drawn in this order (later ones over earlier ones). RGB.
GROUND_LAYERS = ("asphalt", "curb", "sidewalk", "zebra", "paint_white", "paint_yellow")
GROUND_COLOURS = np.array(
    [(74, 74, 78), (158, 156, 150), (128, 126, 121), (214, 214, 208), (222, 222, 216), (214, 176, 62)],
    dtype=np.float64,
)
TERRAIN_COLOUR = (98, 108, 78)
CURB_M = 0.3

BUILDING_COLOURS = np.array(
    [(168, 92, 74), (196, 180, 150), (140, 140, 138), (120, 140, 160), (214, 204, 176),
     (120, 96, 80), (224, 224, 218), (96, 126, 120)], dtype=np.float64)
VEHICLE_COLOURS = np.array(
    [(200, 30, 30), (30, 60, 170), (230, 230, 230), (25, 25, 28), (150, 150, 155), (40, 120, 60),
     (220, 180, 30), (120, 30, 40), (90, 160, 200), (230, 110, 30), (100, 100, 110), (170, 150, 120)],
    dtype=np.float64)
GLASS = np.array((48, 58, 70), dtype=np.float64)
TYRES = np.array((26, 26, 28), dtype=np.float64)
SHIRTS = np.array([(200, 40, 40), (40, 90, 190), (230, 200, 60), (60, 150, 80), (235, 235, 230),
                   (150, 60, 150), (240, 130, 40)], dtype=np.float64)
TROUSERS = np.array([(40, 44, 70), (30, 30, 32), (110, 100, 80), (70, 72, 76), (60, 40, 30)],
                    dtype=np.float64)
SKIN = np.array([(232, 190, 160), (190, 140, 100), (120, 84, 60)], dtype=np.float64)
POLE = np.array((96, 98, 100), dtype=np.float64)
HOUSING = np.array((38, 42, 38), dtype=np.float64)

# Box faces: front (+x local), back, left (+y), right, top, bottom.
FRONT, BACK, LEFT, RIGHT, TOP, BOTTOM = range(6)
_LOCAL_NORMALS = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)], float)
# Corner indices of each face into the 8 box corners ordered (±x, ±y, ±z) as below.
_FACE_CORNERS = np.array([[1, 3, 7, 5], [0, 4, 6, 2], [2, 6, 7, 3], [0, 1, 5, 4],
                          [4, 5, 7, 6], [0, 2, 3, 1]])
_CORNER_SIGNS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float) * 2 - 1


def box_faces(
    xy: np.ndarray, yaw: np.ndarray, half_l: np.ndarray, half_w: np.ndarray,
    z0: np.ndarray, z1: np.ndarray, faces: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray]:
    """Quads (N, K, 4, 3) and normals (N, K, 3) of the chosen faces of N yawed boxes."""
    n = len(xy)
    c, s = np.cos(yaw), np.sin(yaw)
    sx = _CORNER_SIGNS[:, 0][None, :] * half_l[:, None]  # (N, 8) local x
    sy = _CORNER_SIGNS[:, 1][None, :] * half_w[:, None]
    corners = np.empty((n, 8, 3))
    corners[..., 0] = xy[:, 0:1] + c[:, None] * sx - s[:, None] * sy
    corners[..., 1] = xy[:, 1:2] + s[:, None] * sx + c[:, None] * sy
    corners[..., 2] = np.where(_CORNER_SIGNS[:, 2][None, :] > 0, z1[:, None], z0[:, None])
    idx = _FACE_CORNERS[list(faces)]  # (K, 4)
    quads = corners[:, idx]  # (N, K, 4, 3)
    ln = _LOCAL_NORMALS[list(faces)]  # (K, 3)
    normals = np.empty((n, len(faces), 3))
    normals[..., 0] = c[:, None] * ln[None, :, 0] - s[:, None] * ln[None, :, 1]
    normals[..., 1] = s[:, None] * ln[None, :, 0] + c[:, None] * ln[None, :, 1]
    normals[..., 2] = ln[None, :, 2]
    return quads, normals


@dataclass(frozen=True, eq=False)
class Faces:
    """A batch of convex quads with what the painter needs to shade and order them."""

    quads: np.ndarray  # (F, 4, 3) world, m
    normals: np.ndarray  # (F, 3) unit, outward
    colours: np.ndarray  # (F, 3) base RGB
    obj: np.ndarray  # (F,) object index (actors, signals) or -1 for a wall
    sub: np.ndarray  # (F,) drawing order inside its object (later = higher)
    centre: np.ndarray  # (F, 3) mean of the corners

    @staticmethod
    def empty() -> Faces:
        return Faces(np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                     np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))

    def take(self, idx: np.ndarray) -> Faces:
        """The faces at these indices (copies)."""
        return Faces(*(a.take(idx, axis=0) for a in (self.quads, self.normals, self.colours, self.obj, self.sub,
                                                     self.centre)))


@dataclass(frozen=True, eq=False)
class StaticScene:
    """Everything of a town the renderer draws that never moves."""

    # Ground rings, grouped by layer in GROUND_LAYERS order.
    ring_verts: np.ndarray  # (V, 2) float64
    ring_start: np.ndarray  # (R + 1,) offsets into ring_verts
    ring_layer: np.ndarray  # (R,) layer index
    ring_centre: np.ndarray  # (R, 2)
    ring_radius: np.ndarray  # (R,)
    # Building walls (one face per wall segment).
    walls: Faces
    wall_centre: np.ndarray  # (W, 3)
    wall_radius: np.ndarray  # (W,)
    # Signal heads: pole + housing faces (obj = head index) and the three lamps per head.
    signal_faces: Faces
    head_xy: np.ndarray  # (H, 2)
    lamp_centres: np.ndarray  # (H, 3, 3) red, yellow, green lamp centres
    head_facing: np.ndarray  # (H, 2) unit vector the lamps face
    bounds: tuple[float, float, float, float]


LAMP_RADIUS_M = 0.13
LAMP_SPACING_M = 0.34
HOUSING_HALF = (0.16, 0.22, 0.55)  # depth, width, height halves
POLE_HALF_M = 0.09
FACES_PER_HEAD = 10  # pole sides (4) then housing (6); signal_faces holds them head by head


def _dashes(line: np.ndarray) -> list[LineString]:
    ls = LineString(line)
    out, s, length = [], 0.0, ls.length
    while s < length:
        e = min(s + DASH_M, length)
        if e - s > 0.3:
            out.append(substring(ls, s, e))
        s += DASH_M + GAP_M
    return out


def _paint(town_map: TownMap) -> tuple[shapely.Geometry, shapely.Geometry]:
    white, yellow = [], []
    for m in town_map.markings:
        lines = _dashes(m.line) if m.kind.endswith("dashed") else [LineString(m.line)]
        strips = [ln.buffer(m.width_m / 2.0, cap_style="flat", quad_segs=2) for ln in lines]
        (yellow if m.kind.startswith("centre") else white).extend(strips)
    return shapely.union_all(white), shapely.union_all(yellow)


def _rings_of(geom: shapely.Geometry) -> list[np.ndarray]:
    out = []
    for poly in getattr(geom, "geoms", [geom]):
        if poly.is_empty or not isinstance(poly, Polygon):
            if hasattr(poly, "geoms"):
                out += _rings_of(poly)
            continue
        for ring in (poly.exterior, *poly.interiors):
            pts = np.asarray(ring.coords)[:-1, :2]
            if len(pts) >= 3:
                out.append(pts)
    return out


def _ground(town_map: TownMap) -> tuple[list[np.ndarray], list[int]]:
    asphalt = shapely.union_all([Polygon(r) for r in town_map.road_polygons]).buffer(0)
    side = shapely.union_all([Polygon(r) for r in town_map.sidewalks]).buffer(0)
    # A lighter rim where the sidewalk meets the road reads as a curb.
    curb = side.buffer(CURB_M, quad_segs=2).intersection(asphalt.buffer(0.05))
    zebra = shapely.union_all([Polygon(r) for r in town_map.crossing_stripes])
    white, yellow = _paint(town_map)
    x0, y0, x1, y1 = town_map.bounds
    xs = np.arange(math.floor(x0 / TILE_M) * TILE_M, x1 + TILE_M, TILE_M)
    ys = np.arange(math.floor(y0 / TILE_M) * TILE_M, y1 + TILE_M, TILE_M)
    tiles = [box(x, y, x + TILE_M, y + TILE_M) for x in xs for y in ys]
    rings, layers = [], []
    for k, geom in enumerate((asphalt, curb, side, zebra, white, yellow)):
        shapely.prepare(geom)
        for t in tiles:
            if not geom.intersects(t):
                continue
            piece = geom.intersection(t)
            for r in _rings_of(piece):
                rings.append(r)
                layers.append(k)
    return rings, layers


def _walls(town_map: TownMap) -> tuple[Faces, np.ndarray, np.ndarray]:
    quads, normals, colours = [], [], []
    for b in town_map.buildings:
        fp = np.asarray(b.footprint, dtype=np.float64)
        if Polygon(fp).exterior.is_ccw is False:
            fp = fp[::-1]
        base = BUILDING_COLOURS[b.colour % len(BUILDING_COLOURS)]
        for i in range(len(fp)):
            a, c = fp[i], fp[(i + 1) % len(fp)]
            d = c - a
            length = float(np.hypot(*d))
            if length < 0.05:
                continue
            nrm = np.array([d[1] / length, -d[0] / length, 0.0])  # outward for a CCW ring
            k = max(1, math.ceil(length / WALL_SEGMENT_M))
            for j in range(k):
                p = a + d * (j / k)
                q = a + d * ((j + 1) / k)
                quads.append([(p[0], p[1], 0.0), (q[0], q[1], 0.0), (q[0], q[1], b.height_m),
                              (p[0], p[1], b.height_m)])
                normals.append(nrm)
                colours.append(base)
    q = np.array(quads, dtype=np.float64).reshape(-1, 4, 3)
    n = len(q)
    centre = q.mean(axis=1)
    faces = Faces(q, np.array(normals).reshape(-1, 3), np.array(colours).reshape(-1, 3),
                  np.full(n, -1, np.int64), np.zeros(n, np.int64), centre)
    radius = np.linalg.norm(q - centre[:, None, :], axis=2).max(axis=1) if n else np.zeros(0)
    return faces, centre, radius


def _signals(town_map: TownMap) -> tuple[Faces, np.ndarray, np.ndarray, np.ndarray]:
    heads = town_map.signal_heads
    h = len(heads)
    if h == 0:
        return Faces.empty(), np.zeros((0, 2)), np.zeros((0, 3, 3)), np.zeros((0, 2))
    pos = np.array([hd.position for hd in heads], dtype=np.float64)
    pole = np.array([hd.pole for hd in heads], dtype=np.float64)
    facing = np.array([hd.facing_rad for hd in heads], dtype=np.float64)
    ones = np.ones(h)
    # The pole reaches just above the housing; the housing sits on the pole, lamps to the road.
    pq, pn = box_faces(pole, facing, POLE_HALF_M * ones, POLE_HALF_M * ones, 0 * ones,
                       pos[:, 2] + HOUSING_HALF[2] + 0.1, (FRONT, BACK, LEFT, RIGHT))
    hq, hn = box_faces(pos[:, :2], facing, HOUSING_HALF[0] * ones, HOUSING_HALF[1] * ones,
                       pos[:, 2] - HOUSING_HALF[2], pos[:, 2] + HOUSING_HALF[2],
                       (FRONT, BACK, LEFT, RIGHT, TOP, BOTTOM))
    quads = np.concatenate([pq, hq], axis=1)  # (H, 10, 4, 3)
    normals = np.concatenate([pn, hn], axis=1)
    k = quads.shape[1]
    assert k == FACES_PER_HEAD
    colours = np.concatenate([np.broadcast_to(POLE, (h, 4, 3)), np.broadcast_to(HOUSING, (h, 6, 3))], axis=1)
    q = quads.reshape(-1, 4, 3)
    faces = Faces(q, normals.reshape(-1, 3), colours.reshape(-1, 3),
                  np.repeat(np.arange(h), k), np.tile(np.r_[np.zeros(4), np.ones(6)].astype(np.int64), h),
                  q.mean(axis=1))
    fvec = np.stack([np.cos(facing), np.sin(facing)], axis=1)
    front = pos[:, :2] + fvec * (HOUSING_HALF[0] + 0.02)
    lamps = np.empty((h, 3, 3))
    for i, dz in enumerate((LAMP_SPACING_M, 0.0, -LAMP_SPACING_M)):
        lamps[:, i, :2] = front
        lamps[:, i, 2] = pos[:, 2] + dz
    return faces, pos[:, :2].copy(), lamps, fvec


@lru_cache(maxsize=4)
def static_scene(town_map: TownMap) -> StaticScene:
    """The town's static geometry for the renderer, built once per town map (and process)."""
    rings, layers = _ground(town_map)
    order = np.argsort(np.array(layers, dtype=np.int64), kind="stable")
    rings = [rings[i] for i in order]
    layer = np.array(layers, dtype=np.int64)[order]
    lengths = np.array([len(r) for r in rings], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(lengths)])
    verts = np.concatenate(rings) if rings else np.zeros((0, 2))
    centre = np.array([r.mean(axis=0) for r in rings]).reshape(-1, 2)
    radius = np.array([np.linalg.norm(r - c, axis=1).max() for r, c in zip(rings, centre, strict=True)])
    walls, wall_centre, wall_radius = _walls(town_map)
    sig, head_xy, lamps, facing = _signals(town_map)
    return StaticScene(verts, start, layer, centre, radius, walls, wall_centre, wall_radius,
                       sig, head_xy, lamps, facing, town_map.bounds)


# --------------------------------------------------------------------------- actors

def _vehicle_template() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vehicle of unit length, width and height at the origin facing +x: tyres/chassis
    (sides), body and cabin (sides and top). Every corner scales with the vehicle's size,
    so one template serves all vehicles: quads (14, 4, 3), normals (14, 3), sub (14,)."""
    one, zero = np.ones(1), np.zeros(1)
    chassis_top, body_top, back = 0.24, 0.62, -0.08
    sides, body = (FRONT, BACK, LEFT, RIGHT), (FRONT, BACK, LEFT, RIGHT, TOP)
    cq, cn = box_faces(np.zeros((1, 2)), zero, 0.47 * one, 0.45 * one, zero, chassis_top * one, sides)
    bq, bn = box_faces(np.zeros((1, 2)), zero, 0.5 * one, 0.5 * one, (chassis_top - 0.01) * one,
                       body_top * one, body)
    kq, kn = box_faces(np.array([[back, 0.0]]), zero, 0.28 * one, 0.44 * one, body_top * one, one, body)
    quads = np.concatenate([cq, bq, kq], axis=1)[0]
    normals = np.concatenate([cn, bn, kn], axis=1)[0]
    sub = np.array([0] * 4 + [1] * 5 + [2] * 5, dtype=np.int64)
    return quads, normals, sub


_VEHICLE_QUADS, _VEHICLE_NORMALS, _VEHICLE_SUB = _vehicle_template()
_VEHICLE_FACES = len(_VEHICLE_SUB)


def vehicle_faces(xy: np.ndarray, yaw: np.ndarray, size: np.ndarray, colour: np.ndarray,
                  first_obj: int) -> Faces:
    """Each vehicle as tyres/chassis, body and a glass cabin with a painted roof."""
    n = len(xy)
    if n == 0:
        return Faces.empty()
    k = _VEHICLE_FACES
    local = _VEHICLE_QUADS[None] * size[:, None, None, :]  # (N, 14, 4, 3)
    c, s = np.cos(yaw)[:, None, None], np.sin(yaw)[:, None, None]
    quads = np.empty_like(local)
    quads[..., 0] = xy[:, 0, None, None] + c * local[..., 0] - s * local[..., 1]
    quads[..., 1] = xy[:, 1, None, None] + s * local[..., 0] + c * local[..., 1]
    quads[..., 2] = local[..., 2]
    ln = _VEHICLE_NORMALS
    c, s = c[..., 0], s[..., 0]
    normals = np.empty((n, k, 3))
    normals[..., 0] = c * ln[None, :, 0] - s * ln[None, :, 1]
    normals[..., 1] = s * ln[None, :, 0] + c * ln[None, :, 1]
    normals[..., 2] = ln[None, :, 2]
    paint = VEHICLE_COLOURS[np.asarray(colour, dtype=np.int64) % len(VEHICLE_COLOURS)]
    cols = np.empty((n, k, 3))
    cols[:, :4] = TYRES
    cols[:, 4:9] = paint[:, None, :]
    cols[:, 9:13] = GLASS
    cols[:, 13] = paint
    q = quads.reshape(-1, 4, 3)
    centre = 0.25 * (q[:, 0] + q[:, 1] + q[:, 2] + q[:, 3])
    return Faces(q, normals.reshape(-1, 3), cols.reshape(-1, 3),
                 np.repeat(np.arange(first_obj, first_obj + n), k), np.tile(_VEHICLE_SUB, n), centre)


# A pedestrian's three billboard parts (legs, torso, head): corners as (sideways, up)
# fractions of (width scale, height), counter-clockwise seen from the camera.
_PED_PARTS = ((0.17, 0.0, 0.47), (0.23, 0.47, 0.84), (0.11, 0.86, 1.0))  # half width, z0, z1
_PED_SIDE = np.array([[[-hw, hw, hw, -hw] for hw, _, _ in _PED_PARTS]])  # (1, 3, 4)
_PED_UP = np.array([[[z0, z0, z1, z1] for _, z0, z1 in _PED_PARTS]])


def _ped_colours() -> np.ndarray:
    """(P, 3, 3) trousers, shirt and skin for each colour index modulo P (the pattern's period)."""
    idx = np.arange(math.lcm(len(TROUSERS), 5 * len(SHIRTS), 35 * len(SKIN)))
    return np.stack([TROUSERS[idx % len(TROUSERS)], SHIRTS[(idx // 5) % len(SHIRTS)],
                     SKIN[(idx // 35) % len(SKIN)]], axis=1)


_PED_COLOURS = _ped_colours()


def pedestrian_faces(xy: np.ndarray, size: np.ndarray, colour: np.ndarray, eye: np.ndarray,
                     first_obj: int) -> Faces:
    """Each pedestrian as an upright figure (legs, torso, head) turned towards the camera."""
    n = len(xy)
    if n == 0:
        return Faces.empty()
    h = np.clip(size[:, 2], 1.0, 2.2)
    v = xy - eye[None, :2]
    d = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-6)
    tx, ty = -v[:, 0] / d, -v[:, 1] / d  # towards the eye
    side = _PED_SIDE * (np.minimum(h, 1.8) / 1.8)[:, None, None]  # (N, 3, 4), m
    quads = np.empty((n, 3, 4, 3))
    quads[..., 0] = xy[:, 0, None, None] + side * ty[:, None, None]  # sideways = (ty, -tx)
    quads[..., 1] = xy[:, 1, None, None] - side * tx[:, None, None]
    quads[..., 2] = _PED_UP * h[:, None, None]
    cols = _PED_COLOURS[np.asarray(colour, dtype=np.int64) % len(_PED_COLOURS)]
    normals = np.zeros((n, 3, 3))
    normals[..., 0] = tx[:, None]
    normals[..., 1] = ty[:, None]
    centre = np.empty((n, 3, 3))
    centre[..., 0], centre[..., 1] = xy[:, 0, None], xy[:, 1, None]
    centre[..., 2] = 0.5 * (_PED_UP[..., 0] + _PED_UP[..., 2]) * h[:, None]
    return Faces(quads.reshape(-1, 4, 3), normals.reshape(-1, 3), cols.reshape(-1, 3),
                 np.repeat(np.arange(first_obj, first_obj + n), 3), np.tile(np.arange(3), n),
                 centre.reshape(-1, 3))


def concat(parts: list[Faces]) -> Faces:
    parts = [p for p in parts if len(p.quads)]
    if not parts:
        return Faces.empty()
    return Faces(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                   ("quads", "normals", "colours", "obj", "sub", "centre")))
