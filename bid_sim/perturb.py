"""Demonstrations off the expert's own path, labelled by the expert.

`Perturbed`: the expert drives, noise steers, the expert's answer is the label.
`Dagger`: a learned policy drives, the expert labels every step and takes the wheel when the
policy strays too far (DAgger, Ross et al. 2011, with an expert gate as in HG-DAgger).

A policy trained only on clean expert driving never sees the car off the lane centre, so
in closed loop a small error grows (covariate shift). As in conditional imitation
learning (Codevilla et al., 2018), `Perturbed` adds short triangular steering pulses to
what the car executes, while the recorded label stays the expert's own control, which
steers back: the recordings then hold recoveries. Pulses start at random (seeded by the
episode), only above a walking pace, and take about `share` of the driving time.
`Perturbed(turns=)` also begins a share of the junction turns late: the turn's first
steering is damped for a moment, so the car runs wide, as a learned policy's late turn
does, and the expert's label steers it back.
"""

from __future__ import annotations

import numpy as np

from bid_sim.agents import Agent, EpisodeInfo, Observation
from bid_sim.ego import Control, EgoParams
from bid_sim.errors import BidError
from bid_sim.routes import LEFT, RIGHT

PULSE_STEPS = (5, 16)  # duration, 0.5 to 1.5 s at 10 Hz
PULSE_STEER = (0.1, 0.35)  # peak steering offset
MIN_SPEED_MPS = 2.0
# A late turn (`turns`): once the expert's steering under a LEFT or RIGHT command first passes
# LATE_TURN_STEER, the executed steering is its own times a factor in LATE_TURN_KEEP for a
# time in LATE_TURN_STEPS, at any speed: turns begun from a standstill at the line count too.
LATE_TURN_STEER = 0.15
LATE_TURN_KEEP = (0.0, 0.5)
LATE_TURN_STEPS = (4, 13)  # 0.4 to 1.2 s at 10 Hz


class Perturbed:
    """Wraps an agent: executes its control plus a steering pulse now and then.

    `label` is the wrapped agent's own control of the last step; the episode records it
    instead of the executed control. `perturbed` says whether a pulse (or a late turn) was on.
    `turns`: the share of junction turns (LEFT or RIGHT commands) begun late; their draws come
    from a stream of their own, so the pulses stay those of `share` alone.
    """

    def __init__(self, agent: Agent, share: float, turns: float = 0.0):
        if not 0.0 <= share < 1.0:
            raise BidError(f"--perturb must be a share of time in [0, 1), got {share}")
        if not 0.0 <= turns <= 1.0:
            raise BidError(f"--perturb-turns must be a share of the turns in [0, 1], got {turns}")
        self.agent, self.share, self.turns = agent, share, turns
        self._turn_rng = np.random.default_rng(0)
        self._command = 0
        self._late: tuple[int, float] | None = None  # (steps, steering kept) of the turn ahead
        self._holding = 0
        self.late_turns = 0
        mean_steps = sum(PULSE_STEPS) / 2
        self._start_p = share / (mean_steps * (1.0 - share)) if share else 0.0
        self._rng = np.random.default_rng(0)
        self._pulse: np.ndarray | None = None
        self._at = 0
        self.label: Control | None = None
        self.perturbed = False

    def reset(self, info: EpisodeInfo) -> None:
        self.agent.reset(info)
        self._rng = np.random.default_rng((info.seed, 0x9E27))
        self._pulse, self._at = None, 0
        self.label, self.perturbed = None, False
        self._turn_rng = np.random.default_rng((info.seed, 0x7A11))
        self._command, self._late, self._holding = 0, None, 0
        self.late_turns = 0

    def act(self, obs: Observation) -> Control:
        control = self.agent.act(obs)
        self.label = control
        late = self._late_turn(obs.command, control)
        # The draws happen every step, so the noise depends on the seed and the step only.
        start, steps, peak, sign = (self._rng.random(), self._rng.integers(*PULSE_STEPS),
                                    self._rng.uniform(*PULSE_STEER), self._rng.choice((-1.0, 1.0)))
        if self._pulse is None and obs.speed_mps > MIN_SPEED_MPS and start < self._start_p:
            ramp = 1.0 - np.abs(np.linspace(-1.0, 1.0, int(steps) + 2)[1:-1])  # triangle, no zero ends
            self._pulse, self._at = sign * peak * ramp, 0
        pulse = self._pulse
        self.perturbed = pulse is not None or late is not None
        if pulse is not None:
            offset = float(pulse[self._at])
            self._at += 1
            if self._at == len(pulse):
                self._pulse = None
        if late is not None:  # the late turn holds the wheel; a pulse runs out meanwhile
            return Control(control.steer * late, control.accel)
        if pulse is None:
            return control
        return Control(float(np.clip(control.steer + offset, -1.0, 1.0)), control.accel)

    def _late_turn(self, command: int, control: Control) -> float | None:
        """The share of the steering kept this step while a late turn holds the wheel, else None."""
        if not self.turns:
            return None
        if command != self._command:  # a new stretch of road: a turn ahead draws whether it is late
            self._command, self._late, self._holding = command, None, 0
            if command in (LEFT, RIGHT):
                late, steps, keep = (self._turn_rng.random(), int(self._turn_rng.integers(*LATE_TURN_STEPS)),
                                     float(self._turn_rng.uniform(*LATE_TURN_KEEP)))
                self._late = (steps, keep) if late < self.turns else None
        if self._late is not None and not self._holding and abs(control.steer) > LATE_TURN_STEER:
            self._holding = self._late[0]  # the expert begins the turn: hold it back from here
            self.late_turns += 1
        if not self._holding:
            return None
        self._holding -= 1
        keep = self._late[1]
        if not self._holding:
            self._late = None  # once per turn
        return keep


