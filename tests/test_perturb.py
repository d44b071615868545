"""Recovery data: Perturbed steers the car off now and then while the label stays the
expert's, and the episode records the label, not what the car executed; under Dagger a
student drives, the expert labels and takes the wheel when the student strays."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bid_sim.agents import EpisodeInfo, Observation, Scripted
from bid_sim.ego import Control, EgoParams
from bid_sim.episode import run_episode
from bid_sim.errors import BidError
from bid_sim.expert import Expert
from bid_sim.perturb import (
    GIVE_UP_STEPS,
    LATE_SHORT_M,
    LATE_TURN_KEEP,
    LATE_TURN_STEPS,
    PULSE_STEER,
    STALL_STEPS,
    Dagger,
    Perturbed,
)


def _info(seed: int) -> EpisodeInfo:
    return EpisodeInfo("Town02", 0, "ClearNoon", "none", seed, None, EgoParams())


def _drive(agent: Perturbed, seed: int, steps: int, speed: float) -> tuple[list[Control], list[bool]]:
    agent.reset(_info(seed))
    out, flags = [], []
    for _ in range(steps):
        out.append(agent.act(Observation(None, None, 4, speed, None)))
        flags.append(agent.perturbed)
    return out, flags


def test_pulses_take_their_share_and_labels_stay_clean():
    inner = Scripted(lambda step, obs: Control(0.05, 0.3))
    agent = Perturbed(inner, 0.2)
    executed, flags = _drive(agent, seed=7, steps=4000, speed=6.0)
    assert agent.label == Control(0.05, 0.3)
    offsets = np.array([c.steer - 0.05 for c in executed])
    assert 0.15 < np.mean(flags) < 0.25
    assert np.all(np.abs(offsets[~np.array(flags)]) < 1e-12)
    assert 0.05 < np.abs(offsets).max() <= PULSE_STEER[1] + 1e-9
    assert (offsets > 0.01).any() and (offsets < -0.01).any()  # both directions
    assert all(c.accel == 0.3 for c in executed)


def test_no_pulses_when_slow_and_same_seed_same_noise():
    agent = Perturbed(Scripted(lambda step, obs: Control(0.0, 0.0)), 0.3)
    _, slow = _drive(agent, seed=1, steps=500, speed=1.0)
    assert not any(slow)
    a, _ = _drive(agent, seed=2, steps=300, speed=5.0)
    b, _ = _drive(agent, seed=2, steps=300, speed=5.0)
    c, _ = _drive(agent, seed=3, steps=300, speed=5.0)
    assert a == b and a != c


@pytest.mark.parametrize("share", [-0.1, 1.0])
def test_bad_share_is_refused(share):
    with pytest.raises(BidError, match="perturb"):
        Perturbed(Expert(), share)


class _Labels:
    """A recorder that keeps what the episode writes."""

    def __init__(self):
        self.controls = []

    def write(self, snap, frame, control):
        self.controls.append(control)


def _turns(agent: Perturbed, commands: list[int], speed: float = 0.0) -> list[tuple[Control, Control, bool]]:
    out = []
    for command in commands:
        control = agent.act(Observation(None, None, command, speed, None))
        out.append((control, agent.label, agent.perturbed))
    return out


def test_late_turns_damp_the_first_steering_of_a_share_of_turns_and_labels_stay_the_experts():
    """--perturb-turns: a late turn holds the steering back from the expert's first turning
    step, at any speed, once per turn; the label is the expert's throughout."""
    turning = Scripted(lambda step, obs: Control(0.6 if obs.command == 2 and step % 60 >= 8 else 0.05, 0.3))
    agent = Perturbed(turning, 0.0, turns=1.0)
    agent.reset(_info(0))
    out = _turns(agent, [4] * 5 + [2] * 55)  # lane follow, then a right turn from a standstill
    held = [i for i, (_, _, late) in enumerate(out) if late]
    assert held and held[0] == 8 and held == list(range(8, 8 + len(held)))  # from the first turning step on
    assert LATE_TURN_STEPS[0] <= len(held) < LATE_TURN_STEPS[1]
    assert all(abs(out[i][0].steer) <= 0.6 * LATE_TURN_KEEP[1] + 1e-9 for i in held)
    assert all(c.steer == label.steer for i, (c, label, _) in enumerate(out) if i not in held)
    assert all(label.steer == 0.6 for _, label, _ in out[8:]) and agent.late_turns == 1
    # A share of the turns, drawn apart from the pulses: the pulses stay those of --perturb alone.
    commands = ([4] * 5 + [2] * 55) * 40
    half, plain = Perturbed(turning, 0.3, turns=0.5), Perturbed(turning, 0.3)
    for a in (half, plain):
        a.reset(_info(7))
    late, pulsed = _turns(half, commands, 5.0), _turns(plain, commands, 5.0)
    assert 10 <= half.late_turns <= 30
    differ = [i for i in range(len(commands)) if late[i][0] != pulsed[i][0]]
    assert differ and all(late[i][1].steer == 0.6 and abs(late[i][0].steer) <= 0.6 * LATE_TURN_KEEP[1] + 1e-9
                          for i in differ)  # only turning steps held back; elsewhere the same pulses
    again = Perturbed(turning, 0.3, turns=0.5)
    again.reset(_info(7))
    assert _turns(again, commands, 5.0) == late  # same seed, same draws
    with pytest.raises(BidError, match="--perturb-turns must be a share of the turns"):
        Perturbed(turning, 0.0, turns=1.5)


