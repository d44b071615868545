"""Static map geometry of a town: lanes, paved areas, markings, signals and buildings.

Computed once per town from the SUMO ``.net.xml`` (sumolib + shapely), cached on disk in the
town's build folder and memoised in-process. World frame = SUMO net frame (x east, y north,
metres); headings are radians counter-clockwise from +x.

Only edge functions (normal / internal / crossing / walkingarea), lane permissions and
connections are used, never our own edge naming, so a user's net (e.g. from OSM) works too.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import pickle
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import shapely
import sumolib
from shapely.geometry import LineString, Polygon, box
from shapely.geometry.polygon import orient

from bid_sim import towns

log = logging.getLogger(__name__)

# Bump when the geometry changes: old disk caches are then rebuilt.
VERSION = "town-map-v1"

SIGNAL_HEAD_Z_M = 3.5
SIGNAL_SIDE_OFFSET_M = 1.0  # pole this far beyond the right edge of the rightmost car lane
POLE_RADIUS_M = 0.15
PAINT_WIDTH_M = 0.15
STOP_LINE_WIDTH_M = 0.4
ZEBRA_BAR_M = 0.5
ZEBRA_GAP_M = 0.5

BLOCK_MARGIN_M = 30.0  # the town frame reaches this far beyond the network
BUILDING_CLEARANCE_M = 3.6  # from any paved area (≥ 3 m after the approximations below)
OUTER_BAND_M = 25.0  # buildings outside the network stay within this of the paved area
FRONTAGE_M = (8.0, 20.0)
DEPTH_M = (8.0, 16.0)
HEIGHT_M = (5.0, 25.0)
N_COLOURS = 8
MIN_LOT_AREA_M2 = 20.0
MIN_LOT_WIDTH_M = 3.0

GRID_CELL_M = 4.0
GRID_FAST_RADIUS_M = 8.0  # nearest_lanes queries up to this radius look at one grid cell

# Vehicle classes that make a lane asphalt rather than sidewalk.
_ROAD_CLASSES = (
    "passenger",
    "bus",
    "truck",
    "delivery",
    "taxi",
    "motorcycle",
    "moped",
    "bicycle",
    "emergency",
    "coach",
    "evehicle",
)

Ring = np.ndarray  # (N,2) float64 polygon ring, no repeated last point


# --------------------------------------------------------------------------- data types


@dataclass(frozen=True, eq=False)
class LaneGeom:
    """A driving lane (cars): normal, or internal (a junction connector)."""

    id: str
    edge: str
    index: int
    width_m: float
    speed_mps: float
    centre: np.ndarray  # (N,2) polyline in driving direction
    cum_s: np.ndarray  # (N,) cumulative length along centre, m
    internal: bool
    junction: str  # node id for internal lanes, '' otherwise

    def length_m(self) -> float:
        return float(self.cum_s[-1])

    def project(self, x: float, y: float) -> tuple[float, float, float]:
        """(s_m along centre, signed lateral offset_m (+ = left), lane heading_rad at s)."""
        a = self.centre[:-1]
        d = self.centre[1:] - a
        seg = np.diff(self.cum_s)
        px = x - a[:, 0]
        py = y - a[:, 1]
        t = np.clip((px * d[:, 0] + py * d[:, 1]) / (seg * seg), 0.0, 1.0)
        ex = px - t * d[:, 0]
        ey = py - t * d[:, 1]
        i = int(np.argmin(ex * ex + ey * ey))
        cross = d[i, 0] * py[i] - d[i, 1] * px[i]
        lateral = math.hypot(ex[i], ey[i]) * (1.0 if cross >= 0.0 else -1.0)
        return (
            float(self.cum_s[i] + t[i] * seg[i]),
            lateral,
            math.atan2(d[i, 1], d[i, 0]),
        )

    def point_at(self, s_m: float) -> tuple[float, float, float]:
        """x, y, heading_rad at s_m along the centre (clamped to the lane)."""
        s = min(max(s_m, 0.0), self.length_m())
        i = int(np.searchsorted(self.cum_s, s, side="right")) - 1
        i = min(max(i, 0), len(self.cum_s) - 2)
        a, b = self.centre[i], self.centre[i + 1]
        seg = self.cum_s[i + 1] - self.cum_s[i]
        t = (s - self.cum_s[i]) / seg
        p = a + t * (b - a)
        return float(p[0]), float(p[1]), math.atan2(b[1] - a[1], b[0] - a[0])


@dataclass(frozen=True, eq=False)
class StopLine:
    """Where a signalised incoming car lane ends."""

    lane_id: str
    tls_id: str
    link_indices: tuple[int, ...]  # indices into the tls state string, links leaving this lane
    p0: np.ndarray  # (2,) right end of the line across the lane end
    p1: np.ndarray  # (2,) left end
    heading_rad: float  # driving direction at the stop line


@dataclass(frozen=True, eq=False)
class SignalHead:
    """A traffic light housing on a pole at the right side of an incoming road."""

    tls_id: str
    link_index: int  # the rightmost car lane's first link
    lane_id: str  # that rightmost car lane
    position: np.ndarray  # (3,) housing centre x, y, z
    pole: np.ndarray  # (2,) pole base x, y
    facing_rad: float  # lamps face approaching traffic (lane heading + pi)
    link_indices: tuple[int, ...] = ()  # all links of all car lanes of the incoming edge


@dataclass(frozen=True, eq=False)
class Building:
    footprint: np.ndarray  # (N,2) polygon, CCW, no repeated last point
    height_m: float
    colour: int  # 0..7


@dataclass(frozen=True, eq=False)
class Marking:
    """Road paint: lane_dashed, centre_dashed, centre_solid, edge_solid or stop_line."""

    kind: str
    line: np.ndarray  # (N,2) polyline
    width_m: float


class _SegmentGrid:
    """Uniform grid over lane centre segments; each cell lists the segments that can lie
    within ``fast_radius`` of any point in the cell (CSR layout)."""

    def __init__(self, lanes: tuple[LaneGeom, ...], cell: float, fast_radius: float) -> None:
        rows = []
        for li, lane in enumerate(lanes):
            a = lane.centre[:-1]
            d = lane.centre[1:] - a
            seg = np.diff(lane.cum_s)
            rows.append(
                np.column_stack(
                    [
                        a[:, 0],
                        a[:, 1],
                        d[:, 0] / seg,
                        d[:, 1] / seg,
                        seg,
                        np.full(len(seg), li, float),
                        lane.cum_s[:-1],
                        np.arctan2(d[:, 1], d[:, 0]),
                    ]
                )
            )
        segs = np.concatenate(rows) if rows else np.zeros((0, 8))
        self.seg = np.ascontiguousarray(segs.T)  # (8, M)
        self.cell = cell
        self.fast_radius = fast_radius
        reach = fast_radius + cell * math.sqrt(0.5)
        pts = np.concatenate([segs[:, 0:2], segs[:, 0:2] + segs[:, 2:4] * segs[:, 4:5]])
        lo = pts.min(0) - reach - cell if len(pts) else np.zeros(2)
        hi = pts.max(0) + reach + cell if len(pts) else np.ones(2)
        self.x0, self.y0 = float(lo[0]), float(lo[1])
        self.nx = int((hi[0] - lo[0]) // cell) + 1
        self.ny = int((hi[1] - lo[1]) // cell) + 1
        keys, members = [], []
        for k, (ax, ay, ux, uy, length, *_rest) in enumerate(segs):
            bx, by = ax + ux * length, ay + uy * length
            i0 = int((min(ax, bx) - reach - self.x0) // cell)
            i1 = int((max(ax, bx) + reach - self.x0) // cell)
            j0 = int((min(ay, by) - reach - self.y0) // cell)
            j1 = int((max(ay, by) + reach - self.y0) // cell)
            ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
            cx = self.x0 + (ii.ravel() + 0.5) * cell - ax
            cy = self.y0 + (jj.ravel() + 0.5) * cell - ay
            t = np.clip(cx * ux + cy * uy, 0.0, length)
            near = (cx - t * ux) ** 2 + (cy - t * uy) ** 2 <= reach * reach
            cell_keys = ii.ravel()[near] * self.ny + jj.ravel()[near]
            keys.append(cell_keys)
            members.append(np.full(len(cell_keys), k))
        keys_a = np.concatenate(keys) if keys else np.zeros(0, int)
        members_a = np.concatenate(members) if members else np.zeros(0, int)
        order = np.argsort(keys_a, kind="stable")
        self.members = members_a[order].astype(np.int32)
        counts = np.bincount(keys_a, minlength=self.nx * self.ny)
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    def _cell_members(self, x: float, y: float, radius: float) -> np.ndarray:
        c = self.cell
        if radius <= self.fast_radius:
            i = int((x - self.x0) // c)
            j = int((y - self.y0) // c)
            if not (0 <= i < self.nx and 0 <= j < self.ny):
                return self.members[:0]
            k = i * self.ny + j
            return self.members[self.offsets[k] : self.offsets[k + 1]]
        i0 = max(int((x - radius - self.x0) // c), 0)
        i1 = min(int((x + radius - self.x0) // c), self.nx - 1)
        j0 = max(int((y - radius - self.y0) // c), 0)
        j1 = min(int((y + radius - self.y0) // c), self.ny - 1)
        parts = [
            self.members[self.offsets[i * self.ny + j0] : self.offsets[i * self.ny + j1 + 1]]
            for i in range(i0, i1 + 1)
        ]
        return np.unique(np.concatenate(parts)) if parts else self.members[:0]

    def query(self, x: float, y: float, radius: float) -> list[tuple[int, float, float, float]]:
        """(lane index, distance, s, heading) per lane within radius, nearest first."""
        idx = self._cell_members(x, y, radius)
        if idx.size == 0:
            return []
        ax, ay, ux, uy, length, lane, s0, heading = np.take(self.seg, idx, axis=1)
        px = x - ax
        py = y - ay
        t = np.clip(px * ux + py * uy, 0.0, length)
        ex = px - t * ux
        ey = py - t * uy
        d2 = ex * ex + ey * ey
        hit = np.flatnonzero(d2 <= radius * radius)
        if hit.size == 0:
            return []
        hit = hit[np.argsort(d2[hit], kind="stable")]
        out = []
        seen = set()
        for li, dd, s, h in zip(
            lane[hit].tolist(),
            d2[hit].tolist(),
            (s0 + t)[hit].tolist(),
            heading[hit].tolist(),
            strict=True,
        ):
            if li in seen:
                continue
            seen.add(li)
            out.append((int(li), math.sqrt(dd), s, h))
        return out


@dataclass(frozen=True, eq=False)
class TownMap:
    """The static geometry of one town (see the module docstring for frames and units)."""

    name: str
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax incl. buildings
    lanes: tuple[LaneGeom, ...]  # car lanes: normal + internal
    lane_index: dict[str, int]
    road_polygons: tuple[Ring, ...]  # asphalt: one per car lane and per junction area
    sidewalks: tuple[Ring, ...]  # sidewalk lanes and walking areas
    crossings: tuple[Ring, ...]
    crossing_stripes: tuple[Ring, ...]  # zebra bars
    junctions: tuple[Ring, ...]
    junction_ids: tuple[str, ...]
    markings: tuple[Marking, ...]
    stop_lines: tuple[StopLine, ...]
    signal_heads: tuple[SignalHead, ...]
    buildings: tuple[Building, ...]
    poles: np.ndarray  # (K,2) signal pole positions
    # Even-odd ring sets of the per-kind unions, so no polygon overlaps another of its layer:
    # "asphalt", "sidewalk", "crossing", "paved". Junction shapes include the walking areas:
    # draw asphalt, then sidewalk over it, then crossing stripes and markings.
    ground: dict[str, tuple[Ring, ...]] = field(default_factory=dict, repr=False)
    _paved: shapely.Geometry | None = field(default=None, repr=False)
    _grid: _SegmentGrid | None = field(default=None, repr=False)

    def lane(self, lane_id: str) -> LaneGeom:
        return self.lanes[self.lane_index[lane_id]]

    def nearest_lanes(
        self, x: float, y: float, radius_m: float = 6.0
    ) -> list[tuple[str, float, float, float]]:
        """Driving lanes whose centre passes within radius_m of (x, y):
        (lane_id, distance_m, s_m, lane heading_rad), nearest first."""
        lanes = self.lanes
        return [(lanes[li].id, d, s, h) for li, d, s, h in self._grid.query(x, y, radius_m)]

    @cached_property
    def _paved_prepared(self) -> shapely.Geometry:
        shapely.prepare(self._paved)
        return self._paved

    @cached_property
    def _building_boxes(self) -> np.ndarray:
        if not self.buildings:
            return np.zeros((4, 0))
        fp = [b.footprint for b in self.buildings]
        return np.array(
            [
                [f[:, 0].min() for f in fp],
                [f[:, 1].min() for f in fp],
                [f[:, 0].max() for f in fp],
                [f[:, 1].max() for f in fp],
            ]
        )

    @cached_property
    def _building_geoms(self) -> list[Polygon]:
        return [Polygon(b.footprint) for b in self.buildings]

    def is_paved(self, x: float, y: float) -> bool:
        """On road, junction, sidewalk, crossing or walking area."""
        return bool(shapely.intersects_xy(self._paved_prepared, x, y))

    def paved_mask_polygons(self) -> tuple[Ring, ...]:
        """Rings (exteriors and holes) of the paved area; fill them even-odd for a mask."""
        return self.ground.get("paved", ())

    def building_hit(self, corners: np.ndarray) -> int:
        """Index of a building whose footprint intersects the (4,2) box, or -1."""
        bb = self._building_boxes
        if bb.shape[1] == 0:
            return -1
        c = np.asarray(corners, float)
        x0, y0 = c.min(0)
        x1, y1 = c.max(0)
        cand = np.flatnonzero((bb[0] <= x1) & (bb[2] >= x0) & (bb[1] <= y1) & (bb[3] >= y0))
        if cand.size == 0:
            return -1
        poly = Polygon(c)
        geoms = self._building_geoms
        for i in cand.tolist():
            if geoms[i].intersects(poly):
                return i
        return -1

    def pole_hit(self, corners: np.ndarray, radius_m: float = POLE_RADIUS_M) -> int:
        """Index of a pole within radius_m of the (4,2) box, or -1."""
        if len(self.poles) == 0:
            return -1
        c = np.asarray(corners, float)
        x0, y0 = c.min(0) - radius_m
        x1, y1 = c.max(0) + radius_m
        p = self.poles
        cand = np.flatnonzero((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1))
        if cand.size == 0:
            return -1
        poly = Polygon(c)
        for i in cand.tolist():
            if shapely.distance(poly, shapely.Point(p[i])) <= radius_m:
                return i
        return -1

    def off_paved(self, corners: np.ndarray) -> bool:
        """True if any part of the (4,2) box lies outside the paved area."""
        return not bool(shapely.covers(self._paved_prepared, Polygon(np.asarray(corners, float))))


# --------------------------------------------------------------------------- geometry helpers


def _rings(geom: shapely.Geometry, min_area: float = 1e-3) -> list[Ring]:
    """CCW exterior rings of the polygon parts of geom."""
    out = []
    for part in shapely.get_parts(geom):
        if isinstance(part, Polygon) and part.area > min_area:
            ring = np.asarray(orient(part, 1.0).exterior.coords)[:-1]
            step = np.hypot(*(ring - np.roll(ring, 1, axis=0)).T)
            out.append(ring[step > 1e-9].copy())  # no repeated points, closing one included
    return out


def _all_rings(geom: shapely.Geometry) -> tuple[Ring, ...]:
    """Exteriors and holes of the polygon parts of geom (for even-odd filling)."""
    out = []
    for part in shapely.get_parts(geom):
        if isinstance(part, Polygon) and not part.is_empty:
            out.append(np.asarray(part.exterior.coords)[:-1].copy())
            out.extend(np.asarray(r.coords)[:-1].copy() for r in part.interiors)
    return tuple(out)


def _fill_holes(geom: shapely.Geometry, max_area: float) -> shapely.Geometry:
    """geom without holes smaller than max_area (slivers where strips meet at junctions)."""
    parts = []
    for part in shapely.get_parts(geom):
        if isinstance(part, Polygon):
            holes = [r for r in part.interiors if Polygon(r).area >= max_area]
            parts.append(Polygon(part.exterior, holes))
    return shapely.union_all(parts)


def _polyline(shape: list[tuple[float, float]]) -> np.ndarray:
    """Shape points as (N,2) without zero-length steps."""
    p = np.asarray(shape, float)[:, :2]
    if len(p) < 2:
        return p
    keep = np.concatenate([[True], np.hypot(*np.diff(p, axis=0).T) > 1e-6])
    return p[keep]


def _strip(line: np.ndarray, width: float) -> shapely.Geometry:
    return LineString(line).buffer(
        width / 2.0, cap_style="flat", join_style="mitre", mitre_limit=3.0
    )


def _offset(line: np.ndarray, dist: float) -> list[np.ndarray]:
    """Polylines offset dist to the left of line (negative = right), same direction."""
    geom = shapely.offset_curve(LineString(line), dist, join_style="mitre", mitre_limit=3.0)
    return [np.asarray(g.coords) for g in shapely.get_parts(geom) if g.length > 0.5]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _is_car_lane(lane: sumolib.net.lane.Lane) -> bool:
    return lane.allows("passenger")


def _is_road_lane(lane: sumolib.net.lane.Lane) -> bool:
    return any(lane.allows(c) for c in _ROAD_CLASSES)


def _node_id(edge: sumolib.net.edge.Edge) -> str:
    node = edge.getFromNode()
    if node is not None:
        return node.getID()
    return edge.getID()[1:].rsplit("_", 1)[0]


# --------------------------------------------------------------------------- build steps


def _collect_lanes(net: sumolib.net.Net) -> tuple[list[LaneGeom], list[Ring]]:
    """Car lanes (normal and internal) and asphalt strips of every road lane."""
    lanes, asphalt = [], []
    for edge in sorted(net.getEdges(withInternal=True), key=lambda e: e.getID()):
        function = edge.getFunction()
        if function not in ("", "internal"):
            continue
        internal = function == "internal"
        for lane in edge.getLanes():
            if not _is_road_lane(lane):
                continue
            centre = _polyline(lane.getShape())
            if len(centre) < 2:
                continue
            width = float(lane.getWidth())
            asphalt += _rings(_strip(centre, width))
            if not _is_car_lane(lane):
                continue
            cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(centre, axis=0).T))])
            lanes.append(
                LaneGeom(
                    id=lane.getID(),
                    edge=edge.getID(),
                    index=lane.getIndex(),
                    width_m=width,
                    speed_mps=float(lane.getSpeed()),
                    centre=centre,
                    cum_s=cum,
                    internal=internal,
                    junction=_node_id(edge) if internal else "",
                )
            )
    return lanes, asphalt


def _collect_pedestrian(net: sumolib.net.Net, zebra_width_m: float | None = None
                        ) -> tuple[list[Ring], list[Ring], list[Ring]]:
    """Sidewalk polygons (lanes + walking areas), crossing polygons and zebra bars.

    With `zebra_width_m` the bars are painted that wide, grown or shrunk on the junction's side:
    netconvert keeps a crossing's edge at the street's lane end and moves the other with
    `--default.crossing-width`, so a 2 m crossing painted 4 m wide looks as the 4 m one does."""
    sidewalks, crossings, stripes = [], [], []
    for edge in sorted(net.getEdges(withInternal=True), key=lambda e: e.getID()):
        function = edge.getFunction()
        for lane in edge.getLanes():
            shape = _polyline(lane.getShape())
            width = float(lane.getWidth())
            if function == "walkingarea":
                if len(shape) >= 3:
                    sidewalks += _rings(shapely.make_valid(Polygon(shape)))
            elif function == "crossing":
                if len(shape) >= 2:
                    crossings += _rings(_strip(shape, width))
                    a, b = shape[0], shape[-1]
                    if zebra_width_m is not None and zebra_width_m != width:
                        grow = _toward_junction(a, b, edge.getFromNode().getCoord()) * (zebra_width_m - width) / 2
                        a, b, width = a + grow, b + grow, zebra_width_m
                    stripes += _zebra(a, b, width)
            elif (
                function == ""
                and lane.allows("pedestrian")
                and not _is_road_lane(lane)
                and len(shape) >= 2
            ):
                sidewalks += _rings(_strip(shape, width))
    return sidewalks, crossings, stripes


def _toward_junction(a: np.ndarray, b: np.ndarray, node_xy) -> np.ndarray:
    """The unit normal of the crossing a -> b on the side of its junction's centre."""
    u = (b - a) / float(np.hypot(*(b - a)))
    n = np.array([-u[1], u[0]])
    return n if float(np.dot(np.asarray(node_xy[:2], dtype=float) - (a + b) / 2, n)) >= 0 else -n


