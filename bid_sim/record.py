"""`bid record`: the expert drives random routes of a town across weathers and densities, one
MCAP recording per episode (bid_sim.recording), episodes in parallel processes.

The plan is a pure function of (town, episodes, weathers, densities, seed): episode i gets
the i-th random route, weather i mod |weathers|, density (i div |weathers|) mod |densities|
and its own seed. A re-run skips episodes whose recording is finished and re-records
unfinished ones from the start (episodes are deterministic), so an interrupted run resumes.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from tqdm import tqdm

from bid_sim import __version__
from bid_sim.agents import make_agent
from bid_sim.ego import DT_S
from bid_sim.errors import BidError, reason
from bid_sim.parallel import WorkerDied, run_parallel
from bid_sim.perturb import LATE_KINDS, MAX_STALL_STEPS, STALL_STEPS, Dagger, Perturbed
from bid_sim.recording import EpisodeWriter, partial_path, read_facts
from bid_sim.routes import RouteSpec, generate_routes
from bid_sim.towns import Town, crossing_words, net_tag, resolve_town
from bid_sim.weather import check_weather

log = logging.getLogger(__name__)

DENSITIES = ("none", "normal", "crowded")
MAX_STOP_LINE_GAP_M = 5.0  # the largest --stop-line-gap, metres


@dataclass(frozen=True)
class EpisodeSpec:
    index: int
    town: str  # as given: 01, 02, 05 or a folder
    route: RouteSpec
    weather: str
    density: str
    seed: int
    agent: str = "expert"
    max_steps: int | None = None
    perturb: float = 0.0  # share of driving time with steering noise (bid_sim.perturb)
    dagger: str | None = None  # checkpoint of a BID that drives while `agent` labels (bid_sim.perturb.Dagger)
    dagger_options: dict | None = None  # how that BID drives: BIDAgent's options, as `bid evaluate` gives them
    late_brake: float = 0.0  # the teacher brakes for a car ahead of the student only this late (Dagger's late_brake)
    stall_s: float | None = None  # the teacher starts a student standing this long (Dagger's stall_steps; None: 1.5 s)
    perturb_turns: float = 0.0  # share of the junction turns begun late (Perturbed's turns)
    stop_line_gap_m: float | None = None  # the expert stops this far before a red light's line (None: its 1 m)
    late_kinds: tuple[str, ...] = ("vehicle",)  # what the teacher brakes late for (Dagger's late_kinds)
    walkers: float = 0.0  # share of the route's turns met by a walker on the crossing (bid_sim.walkers)

    @property
    def name(self) -> str:
        return f"ep{self.index:05d}_{self.weather}_{self.density}"


def plan_episodes(town: str, episodes: int, weathers: tuple[str, ...], densities: tuple[str, ...],
                  seed: int, agent: str = "expert", max_steps: int | None = None,
                  perturb: float = 0.0, dagger: str | None = None, bends: bool = False,
                  dagger_options: dict | None = None, late_brake: float = 0.0,
                  stall_s: float | None = None, perturb_turns: float = 0.0,
                  stop_line_gap_m: float | None = None,
                  late_kinds: tuple[str, ...] = ("vehicle",), walkers: float = 0.0) -> list[EpisodeSpec]:
    if episodes < 1:
        raise BidError(f"--episodes must be >= 1, got {episodes}")
    if seed < 0:
        raise BidError(f"--seed must be >= 0, got {seed}")
    if not weathers or not densities:
        raise BidError("give at least one weather and one density")
    t = resolve_town(town)
    for w in weathers:
        check_weather(w)
    for d in densities:
        t.density(d)
    routes = generate_routes(t, count=episodes, seed=10_000 + seed, bends=bends)
    if len(routes) < episodes:
        kind = "random routes of >= 150 m" + (" with an early bend" if bends else "")
        raise BidError(f"{t.name} yields only {len(routes)} {kind}; record fewer episodes")
    nw = len(weathers)
    return [EpisodeSpec(i, town, routes[i], weathers[i % nw], densities[(i // nw) % len(densities)],
                        seed * 100_000 + i, agent, max_steps, perturb, dagger, dagger_options, late_brake, stall_s,
                        perturb_turns, stop_line_gap_m, late_kinds, walkers)
            for i in range(episodes)]


def plan_facts(spec: EpisodeSpec) -> dict[str, str]:
    """The facts of `spec` that a recording of it carries (record_episode) and that differ between
    plans: which route, which seed, who drove and how."""
    return {"route": f"{spec.route.start_edge}@{spec.route.start_pos_m}->{spec.route.goal_edge}@{spec.route.goal_pos_m}",
            "seed": str(spec.seed), "agent": spec.agent, "perturb": str(spec.perturb),
            "dagger": Path(spec.dagger).name if spec.dagger else "", "dagger_drive": drive_words(spec.dagger_options),
            "late_brake": f"{spec.late_brake:g}" if spec.late_brake else "",
            "stall_takeover_s": "" if spec.stall_s is None else f"{spec.stall_s:g}",
            "perturb_turns": f"{spec.perturb_turns:g}" if spec.perturb_turns else "",
            "stop_line_gap_m": "" if spec.stop_line_gap_m is None else f"{spec.stop_line_gap_m:g}",
            "late_brake_for": ",".join(spec.late_kinds) if spec.late_brake and spec.late_kinds != ("vehicle",) else "",
            "crossing_walkers": f"{spec.walkers:g}" if spec.walkers else ""}


def drive_words(options: dict | None) -> str:
    """A student's drive options as `bid evaluate`'s flags ("--light-brake 1 --move-off 8"; "" for none)."""
    words = []
    for key, value in sorted((options or {}).items()):
        flag = "--" + key.replace("_", "-")
        words.append(flag if value is True else f"{flag} {value:g}")
    return " ".join(words)


def check_same_plan(spec: EpisodeSpec, path: Path, town: Town, tag: str) -> None:
    """An episode file already in the --out folder is kept (a rerun finishes an interrupted
    recording) only if it is the episode `spec` plans: another --seed, --perturb (or --perturb-turns), --dagger (or
    how its student drives, --late-brake (and --late-brake-for) or --stall-takeover), --stop-line-gap, --crossing-walkers, --agent or town would otherwise mix two recordings under one
    folder unnoticed. `town`, `tag`: the plan's town and its net_tag, found once per recording."""
    theirs = read_facts(path)
    theirs = {**theirs, **{k: theirs.get(k, "") for k in ("dagger", "dagger_drive", "late_brake", "stall_takeover_s",
                                                      "perturb_turns", "stop_line_gap_m", "late_brake_for",
                                                      "crossing_walkers")}}
    differ = [f"{k} {theirs.get(k) or 'none'!r} here, {v or 'none'!r} planned"
              for k, v in plan_facts(spec).items() if theirs.get(k) != v]
    if theirs.get("town") != town.name:
        differ.insert(0, f"town {theirs.get('town')!r} here, {town.name!r} planned")
    elif theirs.get("town_net", tag) != tag:  # files recorded before it was written lack it
        width, zebra = theirs.get("crossing_width_m"), theirs.get("zebra_width_m")
        here = "crossings of unknown width"
        if width:
            here = crossing_words(float(width), float(zebra) if zebra else None)
        differ.insert(0, f"town {town.name} with {here} here, "
                         f"{crossing_words(town.crossing_width_m, town.zebra_width_m)} planned, or another net")
    if differ:
        raise BidError(f"{path} belongs to another recording ({'; '.join(differ)}): record into another "
                       f"--out folder, or give the options that recording was made with to finish it")


