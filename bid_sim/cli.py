"""The `bid` command line. User mistakes print one line naming the fix and exit with 2."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import logging
import os
import sys
import warnings
from pathlib import Path

from bid_sim.errors import BidError


def _towns(args: argparse.Namespace) -> int:
    from bid_sim.towns import BUILT_IN, describe_town, resolve_town

    rows = [describe_town(resolve_town(t)) for t in (args.town or BUILT_IN)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'town':<10}{'size (m)':>14}{'junctions':>11}{'T':>4}{'4-way':>7}{'signals':>9}"
          f"{'lanes/dir':>11}{'streets (km)':>14}{'crossing/zebra (m)':>20}")
    for r in rows:
        lanes = "–".join(str(n) for n in (r["lanes_per_direction"][0], r["lanes_per_direction"][-1]))
        lanes = lanes if r["lanes_per_direction"][0] != r["lanes_per_direction"][-1] else str(r["lanes_per_direction"][0])
        crossings = f"{r['crossing_width_m']:g} / {r['zebra_width_m']:g}"
        print(f"{r['town']:<10}{r['width_m']:>7.0f} × {r['height_m']:<4.0f}{r['junctions']:>11}"
              f"{r['t_junctions']:>4}{r['four_way']:>7}{r['signalised']:>9}{lanes:>11}"
              f"{r['street_length_m'] / 1000:>14.2f}{crossings:>20}")
    return 0


def _routes(args: argparse.Namespace) -> int:
    from bid_sim.routes import COMMAND_NAMES, load_routes, plan_spec, road_graph
    from bid_sim.towns import resolve_town

    town = resolve_town(args.town)
    graph = road_graph(town.net_file)
    rows = []
    for i, spec in enumerate(load_routes(town)):
        r = plan_spec(graph, spec)
        turns = [COMMAND_NAMES[p.command] for p in r.pieces if p.command != 4]
        rows.append({"route": i, "length_m": round(r.length_m, 1), "edges": len(r.edges),
                     "turns": [t for j, t in enumerate(turns) if j == 0 or turns[j - 1] != t]})
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for row in rows:
            print(f"{row['route']:>3} {row['length_m']:>7.1f} m  {' '.join(row['turns'])}")
        mean = sum(r["length_m"] for r in rows) / max(len(rows), 1)
        print(f"{town.name}: {len(rows)} routes, mean length {mean:.0f} m")
    return 0


def _episode(args: argparse.Namespace) -> int:
    from bid_sim.episode import describe, run_episode

    result = run_episode(args.town, args.route, args.weather, args.density, args.seed,
                         _agent(args.agent, args.speed), replan=args.replan,
                         max_steps=args.max_steps)
    print(json.dumps(result.to_dict(), indent=1) if args.json else describe(result))
    return 0


def _agent(name: str, speed_mps: float):
    from bid_sim.agents import make_agent

    return make_agent(name, speed_mps)


def _view(args: argparse.Namespace) -> int:
    from bid_sim.render.view import view, view_recording

    if args.recording:
        print(view_recording(args.recording, args.out, args.step))
        return 0
    print(view(args.town, args.route, args.density, args.seed, args.weather, args.out,
               _agent(args.agent, args.speed), step=50 if args.step is None else args.step, steps=args.steps,
               workers=args.render_workers))
    return 0


def _record(args: argparse.Namespace) -> int:
    from bid_sim.record import describe, record
    from bid_sim.weather import parse_weathers

    densities = tuple(d.strip() for d in args.densities.split(",") if d.strip())
    out = args.out or (f"data/town{args.town}" if args.town.isdigit() else f"data/{Path(args.town).name}")
    summary = record(args.town, args.episodes, parse_weathers(args.weathers), densities, args.seed,
                     args.workers, out, agent=args.agent, max_steps=args.max_steps,
                     progress=not args.json, perturb=args.perturb, perturb_turns=args.perturb_turns, ray_address=args.ray,
                     dagger=args.dagger, bends=args.bends, late_brake=args.late_brake, stall_s=args.stall_takeover,
                     stop_line_gap_m=args.stop_line_gap, walkers=args.crossing_walkers,
                     late_kinds=tuple(k.strip() for k in args.late_brake_for.split(",") if k.strip()),
                     dagger_options=_drive_options(args, None if args.dagger else
                                                   "is how the --dagger student drives; give --dagger CHECKPOINT or drop it"))
    print(json.dumps(summary, indent=1) if args.json else describe(summary))
    return 2 if summary["failed"] else 0


def _recover(args: argparse.Namespace) -> int:
    from bid_sim.recording import recover

    for f in args.files:
        path, steps = recover(f)
        print(f"recovered {steps} steps of {f} -> {path}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from bid_sim.render.view import rerender

    print(rerender(args.recording, args.weather, args.out, workers=args.render_workers))
    return 0


def _tables(args: argparse.Namespace) -> int:
    from bid_sim.tables import tables

    text = tables(args.results)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


def _drive_options(args: argparse.Namespace, misplaced: str | None) -> dict | None:
    """The BID agent's keyword options from the drive flags given (_add_drive_arguments), None if
    none; `misplaced`, when not None, is the error's end for a flag given where no BID drives."""
    given = {"forecast_brake": args.forecast_brake, "hazard_brake": args.hazard_brake,
             "vehicle_brake": args.vehicle_brake, "light_brake": args.light_brake, "move_off": args.move_off,
             "path_memory": args.path_memory, "pedestrian_memory": args.pedestrian_memory,
             "pedestrian_hold": args.pedestrian_hold,
             "max_speed": args.max_speed, "crossing_brake": args.crossing_brake,
             "start_cap": args.start_cap, "start_cap_m": args.start_cap_m, "sc_still": args.sc_still,
             "move_off_to": args.move_off_to, "sc_still_moving": args.sc_still_moving,
             "move_off_braked": args.move_off_braked, "turn_speed": args.turn_speed,
             "move_off_sc": args.move_off_sc, "move_off_light": args.move_off_light,
             "vehicle_second_head": args.vehicle_second_head, "light_still": args.light_still,
             "light_short": args.light_short, "move_off_green": args.move_off_green,
             "green_far": args.green_far, "light_hold": args.light_hold,
             "vehicle_hold": args.vehicle_hold, "sc_logit": args.sc_logit, "fine_logit": args.fine_logit,
             "fine_speed": args.fine_speed, "fine_caution": args.fine_caution}
    for key, value in given.items():
        if value is not None and misplaced is not None:
            raise BidError(f"--{key.replace('_', '-')} {misplaced}")
    # A hold, a wait, a gap or a speed of 0 means something (never hold, no wait, stop at the line, standing
    # too), so it is kept where the other options' 0 is dropped.
    kept = ("pedestrian_hold", "move_off_braked", "light_short", "move_off_green", "fine_speed")
    return {k: v for k, v in given.items() if v or (k in kept and v is not None)} or None


