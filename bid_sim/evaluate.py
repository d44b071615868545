"""`bid evaluate`: the closed-loop benchmark (DESIGN.md section 7). Every route of a town ×
weathers × seeds at one or more densities, driven by an agent in parallel processes, scored
per episode; results are appended as episodes finish, so an interrupted run resumes.

Agents: `expert` and `lanefollow` (privileged, no camera), `bid` (the model package's
camera agent, found through the "bid.agents" entry point group, needs --checkpoint), or a
user's class given as `module:Class` (constructed with no arguments, or with
checkpoint=PATH when one is given; it sees camera frames unless it sets
`uses_camera = False`).

results/NAME/
  config.json      what was asked (a resume must ask the same)
  episodes.jsonl   one line per finished episode: ids, metrics, infractions
  summary.json     SR, SSR, RC, IP, DS (mean and _std over seeds), counts and per-km
                   rates, for the whole run and per density and weather; "outcomes": per
                   density, how the episodes ended and what failed them first
  summary.md       the same as tables laid out like the paper's
  videos/, recordings/  with --video / --record
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import json
import math
import os
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from tqdm import tqdm

from bid_sim import __version__
from bid_sim import metrics as m
from bid_sim.agents import AGENTS, make_agent
from bid_sim.errors import BidError, reason
from bid_sim.parallel import WorkerDied, run_parallel
from bid_sim.routes import load_routes
from bid_sim.towns import CROSSING_WIDTH_M, crossing_words, net_tag, resolve_town
from bid_sim.weather import check_weather

PRIVILEGED = {"expert", "lanefollow"}
# config.json keys that results written by earlier versions lack; such results still resume.
ADDED_KEYS = ("town_net", "crossing_width_m", "zebra_width_m")


@dataclass(frozen=True)
class EvalEpisode:
    town: str
    route: int
    weather: str
    density: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.density}/{self.weather}/r{self.route:02d}/s{self.seed}"

    @property
    def name(self) -> str:
        return f"{self.density}_{self.weather}_r{self.route:02d}_s{self.seed}"


def plan_eval(town: str, densities: tuple[str, ...], weathers: tuple[str, ...], seeds: int,
              routes: list[int] | None = None) -> list[EvalEpisode]:
    t = resolve_town(town)
    for d in densities:
        t.density(d)
    for w in weathers:
        check_weather(w)
    if seeds < 1:
        raise BidError(f"--seeds must be >= 1, got {seeds}")
    n = len(load_routes(t))
    idx = list(range(n)) if routes is None else routes
    bad = [r for r in idx if not 0 <= r < n]
    if bad:
        raise BidError(f"route {bad[0]} out of range; {t.name} has routes 0..{n - 1}")
    return [EvalEpisode(town, r, w, d, s) for d in densities for w in weathers for r in idx for s in range(seeds)]


# ----------------------------------------------------------------------------- agents

def load_agent(spec: str, checkpoint: str | None = None, options: dict | None = None):
    """An agent instance from a name or `module:Class` (BidError naming the problem);
    options are keyword arguments for an entry-point agent (e.g. the BID agent's lesions)."""
    if spec in AGENTS:
        return make_agent(spec)
    if ":" not in spec:
        eps = {ep.name: ep for ep in importlib.metadata.entry_points(group="bid.agents")}
        if spec in eps:
            if checkpoint is None:
                raise BidError(f"the {spec!r} agent needs --checkpoint PATH (a run's best.pt or last.pt)")
            return eps[spec].load()(checkpoint, **(options or {}))
        known = sorted({*AGENTS, *eps})
        raise BidError(f"unknown agent {spec!r}; use one of {', '.join(known)} or module:Class")
    module, _, cls = spec.partition(":")
    try:
        factory = getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as e:
        raise BidError(f"cannot load agent {spec!r} ({type(e).__name__}: {e}); give an importable "
                       "module:Class") from e
    agent = factory(checkpoint=checkpoint) if checkpoint is not None else factory()
    for method in ("reset", "act"):
        if not callable(getattr(agent, method, None)):
            raise BidError(f"agent {spec!r} has no {method}() method; see bid_sim.agents.Agent")
    return agent


def uses_camera(spec: str, agent) -> bool:
    return spec not in PRIVILEGED and bool(getattr(agent, "uses_camera", True))


# ----------------------------------------------------------------------------- workers

_STATE: dict[str, Any] = {}


def _init_worker(agent_spec: str, checkpoint: str | None, options: dict | None = None) -> None:
    import cv2

    cv2.setNumThreads(1)  # one core per worker; a torch agent sets its own threads
    _STATE["agent"] = load_agent(agent_spec, checkpoint, options)
    _STATE["spec"] = agent_spec
    _STATE["renderers"] = {}


def _renderer(town, weather: str, seed: int):
    from bid_sim.render import Renderer
    from bid_sim.town_map import load_town_map

    key = (town.name, weather, seed)
    cache = _STATE["renderers"]
    if key not in cache:
        cache.clear()
        cache[key] = Renderer(load_town_map(town), weather=weather, seed=seed)
    return cache[key]


def run_eval_episode(ep: EvalEpisode, out: str, record: bool, video: frozenset[str] | bool,
                     max_steps: int | None = None) -> dict:
    """One episode in this worker; returns its line for episodes.jsonl.
    video: True for every episode, or the keys of the episodes to film."""
    from bid_sim.episode import run_episode

    agent, spec = _STATE["agent"], _STATE["spec"]
    video = video is True or (bool(video) and ep.key in video)
    town = resolve_town(ep.town)
    camera = uses_camera(spec, agent) or record or video
    renderer = _renderer(town, ep.weather, ep.seed) if camera else None
    recorders, writer, vid = [], None, None
    if record:
        from bid_sim.recording import EpisodeWriter
        from bid_sim.town_map import load_town_map

        facts = {"town": town.name, "town_source": ep.town, "route": str(ep.route), "weather": ep.weather, "density": ep.density,
                 "seed": str(ep.seed), "agent": spec, "software": f"bid-sim {__version__}"}
        writer = EpisodeWriter(Path(out) / "recordings" / f"{ep.name}.mcap", facts,
                               [h.position for h in load_town_map(town).signal_heads])
        recorders.append(writer)
    if video:
        from bid_sim.render.overlay import VideoRecorder

        vid = VideoRecorder(Path(out) / "videos" / f"{ep.name}.mp4", agent)
        recorders.append(vid)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = run_episode(town, ep.route, ep.weather, ep.density, ep.seed, agent,
                             recorder=_Tee(recorders) if recorders else None, renderer=renderer, replan=True,
                             max_steps=max_steps)
    except BaseException:
        if writer is not None:
            writer.abort()
        if vid is not None:
            vid.abort()
        raise
    if writer is not None:
        writer.finish({"status": result.status, "metrics": result.metrics})
    if vid is not None:
        vid.finish()
    line = {"key": ep.key, **result.to_dict(), "row": result.row(),
            "wall_s": round(time.perf_counter() - t0, 3), "cpu_s": round(time.process_time() - c0, 3)}
    return line


class _Tee:
    """Several recorders as one."""

    def __init__(self, recorders: list) -> None:
        self.recorders = recorders

    def write(self, snap, frame, control) -> None:
        for r in self.recorders:
            r.write(snap, frame, control)

    def note(self, infraction) -> None:
        for r in self.recorders:
            if hasattr(r, "note"):
                r.note(infraction)


# ----------------------------------------------------------------------------- the run

def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes: a checkpoint re-exported to the same path is another agent."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def config_diff(old: dict, new: dict) -> list[str]:
    """The keys of a results folder's config.json (`old`) that another run's (`new`) changes, so
    that the two do not mix: not the software version, not a key results written before it was
    added lack, and not the checkpoint's path where its bytes are the same (the same file,
    moved or in another clone)."""
    same_file = old.get("checkpoint_sha256") is not None \
        and old.get("checkpoint_sha256") == new.get("checkpoint_sha256")
    return [k for k in new if k != "software" and old.get(k) != new[k]
            and not (k in ADDED_KEYS and k not in old) and not (k == "checkpoint" and same_file)]


def evaluate(town: str, densities: tuple[str, ...], weathers: tuple[str, ...], seeds: int, agent: str,
             out: str | os.PathLike, checkpoint: str | None = None, workers: int = 1,
             routes: list[int] | None = None, record: bool = False, video: bool | int = False,
             progress: bool = True, options: dict | None = None, max_steps: int | None = None,
             ray_address: str | None = None) -> dict:
    """Runs the plan's unfinished episodes, appending to episodes.jsonl; writes the summary.
    An episode that fails (a SUMO error, an agent's exception) does not stop the others; once
    they are done, a BidError names it and no summary is written, so a rerun retries it.
    video: True films every episode, a number N the plan's first N.
    max_steps cuts episodes short (a smoke run: they end as timeouts).
    ray_address: run the episodes as tasks on a Ray cluster instead of `workers` local
    processes (bid_sim.cluster; "" for $RAY_ADDRESS or a local instance)."""
    out = Path(out)
    if ray_address is not None:
        from bid_sim.cluster import require_ray

        require_ray()  # before any work
    plan = plan_eval(town, densities, weathers, seeds, routes)
    if video is not True and video is not False:
        if video < 0:
            raise BidError(f"--video takes a number of episodes to film (>= 0), got {video}")
        video = frozenset(ep.key for ep in plan[:video])
    if checkpoint is not None and not Path(checkpoint).exists():
        raise BidError(f"checkpoint {checkpoint} does not exist; give a run's best.pt or last.pt")
    load_agent(agent, checkpoint, options)  # fail here, once, before any worker starts
    t = resolve_town(town)
    config = {"town": t.name, "town_net": net_tag(t), "crossing_width_m": t.crossing_width_m,
              "zebra_width_m": t.zebra_width_m,
              "densities": list(densities), "weathers": list(weathers),
              "seeds": seeds, "agent": agent, "checkpoint": str(Path(checkpoint).resolve()) if checkpoint else None,
              "checkpoint_sha256": file_digest(checkpoint) if checkpoint else None,
              "routes": routes, "options": options or None, "max_steps": max_steps, "software": f"bid-sim {__version__}"}
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BidError(f"cannot create {out} ({e.strerror}); pick a writable --out") from e
    cfg_path = out / "config.json"
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        diff = config_diff(old, config)
        if diff == ["seeds"] and isinstance(old.get("seeds"), int) and config["seeds"] > old["seeds"]:
            # More seeds of the same run: an episode's key names its seed, so those done stay valid.
            cfg_path.write_text(json.dumps(config, indent=1))
            diff = []
        if diff:
            changed = " (the checkpoint file changed since these results were written)" \
                if "checkpoint_sha256" in diff else ""
            raise BidError(f"{out} holds results of another configuration ({', '.join(diff)} differ{changed}); "
                           "use another --out, or the same options to resume")
    else:
        cfg_path.write_text(json.dumps(config, indent=1))
    lines_path = out / "episodes.jsonl"
    done = {ln["key"]: ln for ln in read_lines(lines_path)}
    todo = [ep for ep in plan if ep.key not in done]
    bar = tqdm(total=len(plan), initial=len(plan) - len(todo), unit="episode", disable=not progress,
               desc=f"{config['town']} {agent}")
    steps = 0
    t0 = time.perf_counter()

    def finished(line: dict) -> None:
        nonlocal steps
        with lines_path.open("a") as f:
            f.write(json.dumps(line) + "\n")
            f.flush()
            os.fsync(f.fileno())
        done[line["key"]] = line
        steps += line["steps"]
        bar.update(1)
        bar.set_postfix(steps_per_s=f"{steps / max(time.perf_counter() - t0, 1e-9):.0f}")

    failed: list[tuple[str, str]] = []

    def broke(ep: EvalEpisode, e: Exception) -> None:  # the other episodes go on
        failed.append((ep.key, (reason(e).strip().splitlines() or [""])[0]))
        bar.update(1)

    if todo:
        from bid_sim.town_map import load_town_map

        load_town_map(resolve_town(town))  # built once here, not by every worker at once
    try:
        if ray_address is None:
            run_parallel(partial(run_eval_episode, out=str(out), record=record, video=video, max_steps=max_steps),
                         todo, workers, lambda ep, line: finished(line), on_error=broke,
                         initializer=_init_worker, initargs=(agent, checkpoint, options))
        else:
            from bid_sim.cluster import run_ray

            run_ray(partial(run_eval_episode, out=str(out.resolve()), record=record, video=video,
                            max_steps=max_steps),
                    todo, ray_address, lambda ep, line: finished(line), on_error=broke,
                    initializer=_init_worker,
                    initargs=(agent, str(Path(checkpoint).resolve()) if checkpoint else None, options),
                    shared=out if record or video else None)  # only files need a shared --out
    except WorkerDied as e:  # no episode can go on
        raise BidError(f"{e}; the finished episodes ({len(done)}) are kept in {lines_path}; "
                       "rerun the same command to go on") from e
    finally:
        bar.close()
    if failed:
        key, why = failed[0]
        more = f" and {len(failed) - 1} more" if len(failed) > 1 else ""
        raise BidError(f"episode {key}{more} failed ({why}); the finished ones ({len(done)}) are kept "
                       f"in {lines_path}; rerun the same command to retry the rest")
    ordered = [done[ep.key] for ep in plan]
    summary = summarise(ordered, config)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    (out / "summary.md").write_text(summary_markdown(summary))
    return summary


def read_lines(path: Path) -> list[dict]:
    """Finished episodes of a results file; a torn last line (a killed run) is dropped."""
    if not path.exists():
        return []
    out = []
    for i, text in enumerate(path.read_text().splitlines()):
        if not text.strip():
            continue
        try:
            out.append(json.loads(text))
        except json.JSONDecodeError as e:
            raise BidError(f"{path} line {i + 1} is damaged; delete that line to resume") from e
    return out


def summarise(lines: list[dict], config: dict) -> dict:
    rows = [ln["row"] for ln in lines]
    agg = m.aggregate(rows, group_by=("density", "weather"))
    steps = sum(ln["steps"] for ln in lines)
    cpu = sum(ln.get("cpu_s", 0.0) for ln in lines)
    return {"config": config, **agg, "outcomes": outcomes(lines, list(agg["by_density"])), "steps": steps,
            "eval_steps_per_s_per_core": round(steps / cpu, 1) if cpu > 0 else None}


# How an episode ends (EpisodeResult.status; "other" holds DAgger's gave_up).
ENDINGS = ("completed", "route_deviation", "timeout", "blocked", "other")
# What spoils a NoCrash success first: the episode's first collision, else how it ended.
FAILURE_CAUSES = ("vehicle", "pedestrian", "layout", "route_deviation", "timeout", "blocked", "other")
_CONTACT_CAUSE = {m.COLLISION_VEHICLE: "vehicle", m.COLLISION_PEDESTRIAN: "pedestrian",
                  m.COLLISION_LAYOUT: "layout"}


def first_collision(line: dict) -> dict | None:
    """An episode line's earliest collision (its infraction dict), or None."""
    contacts = [inf for inf in line["infractions"] if inf["kind"] in _CONTACT_CAUSE]
    return min(contacts, key=lambda inf: inf["time_s"]) if contacts else None


def failure_cause(line: dict) -> str | None:
    """None for a NoCrash success (SR); else its first collision's kind, or how it ended."""
    if line["metrics"]["SR"] >= 100.0:
        return None
    first = first_collision(line)
    if first is not None:
        return _CONTACT_CAUSE[first["kind"]]
    return line["status"] if line["status"] in FAILURE_CAUSES else "other"


def outcomes(lines: list[dict], densities: list[str]) -> dict:
    """Per density and for all: episodes, their endings and their failures' first causes (counts),
    and their seconds, in all (`time_s`) and standing by reason (`standing_s`, summed from
    EpisodeResult.standing_s): both over the `standing_from` episodes that kept it, so that lines
    written before it was kept leave the shares right."""
    def count(group: list[dict]) -> dict:
        ended = dict.fromkeys(ENDINGS, 0)
        first = dict.fromkeys(FAILURE_CAUSES, 0)
        standing = dict.fromkeys(m.STANDING_REASONS, 0.0)
        timed = 0.0
        with_standing = 0
        for ln in group:
            ended[ln["status"] if ln["status"] in ENDINGS else "other"] += 1
            cause = failure_cause(ln)
            if cause is not None:
                first[cause] += 1
            if ln.get("standing_s"):
                with_standing += 1
                timed += ln["time_s"]
                for why in m.STANDING_REASONS:
                    standing[why] += ln["standing_s"].get(why, 0.0)
        return {"episodes": len(group), "ended": ended, "failed": sum(first.values()), "first_failure": first,
                "time_s": round(timed, 1), "standing_s": {k: round(v, 1) for k, v in standing.items()},
                "standing_from": with_standing}

    return {"by_density": {d: count([ln for ln in lines if ln["density"] == d]) for d in densities},
            "all": count(lines)}


def outcome_tables(out: dict) -> str:
    """summary.md's two tables of `outcomes`."""
    groups = {**out["by_density"], "all": out["all"]}
    ended = ["| group | episodes | " + " | ".join(ENDINGS) + " |", "|---|---|" + "---|" * len(ENDINGS)]
    first = ["| group | failed | " + " | ".join(FAILURE_CAUSES) + " |", "|---|---|" + "---|" * len(FAILURE_CAUSES)]
    for name, g in groups.items():
        ended.append(f"| {name} | {g['episodes']} | " + " | ".join(str(g["ended"][k]) for k in ENDINGS) + " |")
        first.append(f"| {name} | {g['failed']} | " + " | ".join(str(g["first_failure"][k]) for k in FAILURE_CAUSES)
                     + " |")
    text = ("## How the episodes ended\n\n" + "\n".join(ended) + "\n\n"
            "## What failed them first (an episode's first collision, else how it ended)\n\n"
            + "\n".join(first) + "\n")
    if not any(g.get("standing_from") for g in groups.values()):
        return text
    heads = ("at a red light", "behind a vehicle", "for a pedestrian", "with nothing near")
    stood = ["| group | episodes | time s | standing s | " + " | ".join(heads) + " |", "|---|---|---|---|" + "---|" * 4]
    for name, g in groups.items():
        total = sum(g["standing_s"].values())
        stood.append(f"| {name} | {g['standing_from']} | {g['time_s']:.0f} | {total:.0f} ({_share(total, g['time_s'])}) | "
                     + " | ".join(f"{g['standing_s'][k]:.0f}" for k in m.STANDING_REASONS) + " |")
    return (text + "\n## Where the time went: seconds standing, by what stood there (privileged state: a red or amber "
            f"light within {m.STANDING_LIGHT_M:.0f} m, else a vehicle or pedestrian within {m.STANDING_AHEAD_M:.0f} m "
            "straight ahead)\n\n" + "\n".join(stood) + "\n")


def _share(part: float, whole: float) -> str:
    return f"{100.0 * part / whole:.0f} %" if whole > 0 else "–"


PAPER_KEYS_NOCRASH = ("SR", "SSR", "TL", "RC", "DS", "CV", "CP", "CL", "episodes")
PAPER_KEYS_LEADERBOARD = ("RC", "DS", "CV", "CP", "CL", "TL", "OL", "RD", "ABD", "episodes")


def summary_markdown(summary: dict) -> str:
    cfg = summary["config"]
    keys = PAPER_KEYS_LEADERBOARD if cfg["town"] == "Town05" else PAPER_KEYS_NOCRASH
    head = "APA = RC, ADG = DS (the paper's Town05 names)\n\n" if cfg["town"] == "Town05" else ""
    width, zebra = cfg.get("crossing_width_m", CROSSING_WIDTH_M), cfg.get("zebra_width_m")
    plain = width == CROSSING_WIDTH_M and zebra is None
    crossings = "" if plain else f" · {crossing_words(width, zebra)}"
    parts = [f"# {cfg['town']}{crossings} · agent {cfg['agent']} · weathers {', '.join(cfg['weathers'])} · "
             f"{cfg['seeds']} seed(s)\n", head,
             "## By density\n", m.format_table(summary["by_density"], keys), "\n",
             "## By weather\n", m.format_table(summary["by_weather"], keys), "\n",
             "## All\n", m.format_table({"all": summary["all"]}, keys), "\n"]
    if "outcomes" in summary:
        parts.append(outcome_tables(summary["outcomes"]))
    return "\n".join(p for p in parts if p)


def compare(folders: list[str]) -> str:
    """A side-by-side table of several results folders (whole-run figures per density), then
    each folder after the first against the first, episode by episode (paired_table)."""
    cols, rows = [], {}
    for f in folders:
        path = Path(f) / "summary.json"
        if not path.exists():
            raise BidError(f"{path} does not exist; run `bid evaluate --out {f}` first")
        s = json.loads(path.read_text())
        name = f"{Path(f).name} ({s['config']['agent']})"
        if name in cols:
            name = f"{name} #{len(cols) + 1}"
        cols.append(name)
        outs = s.get("outcomes", {})
        for group, st in [("all", s["all"]), *s["by_density"].items()]:
            for key in ("SR", "SSR", "RC", "DS", "TL", "CV", "CP", "CL"):
                rows.setdefault((group, key), {})[name] = m.cell(st, key)
            out = outs.get("all") if group == "all" else outs.get("by_density", {}).get(group)
            if out and out.get("standing_from"):  # runs from before standing_s show —
                stood = sum(out["standing_s"].values())
                rows.setdefault((group, "standing s"), {})[name] = f"{stood:.0f} ({_share(stood, out['time_s'])})"
                rows.setdefault((group, "standing, nothing near s"), {})[name] = f"{out['standing_s']['nothing']:.0f}"
    lines = ["| group | metric | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for (group, key), vals in rows.items():
        lines.append(f"| {group} | {key} | " + " | ".join(vals.get(c, "—") for c in cols) + " |")
    paired = [paired_table(folders[0], f) for f in folders[1:]]
    return "\n".join(lines) + "".join(f"\n\n{t}" for t in paired if t)


def sign_test_p(wins: int, losses: int) -> float:
    """Two-sided exact sign test (McNemar's, exact) of wins against losses of paired episodes:
    the chance of a split at least this uneven were either side as likely to win each."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(wins, losses) + 1)) / 2 ** n
    return min(1.0, 2.0 * tail)


def p_text(p: float) -> str:
    """A p value as the paired table prints it: two decimals, two significant digits below 0.01
    (a lopsided split reads 0.0026, not 0.00)."""
    return f"{p:.2f}" if p >= 0.01 else f"{p:.2g}"


def paired_table(base: str, other: str, listed: int = 20) -> str:
    """The episodes two results folders of one town both ran (the same density, weather, route
    and seed: the same traffic), success against success: how many each alone succeeds in, the
    sign test's p of that split, the mean driving-score difference with its standard error, and
    (up to `listed`) those episodes with the failing side's first cause. Empty where the folders
    share no episode or are of other towns."""
    a_cfg, b_cfg = (json.loads(p.read_text()) if (p := Path(f) / "config.json").exists() else {}
                    for f in (base, other))
    if a_cfg.get("town") != b_cfg.get("town"):
        return ""
    a, b = ({ln["key"]: ln for ln in read_lines(Path(f) / "episodes.jsonl")} for f in (base, other))
    keys = [k for k in a if k in b]
    if not keys:
        return ""
    won = {k: (a[k]["metrics"]["SR"] >= 100.0, b[k]["metrics"]["SR"] >= 100.0) for k in keys}
    only_a = [k for k, (x, y) in won.items() if x and not y]
    only_b = [k for k, (x, y) in won.items() if y and not x]
    both = sum(x and y for x, y in won.values())
    ds = [b[k]["metrics"]["DS"] - a[k]["metrics"]["DS"] for k in keys]
    mean = sum(ds) / len(ds)
    se = (sum((d - mean) ** 2 for d in ds) / (len(ds) - 1) / len(ds)) ** 0.5 if len(ds) > 1 else 0.0
    an, bn = Path(base).name, Path(other).name
    lines = [f"## Episode by episode: {bn} against {an}", "",
             f"| paired episodes | both succeed | both fail | only {an} | only {bn} | sign test p | "
             f"DS {bn} − {an} (mean ± s.e.) |",
             "|---|---|---|---|---|---|---|",
             f"| {len(keys)} | {both} | {len(keys) - both - len(only_a) - len(only_b)} | {len(only_a)} | "
             f"{len(only_b)} | {p_text(sign_test_p(len(only_a), len(only_b)))} | {mean:+.1f} ± {se:.1f} |"]
    changed = only_a + only_b
    if changed:
        lines += ["", f"| episode | {an} | {bn} |", "|---|---|---|"]
        for k in changed[:listed]:
            lines.append(f"| {k} | {failure_cause(a[k]) or 'success'} | {failure_cause(b[k]) or 'success'} |")
        if len(changed) > listed:
            lines.append(f"| … {len(changed) - listed} more | | |")
    return "\n".join(lines)


__all__ = ["EvalEpisode", "compare", "evaluate", "failure_cause", "load_agent", "outcomes", "plan_eval"]