def record_episode(spec: EpisodeSpec, out: Path) -> dict:
    """Drives and records one episode; returns its summary. Runs in a worker process."""
    import cv2

    from bid_sim.episode import run_episode
    from bid_sim.render import Renderer
    from bid_sim.town_map import load_town_map

    cv2.setNumThreads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    town = resolve_town(spec.town)
    town_map = load_town_map(town)
    renderer = Renderer(town_map, weather=spec.weather, seed=spec.seed)
    plan = plan_facts(spec)
    facts = {"town": town.name, "town_source": spec.town, "town_net": net_tag(town),
             "crossing_width_m": f"{town.crossing_width_m:g}",
             "zebra_width_m": "" if town.zebra_width_m is None else f"{town.zebra_width_m:g}",
             "route": plan["route"], "episode": str(spec.index),
             "weather": spec.weather, "density": spec.density, "seed": str(spec.seed), "agent": spec.agent,
             "frame": "900x300 RGB, cameras left|centre|right at yaw +60/0/-60 deg, 60 deg FOV",
             "step_s": "0.1", "perturb": str(spec.perturb), "software": f"bid-sim {__version__}"}
    if spec.stop_line_gap_m is None:
        agent = make_agent(spec.agent)
    else:  # record() lets it through for the expert only
        from bid_sim.expert import Expert, ExpertConfig

        facts["stop_line_gap_m"] = plan["stop_line_gap_m"]
        agent = Expert(ExpertConfig(stop_line_gap_m=spec.stop_line_gap_m))
    if spec.perturb or spec.perturb_turns:
        if spec.perturb_turns:
            facts["perturb_turns"] = plan["perturb_turns"]
        agent = Perturbed(agent, spec.perturb, spec.perturb_turns)
    if spec.dagger:
        from bid_sim.evaluate import load_agent

        facts["dagger"] = Path(spec.dagger).name  # the student that drove; `agent` labelled
        facts["dagger_drive"] = drive_words(spec.dagger_options)  # and how it drove
        facts["late_brake"] = plan["late_brake"]  # and how late the teacher braked for cars
        if plan["late_brake_for"]:
            facts["late_brake_for"] = plan["late_brake_for"]  # and for what, if not for cars alone
        facts["stall_takeover_s"] = plan["stall_takeover_s"]  # and how long the student could stand
        agent = Dagger(load_agent("bid", spec.dagger, spec.dagger_options), agent, spec.late_brake,
                       STALL_STEPS if spec.stall_s is None else round(spec.stall_s / DT_S), spec.late_kinds)
    walkers = None
    if spec.walkers:
        from bid_sim.walkers import CrossingWalkers

        facts["crossing_walkers"] = plan["crossing_walkers"]  # the route's turns met by walkers
        walkers = CrossingWalkers(spec.walkers, spec.seed)
    heads = [h.position for h in town_map.signal_heads]
    writer = EpisodeWriter(out / f"{spec.name}.mcap", facts, heads)
    try:
        result = run_episode(town, spec.route, spec.weather, spec.density, spec.seed, agent,
                             recorder=writer, renderer=renderer, max_steps=spec.max_steps,
                             on_start=walkers and walkers.start, on_step=walkers and walkers.step)
    except BaseException:
        writer.abort()
        raise
    end = {"status": result.status, "steps": result.steps, "metrics": result.metrics,
           "infractions": [i.to_dict() for i in result.infractions]}
    if spec.dagger:
        end["student_share"] = round(agent.student_share, 4)
        end["late_steps"] = agent.late_steps
    if spec.perturb_turns:
        end["late_turns"] = agent.late_turns
    if walkers is not None:
        end["walkers"] = len(walkers.sent)
    writer.finish(end)
    return {"name": spec.name, "frames": writer.frames, "status": result.status,
            "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
            **({"student_share": end["student_share"], "late_steps": end["late_steps"]} if spec.dagger else {}),
            **({"late_turns": end["late_turns"]} if spec.perturb_turns else {}),
            **({"walkers": end["walkers"]} if walkers is not None else {})}