def _evaluate(args: argparse.Namespace) -> int:
    from bid_sim.evaluate import compare, evaluate
    from bid_sim.weather import parse_weathers

    if args.compare:
        print(compare(args.compare))
        return 0
    densities = tuple(d.strip() for d in args.density.split(",") if d.strip())
    routes = [int(r) for r in args.routes.split(",")] if args.routes else None
    out = args.out or f"results/{args.town}_{args.agent.replace(':', '_')}_{'-'.join(densities)}"
    options = _drive_options(args, f"is an option of --agent bid, not of {args.agent!r}; drop it"
                             if args.agent != "bid" else None)
    summary = evaluate(args.town, densities, parse_weathers(args.weathers), args.seeds, args.agent, out,
                       checkpoint=args.checkpoint, workers=args.workers, routes=routes, record=args.record,
                       video=args.video, progress=not args.json, max_steps=args.max_steps,
                       ray_address=args.ray, options=options)
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print((Path(out) / "summary.md").read_text())
        print(f"-> {out}/episodes.jsonl, summary.json, summary.md")
    return 0


def _bench(args: argparse.Namespace) -> int:
    if args.what == "record":
        from bid_sim.record import bench_record

        result = bench_record(args.town, args.density or "normal", args.weather or "ClearNoon",
                              steps=args.frames, agent=args.agent)
        print(json.dumps(result, indent=1) if args.json else
              f"{result['town']} {result['density']} {result['weather']}, {result['agent']}: "
              f"{result['record_fps_per_core']} frames/s per core recorded end to end "
              f"({result['frames']} frames, {result['kb_per_frame']} KB/frame; target 100)")
        return 0
    from bid_sim.render.bench import bench_render

    result = bench_render(args.town, args.density or "crowded", args.weather or "HardRainNoon", frames=args.frames)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        st = result["stage_ms_per_frame"]
        print(f"{result['town']} {result['density']} {result['weather']}: "
              f"{result['render_fps_per_core']} frames/s per core (median {result['render_ms_median']} ms "
              f"over {result['frames']} frames; target 400); stages ms "
              + ", ".join(f"{k} {v}" for k, v in st.items())
              + f"; 700 vs 70 vehicles in town: x{result['render_cost_ratio_700_vs_70']} (target <= 1.3); "
              f"machine speed: one numpy multiply of 1,000 floats {result['machine_numpy_mul_1k_us']} µs "
              "(~1 on a quiet core)")
    return 0