def _zebra(a: np.ndarray, b: np.ndarray, width: float) -> list[Ring]:
    """Bars across the crossing from a to b, centred along its length."""
    length = float(np.hypot(*(b - a)))
    n_bars = int((length + ZEBRA_GAP_M) // (ZEBRA_BAR_M + ZEBRA_GAP_M))
    if n_bars <= 0:
        return []
    u = (b - a) / length
    n = np.array([-u[1], u[0]])
    half = width / 2.0 - 0.25
    start = (length - (n_bars * ZEBRA_BAR_M + (n_bars - 1) * ZEBRA_GAP_M)) / 2.0
    bars = []
    for k in range(n_bars):
        s0 = start + k * (ZEBRA_BAR_M + ZEBRA_GAP_M)
        s1 = s0 + ZEBRA_BAR_M
        bars.append(
            np.array(
                [
                    a + u * s0 - n * half,
                    a + u * s1 - n * half,
                    a + u * s1 + n * half,
                    a + u * s0 + n * half,
                ]
            )
        )
    return bars


def _collect_junctions(net: sumolib.net.Net) -> tuple[list[Ring], list[str]]:
    polys, ids = [], []
    for node in sorted(net.getNodes(), key=lambda n: n.getID()):
        shape = node.getShape()
        if not shape or len(shape) < 3:
            continue
        for ring in _rings(shapely.make_valid(Polygon(_polyline(shape))), min_area=0.1):
            polys.append(ring)
            ids.append(node.getID())
    return polys, ids


def _signals(
    net: sumolib.net.Net, lanes: list[LaneGeom], index: dict[str, int]
) -> tuple[list[StopLine], list[SignalHead]]:
    """One StopLine per signalised incoming car lane, one SignalHead per incoming edge."""
    links: dict[tuple[str, str], set[int]] = {}
    for tls in net.getTrafficLights():
        for in_lane, _out_lane, link in tls.getConnections():
            if in_lane.getEdge().getFunction() == "" and in_lane.getID() in index:
                links.setdefault((in_lane.getID(), tls.getID()), set()).add(int(link))
    stop_lines = []
    for (lane_id, tls_id), idx in sorted(links.items()):
        lane = lanes[index[lane_id]]
        end = lane.centre[-1]
        d = lane.centre[-1] - lane.centre[-2]
        heading = math.atan2(d[1], d[0])
        left = np.array([-math.sin(heading), math.cos(heading)])
        half = lane.width_m / 2.0
        stop_lines.append(
            StopLine(
                lane_id=lane_id,
                tls_id=tls_id,
                link_indices=tuple(sorted(idx)),
                p0=end - left * half,
                p1=end + left * half,
                heading_rad=heading,
            )
        )
    by_edge: dict[tuple[str, str], list[StopLine]] = {}
    for sl in stop_lines:
        by_edge.setdefault((sl.tls_id, lanes[index[sl.lane_id]].edge), []).append(sl)
    heads = []
    for (tls_id, _edge), group in sorted(by_edge.items()):
        right = min(group, key=lambda sl: lanes[index[sl.lane_id]].index)
        lane = lanes[index[right.lane_id]]
        h = right.heading_rad
        rightward = np.array([math.sin(h), -math.cos(h)])
        pole = lane.centre[-1] + rightward * (lane.width_m / 2.0 + SIGNAL_SIDE_OFFSET_M)
        heads.append(
            SignalHead(
                tls_id=tls_id,
                link_index=right.link_indices[0],
                lane_id=right.lane_id,
                position=np.array([pole[0], pole[1], SIGNAL_HEAD_Z_M]),
                pole=pole,
                facing_rad=_wrap(h + math.pi),
                link_indices=tuple(sorted({i for sl in group for i in sl.link_indices})),
            )
        )
    return stop_lines, heads


def _markings(
    net: sumolib.net.Net, lanes: list[LaneGeom], stop_lines: list[StopLine]
) -> list[Marking]:
    """Lane dividers, centre lines, road edges (normal edges only) and stop lines."""
    car: dict[str, list[LaneGeom]] = {}
    for lane in lanes:
        if not lane.internal:
            car.setdefault(lane.edge, []).append(lane)
    for group in car.values():
        group.sort(key=lambda g: g.index)
    ends: dict[tuple[str, str], list[str]] = {}
    for edge in net.getEdges(withInternal=False):
        if edge.getID() in car:
            key = (edge.getFromNode().getID(), edge.getToNode().getID())
            ends.setdefault(key, []).append(edge.getID())

    def left_boundary(edge_id: str) -> list[np.ndarray]:
        top = car[edge_id][-1]
        return _offset(top.centre, top.width_m / 2.0)

    out = []
    for edge_id in sorted(car):
        group = car[edge_id]
        first = group[0]
        out += [
            Marking("edge_solid", ln, PAINT_WIDTH_M)
            for ln in _offset(first.centre, -first.width_m / 2.0)
        ]
        for lane in group[:-1]:
            out += [
                Marking("lane_dashed", ln, PAINT_WIDTH_M)
                for ln in _offset(lane.centre, lane.width_m / 2.0)
            ]
        edge = net.getEdge(edge_id)
        mine = left_boundary(edge_id)
        shared = None
        for other in sorted(ends.get((edge.getToNode().getID(), edge.getFromNode().getID()), [])):
            theirs = left_boundary(other)
            if mine and theirs and _same_line(mine[0], theirs[0]):
                shared = other
                break
        if shared is None:
            out += [Marking("edge_solid", ln, PAINT_WIDTH_M) for ln in mine]
        elif edge_id < shared:
            single = len(group) == 1 and len(car[shared]) == 1
            kind = "centre_dashed" if single else "centre_solid"
            out += [Marking(kind, ln, PAINT_WIDTH_M) for ln in mine]
    for sl in stop_lines:
        back = np.array([math.cos(sl.heading_rad), math.sin(sl.heading_rad)]) * (
            STOP_LINE_WIDTH_M / 2.0
        )
        out.append(Marking("stop_line", np.array([sl.p0 - back, sl.p1 - back]), STOP_LINE_WIDTH_M))
    return out


def _same_line(a: np.ndarray, b: np.ndarray, tol: float = 0.5) -> bool:
    """True if polyline b runs along a (within tol at its midpoint and ends)."""
    la = LineString(a)
    lb = LineString(b)
    return all(la.distance(lb.interpolate(f, normalized=True)) < tol for f in (0.1, 0.5, 0.9))


def _buildings(paved: shapely.Geometry, name: str) -> list[Building]:
    """Lots along the block boundaries, deterministic per town name."""
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    xmin, ymin, xmax, ymax = paved.bounds
    frame = box(
        xmin - BLOCK_MARGIN_M, ymin - BLOCK_MARGIN_M, xmax + BLOCK_MARGIN_M, ymax + BLOCK_MARGIN_M
    )
    clear = paved.buffer(BUILDING_CLEARANCE_M, quad_segs=2)
    band = paved.buffer(BUILDING_CLEARANCE_M + OUTER_BAND_M, quad_segs=2)
    # Lots front only on block sides that face the streets (not the outer band's far side).
    street_side = paved.buffer(BUILDING_CLEARANCE_M + 1.0, quad_segs=2)
    shapely.prepare(street_side)
    pieces = []
    for piece in shapely.get_parts(frame.difference(clear)):
        if piece.intersects(frame.exterior):
            piece = piece.intersection(band)
        for part in shapely.get_parts(piece.simplify(0.3)):
            if isinstance(part, Polygon) and part.area >= MIN_LOT_AREA_M2:
                pieces.append(orient(part, 1.0))
    pieces.sort(key=lambda p: (round(p.centroid.x, 1), round(p.centroid.y, 1)))
    out = []
    for block in pieces:
        taken = Polygon()
        for ring in [block.exterior, *block.interiors]:
            for side in _sides(np.asarray(ring.coords)):
                for lot in _lots(side, block, street_side, rng):
                    lot = _clean_lot(lot.difference(taken))
                    if lot is None:
                        continue
                    taken = taken.union(lot)
                    out.append(
                        Building(
                            footprint=_rings(lot)[0],
                            height_m=float(rng.uniform(*HEIGHT_M)),
                            colour=int(rng.integers(0, N_COLOURS)),
                        )
                    )
    return out


def _clean_lot(lot: shapely.Geometry) -> Polygon | None:
    """The lot without strips narrower than 3 m (left where lots meet), or None if too small."""
    opened = lot.buffer(-MIN_LOT_WIDTH_M / 2.0, join_style="mitre").buffer(
        MIN_LOT_WIDTH_M / 2.0, join_style="mitre"
    )
    parts = [p for p in shapely.get_parts(opened.intersection(lot)) if isinstance(p, Polygon)]
    if not parts:
        return None
    best = max(parts, key=lambda p: p.area)
    best = shapely.remove_repeated_points(best, 1e-3)
    if best.area < MIN_LOT_AREA_M2 or best.buffer(-MIN_LOT_WIDTH_M / 2.0 + 0.01).is_empty:
        return None
    return best


def _sides(ring: np.ndarray, corner_deg: float = 35.0) -> list[np.ndarray]:
    """Splits a closed ring (last point = first) into polylines at sharp corners."""
    p = ring[:-1]
    n = len(p)
    if n < 3:
        return []
    d_in = p - np.roll(p, 1, axis=0)
    d_out = np.roll(p, -1, axis=0) - p
    turn = np.abs(
        np.arctan2(
            d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0],
            (d_in * d_out).sum(1),
        )
    )
    corners = np.flatnonzero(turn > math.radians(corner_deg))
    if corners.size == 0:
        return [ring]
    sides = []
    for a, b in zip(corners, np.roll(corners, -1), strict=True):
        idx = np.arange(a, b + 1) if b > a else np.concatenate([np.arange(a, n), np.arange(b + 1)])
        sides.append(p[idx])
    return sides


