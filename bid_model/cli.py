"""`bid` subcommands of the model package (registered through the "bid.commands" entry point).

torch is imported only when a model command runs, so `bid towns` stays fast.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bid_model.config import PRESETS, PROBE_SOURCES, VARIANTS


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of `bid train` and `python -m bid_model.train`."""
    p.add_argument("--preset", choices=PRESETS, default=None,
                   help="network and schedule: paper, small (default) or tiny")
    p.add_argument("--variant", choices=tuple(VARIANTS), default=None,
                   help="the paper's ablation: baseline, dorsal, navigation, both, full (default)")
    p.add_argument("--data", default="data/town01", help="folder of recordings (default data/town01)")
    p.add_argument("--synthetic", action="store_true", help="train on generated frames instead")
    p.add_argument("--samples", type=int, default=None, help="size of the --synthetic dataset")
    p.add_argument("--epochs", type=int, default=None,
                   help="epochs (the lr milestones scale with them); preset's by default")
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--augment", type=float, default=None, metavar="SHARE",
                   help="share of training samples given a random lighting change (bid_model/augment.py)")
    p.add_argument("--hard-repeat", type=int, default=None, metavar="N",
                   help="train on each frame of hard steering or braking N times (recordings.balance_rows)")
    p.add_argument("--start-repeat", type=int, default=None, metavar="N",
                   help="train on each moving-off frame (below 2 m/s, throttle) N times, the repeats shown "
                        "standing still (recordings.balance_rows; small: 3)")
    p.add_argument("--start-accel", type=float, default=None, metavar="A",
                   help="a standstill's throttle of at most A is trained on as a hold (0) and not "
                        "repeated: the expert closing up on a queue, not moving off (recordings.hold_creep; "
                        "0, every throttle a start, by default)")
    p.add_argument("--hold-repeat", type=int, default=None, metavar="N",
                   help="keep every frame where the expert stands or brakes below 2 m/s with no red "
                        "light ahead (a yield: to pedestrians on the crossing, a car) and train on it "
                        "N times (recordings.yield_frames; 1 by default)")
    p.add_argument("--hard-brake", action=argparse.BooleanOptionalAction, default=None,
                   help="with --hard-repeat, whether hard braking frames are repeated too (default yes)")
    p.add_argument("--brake-lookahead", type=int, default=None, metavar="N",
                   help="train on accel labels that brake as the expert will over the next N frames "
                        "(recordings.anticipate_braking; 1, as recorded, by default)")
    p.add_argument("--forecast", type=float, default=None, metavar="WEIGHT",
                   help="also train a head forecasting the speed 1, 2 and 3 s ahead, its L1 loss "
                        "weighted WEIGHT (speed in units of 10 m/s; 0, none, by default); driving "
                        "ignores it (bid_model/model.py)")
    p.add_argument("--hazard", type=float, default=None, metavar="WEIGHT",
                   help="also train a head saying how far ahead the nearest pedestrian and vehicle in the "
                        "ego's path are, learnt from the recordings' /scene, its L1 loss weighted WEIGHT "
                        "(0, none, by default); driving ignores it (bid_model/hazards.py)")
    p.add_argument("--hazard-pos-weight", type=float, default=None, metavar="W",
                   help="with --hazard, weigh each frame with a pedestrian (vehicle) in the path W times "
                        "in the head's pedestrian (vehicle) loss, so that a rare kind is not fitted as "
                        "'none' (1 by default)")
    p.add_argument("--hazard-turn-weight", type=float, default=None, metavar="W",
                   help="with --hazard, weigh a frame with a pedestrian in the path W times more where "
                        "the command is a turn (LEFT or RIGHT, as shown, mirrored or not): turning, the "
                        "ego meets pedestrians crossing the street it turns into beside others waiting "
                        "on the kerb (1 by default)")
    p.add_argument("--hazard-moving-weight", type=float, default=None, metavar="W",
                   help="with --hazard, weigh a frame with a pedestrian in the path W times more where "
                        "the ego moves (0.3 m/s or faster): the expert has mostly stopped before one is "
                        "near, so its recordings hold few (1 by default)")
    p.add_argument("--hazard-vehicle-moving-weight", type=float, default=None, metavar="W",
                   help="with --hazard, weigh a frame with a vehicle in the path W times more where the "
                        "ego moves (0.3 m/s or faster): the expert keeps its distance, so its recordings "
                        "hold few close approaches (1 by default; bid record --late-brake records some)")
    p.add_argument("--hazard-green-weight", type=float, default=None, metavar="W",
                   help="with --hazard, weigh W times the red-light entry (none) of a frame where the ego "
                        "stands at a green light's stop line (3 m or nearer, or past it): the expert stands "
                        "there almost only at red, and the light output learnt the place (1 by default)")
    p.add_argument("--hazard-ahead", type=float, default=None, metavar="S",
                   help="with --hazard, a pedestrian counts in the path also where the recording shows it "
                        "in the path ahead of the ego within S seconds, so that one about to walk in is "
                        "seen before it does (0, where it is now, by default; bid_model/hazards.py)")
    p.add_argument("--hazard-attend", action="store_true", default=None,
                   help="with --hazard, a head whose per-kind queries attend over V2's and V4's feature "
                        "grids and MPC's tokens, rather than one reading MPC's mean (bid_model/model.py)")
    p.add_argument("--hazard-sc", action="store_true", default=None,
                   help="with --hazard, SC says it too: a shallow pathway on the full input frames and their "
                        "change (never the speed), read at the peaks of its priority maps "
                        "(bid_model/areas.py); the pedestrian and vehicle outputs are the nearer of the "
                        "head's and SC's")
    p.add_argument("--sc-presence", action="store_true", default=None,
                   help="with --hazard-sc, SC also says whether one is in the path at all (a logit per "
                        "kind, fitted by cross-entropy weighted as --hazard-pos-weight and "
                        "--hazard-turn-weight say) and its nearness is fitted only where one is: it "
                        "reads a nearness where it says yes, none elsewhere")
    p.add_argument("--head-presence", action="store_true", default=None,
                   help="with --hazard-sc, the hazard head also says whether a pedestrian is in the path "
                        "(a logit, fitted by cross-entropy weighted as the --hazard-*-weight flags say) and "
                        "her nearness is fitted only where she is: an unsure sighting no longer reads as far "
                        "off; --init from a head without it starts the logit as its nearness >= 0.2")
    p.add_argument("--sc-still", action="store_true", default=None,
                   help="with --hazard-sc, SC reads frame t alone (its change since t-1 zeroed): the "
                        "change is mostly the ego's own motion, from which SC learnt that a moving car "
                        "has nothing in its path; --init from a checkpoint with SC keeps its weights")
    p.add_argument("--sc-scale", type=int, default=None, metavar="N",
                   help="with --hazard-sc, SC reads the frames N times as fine as the cortex (2: 128x384 "
                        "beside small's 64x192; the cortex reads them area-averaged down, as before); "
                        "--init from another scale starts SC afresh and keeps every other weight")
    p.add_argument("--sc-fine", type=int, default=None, metavar="N",
                   help="with --hazard-sc, a second SC with presence logits on frames N times as fine as the "
                        "cortex's, its pedestrian read while the ego moves: a model `bid graft` made, to "
                        "--init from (e.g. --train-only SC_fine; 0: none, the default)")
    p.add_argument("--hazard-speedless", action="store_true", default=None,
                   help="with --hazard and a speed input, the hazard head reads MPC's tokens merged without "
                        "the speed token (standing, the head with it read a car ahead in an empty street); "
                        "--init from a checkpoint without it keeps every weight")
    p.add_argument("--move-off-head", action="store_true", default=None,
                   help="with --hazard and a speed input, a second hazard head, fitted alike, that reads "
                        "MPC without the speed token; `bid evaluate --move-off` waits for the pedestrian and "
                        "vehicle it sees, the brakes and the red light are the first head's; --init from a "
                        "checkpoint without it starts it as that checkpoint's hazard head")
    p.add_argument("--move-off-speed", action="store_true", default=None,
                   help="with --move-off-head, the move-off head reads MPC with the speed token, as the "
                        "first head does: a second head of the same kind, fitted apart (e.g. with "
                        "--hazard-green-weight), whose red light `bid evaluate --move-off-light` reads")
    p.add_argument("--second-bumper", type=float, default=None, metavar="M",
                   help="with --move-off-head, the second head's vehicle target also counts the nearest car "
                        "within M metres ahead of the front bumper along the ego's current heading and turn, "
                        "wherever the route goes (read by `bid evaluate --vehicle-second-head`)")
    p.add_argument("--second-bumper-weight", type=float, default=None, metavar="W",
                   help="with --second-bumper, the frames where the car ahead of the bumper is nearer than "
                        "the path's weigh W times in the second head's loss (they are rare: a wide turn)")
    p.add_argument("--hazard-crossing", action="store_true", default=None,
                   help="with --hazard-sc, a fourth hazard output from a second SC map: how near the next "
                        "crossing on the path with a pedestrian on it is (driven by bid evaluate --crossing-brake)")
    p.add_argument("--mirror", type=float, default=None, metavar="SHARE",
                   help="share of training samples mirrored left to right, commands and steering with "
                        "them (augment.mirror): for fitting a detector such as --train-only SC, since the "
                        "mirrored town drives on the left (0 by default)")
    p.add_argument("--shift", type=int, default=None, metavar="PIXELS",
                   help="move each training sample (frame t and t-1 alike) by up to PIXELS of the input "
                        "down or up and sideways, as a camera pitched or turned a little (augment.shift; "
                        "0 by default)")
    p.add_argument("--stop-keep", type=float, default=None, metavar="SHARE",
                   help="share of standing, braking frames trained on (recordings.balance_rows; small: 0.25)")
    p.add_argument("--motion-drop", type=float, default=None, metavar="SHARE",
                   help="share of training rows shown without motion, frame t-1 = frame t "
                        "(recordings.motion_dropout; small: 0.5)")
    p.add_argument("--frame-hw", default=None, metavar="ROWSxCOLS",
                   help="the network's input size, e.g. 96x288 (the preset's by default: small 64x192); "
                        "with --init from another size the token grids' positional embeddings are resized")
    p.add_argument("--accel-quantile", type=float, default=None, metavar="TAU",
                   help="fit accel's TAU-quantile (pinball loss) rather than its median: below 0.5, "
                        "where the labels of a scene disagree the network brakes as the harder of "
                        "them (0.5, L1, by default)")
    p.add_argument("--speed-noise", type=float, default=None, metavar="SIGMA",
                   help="train on the speed input times exp(SIGMA·N(0,1)), so that the network judges "
                        "gaps from the frames rather than the speed alone (0, exact, by default)")
    p.add_argument("--speed-input", action=argparse.BooleanOptionalAction, default=None,
                   help="feed the measured speed to the network (off in paper, on in small)")
    p.add_argument("--train-only", default=None, metavar="PARTS",
                   help="train only these parts, comma-separated (areas V1 ... CPC, or forecast, hazard, SC, "
                        "speed, dorsal_tokens); the rest stays as --init left it, e.g. --train-only hazard")
    p.add_argument("--keep-accel", action="store_true", default=None,
                   help="with --train-only CPC and --init: the accel labels are the init control head's own, "
                        "so it learns new steering labels (a DAgger round's) and keeps its throttle and brake")
    p.add_argument("--keep-hazard", nargs="?", const="pedestrian,vehicle", default=None, metavar="KINDS",
                   help="with --train-only hazard and --init: the head's targets of these kinds (default "
                        "pedestrian,vehicle; of pedestrian, vehicle, red_light) are the init head's own, so it learns "
                        "the others anew (say red lights from bid record --stop-line-gap) and keeps these")
    p.add_argument("--keep-hazard-standing", action="store_true", default=None,
                   help="with --keep-hazard: on frames of a standing ego every kind is the init head's own, so the "
                        "refit changes what the head reads while the car moves only")
    p.add_argument("--out", default=None, help="run folder (default runs/NAME)")
    p.add_argument("--name", default=None, help="run name under runs/ (default PRESET-VARIANT-TIME)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out / --name")
    p.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="start from this checkpoint's weights (fine-tuning; same preset and flags, "
                        "or another --variant: the areas both have)")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu or cuda")
    p.add_argument("--compile", action="store_true",
                   help="CUDA only: torch.compile each brain area (faster steps after a warm-up)")
    p.add_argument("--workers", type=int, default=None, help="data loader processes")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for torch (default: all cores; 1 on a busy machine)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _train(args: argparse.Namespace) -> int:
    from bid_model.train import run_from_args

    return run_from_args(args)


