"""Pedestrians sent across the crossings the ego's route turns over (`bid record --crossing-walkers`).

The BID's pedestrian failures at normal density are mostly mid-turn at 3-5 m/s, a person on
the crossing of the street the turn leads into (docs/experiments.md): its hazard head reads
nothing there, because the recordings hardly hold such a frame. Background pedestrians seldom
cross where and when the ego turns, and the expert slows for one long before she is near; of
data/gap33's frames, 0.13 % have a pedestrian in the path within 10 m of a moving ego.

CrossingWalkers meets each of the route's turns with a walker: when the ego comes within a
drawn distance (LEAD_M) of the crossing over the street the turn leads into, a pedestrian
starts at one kerb of it, walking to the other. She keeps SUMO's rules (the crossing's signal,
the right of way), so she may wait at the kerb or be on the stripes as the ego turns. The
expert brakes for where she will be, so she walks into its path once it stands: a walker
gives frames of a standing car. In STAND_SHARE of the meetings she stands on the stripes in
the ego's lane instead, sent once the ego is in the junction (STAND_LEAD_M), for a drawn
while (STAND_S), then walks on: the scene of the failures, a person ahead in the path of a
car turning at speed, which the expert brakes for hard (before the junction it would stop at
its entry, 10 m from her). The recording holds her with the hazard targets (bid_model.hazards) of every
frame. Walkers are placed actors (never replaced) and leave when they arrive. Straight
through a junction, the far crossing's walkers have red when the ego has green: only turns
are met.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import libsumo as traci
import numpy as np

from bid_sim.errors import BidError
from bid_sim.traffic import N_COLOURS, PED_SIZE, ActorInfo
from bid_sim.world import DT_S

log = logging.getLogger(__name__)

LEAD_M = (15.0, 40.0)  # the walker starts when the ego's front is this far (drawn) before the crossing
WALK_MPS = (0.7, 1.5)  # her walking speed, drawn
KERB_M = 0.3  # she starts and ends this far from the junction's end of the sidewalk
STAND_SHARE = 0.5  # of the meetings, those where she stands in the ego's lane on the crossing
STAND_S = (6.0, 16.0)  # for this long (drawn) from when she is sent
STAND_LEAD_M = (5.0, 15.0)  # and is sent when the ego's front is this far (drawn) before her: in the junction
STAND_LATERAL_M = 0.8  # up to this far (drawn) either side of the ego's lane centre
STREAM = 7  # the walkers' random stream, apart from the traffic's (same seed, same walkers)


@dataclass(frozen=True)
class Meeting:
    """A crossing on the route where a walker is sent: the crossing edge, the route arc length
    of its centre, and the two sidewalk edges at its ends (start, goal; their junction ends)."""

    crossing: str
    s_m: float
    start: str
    goal: str


class CrossingWalkers:
    """Sends a walker across the crossing after each of a route's turns, in `share` of them.

    Give `start` to run_episode's on_start and `step` to its on_step."""

    def __init__(self, share: float, seed: int):
        if not 0.0 <= share <= 1.0:
            raise BidError(f"crossing walkers meet a share of the route's turns, from 0 to 1; got {share}")
        self.share = share
        self.rng = np.random.default_rng((seed, STREAM))
        self.meetings: list[tuple[Meeting, float, float]] = []  # (meeting, ego route s to send at, stand s)
        self.sent: list[str] = []  # walker ids, in order
        self.standing: dict[str, tuple[float, float, float, int]] = {}  # walker -> x, y, angle, steps left

    def start(self, world) -> None:
        """Finds the route's turns and draws which are met, when, and from which kerb."""
        self.meetings = []
        self.standing = {}
        for meeting in route_meetings(world.graph, world.route):
            lead, flip = float(self.rng.uniform(*LEAD_M)), bool(self.rng.integers(2))
            stand = float(self.rng.uniform(*STAND_S)) if self.rng.random() < STAND_SHARE else 0.0
            if stand:
                lead = float(self.rng.uniform(*STAND_LEAD_M))
            if self.rng.random() >= self.share:
                continue
            if flip:
                meeting = Meeting(meeting.crossing, meeting.s_m, meeting.goal, meeting.start)
            self.meetings.append((meeting, meeting.s_m - lead, stand))

    def step(self, world, snap) -> None:
        """Sends the walkers whose moment the ego's front has reached."""
        front = snap.ego.route_s_m + world.params.length_m / 2
        while self.meetings and front >= self.meetings[0][1]:
            meeting, _, stand = self.meetings.pop(0)
            self._send(world, meeting, stand)
        alive = set(traci.person.getIDList()) if self.standing else set()
        for pid in sorted(self.standing):
            x, y, angle, left = self.standing[pid]
            if left <= 0 or pid not in alive:
                del self.standing[pid]  # walks on from where she stood
                continue
            traci.person.moveToXY(pid, "", x, y, angle, 2)
            self.standing[pid] = (x, y, angle, left - 1)

    def _send(self, world, meeting: Meeting, stand_s: float) -> None:
        pid = f"walker{len(self.sent)}"
        net = world.graph.net
        # Each sidewalk runs along its street's direction: its junction end is its start if the
        # street leaves the crossing's junction, its end if it arrives there.
        node = net.getEdge(meeting.crossing).getFromNode().getID()

        def at_junction(edge: str) -> float:
            e = net.getEdge(edge)
            return KERB_M if e.getFromNode().getID() == node else e.getLength() - KERB_M

        speed = float(self.rng.uniform(*WALK_MPS))
        colour = int(self.rng.integers(N_COLOURS))
        traci.person.add(pid, meeting.start, at_junction(meeting.start))
        traci.person.appendWalkingStage(pid, [meeting.start, meeting.goal], at_junction(meeting.goal))
        traci.person.setSpeed(pid, speed)
        world.traffic.actors[pid] = ActorInfo("pedestrian", PED_SIZE, colour, placed=True)
        self.sent.append(pid)
        if stand_s > 0.0:
            x, y, heading = world.route.point_at(meeting.s_m)
            side = float(self.rng.uniform(-STAND_LATERAL_M, STAND_LATERAL_M))
            x, y = x - side * np.sin(heading), y + side * np.cos(heading)
            angle = float(np.degrees(np.pi / 2 - heading) + 90.0) % 360.0  # SUMO's: facing across the lane
            self.standing[pid] = (float(x), float(y), angle, round(stand_s / DT_S))
            traci.person.moveToXY(pid, "", x, y, angle, 2)
        log.debug("walker %s across %s at %.1f m/s", pid, meeting.crossing, speed)