def _lots(
    side: np.ndarray, block: Polygon, street_side: shapely.Geometry, rng: np.random.Generator
) -> list[Polygon]:
    """Rectangular lots along one block side (block interior on the left), clipped to the block."""
    line = LineString(side)
    total = line.length
    if total < FRONTAGE_M[0]:
        return []
    out = []
    s = 0.0
    while total - s >= FRONTAGE_M[0]:
        f = float(rng.uniform(*FRONTAGE_M))
        depth = float(rng.uniform(*DEPTH_M))
        if total - (s + f) < FRONTAGE_M[0]:
            f = total - s
        mid = line.interpolate(s + f / 2.0)
        if shapely.contains_xy(street_side, mid.x, mid.y):
            a = np.asarray(line.interpolate(s).coords[0])
            b = np.asarray(line.interpolate(s + f).coords[0])
            chord = b - a
            length = float(np.hypot(*chord))
            if length > 1.0:
                u = chord / length
                n = np.array([-u[1], u[0]])
                back = -n * 2.0  # reach behind the chord so the lot front follows curved sides
                rect = Polygon([a + back, b + back, b + n * depth, a + n * depth])
                out.append(rect.intersection(block))
        s += f
    return out


# --------------------------------------------------------------------------- build + cache

_BUILD_COUNT = 0  # how many maps this process built from scratch (tests read it)


