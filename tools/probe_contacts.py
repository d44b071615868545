"""The seconds before a BID's first contacts, with the expert labelling alongside.

Picks the failed episodes of a `bid evaluate` folder whose first failure was a contact,
replays them (episodes are deterministic per seed) with the BID driving as the folder's run
drove it (its drive options) and the expert beside it (bid_model/shadow.py), and prints, for
each, the steps before the contact: speed, the ego's offset from the route, the BID's steer,
its control head's accel and the accel it drove with, the hazard nearness its brakes read
(pedestrian, vehicle, red light, ...), the expert's steer, accel and reason and the BID's accel
at other speed inputs. Then a tally over all of them: steps where the expert braked, where
the BID drove on there, and where it would have braked had its speed input been higher.

    .venv/bin/python tools/probe_contacts.py results/town02_jam10/bid_small_r11f --density normal --max 10
    .venv/bin/python tools/probe_contacts.py RESULTS --cause pedestrian --seconds 3 --json > probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import multiprocessing as mp
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bid_sim.errors import BidError


def _probe(job: tuple) -> dict:
    import torch

    from bid_model.shadow import probe_episode, tally, window
    from bid_sim.evaluate import first_collision

    torch.set_num_threads(1)
    checkpoint, line, seconds, options = job
    result, steps = probe_episode(checkpoint, line["town"], line["route_index"], line["weather"],
                                  line["density"], line["seed"], options=options)
    hit = first_collision(result.to_dict())
    before = window(steps, hit["time_s"], seconds) if hit else []
    return {"key": line["key"], "status": result.status, "contact": hit,
            "replayed": bool(hit) and hit["time_s"] == first_collision(line)["time_s"],
            "steps": [dataclasses.asdict(s) for s in before], "tally": tally(before)}


def _pick(lines: list[dict], cause: str, density: str | None, limit: int) -> list[dict]:
    from bid_sim.evaluate import failure_cause

    causes = {"vehicle", "pedestrian", "layout"} if cause == "any" else {cause}
    return [ln for ln in lines if failure_cause(ln) in causes
            and (density is None or ln["density"] == density)][:limit]


def _show(r: dict, every: int) -> str:
    c = r["contact"]
    head = (f"== {r['key']}: {c['kind']} ({c.get('detail', '')}) at {c['time_s']} s"
            if c else f"== {r['key']}: no contact on replay ({r['status']})")
    if c and not r["replayed"]:
        head += "  [not the evaluation's contact: another checkpoint or code?]"
    from bid_model.shadow import PROBE_SPEEDS

    speeds = ",".join(f"{v:g}" for v in PROBE_SPEEDS)
    rows = [head, f"   t s   v m/s  lat m | BID steer head drove | near (ped veh light ...) | "
                  f"expert steer accel  reason | BID accel at v = {speeds}"]
    for s in r["steps"][::every]:
        at = " ".join(f"{a:+.2f}" for a in s["accel_at"])
        near = " ".join(f"{x:.2f}" for x in s.get("near", ())) or "-"
        head_accel = s.get("head_accel")
        head_accel = "  -  " if head_accel is None else f"{head_accel:+.2f}"
        rows.append(f"  {s['time_s']:5.1f} {s['speed_mps']:5.1f} {s.get('lateral_m', 0.0):+6.2f} |   "
                    f"{s['bid'][0]:+.2f} {head_accel} {s['bid'][1]:+.2f} | {near:<24} |"
                    f"    {s['expert'][0]:+.2f} {s['expert'][1]:+.2f}  {s['reason']:<16} | {at}")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("results", help="a bid evaluate folder (episodes.jsonl, config.json)")
    p.add_argument("--checkpoint", default=None, help="default: the one the folder was evaluated with")
    p.add_argument("--cause", default="any", choices=("any", "vehicle", "pedestrian", "layout"))
    p.add_argument("--density", default=None)
    p.add_argument("--max", type=int, default=10, help="episodes to replay")
    p.add_argument("--seconds", type=float, default=4.0, help="how long before the contact to show")
    p.add_argument("--every", type=int, default=3, help="print every Nth step")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", action="store_true", help="print the probes as JSON instead")
    args = p.parse_args(argv)
    try:
        if args.max < 1 or args.every < 1 or args.workers < 1 or not args.seconds > 0:
            raise BidError("--max, --every and --workers must be 1 or more and --seconds above 0")
        folder = Path(args.results)
        if not (folder / "episodes.jsonl").is_file() or not (folder / "config.json").is_file():
            raise BidError(f"{folder} is not a bid evaluate folder (no episodes.jsonl / config.json); "
                           "give the --out of a bid evaluate run")
        from bid_sim.evaluate import read_lines

        config = json.loads((folder / "config.json").read_text())
        if config.get("agent") != "bid":
            raise BidError(f"{folder} was evaluated with --agent {config.get('agent')}, not bid; nothing to probe")
        checkpoint = args.checkpoint or config["checkpoint"]
        if not Path(checkpoint).is_file():
            raise BidError(f"checkpoint {checkpoint} not found; pass --checkpoint PATH")
        from bid_sim.evaluate import load_agent

        # a damaged or foreign checkpoint, or a drive option it lacks, fails here, once, in one line
        load_agent("bid", checkpoint, config.get("options"))
        if hashlib.sha256(Path(checkpoint).read_bytes()).hexdigest() != config.get("checkpoint_sha256"):
            print(f"note: {checkpoint} is not the checkpoint {folder} was evaluated with; "
                  "episodes will not replay as they ran", file=sys.stderr)
        picked = _pick(read_lines(folder / "episodes.jsonl"), args.cause, args.density, args.max)
        if not picked:
            raise BidError(f"no episode of {folder} failed first by a {args.cause} contact"
                           + (f" at density {args.density}" if args.density else ""))
    except BidError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    options = config.get("options") or {}  # how the run drove: the episodes replay only so
    jobs = [(checkpoint, ln, args.seconds, options) for ln in picked]
    try:
        with mp.get_context("spawn").Pool(min(args.workers, len(jobs))) as pool:
            probes = pool.map(_probe, jobs)
    except BidError as e:  # e.g. a SUMO error mid-episode, from a worker
        print(f"error: {e}", file=sys.stderr)
        return 2
    total = {k: sum(r["tally"][k] for r in probes) for k in probes[0]["tally"]}
    if args.json:
        print(json.dumps({"probes": probes, "tally": total}))
        return 0
    for r in probes:
        print(_show(r, args.every))
    print(f"\nover the last {args.seconds:g} s before {sum(bool(r['contact']) for r in probes)} contacts: "
          f"the expert braked (accel <= -0.2) on {total['expert_braked']} of {total['steps']} steps; "
          f"the BID braked on {total['bid_braked']} of them ({total['bid_braked_hard']} at -0.5 or harder) "
          f"and drove on (accel > 0.1) on {total['bid_drove_on']}, and on "
          f"{total['speed_led']} of those it would have braked at a higher speed input")
    return 0


if __name__ == "__main__":
    sys.exit(main())
