"""Town map geometry on the real built networks of Town01, Town02 and Town05."""

import hashlib
import math
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon

from bid_sim import town_map as tm
from bid_sim import towns
from bid_sim.towns import Town, resolve_town

TOWNS = ("01", "02", "05")
MIN_BUILDINGS = {"01": 40, "02": 20, "05": 20}


@pytest.fixture(scope="module", params=TOWNS)
def town_id(request):
    return request.param


@pytest.fixture(scope="module")
def maps():
    return {t: tm.load_town_map(resolve_town(t)) for t in TOWNS}


@pytest.fixture(scope="module")
def town_map(maps, town_id):
    return maps[town_id]


def angle_diff(a, b):
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def ego_box(x, y, yaw, length=4.6, width=1.9):
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
    return local @ np.array([[c, s], [-s, c]]) + [x, y]


def paved_union(m):
    return shapely.union_all([Polygon(r) for r in m.road_polygons + m.sidewalks + m.crossings])


def footprint_digest(m):
    h = hashlib.sha256()
    for b in m.buildings:
        h.update(b.footprint.tobytes())
        h.update(np.float64(b.height_m).tobytes())
        h.update(bytes([b.colour]))
    return h.hexdigest()


def test_lanes_have_geometry(town_map):
    assert town_map.lanes
    assert any(lane.internal for lane in town_map.lanes)
    for i, lane in enumerate(town_map.lanes):
        assert town_map.lane_index[lane.id] == i
        assert lane.centre.shape[1] == 2 and len(lane.centre) >= 2
        assert lane.length_m() > 0
        assert np.all(np.diff(lane.cum_s) > 0)
        assert 3.5 <= lane.width_m <= 4.0
        assert lane.internal == lane.edge.startswith(":")
        assert bool(lane.junction) == lane.internal


def test_nearest_lane_on_centre(town_map):
    for lane in town_map.lanes:
        x, y, heading = lane.point_at(0.5 * lane.length_m())
        found = town_map.nearest_lanes(x, y)
        assert found and found[0][1] < 1e-6
        if lane.internal:  # junction connectors overlap where they diverge or cross
            match = [f for f in found if f[0] == lane.id]
            assert match and match[0][1] < 1e-6
        else:
            lane_id, _, s, h = found[0]
            assert lane_id == lane.id
            assert s == pytest.approx(0.5 * lane.length_m(), abs=1e-6)
            assert angle_diff(h, heading) < 1e-9
        assert [f[1] for f in found] == sorted(f[1] for f in found)
        assert len({f[0] for f in found}) == len(found)


def test_nearest_lanes_radius_and_speed(town_map):
    lane = next(lane for lane in town_map.lanes if not lane.internal)
    x, y, h = lane.point_at(0.5 * lane.length_m())
    left = (x - 2.0 * math.sin(h), y + 2.0 * math.cos(h))
    near = {f[0]: f[1] for f in town_map.nearest_lanes(*left, radius_m=2.5)}
    assert near[lane.id] == pytest.approx(2.0, abs=1e-6)
    assert lane.id not in {f[0] for f in town_map.nearest_lanes(*left, radius_m=1.5)}
    # A large radius takes the slow path and must agree with the fast one.
    fast = town_map.nearest_lanes(x, y, radius_m=6.0)
    slow = [f for f in town_map.nearest_lanes(x, y, radius_m=30.0) if f[1] <= 6.0]
    assert [f[0] for f in fast] == [f[0] for f in slow]
    far = town_map.bounds[0] - 100.0, town_map.bounds[1] - 100.0
    assert town_map.nearest_lanes(*far) == []
    # Its speed (~20 µs a query) is measured by benchmarks/bench_world.py, not asserted here.


def test_project_round_trips_point_at(town_map):
    for lane in town_map.lanes[::3]:
        for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
            s = frac * lane.length_m()
            x, y, heading = lane.point_at(s)
            ps, lateral, ph = lane.project(x, y)
            assert ps == pytest.approx(s, abs=1e-6)
            assert abs(lateral) < 1e-6
            if 0.0 < frac < 1.0:
                assert angle_diff(ph, heading) < 1e-6
        if not lane.internal:
            x, y, h = lane.point_at(0.5 * lane.length_m())
            _, lateral, _ = lane.project(x - 0.5 * math.sin(h), y + 0.5 * math.cos(h))
            assert lateral == pytest.approx(0.5, abs=1e-3)  # + = left of driving direction