def build_count() -> int:
    return _BUILD_COUNT


def build_town_map(net_file: str | os.PathLike, name: str, zebra_width_m: float | None = None) -> TownMap:
    """Builds the map from a .net.xml without any caching; `zebra_width_m` paints the crossings'
    zebras that wide (see _collect_pedestrian), None as wide as the crossings."""
    global _BUILD_COUNT
    _BUILD_COUNT += 1
    log.info("building town map %s from %s", name, net_file)
    net = sumolib.net.readNet(str(net_file), withInternal=True, withPedestrianConnections=True)
    lanes, asphalt = _collect_lanes(net)
    index = {lane.id: i for i, lane in enumerate(lanes)}
    sidewalks, crossings, stripes = _collect_pedestrian(net, zebra_width_m)
    junctions, junction_ids = _collect_junctions(net)
    stop_lines, heads = _signals(net, lanes, index)
    markings = _markings(net, lanes, stop_lines)
    road = asphalt + junctions

    # Unions close the float slivers where strips meet; holes under 1 m² are such slivers too.
    asphalt_u = _fill_holes(shapely.union_all([Polygon(r) for r in road]), 1.0)
    sidewalk_u = _fill_holes(shapely.union_all([Polygon(r) for r in sidewalks]), 1.0)
    crossing_u = shapely.union_all([Polygon(r) for r in crossings])
    paved = _fill_holes(
        shapely.union_all([asphalt_u, sidewalk_u, crossing_u]).buffer(0.02, quad_segs=1), 1.0
    )
    buildings = _buildings(paved, name)

    everything = [paved.bounds] + [(*b.footprint.min(0), *b.footprint.max(0)) for b in buildings]
    ev = np.array(everything)
    bounds = (
        float(ev[:, 0].min()),
        float(ev[:, 1].min()),
        float(ev[:, 2].max()),
        float(ev[:, 3].max()),
    )
    lanes_t = tuple(lanes)
    return TownMap(
        name=name,
        bounds=bounds,
        lanes=lanes_t,
        lane_index=index,
        road_polygons=tuple(road),
        sidewalks=tuple(sidewalks),
        crossings=tuple(crossings),
        crossing_stripes=tuple(stripes),
        junctions=tuple(junctions),
        junction_ids=tuple(junction_ids),
        markings=tuple(markings),
        stop_lines=tuple(stop_lines),
        signal_heads=tuple(heads),
        buildings=tuple(buildings),
        poles=np.array([h.pole for h in heads]).reshape(-1, 2),
        ground={
            "asphalt": _all_rings(asphalt_u),
            "sidewalk": _all_rings(sidewalk_u),
            "crossing": _all_rings(crossing_u),
            "paved": _all_rings(paved),
        },
        _paved=paved,
        _grid=_SegmentGrid(lanes_t, GRID_CELL_M, GRID_FAST_RADIUS_M),
    )