def _gradcam(args: argparse.Namespace) -> int:
    from bid_model.gradcam import run_gradcam

    targets = ("steer", "accel") if args.target == "both" else (args.target,)
    paths = run_gradcam(Path(args.checkpoint), Path(args.out), data=Path(args.data),
                        synthetic=args.synthetic, area=args.area, targets=targets,
                        samples=args.samples, preset=args.preset)
    print(f"{args.out}: {len(paths)} Grad-CAM overlays ({args.area}, {args.target})")
    return 0


def _lesion(args: argparse.Namespace) -> int:
    from bid_model.lesion import lesion_study
    from bid_sim.weather import parse_weathers

    routes = [int(r) for r in args.routes.split(",")] if args.routes else None
    areas = args.areas.split(",") if args.areas else None
    out = args.out or f"results/lesion_town{args.town}_{args.density}"
    lesion_study(args.checkpoint, args.town, args.density, parse_weathers(args.weathers), args.seeds, out,
                 workers=args.workers, routes=routes, mode=args.mode, areas=areas, max_steps=args.max_steps)
    print((Path(out) / "lesion.md").read_text())
    print(f"-> {out}/lesion.json, lesion.md, lesion.png")
    return 0


def _export(args: argparse.Namespace) -> int:
    from bid_model.checkpoint import export_checkpoint

    card = export_checkpoint(args.run, args.out, args.which, args.recipe)
    size = Path(args.out).stat().st_size / 1e6
    print(f"{args.out}: {size:.1f} MB, epoch {card['epoch']} of {args.run} (git {card['git_hash']}); "
          f"card {Path(args.out).with_suffix('.json')}")
    return 0