def test_episode_records_the_experts_label_not_the_executed_control(town02):
    agent = Perturbed(Expert(), 0.5)
    labels, executed = _Labels(), []
    act = agent.act

    def spy(obs):
        c = act(obs)
        executed.append((c, agent.label))
        return c

    agent.act = spy
    run_episode(town02, 0, "ClearNoon", "none", 4, agent, recorder=labels, max_steps=120)
    assert labels.controls == [label for _, label in executed]
    assert any(c != label for c, label in executed)  # the car was pushed at least once


class _Drifter:
    """A student that drives straight on at a steady throttle, whatever the road does."""

    def reset(self, info):
        pass

    def act(self, obs):
        return Control(0.12, 0.5)


def test_dagger_labels_are_the_teachers_and_the_teacher_takes_the_wheel(town02):
    teacher = Expert()
    agent = Dagger(_Drifter(), teacher)
    labels, log = _Labels(), []
    act = agent.act

    def spy(obs):
        c = act(obs)
        log.append((c, agent.label, obs.snapshot.ego.lateral_m))
        return c

    agent.act = spy
    result = run_episode(town02, 0, "ClearNoon", "none", 3, agent, recorder=labels, max_steps=400)
    recorded = len(log) - (result.status == "gave_up")  # the step it gave up on is not recorded
    assert labels.controls == [label for _, label, _ in log[:recorded]]
    student_steps = [c for c, label, _ in log if c.steer == 0.12]
    assert student_steps and len(student_steps) < len(log)  # both drove
    assert 0.0 < agent.student_share < 1.0
    assert agent.student_share == pytest.approx(len(student_steps) / len(log))
    # The student alone leaves the lane at once; with the gate the car stays near the route.
    assert max(abs(lat) for _, _, lat in log) < 4.0
    assert result.status != "route_deviation"
    # While the teacher brakes, the car brakes at least as hard.
    assert all(c.accel <= max(label.accel, 0.0) + 1e-9 for c, label, _ in log if label.accel < 0 and c.steer == 0.12)


def test_dagger_and_perturb_do_not_mix(tmp_path):
    from bid_sim.record import record

    with pytest.raises(BidError, match="--dagger and --perturb"):
        record("02", 1, ("ClearNoon",), ("none",), 0, 1, tmp_path, perturb=0.2, dagger="checkpoints/bid_small.pt")
    with pytest.raises(BidError, match="no such checkpoint"):
        record("02", 1, ("ClearNoon",), ("none",), 0, 1, tmp_path, dagger=str(tmp_path / "nope.pt"))


def _standing(lateral_m: float) -> Observation:
    ego = SimpleNamespace(lateral_m=lateral_m, heading_error_rad=0.0)
    return Observation(None, None, 2, 0.0, SimpleNamespace(ego=ego))


def test_dagger_gives_up_standing_off_the_route_only():
    full_lock = Scripted(lambda step, obs: Control(-1.0, -1.0))
    agent = Dagger(Scripted(lambda step, obs: Control(0.0, -0.5)), full_lock)
    agent.reset(_info(0))
    flags = [(agent.act(_standing(2.0)), agent.gave_up)[1] for _ in range(GIVE_UP_STEPS)]
    assert not any(flags[:-1]) and flags[-1]
    agent.reset(_info(0))
    assert not agent.gave_up
    for _ in range(3 * GIVE_UP_STEPS):  # waiting on the route (a red light) goes on
        agent.act(_standing(0.1))
    assert not agent.gave_up


