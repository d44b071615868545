"""The world: one SUMO simulation (libsumo, 10 Hz) with background traffic and the ego.

The ego is a SUMO vehicle placed every step with moveToXY(keepRoute=2) from our kinematic
model, its SUMO route held to the planned edges so that SUMO traffic yields to it. libsumo
allows one simulation per process: a World closes any earlier one before it starts.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import libsumo as traci
import numpy as np
import sumo

from bid_sim.ego import EgoParams, EgoState, sumo_angle_deg, yaw_from_sumo
from bid_sim.errors import BidError
from bid_sim.routes import RoadGraph, Route, project_polyline, road_graph
from bid_sim.snapshot import OFF, Actors, EgoView, Snapshot, light_code
from bid_sim.town_map import TownMap, load_town_map
from bid_sim.towns import Town
from bid_sim.traffic import PED_SIZE, ActorInfo, Traffic

log = logging.getLogger(__name__)

EGO_ID = "ego"
EGO_TYPE = "ego_t"
NEARBY_M = 120.0  # actors farther than this from the ego are left out of the snapshot
OVERPASS_M = 15.0  # near a crossing of two streets without a junction, each is on its own level
DT_S = 0.1

# libsumo keeps each moveToXY in a process-wide table (by vehicle ID) until the next step
# takes it up, and closing does not clear it: a simulation closed with one pending hands the
# next one a pointer to its freed ego, which SUMO 1.28 follows in its first step (a segfault
# when the next town differs). True while our last moveToXY waits for a step.
_move_pending = False


class SumoError(BidError):
    """SUMO failed mid-episode."""


def sumo_binary() -> str:
    return str(Path(sumo.SUMO_HOME) / "bin" / "sumo")


class World:
    """A running SUMO simulation of one town with traffic at one density and seed."""

    def __init__(self, town: Town, density: str, seed: int, route: Route,
                 params: EgoParams = EgoParams(), town_map: TownMap | None = None):
        self.town = town
        self.n_vehicles, self.n_pedestrians = town.density(density)
        self.seed = seed
        self.params = params
        self.route = route
        self.graph: RoadGraph = road_graph(town.net_file)
        self.map = town_map if town_map is not None else load_town_map(town)
        self.step_count = 0
        self._road = ""
        self._route_idx = 0
        self._tls_ids: tuple[str, ...] = ()
        self._head_tls: list[tuple[str, int]] = [(h.tls_id, h.link_index) for h in self.map.signal_heads]
        x, y, yaw = route.point_at(0.0)
        self.ego = EgoState(x, y, yaw, 0.0)
        self._start()

    # -- lifecycle ----------------------------------------------------------------------
    def _start(self) -> None:
        _close_sumo()
        args = [
            sumo_binary(), "-n", str(self.town.net_file),
            "--step-length", str(DT_S), "--seed", str(self.seed),
            "--no-step-log", "true", "--no-warnings", "true",
            "--collision.action", "warn", "--collision.check-junctions", "true",
            "--time-to-teleport", "120", "--pedestrian.model", "striping",
            "--default.speeddev", "0.05", "--random-depart-offset", "0",
        ]
        try:
            traci.start(args)
        except traci.TraCIException as e:
            raise SumoError(f"SUMO failed to start on {self.town.net_file}: {e}; rebuild the town") from e
        self._tls_ids = tuple(sorted(traci.trafficlight.getIDList()))
        self._add_ego()
        rng = np.random.default_rng(self.seed)
        drive = sorted(self.graph.car_edges)
        walk = sorted(
            e.getID() for e in self.graph.net.getEdges()
            if e.getFunction() == "" and any(lane.allows("pedestrian") for lane in e.getLanes())
        )
        lengths = {e.getID(): e.getLength() for e in self.graph.net.getEdges()}
        self.traffic = Traffic(rng, drive, walk, lengths, (self.ego.x_m, self.ego.y_m))
        self.traffic.define_types()
        self.traffic.spawn(self.n_vehicles, self.n_pedestrians)
        try:
            self._sumo_step()
            self._place_ego()
        except traci.TraCIException as e:
            raise SumoError(f"SUMO could not place the ego: {e}; check the route's start") from e

    def _add_ego(self) -> None:
        p = self.params
        traci.vehicletype.copy("DEFAULT_VEHTYPE", EGO_TYPE)
        traci.vehicletype.setLength(EGO_TYPE, p.length_m)
        traci.vehicletype.setWidth(EGO_TYPE, p.width_m)
        traci.vehicletype.setHeight(EGO_TYPE, p.height_m)
        traci.vehicletype.setMaxSpeed(EGO_TYPE, 60.0)  # the model sets the speed; avoid "implied speed" warnings
        traci.vehicletype.setAccel(EGO_TYPE, 10.0)
        traci.vehicletype.setDecel(EGO_TYPE, 10.0)
        traci.route.add("ego_route", list(self.route.edges))
        first = self.route.pieces[0]
        lane_index = int(first.lane_id.rsplit("_", 1)[1])
        pos = self.graph.net.getLane(first.lane_id).getLength()
        start_pos = min(pos, max(0.0, _lane_pos(self.graph, first.lane_id, self.ego) + p.length_m / 2))
        traci.vehicle.add(EGO_ID, "ego_route", typeID=EGO_TYPE, departPos=f"{start_pos:.2f}",
                          departLane=str(lane_index), departSpeed="0")
        traci.vehicle.setSpeedMode(EGO_ID, 0)
        traci.vehicle.setLaneChangeMode(EGO_ID, 0)
        traci.vehicle.setColor(EGO_ID, (255, 255, 255, 255))

    def close(self) -> None:
        _close_sumo()

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- stepping -----------------------------------------------------------------------
    def _sumo_step(self) -> None:
        global _move_pending
        traci.simulationStep()
        _move_pending = False

    def _place_ego(self) -> None:
        global _move_pending
        xf, yf = self.ego.front_bumper(self.params)
        _move_pending = True
        traci.vehicle.moveToXY(EGO_ID, "", -1, xf, yf, sumo_angle_deg(self.ego.yaw_rad), keepRoute=2)
        traci.vehicle.setSpeed(EGO_ID, self.ego.speed_mps)

    def set_route(self, route: Route) -> None:
        """Replaces the planned route (after a re-plan); SUMO's route follows."""
        self.route = route
        self._route_idx = 0
        self._road = ""

    def advance(self, ego: EgoState) -> None:
        """Moves the ego to its new state and the simulation one step on."""
        self.ego = ego
        try:
            self._place_ego()
            self._sumo_step()
            self.step_count += 1
            self._hold_route()
        except traci.TraCIException as e:
            raise SumoError(f"SUMO failed at step {self.step_count}: {e}; rerun with another seed") from e

    def _hold_route(self) -> None:
        """moveToXY onto another edge cuts the ego's SUMO route; put the planned edges back."""
        if EGO_ID not in traci.vehicle.getIDList():
            raise SumoError("SUMO removed the ego; rerun with another seed")
        road = traci.vehicle.getRoadID(EGO_ID)
        if road == self._road or not road or road.startswith(":"):
            return
        self._road = road
        edges = self.route.edges
        if road in edges[self._route_idx:]:
            self._route_idx = edges.index(road, self._route_idx)
            ahead = list(edges[self._route_idx:])
        else:
            ahead = [road]
        if tuple(traci.vehicle.getRoute(EGO_ID)[traci.vehicle.getRouteIndex(EGO_ID):]) != tuple(ahead):
            try:
                traci.vehicle.setRoute(EGO_ID, ahead)
            except traci.TraCIException:
                log.debug("could not set the ego route from %s", road)

    # -- observation --------------------------------------------------------------------
    def snapshot(self, ego_view: EgoView) -> Snapshot:
        """Reads the actors near the ego and the signal states."""
        vehicles, pedestrians = self.snapshot_actors()
        tls = {t: traci.trafficlight.getRedYellowGreenState(t) for t in self._tls_ids}
        lights = np.array(
            [light_code(tls[t][i]) if t in tls and i < len(tls[t]) else OFF for t, i in self._head_tls],
            dtype=np.uint8,
        )
        return Snapshot(
            time_s=self.step_count * DT_S,
            step=self.step_count,
            ego=ego_view,
            vehicles=vehicles,
            pedestrians=pedestrians,
            light_states=lights,
            tls_states=tls,
            route_polyline=self.route.polyline,
        )

    def _read_vehicles(self) -> Actors:
        ids = sorted(v for v in traci.vehicle.getIDList() if v != EGO_ID)
        self._all_vehicle_ids = tuple(ids)
        return self._read(ids, traci.vehicle, front_bumper=True)

    def _read_pedestrians(self) -> Actors:
        ids = sorted(traci.person.getIDList())
        self._all_person_ids = tuple(ids)
        return self._read(ids, traci.person, front_bumper=False)

    def _read(self, ids: list[str], domain, front_bumper: bool) -> Actors:
        ex, ey = self.ego.x_m, self.ego.y_m
        # Near where a street passes over or under the ego's, actors on it are on the other
        # level: left out, as the flat world would otherwise have them collide.
        levels = [(other, x, y) for other, x, y in self.graph.overpasses.get(self.route.edges[self._route_idx], ())
                  if math.hypot(x - ex, y - ey) < OVERPASS_M]
        keep, xy, yaw, speed, size, colour = [], [], [], [], [], []
        for aid in ids:
            x, y = domain.getPosition(aid)
            if abs(x - ex) > NEARBY_M or abs(y - ey) > NEARBY_M:
                continue
            if levels and any(math.hypot(x - lx, y - ly) < OVERPASS_M and domain.getRoadID(aid) == other
                              for other, lx, ly in levels):
                continue
            info = self.traffic.actors.get(aid)
            if info is None:
                continue
            a = yaw_from_sumo(domain.getAngle(aid))
            if front_bumper:  # SUMO reports the front bumper; we keep box centres
                x -= 0.5 * info.size[0] * math.cos(a)
                y -= 0.5 * info.size[0] * math.sin(a)
            keep.append(aid)
            xy.append((x, y))
            yaw.append(a)
            speed.append(domain.getSpeed(aid))
            size.append(info.size)
            colour.append(info.colour)
        if not keep:
            return Actors.empty()
        return Actors(tuple(keep), np.array(xy), np.array(yaw), np.array(speed), np.array(size),
                      np.array(colour, dtype=int))

    # -- scenario set-up (tests, hand-made scenarios) -------------------------------------
    def place_vehicle(self, vid: str, lane_id: str, pos_m: float, speed_mps: float = 0.0,
                      hold: bool = True, size=(4.6, 1.9, 1.5), colour: int = 0) -> None:
        """Adds a background vehicle on a lane; hold=True keeps it at speed_mps, else SUMO drives."""
        edge, index = lane_id.rsplit("_", 1)
        traci.route.add(f"r_{vid}", [edge])
        traci.vehicle.add(vid, f"r_{vid}", typeID="bg_sedan", departPos=f"{pos_m:.2f}",
                          departLane=index, departSpeed=f"{speed_mps:.2f}")
        traci.vehicle.setLength(vid, size[0])
        traci.vehicle.setWidth(vid, size[1])
        if hold:
            traci.vehicle.setSpeedMode(vid, 0)
            traci.vehicle.setLaneChangeMode(vid, 0)  # held means held: no lane changes either
            traci.vehicle.setSpeed(vid, speed_mps)
        self.traffic.actors[vid] = ActorInfo("vehicle", tuple(size), colour, placed=True)

    def place_pedestrian(self, pid: str, edge: str, pos_m: float, wait_s: float = 1000.0) -> None:
        """Adds a pedestrian who stands still at a position on a walkable edge."""
        traci.person.add(pid, edge, pos_m)
        traci.person.appendWaitingStage(pid, wait_s)
        self.traffic.actors[pid] = ActorInfo("pedestrian", PED_SIZE, 0, placed=True)

    def step_idle(self, n: int = 1) -> None:
        """Steps SUMO with the ego held where it is (tests, warm-up)."""
        for _ in range(n):
            self.advance(EgoState(self.ego.x_m, self.ego.y_m, self.ego.yaw_rad, 0.0))
            self.snapshot_actors()

    def snapshot_actors(self) -> tuple[Actors, Actors]:
        """Vehicles and pedestrians near the ego, keeping traffic re-tripped."""
        vehicles = self._read_vehicles()
        pedestrians = self._read_pedestrians()
        self.traffic.step(self._all_vehicle_ids, self._all_person_ids)
        return vehicles, pedestrians


def _close_sumo() -> None:
    """Closes the running simulation, if any, after a step that takes up a pending moveToXY
    (see _move_pending); where that step fails, the ego goes first, so SUMO drops the move."""
    global _move_pending
    if not traci.isLoaded():
        return
    if _move_pending:
        try:
            traci.simulationStep()
        except traci.TraCIException:
            try:
                traci.vehicle.remove(EGO_ID)
                traci.simulationStep()
            except traci.TraCIException as e:
                log.debug("could not flush the ego's last move before closing: %s", e)
        _move_pending = False
    traci.close()


def _lane_pos(graph: RoadGraph, lane_id: str, ego: EgoState) -> float:
    """Distance along a lane of the point nearest the ego's centre, m."""
    shape = graph.lane_shape(lane_id)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(shape, axis=0), axis=1))])
    return project_polyline(shape, cum, ego.x_m, ego.y_m)[0]
