"""Towns: resolve a town name or folder, build its SUMO network with netconvert, describe it.

A town is a folder with either plain-XML sources (``*.nod.xml``, ``*.edg.xml`` and optional
``*.con.xml``, ``*.tll.xml``, ``*.typ.xml``) or a ready ``*.net.xml``, plus an optional
``town.toml`` (speed limit, densities, crossing width) and ``routes.toml`` (benchmark routes).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import subprocess
import tempfile
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import sumo

from bid_sim.errors import BidError

log = logging.getLogger(__name__)

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = Path(os.environ.get("BID_SCENARIOS", PACKAGE_ROOT / "scenarios"))
BUILD = Path(os.environ.get("BID_BUILD", PACKAGE_ROOT / "build"))
BUILT_IN = ("01", "02", "05")
DENSITIES = ("none", "normal", "crowded")

# netconvert options verified on SUMO 1.28 (DESIGN.md section 6): sidewalks on every edge,
# crossings and walking areas, static signal programs with pedestrian phases.
NETCONVERT_OPTIONS = (
    "--sidewalks.guess", "true",
    "--sidewalks.guess.max-speed", "20",
    "--crossings.guess", "true",
    "--walkingareas", "true",
    "--default.sidewalk-width", "2.0",
    "--tls.default-type", "static",
    "--junctions.corner-detail", "5",
    "--tls.crossing-min.time", "4",
    "--tls.crossing-clearance.time", "5",
    "--no-turnarounds", "true",
    "--offset.disable-normalization", "true",
    "--geometry.remove", "false",
    "--no-internal-links", "false",
    "--junctions.join", "false",
)
NETCONVERT_VERSION_TAG = "bid-sim-netconvert-v2"
# netconvert's crossing width, for a town whose town.toml names none. At 4 m the outer metre of
# each crossing's end lies in the carriageway beyond the walking area's rounded corner, and
# people waiting there for the light stand where a right-turning car's body passes (Town01 96,
# Town02 59, Town05 230 waiting places); at 2 m none does. The built-in towns set
# `crossing_width_m = 2` and paint them 4 m wide (`zebra_width_m = 4`) since 2026-12-05: their
# figures before were made on 4 m crossings, and the shipped BID, trained on 4 m zebras, drives
# 2 m towns painted 2 m worse (without traffic 35 red lights against 10; docs/experiments.md).
CROSSING_WIDTH_M = 4.0

# Used when a user's town folder has no town.toml.
DEFAULT_DENSITY = {"none": (0, 0), "normal": (20, 50), "crowded": (100, 250)}


@dataclass(frozen=True)
class Town:
    """A resolved town: where its sources are and its settings from town.toml."""

    name: str
    folder: Path
    speed_limit_mps: float = 11.18
    densities: dict[str, tuple[int, int]] = field(default_factory=lambda: dict(DEFAULT_DENSITY))
    crossing_width_m: float = CROSSING_WIDTH_M
    # How wide the crossings' zebras are painted (town.toml `zebra_width_m`); None: as wide as the
    # crossings. Only the picture: walkers keep to the crossing netconvert built.
    zebra_width_m: float | None = None

    @cached_property
    def net_file(self) -> Path:
        """The SUMO network, built on demand and rebuilt when the sources change."""
        return build_net(self)

    def density(self, name: str) -> tuple[int, int]:
        """(vehicles, pedestrians) for a density name."""
        if name not in self.densities:
            raise BidError(
                f"unknown density {name!r}; use one of {', '.join(self.densities)}"
            )
        return self.densities[name]

    @property
    def routes_file(self) -> Path:
        return self.folder / "routes.toml"


def resolve_town(spec: str | os.PathLike) -> Town:
    """Turns '02', 'town02', 'Town02' or a folder path into a Town."""
    text = str(spec)
    m = re.fullmatch(r"(?i)(?:town)?0?(\d)", text)
    if m and f"0{m.group(1)}" in BUILT_IN:
        folder = SCENARIOS / f"town0{m.group(1)}"
        name = f"Town0{m.group(1)}"
    else:
        folder = Path(text)
        if not folder.is_dir():
            known = ", ".join(BUILT_IN)
            raise BidError(
                f"unknown town {text!r}; use one of {known} or a folder with a SUMO network "
                "(*.net.xml or *.nod.xml + *.edg.xml)"
            )
        name = folder.resolve().name
    if not _sources(folder) and not list(folder.glob("*.net.xml")):
        raise BidError(
            f"town folder {folder} has no network; add *.net.xml or plain XML "
            "(*.nod.xml + *.edg.xml)"
        )
    settings = {}
    toml_file = folder / "town.toml"
    if toml_file.exists():
        try:
            settings = tomllib.loads(toml_file.read_text())
        except tomllib.TOMLDecodeError as e:
            raise BidError(f"{toml_file} is not valid TOML ({e}); fix or delete it") from e
    densities = dict(DEFAULT_DENSITY)
    for k, v in settings.get("density", {}).items():
        densities[k] = (int(v[0]), int(v[1]))
    crossing = _width(settings, "crossing_width_m", toml_file) or CROSSING_WIDTH_M
    zebra = _width(settings, "zebra_width_m", toml_file)
    return Town(
        name=settings.get("name", name),
        folder=folder.resolve(),
        speed_limit_mps=float(settings.get("speed_limit_mps", 11.18)),
        densities=densities,
        crossing_width_m=float(crossing),
        zebra_width_m=None if zebra is None or zebra == crossing else float(zebra),
    )


def _width(settings: dict, key: str, toml_file: Path) -> float | None:
    """A crossing or zebra width from town.toml (None where unset), checked to be 1 to 6 m."""
    value = settings.get(key)
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                              or not 1.0 <= value <= 6.0):
        raise BidError(f"{toml_file}: {key} must be a width from 1 to 6 m, got {value!r}; fix it")
    return value


def _sources(folder: Path) -> list[Path]:
    found = []
    for pattern in ("*.nod.xml", "*.edg.xml", "*.con.xml", "*.tll.xml", "*.typ.xml"):
        found += sorted(folder.glob(pattern))
    return found if any(p.name.endswith(".edg.xml") for p in found) else []


def netconvert_binary() -> str:
    return str(Path(sumo.SUMO_HOME) / "bin" / "netconvert")


def crossing_words(width_m: float, zebra_width_m: float | None = None) -> str:
    """How a town's crossings are built and painted, for titles and messages: '2 m crossings' or
    '2 m crossings painted 4 m wide'."""
    return f"{width_m:g} m crossings" + ("" if zebra_width_m is None else f" painted {zebra_width_m:g} m wide")


def net_tag(town: Town) -> str:
    """What the town's net is made of, as 16 hex digits: its plain XML, the crossings' width and
    netconvert's options (or a user's ready .net.xml). Two towns of one name built otherwise (a
    town.toml with another crossing_width_m or zebra_width_m) differ here; results and recordings
    carry it."""
    sources = _sources(town.folder)
    zebra = b"" if town.zebra_width_m is None else f"zebra {town.zebra_width_m:g}".encode()
    if not sources:
        net_bytes = sorted(town.folder.glob("*.net.xml"))[0].read_bytes()
        return hashlib.sha256(net_bytes + zebra).hexdigest()[:16]
    digest = hashlib.sha256(NETCONVERT_VERSION_TAG.encode())
    digest.update(f"crossing {town.crossing_width_m:g}".encode())
    digest.update(zebra)
    for p in sources:
        digest.update(p.name.encode())
        digest.update(p.read_bytes())
    return digest.hexdigest()[:16]


def build_net(town: Town) -> Path:
    """Builds build/<town>/<town>.net.xml from the plain XML when missing or stale.

    A user's ready .net.xml (e.g. converted from OSM) is used as it is.
    """
    sources = _sources(town.folder)
    if not sources:
        nets = sorted(town.folder.glob("*.net.xml"))
        return nets[0]
    tag = net_tag(town)
    out_dir = BUILD / town.folder.name
    net = out_dir / f"{town.folder.name}.net.xml"
    stamp = out_dir / "net.sha"
    if net.exists() and stamp.exists() and stamp.read_text() == tag:
        return net
    out_dir.mkdir(parents=True, exist_ok=True)
    args = [netconvert_binary()]
    for flag, suffix in (
        ("--node-files", ".nod.xml"),
        ("--edge-files", ".edg.xml"),
        ("--connection-files", ".con.xml"),
        ("--tllogic-files", ".tll.xml"),
        ("--type-files", ".typ.xml"),
    ):
        files = [str(p) for p in sources if p.name.endswith(suffix)]
        if files:
            args += [flag, ",".join(files)]
    # A temporary name of its own: parallel workers that find no net build it side by side.
    fd, tmp_name = tempfile.mkstemp(dir=out_dir, prefix=f".{net.stem}.", suffix=".tmp.xml")
    os.close(fd)
    tmp = Path(tmp_name)
    args += [*NETCONVERT_OPTIONS, "--default.crossing-width", f"{town.crossing_width_m:g}",
             "--output-file", str(tmp), "--no-warnings", "true"]
    log.info("netconvert %s", town.name)
    try:
        proc = subprocess.run(args, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            first = (proc.stderr.strip().splitlines() or ["no output"])[0]
            raise BidError(f"netconvert failed on {town.folder}: {first}; fix the plain XML")
        os.replace(tmp, net)  # atomic: a half-written net is never picked up
    finally:
        tmp.unlink(missing_ok=True)
    stamp.write_text(tag)
    return net


def describe_town(town: Town) -> dict:
    """The figures `bid towns` prints: size, junctions, signals, lanes, street length."""
    import numpy as np
    import sumolib

    net = sumolib.net.readNet(str(town.net_file))
    edges = [e for e in net.getEdges() if e.getFunction() == "" and _car_lanes(e)]
    neighbours: dict[str, set[str]] = {}
    for e in edges:
        a, b = e.getFromNode().getID(), e.getToNode().getID()
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)
    # A junction is where three or more streets meet; degree-2 nodes are only geometry.
    arms = {n: _arms(net.getNode(n), edges) for n in neighbours}
    junctions = sorted(n for n, k in arms.items() if k >= 3)
    signalised = [n for n in junctions if net.getNode(n).getType().startswith("traffic_light")]
    pts = np.concatenate([np.asarray(e.getRawShape()) for e in edges])
    lo, hi = pts.min(0), pts.max(0)
    # A two-way street is two edges over the same centre line: count it once.
    seen: set[tuple] = set()
    street_m = 0.0
    for e in sorted(edges, key=lambda e: e.getID()):
        shape = tuple(np.round(np.asarray(e.getRawShape()), 1).ravel())
        back = tuple(np.round(np.asarray(e.getRawShape()[::-1]), 1).ravel())
        if back in seen:
            continue
        seen.add(shape)
        lanes = _car_lanes(e)
        # Street length between junction areas, like CARLA's road lengths.
        street_m += sum(lane.getLength() for lane in lanes) / len(lanes)
    lanes = sorted({len(_car_lanes(e)) for e in edges})
    return {
        "town": town.name,
        "width_m": round(float(hi[0] - lo[0]), 1),
        "height_m": round(float(hi[1] - lo[1]), 1),
        "junctions": len(junctions),
        "t_junctions": sum(arms[n] == 3 for n in junctions),
        "four_way": sum(arms[n] == 4 for n in junctions),
        "signalised": len(signalised),
        "lanes_per_direction": lanes,
        "street_length_m": round(street_m, 1),
        "crossing_width_m": town.crossing_width_m,
        "zebra_width_m": town.zebra_width_m or town.crossing_width_m,
    }


def _car_lanes(edge) -> list:
    return [lane for lane in edge.getLanes() if lane.allows("passenger")]


def _arms(node, edges) -> int:
    """Distinct streets at a node: neighbouring nodes, counting parallel streets apart."""
    ids = {e.getID() for e in edges}
    others = set()
    for e in node.getIncoming() + node.getOutgoing():
        if e.getID() not in ids:
            continue
        other = e.getFromNode() if e.getToNode() == node else e.getToNode()
        others.add((other.getID(), round(_shape_len(e))))
    return len(others)


def _shape_len(edge) -> float:
    import numpy as np

    s = np.asarray(edge.getRawShape())
    return float(np.linalg.norm(np.diff(s, axis=0), axis=1).sum())