def test_dagger_starts_a_standing_student_after_stall_steps_and_its_own_move_off_counts_as_going():
    """The teacher takes the wheel from a student that stands while it would drive after
    stall_steps (STALL_STEPS by default); a student that moves off on its own before then drives."""
    go = Scripted(lambda step, obs: Control(0.3, 0.6))
    for stall in (STALL_STEPS, 80):
        agent = Dagger(Scripted(lambda step, obs: Control(0.0, -0.2)), go, stall_steps=stall)
        agent.reset(_info(0))
        driven = [agent.act(_standing(0.0)) for _ in range(stall + 1)]
        assert all(c.accel == -0.2 for c in driven[:stall - 1]) and driven[-1] == Control(0.3, 0.6), stall
    # Moving off after 50 steps (as --move-off 5 would): with the gate at 80 steps the student drives on.
    agent = Dagger(Scripted(lambda step, obs: Control(0.1, 0.5 if step >= 50 else -0.2)), go, stall_steps=80)
    agent.reset(_info(0))
    driven = [agent.act(_standing(0.0)) for _ in range(120)]
    assert all(c.steer == 0.1 for c in driven) and agent.student_share == 1.0
    for bad in (0, 601):
        with pytest.raises(BidError, match="stall_steps is how long the student may stand"):
            Dagger(Expert(), go, stall_steps=bad)


class _Braking:
    """A teacher that brakes for what `reason` names, `gap_m` ahead, as the expert says it."""

    def __init__(self):
        self.reason, self.gap_m = "speed", math.inf

    def reset(self, info):
        pass

    def act(self, obs):
        return Control(0.0, 0.3 if self.reason == "speed" else -0.6)


def _moving(speed_mps: float) -> Observation:
    ego = SimpleNamespace(lateral_m=0.0, heading_error_rad=0.0)
    return Observation(None, None, 2, speed_mps, SimpleNamespace(ego=ego))


def test_dagger_late_brake_holds_the_teachers_braking_for_a_car_back_until_it_is_needed():
    """late_brake: braking for a vehicle in the path is the student's own until stopping
    LATE_SHORT_M short of it takes that share of full braking; a red light is braked for at once."""
    teacher = _Braking()
    agent = Dagger(Scripted(lambda step, obs: Control(0.1, 0.4)), teacher, late_brake=0.5)
    agent.reset(_info(0))
    # At 4 m/s half of full braking (4 m/s²) stops in 2 m: held back beyond 3 m, braked within.
    edge = LATE_SHORT_M + 4.0 ** 2 / (2 * 0.5 * EgoParams.max_brake_mps2)
    steps = [("vehicle v7", 12.0, 0.4), ("vehicle v7", edge + 0.1, 0.4), ("vehicle v7", edge - 0.1, -0.6),
             ("red light", 12.0, -0.6), ("pedestrian p1", 30.0, -0.6), ("speed", math.inf, 0.4)]
    for reason, gap, executed in steps:
        teacher.reason, teacher.gap_m = reason, gap
        assert agent.act(_moving(4.0)) == Control(0.1, executed), reason
        assert agent.label.accel == (0.3 if reason == "speed" else -0.6)
    assert agent.late_steps == 2 and agent.student_share == 1.0
    agent.reset(_info(0))
    assert agent.late_steps == 0
    on_time = Dagger(Scripted(lambda step, obs: Control(0.1, 0.4)), teacher)
    teacher.reason, teacher.gap_m = "vehicle v7", 12.0
    assert on_time.act(_moving(4.0)).accel == -0.6  # without it the teacher brakes at once
    with pytest.raises(BidError, match="from 0 \\(off\\) to 1"):
        Dagger(Expert(), teacher, late_brake=1.5)
    with pytest.raises(BidError, match="some of vehicle, pedestrian; got cyclist"):
        Dagger(Expert(), teacher, late_brake=0.5, late_kinds=("cyclist",))
    with pytest.raises(BidError, match="what it brakes for"):
        Dagger(Expert(), Scripted(lambda step, obs: Control(0.0, 0.0)), late_brake=0.5)