def signalised_car_lanes(net_file):
    """{incoming car lane id: {(tls id, link index)}} read straight from the XML."""
    root = ET.parse(net_file).getroot()
    car = set()
    for edge in root.iter("edge"):
        if edge.get("function") is None:
            for lane in edge.iter("lane"):
                if lane.get("allow") != "pedestrian":
                    car.add(lane.get("id"))
    out = {}
    for con in root.iter("connection"):
        lane_id = f"{con.get('from')}_{con.get('fromLane')}"
        if con.get("tl") and lane_id in car:
            out.setdefault(lane_id, set()).add((con.get("tl"), int(con.get("linkIndex"))))
    return out


def test_stop_lines_match_the_net(town_map, town_id):
    expected = signalised_car_lanes(resolve_town(town_id).net_file)
    assert len(town_map.stop_lines) == len(expected)
    for sl in town_map.stop_lines:
        assert {(sl.tls_id, i) for i in sl.link_indices} == expected[sl.lane_id]
        lane = town_map.lane(sl.lane_id)
        end = lane.centre[-1]
        assert np.allclose((sl.p0 + sl.p1) / 2, end)
        assert np.hypot(*(sl.p1 - sl.p0)) == pytest.approx(lane.width_m)
        _, lateral, _ = lane.project(*sl.p0)
        assert lateral < 0  # p0 is the right end
    stop_marks = [m for m in town_map.markings if m.kind == "stop_line"]
    assert len(stop_marks) == len(town_map.stop_lines)


def test_signal_heads_face_traffic(town_map):
    heads = town_map.signal_heads
    assert heads
    edges = {(town_map.lane(sl.lane_id).edge, sl.tls_id) for sl in town_map.stop_lines}
    assert len(heads) == len(edges)
    assert town_map.poles.shape == (len(heads), 2)
    for h in heads:
        lane = town_map.lane(h.lane_id)
        _, _, heading = lane.point_at(lane.length_m())
        assert angle_diff(h.facing_rad, heading) == pytest.approx(math.pi, abs=1e-6)
        assert 3.0 <= h.position[2] <= 4.0
        assert np.allclose(h.position[:2], h.pole)
        _, lateral, _ = lane.project(*h.pole)
        assert lateral < -lane.width_m / 2  # right of the road
        assert h.link_index in h.link_indices


def test_markings(town_map, town_id):
    kinds = {m.kind for m in town_map.markings}
    assert {"edge_solid", "stop_line"} <= kinds
    if town_id in ("01", "02"):
        assert "centre_dashed" in kinds and "centre_solid" not in kinds
        assert "lane_dashed" not in kinds
    else:
        assert {"centre_solid", "lane_dashed"} <= kinds
    for m in town_map.markings:
        assert m.line.ndim == 2 and m.line.shape[1] == 2 and len(m.line) >= 2
        assert m.width_m == (0.4 if m.kind == "stop_line" else 0.15)


def test_pedestrian_areas(town_map):
    assert town_map.sidewalks and town_map.crossings
    assert len(town_map.crossing_stripes) >= 4 * len(town_map.crossings)
    assert len(town_map.junctions) == len(town_map.junction_ids)
    for ring in town_map.crossing_stripes:  # 0.5 m bars along the walking direction
        assert ring.shape == (4, 2)
        assert np.hypot(*(ring[1] - ring[0])) == pytest.approx(0.5)