def _average(args: argparse.Namespace) -> int:
    from bid_model.checkpoint import average_checkpoints
    from bid_sim.errors import BidError

    try:
        weights = [float(w) for w in args.weights.split(",")] if args.weights else None
    except ValueError:
        raise BidError(f"--weights takes comma-separated numbers, got {args.weights!r}") from None
    payload = average_checkpoints(args.checkpoints, args.out, weights, keep_heads=args.keep_heads)
    parts = ", ".join(f"{a['weight']:.2f} x {a['path']}" for a in payload["init"]["average"])
    print(f"{args.out}: {parts}")
    return 0


def _graft(args: argparse.Namespace) -> int:
    from bid_model.checkpoint import graft_fine_sc

    payload = graft_fine_sc(args.checkpoint, args.fine_sc, args.out)
    model = payload["config"]["model"]
    scale = max(model["sc_fine"], model.get("sc_scale") or 1)
    print(f"{args.out}: {args.checkpoint} with {args.fine_sc}'s SC beside its own, reading frames at "
          f"{model['sc_fine']}x the cortex's resolution (input {model['frame_hw'][0] * scale}x"
          f"{model['frame_hw'][1] * scale}); its pedestrian read "
          f"{'while the ego moves' if model['fine_moving'] else 'always'}")
    return 0