def record(town: str, episodes: int, weathers: tuple[str, ...], densities: tuple[str, ...], seed: int,
           workers: int, out: str | os.PathLike, agent: str = "expert", max_steps: int | None = None,
           progress: bool = True, perturb: float = 0.0, ray_address: str | None = None,
           dagger: str | None = None, bends: bool = False, dagger_options: dict | None = None,
           late_brake: float = 0.0, stall_s: float | None = None, perturb_turns: float = 0.0,
           stop_line_gap_m: float | None = None, late_kinds: tuple[str, ...] = ("vehicle",),
           walkers: float = 0.0) -> dict:
    """Records the plan's unfinished episodes into `out`; returns a summary.
    bends: only routes that take a bend of the road early (bid_sim.routes.generate_routes).
    dagger: a BID checkpoint that drives while `agent` labels and takes over (bid_sim.perturb.Dagger);
    dagger_options: how it drives (bid_model.agent.BIDAgent's options, as `bid evaluate` passes
    them), so that the student visits the states it visits when evaluated so; late_brake: the
    teacher brakes for a car ahead of it only once stopping 1 m short takes that share of full
    braking (bid_sim.perturb.Dagger), so that the student comes near cars at speed; late_kinds:
    what it brakes late for (bid_sim.perturb.LATE_KINDS: cars, pedestrians or both); stall_s:
    seconds the student may stand while the teacher would drive before the teacher starts it
    (None: bid_sim.perturb.STALL_STEPS), so that a student's own move-off drives it off.
    perturb_turns: the share of junction turns the expert begins late (bid_sim.perturb.Perturbed).
    stop_line_gap_m: how far before a red or amber light's stop line the expert stops (None: its
    own 1 m, bid_sim.expert.ExpertConfig); at 1 m the lamp is above the cameras' view.
    walkers: the share of the route's turns at which a pedestrian is sent across the crossing
    the turn leads over as the ego comes (bid_sim.walkers.CrossingWalkers), so that the
    recordings hold pedestrians in the path of a turning car.
    ray_address: run the episodes as tasks on a Ray cluster instead of `workers` local
    processes (bid_sim.cluster; "" for $RAY_ADDRESS or a local instance)."""
    out = Path(out)
    if ray_address is not None:
        from bid_sim.cluster import require_ray

        require_ray()  # before any work
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise BidError(f"cannot write to {out} ({e.strerror}); pick a writable --out folder") from e
    if workers < 1:
        raise BidError(f"--workers must be >= 1, got {workers}")
    if not 0.0 <= perturb < 1.0:
        raise BidError(f"--perturb must be a share of driving time in [0, 1), got {perturb}")
    if not 0.0 <= perturb_turns <= 1.0:
        raise BidError(f"--perturb-turns must be a share of the turns in [0, 1], got {perturb_turns}")
    if dagger is not None:
        if perturb or perturb_turns:
            raise BidError("--dagger and --perturb (or --perturb-turns) do not go together: the student's own "
                           "errors are the perturbation")
        if not Path(dagger).is_file():
            raise BidError(f"--dagger {dagger}: no such checkpoint; give a run's best.pt or checkpoints/bid_small.pt")
        from bid_sim.evaluate import load_agent

        load_agent("bid", dagger, dagger_options)  # a damaged or foreign checkpoint, or an option it lacks, fails here
        dagger = str(Path(dagger).resolve())
    elif dagger_options or late_brake or stall_s is not None:
        what = ("drive options are how the --dagger student drives" if dagger_options else
                "--late-brake is how late the teacher brakes for the --dagger student" if late_brake else
                "--stall-takeover is how long the --dagger student may stand")
        raise BidError(f"{what}; give --dagger CHECKPOINT or drop them")
    if not 0.0 <= late_brake <= 1.0:
        raise BidError(f"--late-brake is a share of full braking, from 0 (off) to 1; got {late_brake}")
    if late_brake and agent != "expert":
        raise BidError(f"--late-brake needs the expert as the teacher (it says what it brakes for); got --agent {agent}")
    late_kinds = tuple(late_kinds)
    if not late_kinds or set(late_kinds) - set(LATE_KINDS):
        raise BidError(f"--late-brake-for is what the teacher brakes late for, some of {','.join(LATE_KINDS)}; "
                       f"got {','.join(late_kinds) or 'nothing'}")
    if late_kinds != ("vehicle",) and not late_brake:
        raise BidError("--late-brake-for says what --late-brake holds the teacher's braking back for; "
                       "give --late-brake SHARE too, or drop it")
    if stall_s is not None and not 1 <= round(stall_s / DT_S) <= MAX_STALL_STEPS:
        raise BidError(f"--stall-takeover is seconds the student may stand, 0.1 to {MAX_STALL_STEPS * DT_S:g}; got {stall_s}")
    if stop_line_gap_m is not None and agent != "expert":
        raise BidError(f"--stop-line-gap is where the expert stops at a red light; got --agent {agent}")
    if stop_line_gap_m is not None and not 0.0 <= stop_line_gap_m <= MAX_STOP_LINE_GAP_M:
        raise BidError(f"--stop-line-gap is a distance from 0 to {MAX_STOP_LINE_GAP_M:g} m; got {stop_line_gap_m}")
    if not 0.0 <= walkers <= 1.0:
        raise BidError(f"--crossing-walkers is a share of the route's turns, from 0 (off) to 1; got {walkers}")
    specs = plan_episodes(town, episodes, weathers, densities, seed, agent, max_steps, perturb, dagger, bends,
                          dagger_options, late_brake, stall_s, perturb_turns, stop_line_gap_m, late_kinds, walkers)
    plan_town = resolve_town(town)
    plan_tag = net_tag(plan_town)
    for s in specs:
        if (out / f"{s.name}.mcap").exists():
            check_same_plan(s, out / f"{s.name}.mcap", plan_town, plan_tag)
    todo = [s for s in specs if not (out / f"{s.name}.mcap").exists()]
    for s in todo:
        partial_path(out / f"{s.name}.mcap").unlink(missing_ok=True)  # restarted from scratch
    done, failed = [], []
    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), unit="episode", disable=not progress, desc=f"recording {len(todo)} episodes")
    frames = 0

    def finished(summary: dict) -> None:  # in the parent, as each episode completes
        nonlocal frames
        done.append(summary)
        frames += summary["frames"]
        bar.update(1)
        bar.set_postfix(frames=frames, fps=f"{frames / max(time.perf_counter() - t0, 1e-9):.0f}")

    try:
        if ray_address is None:
            run_parallel(partial(record_episode, out=out), todo, workers, lambda spec, summary: finished(summary),
                         on_error=lambda spec, e: failed.append((spec.name, reason(e))))
        else:
            from bid_sim.cluster import run_ray

            run_ray(partial(record_episode, out=out.resolve()), todo, ray_address,
                    lambda spec, summary: finished(summary),
                    on_error=lambda spec, e: failed.append((spec.name, reason(e))), shared=out)
    except WorkerDied as e:  # no episode can go on
        raise BidError(f"{e}; the {len(done)} episodes finished are kept in {out}; "
                       "rerun the same command to record the rest") from e
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    return {"out": str(out), "planned": len(specs), "skipped": len(specs) - len(todo), "recorded": len(done),
            "failed": failed, "frames": frames, "wall_s": round(wall, 1),
            "frames_per_s": round(frames / wall, 1) if wall > 0 else 0.0,
            "statuses": {k: sum(1 for d in done if d["status"] == k) for k in sorted({d["status"] for d in done})},
            **({"student_share": round(sum(d["student_share"] for d in done) / len(done), 3)}
               if dagger and done else {}),
            **({"late_steps": sum(d["late_steps"] for d in done), "late_brake_for": list(late_kinds)}
               if late_brake else {}),
            **({"late_turns": sum(d["late_turns"] for d in done)} if perturb_turns else {}),
            **({"walkers": sum(d["walkers"] for d in done)} if walkers else {})}