def _add_ray_argument(p: argparse.ArgumentParser, files: str) -> None:
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the episodes as tasks on a Ray cluster instead of --workers processes: "
                   "ADDRESS is HOST:6379 (on a node of the cluster), ray://HOST:10001 (Ray Client) "
                   "or auto; --ray alone uses $RAY_ADDRESS, else the cluster last started on this "
                   f"machine, else a new local Ray instance. {files} must be on a filesystem every "
                   "node sees. Results equal a local run's. Needs pip install 'bid-sim[cluster]'")


def _add_drive_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of how a BID drives (bid_model/agent.py): the agent of `bid evaluate --agent bid`,
    the student of `bid record --dagger`."""
    g = p.add_argument_group("how --agent bid drives" if p.prog.endswith("evaluate") else
                             "how the --dagger student drives (as bid evaluate --agent bid drives)")
    g.add_argument("--forecast-brake", type=float, default=None, metavar="GAIN",
                   help="--agent bid with a model trained with --forecast: brake at least GAIN times as "
                        "hard as reaching its forecast speed 1 s ahead takes (bid_model/agent.py)")
    g.add_argument("--hazard-brake", type=float, default=None, metavar="GAIN",
                   help="--agent bid with a model trained with --hazard: brake at least GAIN times as "
                        "hard as stopping short of the pedestrian its hazard head sees in the path takes, "
                        "and stay standing while one is within 8 m (bid_model/agent.py)")
    g.add_argument("--vehicle-brake", type=float, default=None, metavar="GAIN",
                   help="--agent bid with a model trained with --hazard: brake at least GAIN times as "
                        "hard as stopping short of the vehicle its hazard head sees in the path takes, "
                        "once it is nearer than 1 s at the ego's speed + 4 m (bid_model/agent.py)")
    g.add_argument("--light-brake", type=float, default=None, metavar="GAIN",
                   help="--agent bid with a model trained with --hazard: brake at least GAIN times as "
                        "hard as stopping 1 m short of the red light's stop line its hazard head sees "
                        "takes (bid_model/agent.py)")
    g.add_argument("--move-off", type=float, default=None, metavar="S",
                   help="--agent bid with a model trained with --hazard: once the ego has stood S seconds "
                        "and the hazard head sees no red light, pedestrian or vehicle within 8 m, "
                        "move off at accel 0.5 whatever the control head says (bid_model/agent.py)")
    g.add_argument("--move-off-to", type=float, default=None, metavar="MPS",
                   help="--agent bid with --move-off: the speed moving off drives the ego to before the "
                        "control head has it again (default 2) (bid_model/agent.py)")
    g.add_argument("--move-off-braked", type=float, default=None, metavar="S",
                   help="--agent bid with --move-off: after a stop the brakes made against the control "
                        "head, move off once clear for S seconds, not --move-off's (bid_model/agent.py)")
    g.add_argument("--path-memory", type=float, default=None, metavar="S",
                   help="--agent bid with the brakes above: a pedestrian or vehicle its hazard head saw in "
                        "the path within 6 m counts for the brakes and move-off S seconds after the head "
                        "loses it, nearer by the distance driven since (2 m at most); and a vehicle within "
                        "3 m holds an ego slower than 2 m/s (bid_model/agent.py)")
    g.add_argument("--pedestrian-memory", type=float, default=None, metavar="S",
                   help="--agent bid with --hazard-brake: a pedestrian its hazard head saw in the path "
                        "within 8 m, driving at 2 m/s or faster, counts for the brakes S seconds after the head "
                        "loses her, nearer by all the distance driven since (not with --path-memory) "
                        "(bid_model/agent.py)")
    g.add_argument("--pedestrian-hold", type=float, default=None, metavar="M",
                   help="--agent bid with --hazard-brake: a pedestrian seen in the path within M metres "
                        "keeps an ego slower than 2 m/s standing (default 8, as the expert; 0: never "
                        "held, only stopped 2 m short of) (bid_model/agent.py)")
    g.add_argument("--max-speed", type=float, default=None, metavar="MPS",
                   help="--agent bid: brake whenever the ego is faster than MPS m/s, by 1 share of full "
                        "braking per m/s over (0: no cap) (bid_model/agent.py)")
    g.add_argument("--turn-speed", type=float, default=None, metavar="MPS",
                   help="--agent bid: while the command is LEFT or RIGHT (from 20 m before the junction), "
                        "brake whenever the ego is faster than MPS m/s, as --max-speed does (0: no cap) (bid_model/agent.py)")
    g.add_argument("--crossing-brake", type=float, default=None, metavar="GAIN",
                   help="--agent bid with a model trained with --hazard-crossing: brake at least GAIN times as "
                        "hard as stopping 2 m short of the crossing with a pedestrian on it its hazard head "
                        "sees takes, and hold an ego slower than 2 m/s within 6 m of it (bid_model/agent.py)")
    g.add_argument("--start-cap", type=float, default=None, metavar="MPS",
                   help="--agent bid: once the ego has stood 1 s, drive its next 12 m (--start-cap-m) no "
                        "faster than MPS m/s (0: no cap) (bid_model/agent.py)")
    g.add_argument("--start-cap-m", type=float, default=None, metavar="M",
                   help="--agent bid with --start-cap: how many metres of a start it caps (default 12)")
    g.add_argument("--sc-still", action="store_true", default=None,
                   help="--agent bid with SC (--hazard-sc): SC reads frame t alone, its change since t-1 "
                        "zeroed, as a checkpoint trained with --sc-still does (bid_model/agent.py)")
    g.add_argument("--sc-still-moving", action="store_true", default=None,
                   help="--agent bid with SC: as --sc-still, but only while the ego moves (0.3 m/s or "
                        "faster); standing, SC reads both frames as trained (bid_model/agent.py)")
    g.add_argument("--move-off-sc", action="store_true", default=None,
                   help="--agent bid with --move-off and SC: move-off waits for the pedestrian and the "
                        "vehicle SC sees, not the hazard head (which reads the speed input and, standing, "
                        "a car ahead in an empty street) (bid_model/agent.py)")
    g.add_argument("--move-off-light", action="store_true", default=None,
                   help="--agent bid with --move-off and a move-off head (bid train --move-off-head "
                        "--move-off-speed): move-off waits for that head's red light and the first head's "
                        "pedestrian and vehicle (bid_model/agent.py)")
    g.add_argument("--vehicle-second-head", action="store_true", default=None,
                   help="--agent bid with --vehicle-brake or --move-off and a second head (bid train "
                        "--move-off-head --move-off-speed): the vehicle they read is that head's, the "
                        "pedestrian and red light the first head's (bid_model/agent.py)")
    g.add_argument("--light-still", action="store_true", default=None,
                   help="--agent bid with --light-brake or --move-off: below 2 m/s the red light they read "
                        "is the one read from frame t alone (motion in the junction reads as red) "
                        "(bid_model/agent.py)")
    g.add_argument("--light-short", type=float, metavar="M",
                   help="--agent bid with --light-brake: stop this far short of a red light's stop line "
                        "(default 1, the expert's; at 1 m the red lamp is above the cameras' view) "
                        "(bid_model/agent.py)")
    g.add_argument("--move-off-green", type=float, default=None, metavar="S",
                   help="--agent bid with --move-off and --light-brake: after a stop at a red light, move "
                        "off once clear for S seconds, not --move-off's (bid_model/agent.py)")
    g.add_argument("--green-far", type=float, metavar="M",
                   help="--agent bid with --move-off-green: its wait counts only while the red light reads "
                        "farther off than M metres (default 8, as clear) (bid_model/agent.py)")
    g.add_argument("--light-hold", action="store_true", default=None,
                   help="--agent bid with --light-brake: below 2 m/s a red light read within 8 m brakes fully, "
                        "unless --move-off is moving the ego off (bid_model/agent.py)")
    g.add_argument("--vehicle-hold", type=float, default=None, metavar="M",
                   help="--agent bid with --vehicle-brake: below 2 m/s a vehicle read in the path within M metres "
                        "(0 to 8) brakes fully; below about 1 m/s the vehicle brake alone asks nothing, so the "
                        "control head could creep into a car it reads 3-4 m off (bid_model/agent.py)")
    g.add_argument("--sc-logit", type=float, default=None, metavar="T",
                   help="--agent bid with SC presence logits (bid train --sc-presence): SC's pedestrian counts only "
                        "where its logit is above T (default 0, the odds its training's weight set); higher, surer "
                        "(bid_model/agent.py)")
    g.add_argument("--fine-logit", type=float, default=None, metavar="T",
                   help="--agent bid with a grafted fine SC (bid graft --fine-sc): its pedestrian counts only where "
                        "its presence logit is above T (default 0) (bid_model/agent.py)")
    g.add_argument("--fine-speed", type=float, default=None, metavar="MPS",
                   help="--agent bid with a grafted fine SC read while moving: its pedestrian counts only at MPS "
                        "(0 to 15) or faster (default 0.3) (bid_model/agent.py)")
    g.add_argument("--fine-caution", type=float, default=None, metavar="MPS",
                   help="--agent bid with --hazard-brake and a grafted fine SC read while moving: its pedestrian "
                        "leaves the merge; read within 5 m it is stopped for, farther only slowed for, to MPS by "
                        "where it is read (bid_model/agent.py)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bid", description="bid-sim: closed-loop brain-inspired driving on a CPU")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("towns", help="size, junctions, signals, lanes and street length of the towns")
    t.add_argument("town", nargs="*", help="town names (01, 02, 05) or folders; default: all built-in")
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=_towns)

    r = sub.add_parser("routes", help="the benchmark routes of a town")
    r.add_argument("--town", default="02")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=_routes)

    e = sub.add_parser("episode", help="run one episode with a scripted agent and print its summary")
    e.add_argument("--town", default="02", help="01, 02, 05 or a folder with a SUMO network")
    e.add_argument("--route", type=int, default=0)
    e.add_argument("--weather", default="ClearNoon")
    e.add_argument("--density", default="normal", help="none, normal or crowded")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--agent", default="expert", help="expert (default) or lanefollow")
    e.add_argument("--speed", type=float, default=6.0, help="lane follower's speed, m/s")
    e.add_argument("--replan", action="store_true", help="re-plan when the ego leaves its route")
    e.add_argument("--max-steps", type=int, default=None)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_episode)

    v = sub.add_parser("view", help="camera frames of an episode or a recording as a PNG or an MP4")
    v.add_argument("recording", nargs="?", help="a .mcap recording to show instead of running an episode "
                   "(PNG: --step, or a contact sheet without it)")
    v.add_argument("--town", default="02")
    v.add_argument("--route", type=int, default=0)
    v.add_argument("--density", default="normal")
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--weather", default="ClearNoon", help="a weather, or 'all' for the six stacked (PNG)")
    v.add_argument("--agent", default="lanefollow")
    v.add_argument("--speed", type=float, default=6.0, help="lane follower's speed, m/s")
    v.add_argument("--step", type=int, default=None, help="the step a PNG shows (default 50)")
    v.add_argument("--steps", type=int, default=200, help="steps an MP4 shows (0.1 s each)")
    v.add_argument("--render-workers", type=int, default=1, help="worker processes rendering (MP4)")
    v.add_argument("--out", default="view.png", help="a .png or .mp4 path")
    v.set_defaults(func=_view)

    rec = sub.add_parser("record", help="the expert drives random routes; one MCAP recording per episode")
    rec.add_argument("--town", default="01")
    rec.add_argument("--episodes", type=int, default=24)
    rec.add_argument("--weathers", default="train", help="train, test, all or a comma-separated list")
    rec.add_argument("--densities", default="none,normal,crowded")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--workers", type=int, default=max(1, min(os.cpu_count() or 1, 8)),
                     help="episodes in parallel (processes)")
    rec.add_argument("--max-steps", type=int, default=900, help="steps per episode at most (0.1 s each)")
    rec.add_argument("--agent", default="expert")
    rec.add_argument("--perturb", type=float, default=0.0,
                     help="share of driving time with steering noise; labels stay the expert's (recovery data)")
    rec.add_argument("--perturb-turns", type=float, default=0.0, metavar="SHARE",
                     help="share of the junction turns begun late: the turn's first steering damped for 0.4-1.2 s, "
                          "at any speed, so the car runs wide; labels stay the expert's, which steer it back")
    rec.add_argument("--stop-line-gap", type=float, default=None, metavar="M",
                     help="the expert stops this far before a red or amber light's stop line (default 1; at 1 m "
                          "the lamp is above the cameras' view, from about 2 m it is whole)")
    rec.add_argument("--crossing-walkers", type=float, default=0.0, metavar="SHARE",
                     help="send a pedestrian across the crossing after this share of each route's turns as the "
                          "ego comes (0 off): recordings of pedestrians in the path of a turning car")
    rec.add_argument("--dagger", default=None, metavar="CHECKPOINT",
                     help="a BID checkpoint drives, the --agent labels and takes over when it strays (DAgger)")
    _add_drive_arguments(rec)
    rec.add_argument("--late-brake", type=float, default=0.0, metavar="SHARE",
                     help="with --dagger: the teacher brakes for a car ahead of the student only once stopping "
                          "1 m short of it takes this share of full braking (0.5; default 0: at once), so "
                          "that the recordings hold the student near cars at speed")
    rec.add_argument("--late-brake-for", default="vehicle", metavar="KINDS",
                     help="with --late-brake: what the teacher brakes late for, vehicle, pedestrian or "
                          "vehicle,pedestrian (default vehicle), so that the recordings hold the student near "
                          "pedestrians in its path at speed too")
    rec.add_argument("--stall-takeover", type=float, default=None, metavar="S",
                     help="with --dagger: the teacher starts a student that stands while it would drive only "
                          "after S seconds (default 1.5); beyond the student's --move-off wait (say 10 with "
                          "--move-off 8) the student's own move-offs, and the turns begun by them, are recorded")
    rec.add_argument("--bends", action="store_true",
                     help="only routes that take a bend of the road (a corner, driven under LANEFOLLOW) "
                          "in their first 250 m; few random routes do")
    rec.add_argument("--out", default=None, help="folder (default data/townNN)")
    _add_ray_argument(rec, "--out")
    rec.add_argument("--json", action="store_true")
    rec.set_defaults(func=_record)

    rc = sub.add_parser("recover", help="salvage recordings whose writer was killed (.mcap.partial)")
    rc.add_argument("files", nargs="+")
    rc.set_defaults(func=_recover)

    rr = sub.add_parser("render", help="re-render a recording (or a folder) under another weather")
    rr.add_argument("recording")
    rr.add_argument("--weather", required=True)
    rr.add_argument("--out", required=True, help="a .mcap file, or a folder for a folder")
    rr.add_argument("--render-workers", type=int, default=1)
    rr.set_defaults(func=_render)

    ev = sub.add_parser("evaluate", help="closed-loop benchmark: every route x weathers x seeds, scored")
    ev.add_argument("--town", default="02")
    ev.add_argument("--density", default="none,normal,crowded", help="one or a comma-separated list")
    ev.add_argument("--weathers", default="test", help="train, test, all or a comma-separated list")
    ev.add_argument("--seeds", type=int, default=3)
    ev.add_argument("--agent", default="expert", help="expert, lanefollow, bid or module:Class")
    ev.add_argument("--checkpoint", default=None, help="the model checkpoint for --agent bid")
    _add_drive_arguments(ev)
    ev.add_argument("--workers", type=int, default=max(1, min(os.cpu_count() or 1, 8)))
    ev.add_argument("--routes", default=None, help="a comma-separated subset of route indices")
    ev.add_argument("--record", action="store_true", help="write each episode's MCAP recording")
    ev.add_argument("--video", nargs="?", type=int, const=True, default=False, metavar="N",
                    help="write each episode's MP4 with overlays (or only the first N episodes')")
    ev.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke runs)")
    ev.add_argument("--out", default=None, help="results folder (default results/TOWN_AGENT_DENSITY)")
    _add_ray_argument(ev, "With --record or --video, --out")
    ev.add_argument("--compare", nargs="+", default=None, metavar="RESULTS",
                    help="print results folders side by side, then each against the first episode by "
                         "episode (paired successes, sign test p, mean DS difference)")
    ev.add_argument("--json", action="store_true")
    ev.set_defaults(func=_evaluate)

    tb = sub.add_parser("tables", help="the result tables of many `bid evaluate` runs, next to the paper's")
    tb.add_argument("results", nargs="?", default="results", help="folder holding results folders (default results)")
    tb.add_argument("--out", default=None, help="write the Markdown here too (e.g. results/tables.md)")
    tb.set_defaults(func=_tables)

    b = sub.add_parser("bench", help="benchmarks: 'render' (frames/s per core, stage costs), "
                       "'record' (end-to-end recording frames/s per core)")
    b.add_argument("what", choices=["render", "record"])
    b.add_argument("--town", default="01")
    b.add_argument("--density", default=None, help="default: crowded (render), normal (record)")
    b.add_argument("--weather", default=None, help="default: HardRainNoon, every effect on (render), ClearNoon (record)")
    b.add_argument("--frames", type=int, default=240, help="frames to time (render) or record (record)")
    b.add_argument("--agent", default="expert", help="record: the driving agent")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=_bench)

    # Commands contributed by other packages (the model's train, gradcam, ...), found through
    # the "bid.commands" entry point group so that bid_sim does not depend on them.
    for ep in sorted(importlib.metadata.entry_points(group="bid.commands"), key=lambda e: e.name):
        ep.load()(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    warnings.filterwarnings("ignore", module="sumolib")
    try:
        return args.func(args)
    except BidError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