def test_buildings_clear_of_paved_area(town_map, town_id):
    assert len(town_map.buildings) > MIN_BUILDINGS[town_id]
    paved = paved_union(town_map)
    shapely.prepare(paved)
    x0, y0, x1, y1 = town_map.bounds
    for b in town_map.buildings:
        poly = Polygon(b.footprint)
        assert poly.is_valid and poly.area >= 20.0
        assert shapely.is_ccw(poly.exterior)
        assert not np.allclose(b.footprint[0], b.footprint[-1])
        assert paved.distance(poly) >= 3.0  # corners stay open so the lights are visible
        assert 5.0 <= b.height_m <= 25.0 and 0 <= b.colour <= 7
        bx0, by0 = b.footprint.min(0)
        bx1, by1 = b.footprint.max(0)
        assert x0 <= bx0 and y0 <= by0 and bx1 <= x1 and by1 <= y1
    polys = [Polygon(b.footprint) for b in town_map.buildings]
    tree = shapely.STRtree(polys)
    for i, j in tree.query(polys, predicate="intersects").T:
        if i < j:  # neighbours may share a wall, never floor area
            assert polys[i].intersection(polys[j]).area < 1e-3


def test_buildings_deterministic_across_processes(maps):
    town = resolve_town("02")
    a = tm.build_town_map(town.net_file, town.name)
    b = tm.build_town_map(town.net_file, town.name)
    assert footprint_digest(a) == footprint_digest(b) == footprint_digest(maps["02"])
    code = (
        "import sys; sys.path.insert(0, 'tests'); from test_town_map import footprint_digest;"
        "from bid_sim import town_map as tm; from bid_sim.towns import resolve_town;"
        "t = resolve_town('02'); print(footprint_digest(tm.build_town_map(t.net_file, t.name)))"
    )
    root = towns.PACKAGE_ROOT
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == footprint_digest(a)


def test_is_paved(town_map):
    for lane in town_map.lanes[::2]:
        x, y, _ = lane.point_at(0.5 * lane.length_m())
        assert town_map.is_paved(x, y)
    for b in town_map.buildings[::5]:
        p = Polygon(b.footprint).representative_point()
        assert not town_map.is_paved(p.x, p.y)


def test_box_checks(town_map):
    for i, b in enumerate(town_map.buildings[::7]):
        p = Polygon(b.footprint).buffer(-0.5).representative_point()
        inside = np.array([[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]) + np.array([p.x, p.y])
        assert town_map.building_hit(inside) == 7 * i
        assert town_map.off_paved(inside)
    for lane in town_map.lanes:
        if lane.internal:
            continue
        x, y, h = lane.point_at(0.5 * lane.length_m())
        box = ego_box(x, y, h)
        assert town_map.building_hit(box) == -1
        assert not town_map.off_paved(box)
        assert town_map.pole_hit(box) == -1
    for k, pole in enumerate(town_map.poles):
        near = ego_box(pole[0] + 1.1, pole[1], 0.0, 2.0, 1.0)  # box edge 0.1 m from the pole
        assert town_map.pole_hit(near) == k
        assert town_map.pole_hit(near, radius_m=0.05) == -1


def test_disk_cache_reused_and_invalidated(tmp_path, monkeypatch):
    folder = tmp_path / "mytown"
    folder.mkdir()
    net = folder / "mytown.net.xml"
    shutil.copy(resolve_town("02").net_file, net)
    monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
    town = Town(name="MyTown", folder=folder)

    before = tm.build_count()
    first = tm.load_town_map(town)
    assert tm.build_count() == before + 1
    caches = list((tmp_path / "build" / "mytown").glob("town_map-*.pkl"))
    assert len(caches) == 1
    assert tm.load_town_map(town) is first  # in-process memo

    tm._MEMO.clear()
    mtime = caches[0].stat().st_mtime_ns
    again = tm.load_town_map(town)
    assert tm.build_count() == before + 1  # read from disk, not rebuilt
    assert caches[0].stat().st_mtime_ns == mtime
    assert footprint_digest(again) == footprint_digest(first)
    assert again.nearest_lanes(*again.lanes[0].centre[0])

    with net.open("a") as f:
        f.write("<!-- edited -->\n")
    changed = Town(name="MyTown", folder=folder)
    tm.load_town_map(changed)
    assert tm.build_count() == before + 2
    now = list((tmp_path / "build" / "mytown").glob("town_map-*.pkl"))
    assert len(now) == 1 and now[0] != caches[0]