# Dagger's gate: the teacher takes over beyond these, until the car is back near the route.
TAKEOVER_LATERAL_M = 1.5
TAKEOVER_HEADING_RAD = 0.35  # 20 degrees
RELEASE_LATERAL_M = 0.3
RELEASE_HEADING_RAD = 0.05
TAKEOVER_MIN_STEPS = 10  # 1 s at least, so that control does not flicker at the gate
STALL_STEPS = 15  # the student stands while the teacher would go: 1.5 s, then the teacher starts
MAX_STALL_STEPS = 600  # `stall_steps` at most: 60 s, the longest a student may stand for nothing
GIVE_UP_STEPS = 50  # 5 s standing still off the route: a dead end (say, past a turn, facing a wall)
GIVE_UP_LATERAL_M = 0.75
GIVE_UP_HEADING_RAD = 0.17  # 10 degrees
LATE_SHORT_M = 1.0  # late braking: the stop it judges is this far short of the car ahead
LATE_KINDS = ("vehicle", "pedestrian")  # what late braking may hold back for (the expert's reason's first word)


class Dagger:
    """The student drives; `label` is the teacher's control at every step.

    A policy trained on demonstrations visits states the expert never did (the car off the
    lane centre after a turn, late into a junction) and nothing told it what to do there.
    Here the student's own mistakes make those states and the teacher (the expert, which
    reads the snapshot) labels them. For the episode to go on, the teacher takes the wheel
    when the car is over TAKEOVER_LATERAL_M off the route or TAKEOVER_HEADING_RAD askew, or
    when the student stands still while the teacher would drive on, and gives it back once
    the car is near the route again; the teacher also brakes for the student (the executed
    accel is the lower of the two while the teacher brakes), so red lights and cars ahead do
    not end an episode in a crash. `student_share` is the share of steps the student drove.

    With that braking the student never comes near a car or a pedestrian at speed, and the
    recordings hold few such frames to learn "a car close ahead" (or a pedestrian) from
    (docs/experiments.md). `late_brake` (a share of full braking, 0 for off) holds the teacher's
    braking for a vehicle in the path (with `late_kinds`, for those kinds of LATE_KINDS) back
    until stopping LATE_SHORT_M short of it would take at least that share
    (v² / 2(gap − LATE_SHORT_M)): until then the student's own brakes decide. The teacher must
    say what it brakes for (bid_sim.expert.Expert's `reason` and `gap_m`). `late_steps` counts
    the steps held back.

    A forward-only car can strand itself (past a missed turn, nose against a building): the
    expert then stands with the wheel at full lock, and nothing of that is worth learning.
    After GIVE_UP_STEPS standing still off the route, `gave_up` is set and the episode ends
    (run_episode stops on it) rather than record a minute of a stuck car.

    A student that stands while the teacher would drive is started by the teacher after
    `stall_steps` (STALL_STEPS, 1.5 s, by default). A BID driven with a move-off (`bid evaluate
    --move-off S`) starts itself after S seconds, on a control head that still says "stand", and
    a turn begun that way can run wide (docs/experiments.md); with `stall_steps` beyond the
    move-off's wait the student moves off on its own and the recordings hold those starts.
    """

    def __init__(self, student: Agent, teacher: Agent, late_brake: float = 0.0, stall_steps: int = STALL_STEPS,
                 late_kinds: tuple[str, ...] = ("vehicle",)):
        self.student, self.teacher = student, teacher
        if not 0.0 <= late_brake <= 1.0:
            raise BidError(f"late_brake is a share of full braking, from 0 (off) to 1; got {late_brake}")
        if not late_kinds or set(late_kinds) - set(LATE_KINDS):
            raise BidError(f"late_kinds are what late braking holds back for, some of {', '.join(LATE_KINDS)}; "
                           f"got {', '.join(late_kinds) or 'none'}")
        if late_brake and not (hasattr(teacher, "reason") and hasattr(teacher, "gap_m")):
            raise BidError("late_brake needs a teacher that says what it brakes for (the expert); "
                           "record with --agent expert, or drop it")
        if not 1 <= stall_steps <= MAX_STALL_STEPS:
            raise BidError(f"stall_steps is how long the student may stand while the teacher would drive, "
                           f"1 to {MAX_STALL_STEPS} steps of 0.1 s; got {stall_steps}")
        self.late_brake = late_brake
        self.late_kinds = tuple(late_kinds)
        self.stall_steps = stall_steps
        self.late_steps = 0
        self.label: Control | None = None
        self._takeover = 0  # steps of teacher control left (at least)
        self._stall = self._stuck = 0
        self._steps = self._student_steps = 0
        self.gave_up = False

    @property
    def student_share(self) -> float:
        return self._student_steps / self._steps if self._steps else 0.0

    def reset(self, info: EpisodeInfo) -> None:
        self.student.reset(info)
        self.teacher.reset(info)
        self.label = None
        self._takeover = self._stall = self._stuck = 0
        self._steps = self._student_steps = 0
        self.late_steps = 0
        self.gave_up = False

    def act(self, obs: Observation) -> Control:
        mine = self.student.act(obs)  # every step: the student keeps its previous frame
        teacher = self.teacher.act(obs)
        self.label = teacher
        ego = obs.snapshot.ego
        lateral, heading = abs(ego.lateral_m), abs(ego.heading_error_rad)
        stalled = obs.speed_mps < 0.5 and teacher.accel > 0.05 and mine.accel <= 0.05
        self._stall = self._stall + 1 if stalled else 0
        off_route = lateral > GIVE_UP_LATERAL_M or heading > GIVE_UP_HEADING_RAD
        self._stuck = self._stuck + 1 if obs.speed_mps < 0.1 and off_route else 0
        self.gave_up = self._stuck >= GIVE_UP_STEPS
        if lateral > TAKEOVER_LATERAL_M or heading > TAKEOVER_HEADING_RAD or self._stall >= self.stall_steps:
            self._takeover = max(self._takeover, TAKEOVER_MIN_STEPS)
            self._stall = 0
        elif self._takeover and lateral < RELEASE_LATERAL_M and heading < RELEASE_HEADING_RAD:
            self._takeover -= 1
        self._steps += 1
        if self._takeover:
            return teacher
        self._student_steps += 1
        brakes = teacher.accel < 0.0
        if brakes and self.late_brake and self.teacher.reason.split(" ", 1)[0] in self.late_kinds:
            room = max(self.teacher.gap_m - LATE_SHORT_M, 0.05)
            if obs.speed_mps ** 2 / (2.0 * room) < self.late_brake * EgoParams.max_brake_mps2:
                brakes = False  # not yet: the student's own brakes decide
                self.late_steps += 1
        accel = min(mine.accel, teacher.accel) if brakes else mine.accel
        return Control(mine.steer, accel)