def _probe(args: argparse.Namespace) -> int:
    from bid_model.probe import probe_hazards, probe_table, write_probe

    result = probe_hazards(args.checkpoint, args.data, every=args.every, threads=args.threads,
                           second=args.second_head, source=args.source, hazard_ahead_s=args.hazard_ahead)
    print(probe_table(result))
    if args.out:
        out = write_probe(result, args.out)
        print(f"-> {out.with_suffix('.json')}, {out.with_suffix('.md')}")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add the model's subcommands (train, gradcam, export, average, graft, lesion, probe) to the `bid` parser."""
    t = sub.add_parser("train", help="train the BID model (runs/NAME holds config, metrics, "
                                     "checkpoints and plots)")
    add_train_arguments(t)
    t.set_defaults(func=_train)

    g = sub.add_parser("gradcam", help="sign-aware Grad-CAM overlays of a trained model")
    g.add_argument("--checkpoint", required=True, help="last.pt or best.pt of a run")
    g.add_argument("--out", required=True, help="folder for the PNG overlays")
    g.add_argument("--data", default="data/town01", help="folder of recordings")
    g.add_argument("--synthetic", action="store_true", help="explain generated frames instead")
    g.add_argument("--area", default="IT", help="V1, V2, V4, IT (default) or MT")
    g.add_argument("--target", choices=("steer", "accel", "both"), default="steer")
    g.add_argument("--samples", type=int, default=6, help="validation frames to explain")
    g.add_argument("--preset", choices=PRESETS, default=None,
                   help="refuse a checkpoint of another preset")
    g.set_defaults(func=_gradcam)

    x = sub.add_parser("export", help="a small checkpoint to ship: model, config, metrics, data recipe; "
                                      "no optimiser state")
    x.add_argument("run", help="a run folder of `bid train`")
    x.add_argument("--out", required=True, help="the .pt to write (a .json card goes beside it)")
    x.add_argument("--which", default="best.pt", help="best.pt (default) or last.pt")
    x.add_argument("--recipe", default=None, help="how the data and the run were made (commands)")
    x.set_defaults(func=_export)

    av = sub.add_parser("average", help="one checkpoint whose weights are the average of fine-tunings of "
                                        "one model (weight-space ensemble)")
    av.add_argument("checkpoints", nargs="+", help="two or more checkpoints of the same network")
    av.add_argument("--weights", default=None, help="comma-separated, one per checkpoint (default: equal)")
    av.add_argument("--out", required=True, help="the .pt to write (e.g. runs/NAME/last.pt, for `bid export`)")
    av.add_argument("--keep-heads", action="store_true",
                    help="keep an auxiliary head (--forecast, --hazard) that only some have, averaged over "
                         "those (default: leave it out)")
    av.set_defaults(func=_average)

    gr = sub.add_parser("graft", help="a checkpoint with a second SC beside its own, another checkpoint's "
                                      "(no training): its pedestrian joins the hazard reading while moving")
    gr.add_argument("checkpoint", help="a checkpoint with SC (--hazard-sc), e.g. checkpoints/bid_small.pt")
    gr.add_argument("--fine-sc", required=True, metavar="CKPT",
                    help="a checkpoint of the same preset whose SC has presence logits (--sc-presence), "
                         "usually on finer frames (--sc-scale 2)")
    gr.add_argument("--out", required=True, help="the .pt to write")
    gr.set_defaults(func=_graft)

    le = sub.add_parser("lesion", help="closed-loop benchmark with each brain area switched off in turn")
    le.add_argument("--checkpoint", required=True)
    le.add_argument("--town", default="02")
    le.add_argument("--density", default="normal")
    le.add_argument("--weathers", default="test")
    le.add_argument("--seeds", type=int, default=1)
    le.add_argument("--routes", default=None, help="a comma-separated subset of route indices")
    le.add_argument("--areas", default=None, help="a comma-separated subset (default: all but V1)")
    le.add_argument("--mode", choices=("zero", "mean"), default="zero")
    le.add_argument("--workers", type=int, default=2)
    le.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke runs)")
    le.add_argument("--out", default=None)
    le.set_defaults(func=_lesion)

    pr = sub.add_parser("probe", help="how often a model's hazard outputs see what is in the path, on "
                                      "recordings it never trained on (another town, the test weathers)")
    pr.add_argument("--checkpoint", required=True, help="a checkpoint with a hazard head (--hazard)")
    pr.add_argument("--data", required=True,
                    help="folder of recordings, e.g. of `bid record --town 02 --weathers test`")
    pr.add_argument("--every", type=int, default=1, metavar="N", help="probe every N-th frame (default 1)")
    pr.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    pr.add_argument("--second-head", action="store_true",
                    help="probe the second head (bid train --move-off-head), not the first")
    pr.add_argument("--source", choices=PROBE_SOURCES, default="merged",
                    help="with SC (--hazard-sc): probe the reading driving uses (merged, the default), the "
                         "head's alone, SC's alone (with --sc-presence also its logits at lower thresholds) "
                         "or the fine SC's alone (bid graft; standing too, and its logits)")
    pr.add_argument("--hazard-ahead", type=float, default=0.0, metavar="S",
                    help="count a pedestrian in the path also where she will be within S seconds, as "
                         "`bid train --hazard-ahead` does (default 0: where she is)")
    pr.add_argument("--out", default=None, metavar="PATH", help="also write PATH.json and PATH.md")
    pr.set_defaults(func=_probe)