def describe(summary: dict) -> str:
    lines = [f"{summary['recorded']} episodes recorded ({summary['frames']} frames, {summary['frames_per_s']} "
             f"frames/s over {summary['wall_s']} s), {summary['skipped']} already there, "
             f"{len(summary['failed'])} failed -> {summary['out']}"]
    if summary["statuses"]:
        lines.append("  endings: " + ", ".join(f"{k} {v}" for k, v in summary["statuses"].items()))
    if "student_share" in summary:
        lines.append(f"  the student drove {100 * summary['student_share']:.0f} % of the steps, the expert the rest")
    if "late_steps" in summary:
        what = " or ".join({"vehicle": "a car", "pedestrian": "a pedestrian"}[k]
                           for k in summary.get("late_brake_for", ["vehicle"]))
        lines.append(f"  the expert held back its braking for {what} ahead {summary['late_steps']} steps (--late-brake)")
    if "late_turns" in summary:
        lines.append(f"  the expert began {summary['late_turns']} turns late (--perturb-turns)")
    if "walkers" in summary:
        lines.append(f"  {summary['walkers']} walkers sent across the crossings of the routes' turns (--crossing-walkers)")
    lines += [f"  failed {name}: {msg}" for name, msg in summary["failed"]]
    return "\n".join(lines)