def test_dagger_late_brake_for_pedestrians_holds_back_only_the_kinds_it_is_given():
    """late_kinds: with ("pedestrian",) braking for a pedestrian in the path is held back as for
    a car, and braking for a car is at once; with both, both are held back."""
    teacher = _Braking()
    edge = LATE_SHORT_M + 4.0 ** 2 / (2 * 0.5 * EgoParams.max_brake_mps2)
    for kinds, held in ((("pedestrian",), {"pedestrian p1", "pedestrian p2 beside"}),
                        (("vehicle", "pedestrian"), {"pedestrian p1", "pedestrian p2 beside", "vehicle v7"})):
        agent = Dagger(Scripted(lambda step, obs: Control(0.1, 0.4)), teacher, late_brake=0.5, late_kinds=kinds)
        agent.reset(_info(0))
        for reason in ("pedestrian p1", "pedestrian p2 beside", "vehicle v7", "red light", "exit blocked (vehicle v7)"):
            teacher.reason = reason
            teacher.gap_m = edge + 0.1
            assert agent.act(_moving(4.0)).accel == (0.4 if reason in held else -0.6), (kinds, reason)
            teacher.gap_m = edge - 0.1  # within the edge the teacher brakes, whatever it brakes for
            assert agent.act(_moving(4.0)).accel == -0.6, (kinds, reason)
        assert agent.late_steps == len(held)


class _Quitter:
    def reset(self, info):
        self.steps = 0

    def act(self, obs):
        self.steps += 1
        self.gave_up = self.steps > 5
        return Control(0.0, 0.5)


def test_an_agent_that_gives_up_ends_the_episode_unrecorded_from_there(town02):
    labels = _Labels()
    result = run_episode(town02, 0, "ClearNoon", "none", 0, _Quitter(), recorder=labels, max_steps=100)
    assert result.status == "gave_up" and len(labels.controls) == 5


def test_bid_record_dagger_writes_labelled_recordings(tmp_path):
    from bid_model.recordings import _index, find_recordings
    from bid_sim.cli import main as bid

    out = tmp_path / "dagger"
    assert bid(["record", "--town", "02", "--episodes", "1", "--densities", "none", "--weathers", "ClearNoon",
                "--max-steps", "40", "--workers", "1", "--dagger", "checkpoints/bid_small.pt", "--out", str(out),
                "--json"]) == 0
    files, partial = find_recordings(out)
    assert len(files) == 1 and not partial
    ix = _index(files, keep_jpeg=False)
    assert ix.facts[0]["dagger"] == "bid_small.pt" and len(ix.step) == 40


def test_bid_record_dagger_drives_the_student_with_the_drive_flags_given(tmp_path, capsys):
    from bid_model.recordings import _index, find_recordings
    from bid_sim.cli import main as bid

    def record(out, *drive):
        return bid(["record", "--town", "02", "--episodes", "1", "--densities", "none", "--weathers", "ClearNoon",
                    "--max-steps", "60", "--workers", "1", "--dagger", "checkpoints/bid_small.pt",
                    *drive, "--out", str(out), "--json"])

    def speeds_and_facts(out):
        files, _ = find_recordings(out)
        ix = _index(files, keep_jpeg=False)
        return ix.speed, ix.facts[0]

    assert record(tmp_path / "free") == 0
    assert record(tmp_path / "capped", "--max-speed", "1", "--move-off", "8") == 0
    free, free_facts = speeds_and_facts(tmp_path / "free")
    capped, facts = speeds_and_facts(tmp_path / "capped")
    assert free_facts["dagger_drive"] == "" and facts["dagger_drive"] == "--max-speed 1 --move-off 8"
    assert free.max() > 3.0 and capped.max() < 2.5  # the student drove under the cap
    # Finishing that folder needs the same drive; a drive flag needs a student.
    assert record(tmp_path / "capped", "--max-speed", "1") == 2
    assert "dagger_drive '--max-speed 1 --move-off 8' here, '--max-speed 1' planned" in capsys.readouterr().err
    assert bid(["record", "--town", "02", "--episodes", "1", "--light-brake", "1", "--out", str(tmp_path / "x")]) == 2
    assert "--light-brake is how the --dagger student drives; give --dagger" in capsys.readouterr().err


