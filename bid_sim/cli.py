"""The `bid` command line. User mistakes print one line naming the fix and exit with 2."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import logging
import sys
import warnings

from bid_sim.errors import BidError


def _towns(args: argparse.Namespace) -> int:
    from bid_sim.towns import BUILT_IN, describe_town, resolve_town

    rows = [describe_town(resolve_town(t)) for t in (args.town or BUILT_IN)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'town':<10}{'size (m)':>14}{'junctions':>11}{'T':>4}{'4-way':>7}{'signals':>9}"
          f"{'lanes/dir':>11}{'streets (km)':>14}")
    for r in rows:
        lanes = "–".join(str(n) for n in (r["lanes_per_direction"][0], r["lanes_per_direction"][-1]))
        lanes = lanes if r["lanes_per_direction"][0] != r["lanes_per_direction"][-1] else str(r["lanes_per_direction"][0])
        print(f"{r['town']:<10}{r['width_m']:>7.0f} × {r['height_m']:<4.0f}{r['junctions']:>11}"
              f"{r['t_junctions']:>4}{r['four_way']:>7}{r['signalised']:>9}{lanes:>11}"
              f"{r['street_length_m'] / 1000:>14.2f}")
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
    from bid_sim.agents import LaneFollower

    if name == "lanefollow":
        return LaneFollower(target_speed_mps=speed_mps)
    raise BidError(f"unknown agent {name!r}; use 'lanefollow'")


def _view(args: argparse.Namespace) -> int:
    from bid_sim.render.view import view

    print(view(args.town, args.route, args.density, args.seed, args.weather, args.out,
               _agent(args.agent, args.speed), step=args.step, steps=args.steps,
               workers=args.render_workers))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from bid_sim.render.bench import bench_render

    result = bench_render(args.town, args.density, args.weather, frames=args.frames)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        st = result["stage_ms_per_frame"]
        print(f"{result['town']} {result['density']} {result['weather']}: "
              f"{result['render_fps_per_core']} frames/s per core (median {result['render_ms_median']} ms "
              f"over {result['frames']} frames; target 400); stages ms "
              + ", ".join(f"{k} {v}" for k, v in st.items())
              + f"; 700 vs 70 vehicles in town: x{result['render_cost_ratio_700_vs_70']} (target <= 1.3)")
    return 0


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
    e.add_argument("--agent", default="lanefollow")
    e.add_argument("--speed", type=float, default=6.0, help="lane follower's speed, m/s")
    e.add_argument("--replan", action="store_true", help="re-plan when the ego leaves its route")
    e.add_argument("--max-steps", type=int, default=None)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_episode)

    v = sub.add_parser("view", help="write camera frames of an episode as a PNG (one step) or an MP4")
    v.add_argument("--town", default="02")
    v.add_argument("--route", type=int, default=0)
    v.add_argument("--density", default="normal")
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--weather", default="ClearNoon", help="a weather, or 'all' for the six stacked (PNG)")
    v.add_argument("--agent", default="lanefollow")
    v.add_argument("--speed", type=float, default=6.0, help="lane follower's speed, m/s")
    v.add_argument("--step", type=int, default=50, help="the step a PNG shows")
    v.add_argument("--steps", type=int, default=200, help="steps an MP4 shows (0.1 s each)")
    v.add_argument("--render-workers", type=int, default=1, help="worker processes rendering (MP4)")
    v.add_argument("--out", default="view.png", help="a .png or .mp4 path")
    v.set_defaults(func=_view)

    b = sub.add_parser("bench", help="benchmarks: 'render' (frames/s per core, stage costs)")
    b.add_argument("what", choices=["render"])
    b.add_argument("--town", default="01")
    b.add_argument("--density", default="crowded")
    b.add_argument("--weather", default="HardRainNoon", help="HardRainNoon: every effect on")
    b.add_argument("--frames", type=int, default=240)
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
