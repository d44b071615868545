"""Background traffic: vehicles and pedestrians on random trips, re-tripped so density holds.

All randomness comes from one numpy Generator seeded per episode; ids are handled in sorted
order, never through a Python set, so a seed gives the same traffic in every process.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import libsumo as traci
import numpy as np

log = logging.getLogger(__name__)

# Vehicle body variants: (vType id, length, width, height). Colours are drawn per vehicle.
VEHICLE_TYPES = (
    ("bg_compact", 3.9, 1.75, 1.45),
    ("bg_sedan", 4.6, 1.85, 1.45),
    ("bg_suv", 4.8, 2.0, 1.75),
    ("bg_van", 5.2, 2.05, 2.1),
)
PED_SIZE = (0.5, 0.6, 1.75)
N_COLOURS = 8
KEEP_CLEAR_M = 10.0  # no actor spawns this close to the ego's start
RETRIP_EVERY = 10  # steps between checks for actors near the end of their trip
# Dense traffic on a small grid of blocks (crowded Town02) locks up in rings of queues, each
# waiting for the next, that only SUMO's teleport (--time-to-teleport) would break, much later
# and with every car in it stuck. A car that has stood JAM_S seconds with no red or amber
# light holding it (a queue moves up within seconds of green) is in such a lock: the
# longest-standing one is taken out and spawned elsewhere, one per check, until queues move.
# Almost all such cars stand at a green stop line with the street beyond full, or inside a
# junction; 10 s (not 30 s) is what lets the expert finish 96 % of crowded Town02 routes in
# time (README, "The expert"), at about one car taken out every 5 s there.
JAM_S = 10.0
SIGNAL_HOLD_M = 60.0  # a red light this far ahead (or nearer) may hold a queue
STANDING_MPS = 0.1  # SUMO's own threshold for waiting


@dataclass
class ActorInfo:
    kind: str  # "vehicle" | "pedestrian"
    size: tuple[float, float, float]
    colour: int
    placed: bool = False  # put there by a scenario or test (World.place_vehicle): never replaced


class Traffic:
    """Spawns and re-trips background actors in the running SUMO simulation."""

    def __init__(self, rng: np.random.Generator, drive_edges: list[str], walk_edges: list[str],
                 edge_lengths: dict[str, float], keep_clear_xy: tuple[float, float]):
        self.rng = rng
        self.drive_edges = sorted(drive_edges)
        self.walk_edges = sorted(walk_edges)
        self.edge_lengths = edge_lengths
        self.keep_clear = np.asarray(keep_clear_xy, dtype=float)
        self.actors: dict[str, ActorInfo] = {}
        self._walkable = set(walk_edges)
        self._walk_goal: dict[str, tuple[str, float]] = {}  # person -> (edge, pos) of its trip end
        self._next_vehicle = 0
        self._next_person = 0
        self._steps = 0
        self.gridlock_removals = 0  # cars taken out of a gridlock (_clear_gridlock)
        self._held: dict[str, float] = {}  # standing car -> seconds no signal held it

    def define_types(self) -> None:
        for type_id, length, width, height in VEHICLE_TYPES:
            traci.vehicletype.copy("DEFAULT_VEHTYPE", type_id)
            traci.vehicletype.setLength(type_id, length)
            traci.vehicletype.setWidth(type_id, width)
            traci.vehicletype.setHeight(type_id, height)
            traci.vehicletype.setMinGap(type_id, 2.5)
            traci.vehicletype.setImperfection(type_id, 0.0)

    def spawn(self, n_vehicles: int, n_pedestrians: int) -> None:
        for _ in range(n_vehicles):
            self._add_vehicle()
        for _ in range(n_pedestrians):
            self._add_person()

    # -- vehicles -----------------------------------------------------------------------
    def _random_pos(self, edges: list[str], margin_m: float) -> tuple[str, float]:
        for _ in range(50):
            edge = edges[int(self.rng.integers(len(edges)))]
            length = self.edge_lengths[edge]
            if length <= 2 * margin_m:
                continue
            pos = float(self.rng.uniform(margin_m, length - margin_m))
            lane = 0 if edge in self._walkable else 1
            # A vehicle's position is its front bumper: keep its whole body clear.
            ends = [traci.simulation.convert2D(edge, p, lane) for p in (pos, max(pos - 6.0, 0.0))]
            if all(math.hypot(x - self.keep_clear[0], y - self.keep_clear[1]) > KEEP_CLEAR_M for x, y in ends):
                return edge, pos
        return edge, pos

    def _route_from(self, edge: str) -> list[str]:
        for _ in range(20):
            goal = self.drive_edges[int(self.rng.integers(len(self.drive_edges)))]
            if goal == edge:
                continue
            found = traci.simulation.findRoute(edge, goal, vType="bg_sedan")
            if len(found.edges) >= 2:
                return list(found.edges)
        return [edge]

    def _add_vehicle(self) -> None:
        vid = f"veh{self._next_vehicle}"
        self._next_vehicle += 1
        edge, pos = self._random_pos(self.drive_edges, 6.0)
        route_id = f"r_{vid}"
        traci.route.add(route_id, self._route_from(edge))
        vt = VEHICLE_TYPES[int(self.rng.integers(len(VEHICLE_TYPES)))]
        traci.vehicle.add(vid, route_id, typeID=vt[0], departPos=f"{pos:.1f}", departLane="best",
                          departSpeed="0")
        self.actors[vid] = ActorInfo("vehicle", vt[1:], int(self.rng.integers(N_COLOURS)))

    def _retrip_vehicle(self, vid: str) -> None:
        route = traci.vehicle.getRoute(vid)
        idx = traci.vehicle.getRouteIndex(vid)
        if idx < 0 or idx < len(route) - 1:
            return
        nxt = self._route_from(route[-1])
        if len(nxt) >= 2:
            traci.vehicle.setRoute(vid, nxt)

    # -- pedestrians --------------------------------------------------------------------
    def _add_person(self) -> None:
        pid = f"ped{self._next_person}"
        self._next_person += 1
        edge, pos = self._random_pos(self.walk_edges, 1.0)
        traci.person.add(pid, edge, pos)
        self._append_walk(pid, edge, pos)
        speed = float(self.rng.uniform(1.0, 1.5))
        traci.person.setSpeed(pid, speed)
        self.actors[pid] = ActorInfo("pedestrian", PED_SIZE, int(self.rng.integers(N_COLOURS)))

    def _append_walk(self, pid: str, edge: str, pos: float) -> None:
        for _ in range(20):
            goal = self.walk_edges[int(self.rng.integers(len(self.walk_edges)))]
            if goal == edge:
                continue
            arrival = float(self.rng.uniform(0.2, 0.8) * self.edge_lengths[goal])
            stages = traci.simulation.findIntermodalRoute(edge, goal, modes="", departPos=pos,
                                                          arrivalPos=arrival)
            walk = [s for s in stages if s.edges]
            if walk:
                edges = [e for s in walk for e in s.edges]
                traci.person.appendWalkingStage(pid, _dedup(edges), arrival)
                self._walk_goal[pid] = (goal, arrival)
                return

    # -- per step -----------------------------------------------------------------------
    def step(self, vehicle_ids: tuple[str, ...], person_ids: tuple[str, ...]) -> None:
        """Keeps every actor travelling: new trips before they arrive, replacements if lost."""
        self._steps += 1
        if self._steps % RETRIP_EVERY == 0:
            for vid in vehicle_ids:
                if vid in self.actors:
                    self._retrip_vehicle(vid)
            for pid in person_ids:
                goal = self._walk_goal.get(pid)
                if goal is not None and traci.person.getRemainingStages(pid) <= 1 \
                        and traci.person.getRoadID(pid) == goal[0]:
                    self._append_walk(pid, *goal)
        # Actors SUMO removed (arrived, teleported away) are replaced elsewhere.
        for vid in sorted(traci.simulation.getArrivedIDList()):
            if self.actors.pop(vid, None) is not None:
                self._add_vehicle()
        if self._steps % RETRIP_EVERY == 0:
            self._clear_gridlock(vehicle_ids)
            # A car whose spawn spot stayed blocked is tried again elsewhere.
            for vid in sorted(traci.simulation.getPendingVehicles()):
                if vid in self.actors and vid.startswith("veh"):
                    traci.vehicle.remove(vid)
                    self.actors.pop(vid)
                    self._add_vehicle()
            alive = set(person_ids)
            gone = sorted(p for p, a in self.actors.items() if a.kind == "pedestrian" and p not in alive)
            for pid in gone:
                placed = self.actors.pop(pid).placed
                self._walk_goal.pop(pid, None)
                if not placed:  # a scenario's walker that arrived is not replaced
                    self._add_person()

    def _clear_gridlock(self, vehicle_ids: tuple[str, ...]) -> None:
        """Counts, per car, the seconds it has stood with no red or amber light ahead, and
        takes the car with the most, if JAM_S or over, out of the traffic for a new one
        elsewhere. Neither the ego (not one of the actors) nor a placed car is touched."""
        dt = RETRIP_EVERY * traci.simulation.getDeltaT()
        held = {}
        for vid in vehicle_ids:
            info = self.actors.get(vid)
            if (info is None or info.kind != "vehicle" or info.placed
                    or traci.vehicle.getSpeed(vid) >= STANDING_MPS):
                continue
            signal = [state for _, _, dist, state in traci.vehicle.getNextTLS(vid)[:1]
                      if dist <= SIGNAL_HOLD_M and state in "rRyYu"]
            held[vid] = self._held.get(vid, 0.0) + (0.0 if signal else dt)
        self._held = held
        stuck = [(t, vid) for vid, t in held.items() if t >= JAM_S - 1e-9]
        if not stuck:
            return
        _, vid = min(stuck, key=lambda tv: (-tv[0], tv[1]))
        traci.vehicle.remove(vid)
        self.actors.pop(vid)
        self._held.pop(vid)
        self.gridlock_removals += 1
        self._add_vehicle()


def _dedup(edges: list[str]) -> list[str]:
    out: list[str] = []
    for e in edges:
        if not out or out[-1] != e:
            out.append(e)
    return out