def bench_record(town: str = "01", density: str = "normal", weather: str = "ClearNoon", steps: int = 600,
                 agent: str = "expert") -> dict:
    """End-to-end recording speed in this process on one core: SUMO, the agent, rendering,
    JPEG and MCAP writing of one episode; frames per CPU second."""
    import tempfile

    spec = plan_episodes(town, 1, (weather,), (density,), seed=0, agent=agent, max_steps=steps)[0]
    with tempfile.TemporaryDirectory() as tmp:
        record_episode(EpisodeSpec(spec.index, town, spec.route, weather, density, spec.seed, agent, 30), Path(tmp))
        s = record_episode(spec, Path(tmp))
        size = sum(f.stat().st_size for f in Path(tmp).glob("*.mcap"))
    return {"town": town, "density": density, "weather": weather, "agent": agent, "frames": s["frames"],
            "status": s["status"], "wall_s": round(s["seconds"], 2), "cpu_s": round(s["cpu_seconds"], 2),
            "record_fps_per_core": round(s["frames"] / s["cpu_seconds"], 1),
            "record_fps_wall": round(s["frames"] / s["seconds"], 1),
            "record_fps_target_ratio": round(s["frames"] / s["cpu_seconds"] / 100.0, 3),
            "kb_per_frame": round(size / 1024 / max(1, s["frames"] + 30), 1)}