_MEMO: dict[tuple[str, str, float | None, int, int], TownMap] = {}


def cache_key(net_file: Path, name: str, zebra_width_m: float | None = None) -> str:
    """Hash of the net's bytes, the town name (it seeds the buildings), the zebras' painted
    width when set and VERSION."""
    h = hashlib.sha256(VERSION.encode())
    h.update(name.encode())
    if zebra_width_m is not None:
        h.update(f"zebra {zebra_width_m:g}".encode())
    h.update(net_file.read_bytes())
    return h.hexdigest()[:20]


def load_town_map(town: towns.Town, cache_dir: str | os.PathLike | None = None) -> TownMap:
    """The town's map: from memory, else from the disk cache, else built and cached.

    cache_dir defaults to the town's build folder (``BUILD / town.folder.name``).
    """
    net_file = Path(town.net_file).resolve()
    st = net_file.stat()
    memo_key = (str(net_file), town.name, town.zebra_width_m, st.st_mtime_ns, st.st_size)
    if memo_key in _MEMO:
        return _MEMO[memo_key]
    folder = Path(cache_dir) if cache_dir is not None else towns.BUILD / town.folder.name
    key = cache_key(net_file, town.name, town.zebra_width_m)
    path = folder / f"town_map-{key}.pkl"
    town_map = None
    if path.exists():
        try:
            with path.open("rb") as f:
                town_map = pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError) as e:
            log.warning("ignoring unreadable town map cache %s (%s)", path, e)
    if town_map is None:
        town_map = build_town_map(net_file, town.name, town.zebra_width_m)
        folder.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        with tmp.open("wb") as f:
            pickle.dump(town_map, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)  # atomic: readers never see a half-written cache
        for old in folder.glob("town_map-*.pkl"):
            if old != path:
                old.unlink(missing_ok=True)
    _MEMO[memo_key] = town_map
    return town_map
