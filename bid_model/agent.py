"""The BID network as a driving agent for the closed loop (`bid evaluate --agent bid`).

It sees what a learned policy may see: the camera frame t, frame t−1, the route command
(corrected by the episode after a route departure) and, if the model was trained with it,
the measured speed; never the privileged snapshot. Registered as the "bid" entry of the
"bid.agents" entry point group.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from bid_model.checkpoint import load_model
from bid_model.config import MOVING_MPS, PATH_KINDS
from bid_model.data import command_one_hot, prepare_frame
from bid_model.hazards import HAZARD_AHEAD_M, SEEN_NEARNESS, nearness_m
from bid_sim.agents import EpisodeInfo, Observation
from bid_sim.ego import DT_S, Control, EgoParams
from bid_sim.errors import BidError
from bid_sim.routes import LEFT, RIGHT

STOP_SHORT_M = 2.0  # how far short of a seen pedestrian the ego brakes to stop
HOLD_M = 8.0  # a pedestrian seen this close keeps a slow (< START_MPS) ego standing
START_MPS = 2.0
HEADWAY_S = 1.0  # a vehicle in the path closer than this many seconds at the ego's speed...
MIN_GAP_M = 4.0  # ...plus this, front bumper to its back, is braked for
VEHICLE_SHORT_M = 1.0  # how far short of it the ego would stop were it standing
# With `path_memory`, a vehicle this close keeps a slow (< START_MPS) ego standing: the expert
# stands 2.5 m behind one, and below about 1 m/s stopping short asks less than BIND_SHARE, so
# the control head's creep rolled the ego into the car ahead (route 20, docs/experiments.md).
VEHICLE_HOLD_M = 3.0
LIGHT_SHORT_M = 1.0  # how far short of a red light's stop line the ego stops (as the expert)
# A vehicle or light brake asking for less than this share of full braking (0.8 m/s²) asks
# nothing: the ego can still stop short by braking later. Without it a creeping ego was held
# at any seen stop line or car, v²/2d being above 0 for any v > 0 (docs/experiments.md).
BIND_SHARE = 0.1
STILL_MPS = 0.1  # slower than this is standing (bid_sim.infractions.BLOCKED_SPEED_MPS)
MOVE_OFF_ACCEL = 0.5  # the accel `move_off` gives a standing ego (the expert's is 0.67)
CLEAR_M = 8.0  # move_off waits while a pedestrian, vehicle or red light is seen nearer than this
CLEAR_READ = 1.0 - CLEAR_M / HAZARD_AHEAD_M  # the hazard head's nearness at CLEAR_M (0.68)
# `path_memory`: a pedestrian or vehicle seen in the path this close is remembered once unseen. The
# recordings hold no car nearer than the 2.5 m the expert stops at, so the detectors lose one
# the ego creeps closer to (route 21, docs/experiments.md); farther off, losing one is mostly a
# false sighting ending, and remembering that would brake for nothing.
REMEMBER_M = 6.0
# A remembered actor draws nearer by the distance driven, at most this far: a false sighting
# 5 m ahead, drawn nearer by a creeping ego, held it standing in crowded traffic.
MEMORY_CLOSE_M = 2.0
# `pedestrian_memory`: a pedestrian seen in the path this close is remembered, drawn nearer by all
# the distance driven. Turning at 3-5 m/s, the hazard head sees one standing on the exit crossing
# at 5-8 m for about a second and loses her for the last 3-5 m. Remembered, she was held where
# the head placed her, too far: the ego stood across her way (docs/experiments.md, "Remembering
# a pedestrian the head loses"; opt-in).
PEDESTRIAN_REMEMBER_M = 8.0
# `crossing_brake`: stop this far short of a crossing with a pedestrian on it, as the expert does.
CROSSING_SHORT_M = 2.0
# ...and keep a slow (< START_MPS) ego standing while one is seen this close: at a red light the
# ego stands 1 m short of the stop line, the crossing a few metres on.
CROSSING_HOLD_M = 6.0
# `max_speed`: above the cap the ego brakes this share of full braking per m/s over it.
CRUISE_GAIN = 1.0
# `start_cap`: standing this long makes the next metres a start, driven under the cap.
START_STAND_S = 1.0
START_CAP_M = 12.0  # how far a start is capped unless told (Town02: past the stop line, the crossing, the turn)
# `move_off_braked`: a stop counts as the brakes' when they overrode a control head asking for no
# braking (accel >= 0) within this long before the ego came to stand.
BRAKED_STOP_S = 1.0
# `sc_logit`, `fine_logit`: a presence logit past this says yes (odds 1 to 20 000) or no to everything.
MAX_SC_LOGIT = 10.0
# `fine_caution`: a pedestrian the fine SC reads this close is stopped for, as the merge's; farther,
# only slowed for. Moving, it reads those in the path at a median 4.3 m (docs/experiments.md).
CAUTION_STOP_M = 5.0


def _stop_short(dist_m: float, speed_mps: float, short_m: float) -> float:
    """The share of full braking (0..1) that stops the ego `short_m` before `dist_m` ahead."""
    gap = max(dist_m - short_m, 0.5)
    return min(speed_mps * speed_mps / (2.0 * gap) / EgoParams.max_brake_mps2, 1.0)


def cruise_brake(speed_mps: float, max_speed_mps: float) -> float:
    """Braking, as a share of full braking (0..1), that brings an ego faster than
    `max_speed_mps` back to it: CRUISE_GAIN per m/s over; 0 at or below it."""
    return min(max(speed_mps - max_speed_mps, 0.0) * CRUISE_GAIN, 1.0)


def pedestrian_brake(nearness: float, speed_mps: float, hold_m: float = HOLD_M) -> float:
    """Braking, as a share of full braking (0..1), to stop STOP_SHORT_M short of a pedestrian
    the hazard head sees in the path at `nearness` (bid_model.recordings.hazard_nearness):
    0 when it sees none; full while slow with one within `hold_m` (HOLD_M, where the expert
    holds)."""
    if nearness < SEEN_NEARNESS:
        return 0.0
    dist_m = nearness_m(nearness)
    if speed_mps < START_MPS and dist_m < hold_m:
        return 1.0
    return _stop_short(dist_m, speed_mps, STOP_SHORT_M)


def caution_brake(nearness: float, speed_mps: float, cap_mps: float) -> float:
    """Braking (0..1) for a pedestrian read at `nearness` by a look-ahead detector (the fine SC
    with `fine_caution`): within CAUTION_STOP_M, to stop STOP_SHORT_M short of her (never a
    hold); farther, only to be at `cap_mps` STOP_SHORT_M short of where she is read, 0 at or
    below it. One about to walk in is met slowly; one read wrongly slows the ego, not stops it."""
    if nearness < SEEN_NEARNESS:
        return 0.0
    dist_m = nearness_m(nearness)
    if dist_m <= CAUTION_STOP_M:
        return _stop_short(dist_m, speed_mps, STOP_SHORT_M)
    if speed_mps <= cap_mps:
        return 0.0
    gap = max(dist_m - STOP_SHORT_M, 0.5)
    return min((speed_mps**2 - cap_mps**2) / (2.0 * gap) / EgoParams.max_brake_mps2, 1.0)


def _binding(need: float) -> float:
    return need if need >= BIND_SHARE else 0.0


def light_brake(nearness: float, speed_mps: float, short_m: float = LIGHT_SHORT_M) -> float:
    """Braking (0..1) to stop `short_m` (LIGHT_SHORT_M) short of the stop line of the red or amber light the
    hazard head sees at `nearness`, once that takes BIND_SHARE or more. It does not hold a
    standing ego (moving off is the control head's call): holding while the head saw a light
    within HOLD_M left 6 of the first 27 episodes standing ("blocked"; docs/experiments.md)."""
    if nearness < SEEN_NEARNESS:
        return 0.0
    return _binding(_stop_short(nearness_m(nearness), speed_mps, short_m))


def crossing_brake(nearness: float, speed_mps: float) -> float:
    """Braking (0..1) to stop CROSSING_SHORT_M short of the crossing with a pedestrian on it the
    hazard head sees at `nearness` (hazards.crossing_distances), once that takes BIND_SHARE or
    more; full while slow with one within CROSSING_HOLD_M, so that a light turning green does not
    move the ego off into people still on the stripes."""
    if nearness < SEEN_NEARNESS:
        return 0.0
    dist_m = nearness_m(nearness)
    if speed_mps < START_MPS and dist_m < CROSSING_HOLD_M:
        return 1.0
    return _binding(_stop_short(dist_m, speed_mps, CROSSING_SHORT_M))


def vehicle_brake(nearness: float, speed_mps: float, hold_m: float = 0.0) -> float:
    """Braking, as a share of full braking (0..1), for a vehicle the hazard head sees in the
    path at `nearness`: none while it is farther than HEADWAY_S at the ego's speed plus
    MIN_GAP_M (a car ahead moving off, or followed at a safe gap), else as hard as stopping
    VEHICLE_SHORT_M short of it would take, were it standing. The head gives no speed of its
    own, so a slower car followed too closely is braked for as a standing one, and the ego
    falls back to the headway. Below BIND_SHARE it asks nothing; full while slow (< START_MPS)
    with one within `hold_m` (0: never)."""
    if nearness < SEEN_NEARNESS:
        return 0.0
    dist_m = nearness_m(nearness)
    if speed_mps < START_MPS and dist_m < hold_m:
        return 1.0
    if dist_m > speed_mps * HEADWAY_S + MIN_GAP_M:
        return 0.0
    return _binding(_stop_short(dist_m, speed_mps, VEHICLE_SHORT_M))


def clear_to_move_off(near: tuple[float, ...]) -> bool:
    """Whether the hazard head's (pedestrian, vehicle, red light) nearness leaves a standing ego
    free to move off: nothing seen within CLEAR_M. A light farther off is the light brake's (it
    stops the ego short of it); on green the light output wanders up to 0.3 (17 m), which, had
    any seen light counted, kept restarting the wait (route 10, seed 2: blocked)."""
    return max(near[:3]) < CLEAR_READ


class PathMemory:
    """The pedestrian and the vehicle last seen in the path within `remember_m` (REMEMBER_M), kept
    `keep_s` seconds once the detectors lose them, drawn nearer by the distance the ego drives
    meanwhile (as if standing; by `close_m`, MEMORY_CLOSE_M, at most; None: all the way). `update`
    gives the nearness the brakes and move-off read: the larger of what the head sees now and
    what is remembered. `kinds` are the PATH_KINDS indices kept (0 pedestrian, 1 vehicle); only
    sightings at `learn_mps` or faster are remembered (slower, the memory only ages). A working
    memory beside the network, which itself sees two frames only."""

    def __init__(self, keep_s: float, kinds: tuple[int, ...] = (0, 1), remember_m: float = REMEMBER_M,
                 close_m: float | None = MEMORY_CLOSE_M, learn_mps: float = 0.0):
        self.keep_steps = round(keep_s / DT_S)
        self.kinds, self.remember_m, self.close_m, self.learn_mps = kinds, remember_m, close_m, learn_mps
        self.reset()

    def reset(self) -> None:
        self._dist_m: dict[int, float | None] = dict.fromkeys(self.kinds)
        self._seen_m = dict.fromkeys(self.kinds, 0.0)  # where each was last seen
        self._unseen = dict.fromkeys(self.kinds, 0)  # steps since last seen within remember_m

    def update(self, near: tuple[float, ...], speed_mps: float) -> tuple[float, ...]:
        out = list(near)
        for k in self.kinds:
            seen_m = nearness_m(near[k]) if near[k] >= SEEN_NEARNESS else None
            if seen_m is not None and seen_m <= self.remember_m and speed_mps >= self.learn_mps:
                self._dist_m[k] = self._seen_m[k] = seen_m
                self._unseen[k] = 0
                continue
            if self._dist_m[k] is None:
                continue
            self._unseen[k] += 1
            if self._unseen[k] > self.keep_steps:
                self._dist_m[k] = None
                continue
            floor = 0.0 if self.close_m is None else self._seen_m[k] - self.close_m
            self._dist_m[k] = max(self._dist_m[k] - speed_mps * DT_S, floor, 0.0)
            out[k] = max(out[k], 1.0 - self._dist_m[k] / HAZARD_AHEAD_M)
        return tuple(out)


class BIDAgent:
    """Drives with a trained checkpoint; one frame's forward pass per step on the CPU.

    lesions: {area: "zero" | "mean"} switched off at inference (see BID.set_lesions).
    gradcam_area: with `overlay`, the area whose sign-aware Grad-CAM of steer is drawn.
    forecast_brake: for a model trained with `--forecast`, brake at least as hard as it takes
    to reach the speed the network forecasts 1 s ahead, times this gain (0: drive on the
    control head alone). The control head and the forecast are two readings of the same
    network, as the control and trajectory branches of TCP (Wu et al. 2022) are.
    hazard_brake: for a model trained with `--hazard`, brake at least this gain times as hard
    as `pedestrian_brake` asks for the pedestrian its hazard head sees in the path (0: not).
    vehicle_brake: likewise by `vehicle_brake` for the vehicle it sees there.
    light_brake: likewise by `light_brake` for the red light it sees ahead (a head trained
    with the red-light output, model.hazard_light).
    move_off: seconds; once the ego has stood this long with the head seeing nothing within
    CLEAR_M (`clear_to_move_off`; a light turning green starts the count), accelerate at
    least at MOVE_OFF_ACCEL until START_MPS or until the head sees something (0: standing and
    moving off are the control head's call). It answers a control head that stands where
    nothing is in the way (docs/experiments.md). With a move-off head (model.move_off_head,
    `bid train --move-off-head`) the pedestrian and the vehicle it waits for are that head's
    (beside SC's), the red light still the first head's: the move-off head reads no speed, so
    standing it does not see a vehicle because the ego stands; reading its red light too, the
    ego moved off through red lights it stood at (docs/experiments.md, "Two hazard heads"). With
    path_memory, move-off reads what the memory keeps, as the brakes do.
    move_off_light: with a move-off head, move-off waits for that head's red light and the first
    head's pedestrian and vehicle instead (a head reading the speed, model.move_off_speed, fitted
    to read a green light at the stop line as none: `bid train --hazard-green-weight`), so that
    the head the brakes read, pedestrian and vehicle, stays as it was (docs/experiments.md).
    vehicle_second_head: with a second head (model.move_off_head, `bid train --move-off-head
    --move-off-speed`), the vehicle the brakes and move-off read is that head's (beside SC's),
    the pedestrian and the red light still the first head's: a head refitted for vehicles near
    a moving ego (`bid record --late-brake`, `bid train --hazard-vehicle-moving-weight`) leaves
    the others as they were (docs/experiments.md).
    move_off_to: m/s; with move_off, the speed it moves the ego off to (START_MPS when None). A
    control head that waits where the expert would go brakes a moved-off ego back to standing
    from START_MPS; moved off to 4 m/s, crowded routes finish more often, with more contacts
    (docs/experiments.md, "Out of time in crowded traffic").
    path_memory: seconds; a pedestrian or vehicle seen in the path within REMEMBER_M is remembered
    this long once the hazard head loses it (PathMemory), for the brakes and move-off, and a
    vehicle within VEHICLE_HOLD_M holds a slow ego (`vehicle_brake`'s hold) (0: neither).
    pedestrian_memory: seconds; the pedestrian alone, seen in the path within
    PEDESTRIAN_REMEMBER_M by an ego at START_MPS or faster, is remembered this long once the hazard
    head loses her, drawn nearer by all the distance driven since (PathMemory), for the brakes
    (0: not). Move-off reads the head as it sees now: remembered too, a pedestrian read on the
    kerb 7-7.5 m off kept a standing ego from moving off until the episode's time ran out
    (docs/experiments.md).
    pedestrian_hold: metres; with hazard_brake, a pedestrian seen in the path within this keeps
    a slow ego standing (HOLD_M when None; 0: never held, only stopped short of). A detector
    that reads pedestrians waiting on the kerb as in the path 7-7.5 m off held the ego through
    whole green phases at 8 m (docs/experiments.md).
    crossing_brake: for a model trained with `--hazard-crossing`, brake at least this gain times as
    hard as `crossing_brake` asks for the crossing with a pedestrian on it the head sees ahead.
    max_speed: m/s; brake by `cruise_brake` whenever the ego is faster (0: no cap). The
    network slows for a bend it sees too late at Town02's 11.2 m/s limit under the sunset
    weathers, and drives on past it (docs/experiments.md).
    turn_speed: m/s; while the command is a turn (LEFT or RIGHT: from COMMAND_LEAD_M before the
    junction to its exit), brake by `cruise_brake` whenever the ego is faster (0: no cap). The BID
    met pedestrians turning across crossings at 3.3-7.1 m/s, where the expert, keeping its lateral
    acceleration to 2.5 m/s², turns at about 4; capped at 4 it met fewer in normal traffic and ran
    out of time more often in crowded traffic (docs/experiments.md).
    start_cap: m/s; once the ego has stood START_STAND_S, drive its next `start_cap_m` metres
    no faster than this (`cruise_brake`; 0: no cap). Of the BID's 13 first pedestrian contacts
    in normal traffic (seed 0) 7 came 3.6-4.7 s after it moved off from a stand at a junction,
    at 3.3-4.5 m/s, people walking into its side or front on the crossing beyond, while its
    hazard outputs read nothing (docs/experiments.md).
    sc_still: for a model with SC (`--hazard-sc`), SC reads frame t alone, its change since t−1
    zeroed (model config sc_still, `bid train --sc-still`): SC fitted on the change reads a
    moving ego's path as clear (docs/experiments.md, "SC reads the ego's own motion").
    sc_still_moving: the same, but only while the ego moves (MOVING_MPS or faster); standing, SC
    reads both frames as trained. Read still at every step, SC sees more of a moving ego's
    pedestrians and the standing ego waited longer in crowded traffic (docs/experiments.md).
    move_off_braked: seconds; with move_off, the wait before moving off after a stop the brakes
    made against the control head (they overrode an accel of 0 or more within BRAKED_STOP_S of
    the ego coming to stand). The control head, standing, mostly stands on: a stop it did not ask
    for then costs move_off's whole wait (docs/experiments.md).
    move_off_sc: with move_off, for a model with SC, the pedestrian and the vehicle move-off waits
    for are SC's alone, not the larger of SC's and the hazard head's (the brakes still read
    both). The head reads the speed input, and standing it reads a vehicle 7-8 m ahead in an
    empty street (the expert stands mostly behind one); SC reads the frames alone
    (docs/experiments.md, "The hazard head reads the speed").
    light_still: while the ego is slower than START_MPS, the red light the light brake and move-off
    read is the one the first head reads from frame t paired with itself (a second forward pass),
    the lamp being a still thing: from two frames the network reads others moving in the junction
    as cross traffic flowing, that is a red light. At a stop line with the green lamp in view and
    people walking on the crossings it read red at 0.4-0.9 for three minutes; from frame t alone,
    0.0 (route 10, docs/experiments.md, "Red from motion").
    light_short: metres; with light_brake, stop this far short of a red light's stop line
    (LIGHT_SHORT_M, the expert's 1 m, when None). At 1 m the lamp's red is above the cameras' view
    (the head 3.5 m up, 1 m right of the lane, the cameras 1.6 m up and 1.5 m behind the front
    bumper, 60° high); from about 2 m it is whole, and the green lamp is read there (docs/experiments.md).
    The control head may still creep closer: below BIND_SHARE the light brake asks nothing.
    move_off_green: seconds; with move_off and light_brake, the wait before moving off after a
    stop at a red light: the head has read one within CLEAR_M since the ego last drove at
    START_MPS or faster without one (the light brake stops binding near 2 m/s, and the control head
    rolls the ego the last metres). Standing 2.4 m short of a line at green (`light_short` 2.5),
    frame t alone read the light 0.2 but the control head did not go, so every light cost
    move_off's whole wait once it turned green (docs/experiments.md).
    green_far: metres; with move_off_green, its shorter wait counts only while the red light reads
    farther off than this (CLEAR_M, as move_off's own wait, when None). Standing 1.3 m short of a
    red light the head read it 0.46-0.89 (CLEAR_M is 0.68), and a second of reads below 0.68 moved
    the ego off into the red; before a green lamp, from 2.3-2.7 m, it read -0.5..0.4 (docs/experiments.md).
    light_hold: with light_brake, a red light read within CLEAR_M holds an ego slower than START_MPS
    (full braking) unless moving off. The light brake asks nothing below BIND_SHARE, and the control
    head crept up from 2.5 m to 1.3 m short, where frame t alone read a red light 0.46-0.89 and a
    second of reads below CLEAR_READ moved the ego off into it (docs/experiments.md).
    sc_logit: with SC's presence logits (bid train --sc-presence), SC's pedestrian counts only where
    its logit is above this (0, the config's, when None; ModelConfig.sc_logit). Fitted with weight
    4 on pedestrians and look-ahead targets, ahead46 said yes on 10-18 % of frames with none in
    the path (docs/experiments.md).
    fine_logit: the same for the fine SC's pedestrian (a grafted checkpoint, bid graft;
    ModelConfig.fine_logit).
    fine_speed: the fine SC's pedestrian counts only at this speed (m/s) or faster (MOVING_MPS,
    the config's, when None; ModelConfig.fine_speed).
    fine_caution: m/s (0: off); with hazard_brake, the fine SC's pedestrian leaves the merge and
    brakes by `caution_brake` (times hazard_brake): stopped for within CAUTION_STOP_M, farther
    only slowed to this speed by where it reads her. Trained on look-ahead targets, it saw 3 to 5
    of 7 pedestrians walking into the path 0.5-1 s before, and one on 12 % of the moving frames
    with none coming (`bid probe`, docs/experiments.md): stopping for those cost crowded traffic.
    """

    uses_camera = True

    def __init__(self, checkpoint: str | Path, lesions: Mapping[str, str] | None = None,
                 threads: int = 1, gradcam_area: str = "IT", forecast_brake: float = 0.0,
                 hazard_brake: float = 0.0, vehicle_brake: float = 0.0, light_brake: float = 0.0,
                 move_off: float = 0.0, path_memory: float = 0.0, pedestrian_memory: float = 0.0, pedestrian_hold: float | None = None,
                 max_speed: float = 0.0, crossing_brake: float = 0.0, start_cap: float = 0.0,
                 start_cap_m: float | None = None, sc_still: bool = False, move_off_to: float | None = None,
                 sc_still_moving: bool = False, move_off_braked: float | None = None,
                 turn_speed: float = 0.0, move_off_sc: bool = False, move_off_light: bool = False,
                 vehicle_second_head: bool = False, light_still: bool = False,
                 light_short: float | None = None, move_off_green: float | None = None,
                 green_far: float | None = None, light_hold: bool = False, vehicle_hold: float = 0.0,
                 sc_logit: float | None = None, fine_logit: float | None = None,
                 fine_speed: float | None = None, fine_caution: float = 0.0):
        torch.set_num_threads(threads)
        self.model, self.config = load_model(checkpoint)
        for name, value in (("sc_still", sc_still), ("sc_still_moving", sc_still_moving)):
            if value and not self.config.model.hazard_sc:
                raise BidError(f"{checkpoint} has no SC to read frame t alone; train one with --hazard-sc, "
                               f"or drop {name}")
        if sc_still and sc_still_moving:
            raise BidError("sc_still reads SC still at every step, sc_still_moving only while moving; keep one")
        if sc_logit is not None and not self.config.model.sc_presence:
            raise BidError(f"sc_logit is where SC's presence logit says yes; {checkpoint}'s SC has none: "
                           "train one with --hazard-sc --sc-presence, or drop it")
        if fine_logit is not None and not self.config.model.sc_fine:
            raise BidError(f"fine_logit is where the fine SC's presence logit says yes; {checkpoint} has no fine SC: "
                           "add one with bid graft --fine-sc, or drop it")
        logits = {name: float(value) for name, value in (("sc_logit", sc_logit), ("fine_logit", fine_logit))
                  if value is not None}
        for name, value in logits.items():
            if not -MAX_SC_LOGIT <= value <= MAX_SC_LOGIT:
                raise BidError(f"{name} is a logit from {-MAX_SC_LOGIT:g} to {MAX_SC_LOGIT:g}; got {value}")
        if fine_speed is not None and not (self.config.model.sc_fine and self.config.model.fine_moving):
            raise BidError(f"fine_speed is where the fine SC starts to count while moving; {checkpoint} has no fine SC "
                           "read while moving: add one with bid graft --fine-sc, or drop it")
        if fine_caution:
            if not 0 < fine_caution < 100:
                raise BidError(f"fine_caution is a speed in m/s, 0 (off) or more; got {fine_caution}")
            if not (self.config.model.sc_fine and self.config.model.fine_moving):
                raise BidError(f"fine_caution slows for the fine SC's pedestrians; {checkpoint} has no fine SC read "
                               "while moving: add one with bid graft --fine-sc, or drop it")
            if not hazard_brake:
                raise BidError("fine_caution is read by the pedestrian brake; add hazard_brake, or drop it")
        self.fine_caution = fine_caution
        # How SC reads (config's READ_FIELDS), set on the loaded model's config.
        reads = {**logits, **({"sc_still": True} if sc_still else {}),
                 **({"fine_speed": float(fine_speed)} if fine_speed is not None else {})}
        if reads:
            try:
                model_config = dataclasses.replace(self.config.model, **reads)
            except ValueError as e:
                raise BidError(f"{checkpoint}: {e}") from None
            self.model.config, self.config = model_config, dataclasses.replace(self.config, model=model_config)
        # With sc_still_moving the model's config is swapped per step: SC's reading is the config's.
        self._sc_configs = ((self.config.model, dataclasses.replace(self.config.model, sc_still=True))
                            if sc_still_moving and not self.config.model.sc_still else None)
        if not forecast_brake >= 0:
            raise BidError(f"forecast_brake is a gain, 0 or more; got {forecast_brake}")
        if forecast_brake > 0 and not self.config.model.forecast_s:
            raise BidError(f"{checkpoint} has no speed forecast to brake by; train it with --forecast "
                           "or drop forecast_brake")
        self.forecast_brake = forecast_brake
        for name, gain in (("hazard_brake", hazard_brake), ("vehicle_brake", vehicle_brake),
                           ("light_brake", light_brake), ("move_off", move_off), ("path_memory", path_memory),
                           ("pedestrian_memory", pedestrian_memory),
                           ("crossing_brake", crossing_brake)):
            if not gain >= 0:
                raise BidError(f"{name} must be 0 or more; got {gain}")
            if gain > 0 and not self.config.model.hazard:
                raise BidError(f"{checkpoint} has no hazard head to brake by; train it with --hazard "
                               f"or drop {name}")
        for name, value in (("light_brake", light_brake), ("move_off", move_off)):
            if value > 0 and not self.config.model.hazard_light:
                raise BidError(f"{checkpoint}'s hazard head has no red-light output (trained before it existed); "
                               f"train one with --hazard, or drop {name}")
        if crossing_brake > 0 and not self.config.model.hazard_crossing:
            raise BidError(f"{checkpoint}'s hazard head has no crossing output; train one with --hazard-crossing, "
                           "or drop crossing_brake")
        self.hazard_brake, self.vehicle_brake, self.light_brake = hazard_brake, vehicle_brake, light_brake
        self.crossing_brake = crossing_brake
        self.move_off_steps = round(move_off / DT_S) if move_off > 0 else 0
        if move_off_to is not None and not move_off:
            raise BidError("move_off_to is the speed move_off drives to; add move_off, or drop it")
        if move_off_to is not None and not 0 < move_off_to < 100:
            raise BidError(f"move_off_to is a speed in m/s, more than 0; got {move_off_to}")
        self.move_off_to = START_MPS if move_off_to is None else move_off_to
        if move_off_braked is not None and not move_off:
            raise BidError("move_off_braked is move_off's wait after a stop the brakes made; add move_off, or drop it")
        if move_off_braked is not None and not 0 <= move_off_braked <= move_off:
            raise BidError(f"move_off_braked is a wait in seconds, from 0 to move_off ({move_off:g}); got {move_off_braked}")
        self.braked_steps = round(move_off_braked / DT_S) if move_off_braked is not None else None
        if move_off_sc and not move_off:
            raise BidError("move_off_sc is what move_off waits for; add move_off, or drop it")
        if move_off_sc and not self.config.model.hazard_sc:
            raise BidError(f"{checkpoint} has no SC for move_off_sc to read; train one with --hazard-sc, "
                           "or drop move_off_sc")
        for name, memory in (("path_memory", path_memory), ("pedestrian_memory", pedestrian_memory)):
            if move_off_sc and memory:
                raise BidError(f"move_off_sc reads SC as it sees now, {name} what was seen; keep one")
        self.move_off_sc = move_off_sc
        if move_off_light and not (move_off and self.config.model.move_off_head):
            raise BidError(f"move_off_light is the red light move_off reads from the move-off head; "
                           f"{'add move_off' if not move_off else f'{checkpoint} has none (bid train --move-off-head)'}, "
                           "or drop it")
        self.move_off_light = move_off_light
        if vehicle_second_head and not self.config.model.move_off_head:
            raise BidError(f"vehicle_second_head reads the vehicle of a second head; {checkpoint} has none "
                           "(bid train --move-off-head --move-off-speed), or drop it")
        if vehicle_second_head and (move_off_light or move_off_sc):
            raise BidError("vehicle_second_head and move_off_light or move_off_sc read the second head or SC "
                           "for move-off two ways; keep one")
        if vehicle_second_head and not (vehicle_brake or move_off):
            raise BidError("vehicle_second_head is the vehicle the vehicle brake and move-off read; add "
                           "vehicle_brake or move_off, or drop it")
        self.vehicle_second_head = vehicle_second_head
        if light_still and not (light_brake or move_off):
            raise BidError("light_still is the red light the light brake and move-off read; add light_brake "
                           "or move_off, or drop it")
        if light_still and move_off_light:
            raise BidError("move_off_light reads the move-off head's red light, light_still the first head's "
                           "from frame t alone; keep one")
        self.light_still = light_still
        if light_short is not None and not light_brake:
            raise BidError("light_short is where the light brake stops the ego; add light_brake, or drop it")
        if light_short is not None and not 0 <= light_short <= HAZARD_AHEAD_M / 2:
            raise BidError(f"light_short is a distance from 0 to {HAZARD_AHEAD_M / 2:g} m; got {light_short}")
        self.light_short_m = LIGHT_SHORT_M if light_short is None else light_short
        if move_off_green is not None and not (move_off and light_brake):
            raise BidError("move_off_green is move_off's wait after a stop at a red light; add move_off and "
                           "light_brake, or drop it")
        if move_off_green is not None and not 0 <= move_off_green <= move_off:
            raise BidError(f"move_off_green is a wait in seconds, from 0 to move_off ({move_off:g}); got {move_off_green}")
        self.green_steps = round(move_off_green / DT_S) if move_off_green is not None else None
        if green_far is not None and move_off_green is None:
            raise BidError("green_far is where move_off_green's wait reads a red light; add move_off_green, or drop it")
        if green_far is not None and not CLEAR_M <= green_far <= HAZARD_AHEAD_M:
            raise BidError(f"green_far is a distance from {CLEAR_M:g} to {HAZARD_AHEAD_M:g} m; got {green_far}")
        self.green_read = CLEAR_READ if green_far is None else 1.0 - green_far / HAZARD_AHEAD_M
        if light_hold and not light_brake:
            raise BidError("light_hold keeps the light brake's stop; add light_brake, or drop it")
        self.light_hold = light_hold
        if vehicle_hold and not vehicle_brake:
            raise BidError("vehicle_hold is where the vehicle brake holds a slow ego; add vehicle_brake, or drop it")
        if not 0 <= vehicle_hold <= CLEAR_M:
            raise BidError(f"vehicle_hold is a distance from 0 to {CLEAR_M:g} m; got {vehicle_hold}")
        self.vehicle_hold_m = vehicle_hold
        self._braked_stop_steps = round(BRAKED_STOP_S / DT_S)
        self.memory = PathMemory(path_memory) if path_memory > 0 else None
        if self.memory is not None:
            self.vehicle_hold_m = max(self.vehicle_hold_m, VEHICLE_HOLD_M)
        if self.memory is not None and not (hazard_brake or vehicle_brake or light_brake or move_off):
            raise BidError("path_memory is read by the brakes and move-off; add hazard_brake, vehicle_brake "
                           "or move_off, or drop it")
        if pedestrian_memory > 0:
            if self.memory is not None:
                raise BidError("path_memory already remembers the pedestrian; keep path_memory or pedestrian_memory")
            if not hazard_brake:
                raise BidError("pedestrian_memory is read by the pedestrian brake; add hazard_brake, or drop it")
            self.memory = PathMemory(pedestrian_memory, kinds=(0,), remember_m=PEDESTRIAN_REMEMBER_M, close_m=None,
                                     learn_mps=START_MPS)
        if pedestrian_hold is not None:
            if not 0 <= pedestrian_hold <= HAZARD_AHEAD_M:
                raise BidError(f"pedestrian_hold is a distance from 0 to {HAZARD_AHEAD_M:g} m; got {pedestrian_hold}")
            if not hazard_brake:
                raise BidError("pedestrian_hold is read by the pedestrian brake; add hazard_brake, or drop it")
        self.pedestrian_hold_m = HOLD_M if pedestrian_hold is None else pedestrian_hold
        if not 0 <= max_speed < 100:
            raise BidError(f"max_speed is a speed in m/s, 0 (no cap) or more; got {max_speed}")
        self.max_speed = max_speed
        if not 0 <= turn_speed < 100:
            raise BidError(f"turn_speed is a speed in m/s, 0 (no cap) or more; got {turn_speed}")
        self.turn_speed = turn_speed
        if not 0 <= start_cap < 100:
            raise BidError(f"start_cap is a speed in m/s, 0 (no cap) or more; got {start_cap}")
        if start_cap_m is not None and not start_cap:
            raise BidError("start_cap_m is how far start_cap caps a start; add start_cap, or drop it")
        if start_cap_m is not None and not 0 < start_cap_m < 1e3:
            raise BidError(f"start_cap_m is a distance in metres, more than 0; got {start_cap_m}")
        self.start_cap = start_cap
        self.start_cap_m = START_CAP_M if start_cap_m is None else start_cap_m
        self._start_stand_steps = round(START_STAND_S / DT_S)
        self._stand_steps = 0  # consecutive steps standing, for start_cap
        self._start_left_m = 0.0  # metres of the start still capped
        if lesions:
            self.model.set_lesions(dict(lesions))
        self.hw = self.config.model.input_hw
        self.gradcam_area = gradcam_area
        self._prev: torch.Tensor | None = None
        self._inputs: tuple | None = None
        self._still_steps = 0  # consecutive steps standing with the head seeing it clear, for move_off
        self._moving_off = False
        self._since_override = 10**9  # steps since the brakes last overrode an accel >= 0, for move_off_braked
        self._braked_stop = False  # the ego stands where the brakes stopped it
        self._light_approach = False  # a red light read within CLEAR_M since the ego last drove on without one
        self._green_count = 0  # consecutive steps standing clear with the red light read beyond green_far
        # The last step's control-head accel and the nearness the brakes read (for inspection:
        # bid_model.shadow); () when no brake or move-off reads the hazard outputs.
        self.head_accel = 0.0
        self.near: tuple[float, ...] = ()

    def reset(self, info: EpisodeInfo) -> None:
        self._prev = None
        self._inputs = None
        self._still_steps = 0
        self._moving_off = False
        self._since_override = 10**9
        self._braked_stop = False
        self._light_approach = False
        self._green_count = 0
        self._stand_steps = 0
        self._start_left_m = 0.0
        self.head_accel, self.near = 0.0, ()
        if self.memory is not None:
            self.memory.reset()

    @torch.inference_mode()
    def act(self, obs: Observation) -> Control:
        if obs.frame is None:
            raise BidError("the BID agent needs camera frames: run it with a renderer")
        frame = prepare_frame(obs.frame, self.hw)[None]
        prev = self._prev if self._prev is not None else frame  # frame t at an episode's start
        cmd = command_one_hot(int(obs.command))
        speed = torch.tensor([float(obs.speed_mps)])  # the input with speed_input; the merge's with sc_fine
        self._prev = frame
        self._inputs = (frame, prev, cmd, speed)
        if self._sc_configs is not None:
            self.model.config = self._sc_configs[float(obs.speed_mps) >= MOVING_MPS]
        by_forecast = self.forecast_brake > 0
        by_hazard = (self.hazard_brake > 0 or self.vehicle_brake > 0 or self.light_brake > 0
                     or self.move_off_steps > 0 or self.crossing_brake > 0)
        # move-off's own head, unless move_off_sc reads SC in its place (and it gives no red light);
        # or the vehicle's for both the brakes and move-off
        second = self.vehicle_second_head or (self.move_off_steps > 0 and self.config.model.move_off_head
                                              and (self.move_off_light or not self.move_off_sc))
        caution = by_hazard and self.fine_caution > 0  # the fine SC's pedestrian read apart
        apart = self.move_off_sc or caution
        out = self.model(frame, prev, cmd, speed, forecast=by_forecast, hazard=by_hazard,
                         hazard_apart=apart, move_off=second)
        control, *extra = out if isinstance(out, tuple) else (out,)
        accel, v = float(control[0, 1]), float(obs.speed_mps)
        self.head_accel = accel
        if by_forecast:
            ahead = extra.pop(0)
            # The deceleration to the forecast speed of the first horizon, as a share of full braking.
            horizon_s = self.config.model.forecast_s[0]
            need = (v - float(ahead[0, 0])) / horizon_s / EgoParams.max_brake_mps2
            if need > 0:
                accel = min(accel, -self.forecast_brake * need)
        if by_hazard:
            hazard = extra.pop(0)
            merged = (lambda h: self.model.merge_hazard(h, speed, fine=not caution)) if apart else (lambda h: h)
            fine = float(self.model.fine_near(hazard, speed)[0]) if caution else 0.0
            near = clear_near = tuple(float(x) for x in merged(hazard)[0])
            k = len(PATH_KINDS)
            if second:
                own = tuple(float(x) for x in merged(extra.pop(0))[0])
                veh = PATH_KINDS.index("vehicle")
                if self.vehicle_second_head:  # its vehicle, the first head's others, for everything
                    near = clear_near = (*near[:veh], own[veh], *near[veh + 1:])
                else:  # its red light, the first head's pedestrian and vehicle; else the other way round
                    clear_near = ((*near[:k], own[k], *near[k + 1:]) if self.move_off_light
                                  else (*own[:k], *near[k:]))
            if self.move_off_sc:  # SC's pedestrian and vehicle, the red light as above
                clear_near = (*(float(x) for x in self.model.sc_near(hazard)[0]), *clear_near[k:])
            if self.light_still and v < START_MPS:  # the red light from frame t alone, for both
                _, still = self.model(frame, frame, cmd, speed, hazard=True, hazard_apart=self.move_off_sc)
                light = float(still[0, k])
                near, clear_near = (*near[:k], light, *near[k + 1:]), (*clear_near[:k], light, *clear_near[k + 1:])
            if self.memory is not None:  # the pedestrian memory is the brakes' alone: see pedestrian_memory
                near = self.memory.update(near, v)
                clear_near = near if 1 in self.memory.kinds else clear_near
            self.near = near
            if self.green_steps is not None:
                red_near = near[2] >= CLEAR_READ
                if red_near or v >= START_MPS:
                    self._light_approach = red_near
            if self.move_off_steps:
                accel = self._move_off(accel, v, clear_near)
            need = max(self.hazard_brake * pedestrian_brake(near[0], v, self.pedestrian_hold_m),
                       self.vehicle_brake * vehicle_brake(near[1], v, self.vehicle_hold_m),
                       self.light_brake * light_brake(near[2], v, self.light_short_m) if self.light_brake > 0 else 0.0,
                       self.crossing_brake * crossing_brake(near[3], v) if self.crossing_brake > 0 else 0.0,
                       self.hazard_brake * caution_brake(fine, v, self.fine_caution) if caution else 0.0)
            if self.light_hold and v < START_MPS and near[2] >= CLEAR_READ and not self._moving_off:
                need = 1.0
            if need > 0:
                overrode = accel >= 0
                accel = min(accel, -need)
            else:
                overrode = False
            self._since_override = 0 if overrode else self._since_override + 1
        if self.max_speed > 0 and v > self.max_speed:
            accel = min(accel, -cruise_brake(v, self.max_speed))
        if self.turn_speed > 0 and v > self.turn_speed and int(obs.command) in (LEFT, RIGHT):
            accel = min(accel, -cruise_brake(v, self.turn_speed))
        if self.start_cap > 0:
            accel = self._start(accel, v)
        return Control(steer=float(control[0, 0]), accel=max(accel, -1.0))

    def _move_off(self, accel: float, speed_mps: float, near: tuple[float, ...]) -> float:
        """`accel`, raised to MOVE_OFF_ACCEL while moving off (see `move_off`); the brakes apply after."""
        clear = clear_to_move_off(near)
        if speed_mps >= STILL_MPS:
            self._braked_stop = False
        elif self.braked_steps is not None and self._since_override <= self._braked_stop_steps:
            self._braked_stop = True  # came to stand (or stands on) where the brakes held it
        wait = self.braked_steps if self._braked_stop else self.move_off_steps
        self._still_steps = self._still_steps + 1 if speed_mps < STILL_MPS and clear else 0
        green = clear and near[2] < self.green_read
        self._green_count = self._green_count + 1 if speed_mps < STILL_MPS and green else 0
        if self._still_steps >= max(wait, 1) and clear:
            self._moving_off = True
        if (self.green_steps is not None and self._light_approach  # stands at a red light, or one misread
                and self._green_count >= max(self.green_steps, 1)):
            self._moving_off = True
        if self._moving_off and (not clear or speed_mps >= self.move_off_to):
            self._moving_off = False
        return max(accel, MOVE_OFF_ACCEL) if self._moving_off else accel

    def _start(self, accel: float, speed_mps: float) -> float:
        """`accel`, braked to keep a start (see `start_cap`) under the cap."""
        self._stand_steps = self._stand_steps + 1 if speed_mps < STILL_MPS else 0
        if self._stand_steps >= self._start_stand_steps:
            self._start_left_m = self.start_cap_m
        elif self._start_left_m > 0:
            self._start_left_m -= speed_mps * DT_S
            if speed_mps > self.start_cap:
                accel = min(accel, -cruise_brake(speed_mps, self.start_cap))
        return accel

    def overlay(self, frame: np.ndarray) -> np.ndarray | None:
        """The last step's Grad-CAM of steer over the three cameras (for evaluation videos)."""
        from bid_model.gradcam import gradcam, overlay

        if self._inputs is None:
            return None
        frame_t, prev, cmd, speed = self._inputs
        with torch.inference_mode(False), torch.enable_grad():
            cam = gradcam(self.model, frame_t.clone(), prev.clone(), cmd.clone(),
                          None if speed is None else speed.clone(), area=self.gradcam_area)[0].numpy()
        import cv2

        h, w = frame.shape[:2]
        return overlay(frame, cv2.resize(cam, (w, h), interpolation=cv2.INTER_LINEAR))