def test_bid_record_late_brake_is_recorded_and_kept_to(tmp_path, capsys):
    """bid record --dagger --late-brake (and --stall-takeover): the recordings say how late the
    teacher braked (and started the student), and a folder is finished only with the same;
    without --dagger, or with another teacher, refused."""
    from bid_model.recordings import _index, find_recordings
    from bid_sim.cli import main as bid
    from bid_sim.record import describe

    def record(out, *flags):
        return bid(["record", "--town", "02", "--episodes", "1", "--densities", "normal", "--weathers", "ClearNoon",
                    "--max-steps", "30", "--workers", "1", *flags, "--out", str(out), "--json"])

    late = ("--dagger", "checkpoints/bid_small.pt", "--late-brake", "0.5")
    assert record(tmp_path / "late", *late) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["late_steps"] >= 0 and summary["recorded"] == 1
    files, _ = find_recordings(tmp_path / "late")
    assert _index(files, keep_jpeg=False).facts[0]["late_brake"] == "0.5"
    assert record(tmp_path / "late", "--dagger", "checkpoints/bid_small.pt") == 2
    assert "late_brake '0.5' here, 'none' planned" in capsys.readouterr().err
    assert record(tmp_path / "late", *late) == 0  # the same plan: found done
    capsys.readouterr()
    assert record(tmp_path / "late", *late, "--stall-takeover", "10") == 2  # another gate: another plan
    assert "stall_takeover_s 'none' here, '10' planned" in capsys.readouterr().err
    assert record(tmp_path / "stall", *late, "--stall-takeover", "10") == 0
    capsys.readouterr()
    assert _index(find_recordings(tmp_path / "stall")[0], keep_jpeg=False).facts[0]["stall_takeover_s"] == "10"
    assert record(tmp_path / "late", *late, "--late-brake-for", "pedestrian") == 2  # braking late for others
    assert "late_brake_for 'none' here, 'pedestrian' planned" in capsys.readouterr().err
    assert record(tmp_path / "peds", *late, "--late-brake-for", "vehicle,pedestrian") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["late_brake_for"] == ["vehicle", "pedestrian"]
    assert "held back its braking for a car or a pedestrian ahead" in describe(summary)
    peds = _index(find_recordings(tmp_path / "peds")[0], keep_jpeg=False).facts[0]
    assert peds["late_brake_for"] == "vehicle,pedestrian" and peds["late_brake"] == "0.5"
    for flags, says in ((("--late-brake", "0.5"), "--late-brake is how late the teacher brakes for the --dagger"),
                        (("--stall-takeover", "10"), "--stall-takeover is how long the --dagger student may stand"),
                        ((*late, "--stall-takeover", "0"), "--stall-takeover is seconds the student may stand, 0.1 to 60"),
                        ((*late[:2], "--late-brake", "2"), "a share of full braking, from 0 (off) to 1; got 2"),
                        ((*late, "--agent", "lanefollow"), "--late-brake needs the expert as the teacher"),
                        ((*late, "--late-brake-for", "cyclist"), "some of vehicle,pedestrian; got cyclist"),
                        ((*late[:2], "--late-brake-for", "pedestrian"), "give --late-brake SHARE too")):
        assert record(tmp_path / "x", *flags) == 2, flags
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err


def test_bid_record_perturb_turns_is_recorded_and_kept_to(tmp_path, capsys):
    """bid record --perturb-turns: the recordings say the share, the summary counts the late
    turns, and a folder is finished only with the same; with --dagger or out of [0, 1], refused."""
    from bid_model.recordings import _index, find_recordings
    from bid_sim.cli import main as bid

    def record(out, *flags):
        return bid(["record", "--town", "02", "--episodes", "1", "--densities", "none", "--weathers", "ClearNoon",
                    "--max-steps", "300", "--workers", "1", *flags, "--out", str(out), "--json"])

    assert record(tmp_path / "turns", "--perturb-turns", "1") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["recorded"] == 1 and summary["late_turns"] >= 0
    files, _ = find_recordings(tmp_path / "turns")
    assert _index(files, keep_jpeg=False).facts[0]["perturb_turns"] == "1"
    from bid_model.recordings import open_recordings

    description = open_recordings(tmp_path / "turns", (32, 96), 0.0, 0, cache=False)[2]
    assert description["late_turn_recordings"] == 1 and description["perturbed_recordings"] == 0
    assert record(tmp_path / "turns") == 2
    assert "perturb_turns '1' here, 'none' planned" in capsys.readouterr().err
    for flags, says in ((("--perturb-turns", "1.5"), "--perturb-turns must be a share of the turns in [0, 1]"),
                        (("--perturb-turns", "0.5", "--dagger", "checkpoints/bid_small.pt"),
                         "--dagger and --perturb (or --perturb-turns) do not go together")):
        assert record(tmp_path / "x", *flags) == 2, flags
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, err
