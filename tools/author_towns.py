"""Authoring aid, run by a developer, never at run time: writes scenarios/townNN plain XML.

It reads the CARLA layout facts in ../shared/reference (junction positions, which junctions
each street joins, the street's polyline, lanes per direction, signals) and writes our own
SUMO plain-XML nodes and edges. Users do not have ../shared; they get the written XML.

    .venv/bin/python tools/author_towns.py ../shared/reference

Frames: the reference is in CARLA's left-handed frame (x east, y south); ours is x east,
y north, so y flips sign. Right-hand traffic is a physical fact and survives the flip.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MPH25 = 11.18  # 25 mph in m/s
RING_SPEED = 13.89  # Town05 outer ring (50 km/h)


def _flip(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    return np.column_stack([p[:, 0], -p[:, 1]])


def _chain(polylines: list[np.ndarray], start: np.ndarray) -> np.ndarray:
    """Joins per-road polylines into one from the end nearest `start`."""
    rest = list(polylines)
    out = [start[None, :]]
    cur = start
    while rest:
        best = min(
            range(len(rest)),
            key=lambda i: min(np.linalg.norm(rest[i][0] - cur), np.linalg.norm(rest[i][-1] - cur)),
        )
        p = rest.pop(best)
        if np.linalg.norm(p[-1] - cur) < np.linalg.norm(p[0] - cur):
            p = p[::-1]
        out.append(p)
        cur = p[-1]
    return np.concatenate(out[1:])


def _offset_left(line: np.ndarray, dist_m: float) -> np.ndarray:
    """Shifts a polyline to its left (driving direction) by dist_m."""
    d = np.gradient(line, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    left = np.column_stack([-d[:, 1], d[:, 0]])
    return line + dist_m * left


def _simplify(line: np.ndarray, min_step_m: float = 2.0) -> np.ndarray:
    keep = [line[0]]
    for p in line[1:]:
        if np.linalg.norm(p - keep[-1]) >= min_step_m:
            keep.append(p)
    return np.array(keep)


def _meeting_point(ends: list[tuple[np.ndarray, np.ndarray]], fallback: np.ndarray) -> np.ndarray:
    """Least-squares point closest to the lines through each arm's end segment."""
    a = np.zeros((2, 2))
    b = np.zeros(2)
    for p, d in ends:
        n = d / np.linalg.norm(d)
        m = np.eye(2) - np.outer(n, n)
        a += m
        b += m @ p
    if np.linalg.cond(a) > 1e6:
        return fallback
    q = np.linalg.solve(a, b)
    return q if np.linalg.norm(q - fallback) < 12.0 else fallback


def author(ref_dir: Path, town: str) -> None:
    ref = json.loads((ref_dir / f"carla_town{town}_layout.json").read_text())
    junctions = {j["id"]: j for j in ref["junctions"]}
    centre = {jid: _flip([[j["x"], j["y"]]])[0] for jid, j in junctions.items()}
    lane_w = 4.0 if town in ("01", "02") else 3.5

    streets = []
    for s in ref["streets"]:
        a, b = s["junction_a"], s["junction_b"]
        if "polyline_carla_per_road" in s:
            line = _chain([_flip(p) for p in s["polyline_carla_per_road"]], centre[a])
            n_ab = n_ba = s["lanes_per_direction"]
        else:
            n_ab = s["driving_lanes_a_to_b"][0]
            n_ba = s["driving_lanes_b_to_a"][0]
            line = _offset_left(_flip(s["polyline_carla_rightmost_lane_a_to_b"]), (n_ab - 0.5) * lane_w)
        if np.linalg.norm(line[0] - centre[a]) > np.linalg.norm(line[-1] - centre[a]):
            line = line[::-1]
        streets.append({"id": s["id"], "a": a, "b": b, "line": _simplify(line), "n_ab": n_ab, "n_ba": n_ba})

    # Junction nodes where the street axes meet (the reference gives the junction area's
    # centroid, which sits off the through street at a T).
    node = {}
    for jid in junctions:
        ends = []
        for s in streets:
            line = s["line"]
            if s["a"] == jid and len(line) >= 2:
                ends.append((line[0], line[1] - line[0]))
            if s["b"] == jid and len(line) >= 2:
                ends.append((line[-1], line[-2] - line[-1]))
        node[jid] = _meeting_point(ends, centre[jid])

    out = ROOT / "scenarios" / f"town{town}"
    out.mkdir(parents=True, exist_ok=True)
    nod = ['<?xml version="1.0" encoding="UTF-8"?>', f"<!-- Town{town}: junctions (authored from CARLA layout facts) -->", "<nodes>"]
    for jid, j in sorted(junctions.items(), key=lambda kv: int(kv[0])):
        kind = "traffic_light" if j.get("traffic_light") else "priority"
        x, y = node[jid]
        nod.append(f'    <node id="J{jid}" x="{x:.2f}" y="{y:.2f}" type="{kind}"/>')
    nod.append("</nodes>")
    (out / "town.nod.xml").write_text("\n".join(nod) + "\n")

    edg = ['<?xml version="1.0" encoding="UTF-8"?>', f"<!-- Town{town}: one street = two edges, id and -id; shapes are street centre lines -->", "<edges>"]
    for s in sorted(streets, key=lambda s: int(s["id"][1:])):
        inner = [p for p in s["line"] if min(np.linalg.norm(p - node[s["a"]]), np.linalg.norm(p - node[s["b"]])) > 10.0]
        n_max = max(s["n_ab"], s["n_ba"])
        speed = RING_SPEED if n_max >= 3 else MPH25
        for eid, frm, to, n, pts in (
            (s["id"], s["a"], s["b"], s["n_ab"], inner),
            (f"-{s['id']}", s["b"], s["a"], s["n_ba"], inner[::-1]),
        ):
            shape = ""
            if pts:
                full = [node[frm], *pts, node[to]]
                shape = ' shape="' + " ".join(f"{x:.2f},{y:.2f}" for x, y in full) + '"'
            edg.append(
                f'    <edge id="{eid}" from="J{frm}" to="J{to}" numLanes="{n}" speed="{speed}"'
                f' width="{lane_w}"{shape}/>'
            )
    edg.append("</edges>")
    (out / "town.edg.xml").write_text("\n".join(edg) + "\n")
    print(f"town{town}: {len(junctions)} junctions, {len(streets)} streets -> {out}")


if __name__ == "__main__":
    ref_dir = Path(sys.argv[1] if len(sys.argv) > 1 else ROOT.parent / "shared" / "reference")
    for t in ("01", "02", "05"):
        author(ref_dir, t)