def route_meetings(graph, route) -> list[Meeting]:
    """The crossings a route's turns lead over, in route order: at each junction where the route
    turns (leaves on a street that is neither straight on nor back), the crossing over the street
    it leaves on, with the sidewalks of both of that street's directions at its ends."""
    net = graph.net
    crossings = {}
    for edge in net.getEdges(withInternal=True):
        if edge.getFunction() == "crossing":
            crossings[(edge.getFromNode().getID(), frozenset(e.getID() for e in edge.getCrossingEdges()))] = edge
    out = []
    edges = [e for e in route.edges if not e.startswith(":")]
    for e_in, e_out in itertools.pairwise(edges):
        a, b = net.getEdge(e_in), net.getEdge(e_out)
        node = a.getToNode().getID()
        if b.getFromNode().getID() != node or not _turns(a, b):
            continue
        back = next((e for e in b.getToNode().getOutgoing() if e.getToNode().getID() == node), None)
        if back is None:
            continue
        crossing = crossings.get((node, frozenset((e_out, back.getID()))))
        if crossing is None or not all(_walkable(e) for e in (b, back)):
            continue
        centre = np.mean(np.asarray(crossing.getLanes()[0].getShape(), dtype=float), axis=0)
        s_m, _, _ = route.project(float(centre[0]), float(centre[1]), _s_hint(route, b))
        out.append(Meeting(crossing.getID(), float(s_m), e_out, back.getID()))
    return out


def _turns(a, b) -> bool:
    """Whether leaving edge `a` onto `b` turns: their headings at the junction differ by 45° to 135°."""
    ha, hb = _heading(a.getShape()[-2:]), _heading(b.getShape()[:2])
    d = abs((hb - ha + np.pi) % (2 * np.pi) - np.pi)
    return np.pi / 4 < d < 3 * np.pi / 4


def _heading(pts) -> float:
    (x0, y0), (x1, y1) = pts[0][:2], pts[-1][:2]
    return float(np.arctan2(y1 - y0, x1 - x0))


def _walkable(edge) -> bool:
    return any(lane.allows("pedestrian") for lane in edge.getLanes())


def _s_hint(route, edge) -> float:
    """Route arc length where `edge` begins (0 if it is not a piece of the route)."""
    for piece in route.pieces:
        if piece.lane_id.rsplit("_", 1)[0] == edge.getID():
            return float(piece.s0_m)
    return 0.0
