"""Configuration of the BID model ("Brain-inspired driving", BID) and of its training.

Frozen dataclasses whose defaults are the paper's values. `paper()`, `small()` and `tiny()`
build the presets; `with_variant` switches on the paper's ablations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from bid_sim.errors import BidError

# The paper's ablations: which streams feed the decision network.
# baseline = ventral stream only; dorsal adds MT/MST (motion), navigation adds OFC (the
# command), both adds the two; full BID also relates foreground and background in DPC.
VARIANTS: dict[str, dict[str, bool]] = {
    "baseline": {"dorsal": False, "navigation": False, "relations": False},
    "dorsal": {"dorsal": True, "navigation": False, "relations": False},
    "navigation": {"dorsal": False, "navigation": True, "relations": False},
    "both": {"dorsal": True, "navigation": True, "relations": False},
    "full": {"dorsal": True, "navigation": True, "relations": True},
}

# The model fields a variant sets: a checkpoint of one variant can start another (`--init`).
VARIANT_FIELDS = frozenset({"variant", *VARIANTS["full"]})
# Fields whose change only adds or drops parts: `--init` starts those afresh.
# (sc_scale: SC and the crossing map start afresh at their new resolution.)
INIT_FIELDS = VARIANT_FIELDS | {"forecast_s", "hazard", "hazard_light", "hazard_attend", "hazard_sc",
                               "sc_presence", "hazard_crossing", "move_off_head", "head_presence", "sc_scale",
                               "sc_fine"}
# Fields `--init` adapts to: the input size (the token grids' positional embeddings are
# resized, model.resize_grid_tokens; the convolutions do not depend on it).
RESIZE_FIELDS = frozenset({"frame_hw"})
# Fields that change what a part reads, not its weights: `--init` keeps the weights as they are.
READ_FIELDS = frozenset({"sc_still", "hazard_speedless", "move_off_speed", "fine_moving", "sc_logit",
                         "fine_logit", "fine_speed"})

# Horizons of `--forecast`: the speed 1, 2 and 3 s ahead. At Town01's 11 m/s the expert
# starts braking for a 90° corner about 3 s before it.
FORECAST_S = (1.0, 2.0, 3.0)

# The columns of the hazard targets (bid_model.hazards; red_light: hazard_light; crossing:
# hazard_crossing), here so that the network imports without the simulator.
KINDS = ("pedestrian", "vehicle", "red_light", "crossing")
PATH_KINDS = KINDS[:2]  # those found in the path (hazards.path_hazards)
# The ego moves at this speed or faster (train --hazard-moving-weight, bid probe, config.fine_moving).
MOVING_MPS = 0.3
# config.fine_speed at most (the town's limit is 9 m/s).
MAX_FINE_SPEED_MPS = 15.0
# What `bid probe --source` probes: the hazard reading the brakes use (with SC, the larger of the
# head's and SC's), the head's alone, SC's alone, or the fine SC's alone (sc_fine); the merged
# reading hides which of them sees and which reads wrongly. Here so the CLI lists them without torch.
PROBE_SOURCES = ("merged", "head", "SC", "SC_fine")

PRESETS = ("paper", "small", "tiny")

# The paper halves the learning rate at these epochs of its 100.
PAPER_EPOCHS = 100
PAPER_MILESTONES = (25, 45, 70)


@dataclass(frozen=True)
class ModelConfig:
    """Shape of the network. Widths are channels; `frame_hw` is (rows, columns) of the input."""

    preset: str = "paper"
    variant: str = "full"
    frame_hw: tuple[int, int] = (300, 900)
    widths: tuple[int, int, int, int] = (64, 128, 256, 512)  # V1, V2, V4, IT
    times: tuple[int, int, int] = (2, 4, 2)  # recurrent steps of V2, V4, IT
    expansion: int = 4  # bottleneck expansion inside V2, V4, IT
    depthwise: bool = False  # expanded 3×3 per channel (MobileNet-style) instead of full (CORnet-S)
    mt_kernel: int = 5  # dynamic filter size of MT, on the V1 grid
    mt_groups: int = 4
    dpc_kernel: int = 3  # dynamic filter size of DPC, on the IT grid
    dpc_groups: int = 4
    mpc_layers: int = 4
    mpc_heads: int = 4
    mpc_ff_mult: int = 4
    cpc_hidden: tuple[int, int] = (256, 256)
    dropout: float = 0.1
    n_commands: int = 6
    dorsal: bool = True
    navigation: bool = True
    relations: bool = True
    speed_input: bool = False  # measured speed as an extra token (off in the paper)
    # Seconds ahead of the auxiliary speed forecast (BID.forward(forecast=True)); () = none.
    # A training signal only: driving uses (steer, accel) alone. Not in the paper.
    forecast_s: tuple[float, ...] = ()
    # An auxiliary head for what stands in the path: the distance to the nearest pedestrian
    # and vehicle in it (bid_model.hazards; BID.forward(hazard=True)). A training signal only.
    hazard: bool = False
    # With it, a third output: how near the stop line of a red or amber light on the route is
    # (bid_model.hazards.light_distance). Every new --hazard head has it; older ones do not.
    hazard_light: bool = False
    # The head attends over V2's and V4's grids and MPC's tokens rather than reading MPC's mean
    # (model.AttendingHazardHead): a small pedestrian is one cell of V2's grid.
    hazard_attend: bool = False
    # SC (areas.SC), a shallow pathway on the full input frames beside the cortex, says it too:
    # the pedestrian and vehicle outputs are the nearer of the head's and SC's (BID.forward_hazard).
    hazard_sc: bool = False
    # SC says also whether one is in the path at all, a presence logit per kind fitted apart from
    # its nearness (areas.SC): it reads a nearness only where it says yes, rather than the
    # blend of "none" and "near" an L1 fit on both gives an actor it is unsure of.
    sc_presence: bool = False
    # SC's pedestrian counts only where its presence logit is above this: at 0, where it judges
    # the odds above 1 / (1 + w) for its training's weight w (train.presence_loss); higher,
    # surer (a reading, not a weight: `bid evaluate --sc-logit`; the vehicle's stays at 0).
    sc_logit: float = 0.0
    # SC reads frame t alone, its change since t−1 zeroed: that change is the ego's own motion as
    # much as the actors', and SC fitted on it read "moving, so nothing in the path" (on a held-out
    # Town01 seed it saw 12 % of a moving ego's pedestrians, 48 % with the change zeroed;
    # docs/experiments.md). Still, a moving car's frame looks like a standing one's.
    sc_still: bool = False
    # A fourth hazard output from a second SC map of its own (BID.hazard_crossing): how near the
    # next crossing on the path with a pedestrian on it is (bid_model.hazards.crossing_distances).
    hazard_crossing: bool = False
    # SC (and the crossing map) read the frames at sc_scale times the cortex's resolution: the
    # network's input is frame_hw × sc_scale (input_hw) and the cortex reads it area-averaged down
    # to frame_hw, which is what it read before up to rounding (an area resize by a whole factor
    # is the average of the finer one's cells). At 64×192 a person 10 m off is 3 pixels wide.
    sc_scale: int = 1
    # A second SC with presence logits (BID.hazard_sc_fine) reading the frames at sc_fine times
    # frame_hw (0: none), beside the first: another checkpoint's SC grafted in (`bid graft`), so
    # that two SCs each read what they read best. Its pedestrian joins the merge (the vehicle stays
    # the head's and the first SC's): the shipped SC at 1× saw 46 % of a standing ego's pedestrians
    # within 10 m and 8 % of a moving one's, sp40b's at 2× 20 % and 25 % (docs/experiments.md).
    # The input is frame_hw × the larger of sc_scale and sc_fine; each reads it area-averaged down.
    sc_fine: int = 0
    # The fine SC's pedestrian counts only while the ego moves (fine_speed or faster): standing it
    # added 2.4 points of pedestrians seen for 3.1 points of false sightings, moving 23 for 3.4.
    fine_moving: bool = True
    # The fine SC's pedestrian counts only where its presence logit is above this (a reading, as
    # sc_logit is the first SC's: `bid evaluate --fine-logit`).
    fine_logit: float = 0.0
    # With fine_moving, the speed from which the fine SC's pedestrian counts (m/s; a reading,
    # `bid evaluate --fine-speed`). The shipped BID meets its pedestrians at 3-9 m/s; ahead46's SC
    # read from 3 m/s left Town02 as it was, from 0.3 m/s it braked crowded into queues and junctions
    # (docs/experiments.md).
    fine_speed: float = MOVING_MPS
    # The hazard head reads MPC's tokens merged a second time without the speed token, so that it
    # cannot read "standing, so something ahead": with the speed, the shipped head read a vehicle
    # 7.5 m ahead of a standing ego in an empty street (at 5 m/s: none), which kept move-off
    # waiting (docs/experiments.md, "The hazard head reads the speed"). The forecast and the
    # control head still read the speed.
    hazard_speedless: bool = False
    # A second hazard head, alike, reading MPC's tokens merged without the speed token, whose
    # pedestrian and vehicle move-off's clear check reads (BIDAgent); the brakes and move-off's
    # red light keep the first head, which reads the speed: the speedless head saw 71.5 % of the
    # red lights a moving ego met within 10 m where the first saw 99.2 %, and standing it no
    # longer reads "standing, so a vehicle ahead" (docs/experiments.md, "Two hazard heads").
    move_off_head: bool = False
    # The move-off head reads MPC with the speed token, as the first head does: a second head of the
    # same kind fitted to other data or weights (`bid train --move-off-speed`), whose red light
    # move-off can read (BIDAgent's move_off_light) while the brakes keep the first head.
    move_off_speed: bool = False
    # The hazard head says also whether a pedestrian is in the path at SEEN_NEARNESS or nearer, a
    # logit fitted apart from her nearness (model.PresenceHazardHead): it reads a nearness only
    # where it says yes. Under the weighted L1 fit of both, a pedestrian the head was unsure of
    # read as the low end of the nearness she could have, far off: refitted for a moving ego, the
    # head saw 45 % of them within 10 m and placed them at a median 16.5 m (docs/experiments.md).
    head_presence: bool = False
    lesion_momentum: float = 0.05  # running mean of each area's output, for "mean" lesions

    def __post_init__(self) -> None:
        if self.widths[3] % self.mpc_heads:
            raise ValueError(f"IT width {self.widths[3]} must be divisible by {self.mpc_heads} heads")
        if len(self.times) != 3 or min(self.times) < 1:
            raise ValueError(f"times must be 3 positive step counts, got {self.times}")
        if self.widths[0] % self.mt_groups or self.widths[3] % self.dpc_groups:
            raise ValueError("filter groups must divide the filtered widths")
        if self.relations and not self.dorsal:
            raise ValueError("relations (DPC) need the dorsal stream (MT)")
        if self.hazard_sc and not self.hazard:
            raise ValueError("hazard_sc (SC) reads beside the hazard head: it needs hazard")
        if self.sc_presence and not self.hazard_sc:
            raise ValueError("sc_presence is a part of SC: it needs hazard_sc")
        if self.sc_logit and not self.sc_presence:
            raise ValueError("sc_logit is where SC's presence logit says yes: it needs sc_presence")
        if self.sc_still and not self.hazard_sc:
            raise ValueError("sc_still is how SC reads: it needs hazard_sc")
        if not (isinstance(self.sc_scale, int) and 1 <= self.sc_scale <= 4):
            raise ValueError(f"sc_scale is a whole factor, 1 to 4, got {self.sc_scale!r}")
        if self.sc_scale > 1 and not self.hazard_sc:
            raise ValueError("sc_scale is SC's resolution: it needs hazard_sc")
        if not (isinstance(self.sc_fine, int) and 0 <= self.sc_fine <= 4):
            raise ValueError(f"sc_fine is a whole factor, 1 to 4, or 0 for none; got {self.sc_fine!r}")
        if self.sc_fine and not self.hazard_sc:
            raise ValueError("sc_fine is a second SC beside the first: it needs hazard_sc")
        if not 0 <= self.fine_speed <= MAX_FINE_SPEED_MPS:
            raise ValueError(f"fine_speed is a speed from 0 to {MAX_FINE_SPEED_MPS:g} m/s; got {self.fine_speed}")
        if self.fine_speed != MOVING_MPS and not (self.sc_fine and self.fine_moving):
            raise ValueError("fine_speed is where the fine SC starts to count while moving: it needs sc_fine "
                             "and fine_moving")
        if self.fine_logit and not self.sc_fine:
            raise ValueError("fine_logit is where the fine SC's presence logit says yes: it needs sc_fine")
        if self.sc_fine and self.input_scale % min(self.sc_scale, self.sc_fine):
            raise ValueError(f"sc_scale {self.sc_scale} and sc_fine {self.sc_fine} read one input each "
                             "area-averaged down by a whole factor: one must divide the other")
        if self.hazard_crossing and not (self.hazard_sc and self.hazard_light):
            raise ValueError("hazard_crossing is the fourth hazard output, beside SC: it needs hazard_sc and hazard_light")
        if self.hazard_speedless and not (self.hazard and self.speed_input):
            raise ValueError("hazard_speedless keeps the speed input from the hazard head: it needs hazard and speed_input")
        if self.move_off_head and not (self.hazard and self.speed_input):
            raise ValueError("move_off_head is a hazard head without the speed input: it needs hazard and speed_input")
        if self.move_off_head and self.hazard_speedless:
            raise ValueError("with hazard_speedless the hazard head already reads no speed: drop move_off_head")
        if self.move_off_speed and not self.move_off_head:
            raise ValueError("move_off_speed is how the move-off head reads: it needs move_off_head")
        if self.head_presence and not (self.hazard_sc and not self.hazard_attend and not self.move_off_head):
            raise ValueError("head_presence is a logit beside the plain hazard head's nearness, read with SC: "
                             "it needs hazard_sc, and neither hazard_attend nor move_off_head")
        if any(not t > 0 for t in self.forecast_s):
            raise ValueError(f"forecast horizons must be positive seconds, got {self.forecast_s}")

    @property
    def width(self) -> int:
        """Width of the decision network (= the ventral output width)."""
        return self.widths[3]

    @property
    def input_scale(self) -> int:
        """How many times finer than frame_hw the network's input is: SC's or the fine SC's scale."""
        return max(self.sc_scale, self.sc_fine)

    def scaled_hw(self, scale: int) -> tuple[int, int]:
        """(rows, columns) of frame_hw `scale` times finer."""
        return self.frame_hw[0] * scale, self.frame_hw[1] * scale

    @property
    def input_hw(self) -> tuple[int, int]:
        """(rows, columns) of the frames the network takes: frame_hw, input_scale times finer."""
        return self.scaled_hw(self.input_scale)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation: L1 loss, AdamW, step schedule; the paper's values as defaults."""

    epochs: int = PAPER_EPOCHS
    milestones: tuple[int, ...] = PAPER_MILESTONES
    lr_gamma: float = 0.5
    batch_size: int = 100
    lr: float = 2e-4
    weight_decay: float = 0.02
    lambda_steer: float = 0.5
    lambda_accel: float = 0.5
    val_fraction: float = 0.1
    stop_keep: float = 1.0  # share of standing, braking frames trained on (recordings.balance_rows)
    start_repeat: int = 1  # times each moving-off frame is trained on
    start_accel: float = 0.0  # a standstill's throttle up to this is a hold, not a start (recordings.hold_creep)
    hard_repeat: int = 1  # times each frame of hard steering or braking while moving is trained on
    hard_brake: bool = True  # whether hard braking counts as hard (else only steering)
    hold_repeat: int = 1  # times each frame of yielding (no red light) is trained on (recordings.yield_frames)
    brake_lookahead: int = 1  # frames over which training labels brake ahead (recordings.anticipate_braking)
    motion_drop: float = 0.0  # share of training rows shown without motion (recordings.motion_dropout)
    augment: float = 0.0  # share of training samples given a random lighting change (augment.py)
    mirror: float = 0.0  # share of training samples mirrored left to right (augment.mirror)
    shift: int = 0  # pixels each training sample is moved by at most, down or up and sideways (augment.shift)
    lambda_forecast: float = 0.0  # weight of the speed forecast's L1 loss (model.forecast_s)
    lambda_hazard: float = 0.0  # weight of the hazard head's L1 loss (model.hazard)
    # Weight, in that loss, of a frame with an actor of that kind in the path (train.hazard_loss).
    hazard_pos_weight: float = 1.0
    # Further weight of a frame with a pedestrian in the path while turning (train.hazard_loss).
    hazard_turn_weight: float = 1.0
    # Further weight of a frame with a pedestrian in the path while the ego moves (train.hazard_loss).
    hazard_moving_weight: float = 1.0
    # Further weight of the red-light entry (none there) of a frame where the ego stands at a green
    # light's stop line (hazards.AT_LINE_M; train.hazard_weights).
    hazard_green_weight: float = 1.0
    # Further weight of a frame with a vehicle in the path while the ego moves (train.hazard_weights).
    hazard_vehicle_moving_weight: float = 1.0
    # The second head's vehicle target also counts a vehicle this far ahead of the bumper along
    # the ego's heading and turn (hazards.bumper_vehicles; 0: the path's, as the first head's).
    second_bumper_m: float = 0.0
    # With it, the second head's vehicle entries where that car is nearer than the path's weigh this much more.
    second_bumper_weight: float = 1.0
    # Pedestrians count in the path where they will be within this many seconds (hazards.path_hazards).
    hazard_ahead_s: float = 0.0
    accel_quantile: float = 0.5  # the quantile of accel the loss fits: 0.5 is L1 (losses.l1_loss)
    speed_noise: float = 0.0  # σ of the log-normal factor the speed input is trained with (train.noisy_speed)
    train_only: tuple[str, ...] = ()  # the parts trained (BID.parts), the rest frozen; () all (train.freeze_all_but)
    # With train_only CPC from --init: the accel label is the init control head's own (train.KeptAccel).
    keep_accel: bool = False
    # With train_only hazard from --init: the targets of these kinds are the init head's own (train.KeptHazard).
    keep_hazard: bool = False
    keep_hazard_kinds: tuple[str, ...] = ("pedestrian", "vehicle")  # the kinds kept with keep_hazard (KINDS)
    keep_hazard_standing: bool = False  # with keep_hazard, every kind kept on frames of a standing ego
    seed: int = 0
    workers: int = 2
    synthetic_samples: int = 2000  # size of the generated dataset of `--synthetic`

    def with_epochs(self, epochs: int) -> TrainConfig:
        """The same schedule stretched to `epochs` (milestones scale with the paper's 100)."""
        if epochs < 1:
            raise BidError(f"--epochs must be at least 1, got {epochs}")
        return dataclasses.replace(self, epochs=epochs, milestones=scaled_milestones(epochs))


@dataclass(frozen=True)
class RunConfig:
    """A preset: the model and how to train it."""

    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @property
    def preset(self) -> str:
        return self.model.preset

    def to_dict(self) -> dict[str, Any]:
        return {"model": dataclasses.asdict(self.model), "train": dataclasses.asdict(self.train)}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> RunConfig:
        return RunConfig(model=_from_dict(ModelConfig, d["model"]),
                         train=_from_dict(TrainConfig, d["train"]))


def model_config_from_dict(d: dict[str, Any]) -> ModelConfig:
    return _from_dict(ModelConfig, d)


def _from_dict(cls: type, d: dict[str, Any]) -> Any:
    known = {f.name for f in dataclasses.fields(cls)}
    # JSON turns tuples into lists; frozen configs keep tuples so they stay hashable.
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in known})


def scaled_milestones(epochs: int) -> tuple[int, ...]:
    """The paper's lr milestones (25, 45, 70 of 100) scaled to `epochs`, at least epoch 1."""
    return tuple(max(1, round(m * epochs / PAPER_EPOCHS)) for m in PAPER_MILESTONES)


def with_variant(model: ModelConfig, variant: str) -> ModelConfig:
    """`model` switched to one of the paper's ablations (see VARIANTS)."""
    if variant not in VARIANTS:
        raise BidError(f"unknown variant {variant!r}; use one of {', '.join(VARIANTS)}")
    return dataclasses.replace(model, variant=variant, **VARIANTS[variant])


def paper() -> RunConfig:
    """The paper's network: 900×300 input, widths 64/128/256/512, 100 epochs of batch 100."""
    return RunConfig(ModelConfig(), TrainConfig())


def small() -> RunConfig:
    """Trains on a 2-core CPU in tens of minutes on ~20k frames: 64×192 input, narrow widths.

    Each camera becomes 64×64 pixels; widths 16/32/64/128, so the ventral output is a 2×6 grid
    of 128-wide tokens. The expanded 3×3 convolutions of V2, V4 and IT are depthwise and MPC's
    feed-forward is 2× wide (benchmarks/bench_model.py): about 100 samples/s of training on two
    cores, about 12 ms per frame of inference on one. 10 epochs; data loads in the training
    process (workers=0), which leaves both cores to torch.

    Unlike `paper`, it sees the measured speed (accel depends on it, and 64 pixels per camera
    show little of it) and trains on rebalanced data: a quarter of the standing frames, moving-off
    frames three times, twice of them shown standing still (recordings.balance_rows); without
    that it learns to stand still. Half of the rows are shown without motion (frame t−1 =
    frame t, recordings.motion_dropout); without that it steers only while already turning.
    """
    model = ModelConfig(
        preset="small", frame_hw=(64, 192), widths=(16, 32, 64, 128), depthwise=True,
        mt_kernel=3, mpc_ff_mult=2, cpc_hidden=(128, 64), dropout=0.0, speed_input=True,
    )
    return RunConfig(model, TrainConfig(workers=0, stop_keep=0.25, start_repeat=3,
                                        motion_drop=0.5).with_epochs(10))


def tiny() -> RunConfig:
    """For unit tests: 32×96 input, widths 8/8/16/16, a step takes well under a second."""
    model = ModelConfig(
        preset="tiny", frame_hw=(32, 96), widths=(8, 8, 16, 16), mt_kernel=3,
        mt_groups=2, dpc_groups=2, mpc_layers=4, mpc_heads=4, mpc_ff_mult=2,
        cpc_hidden=(16, 16), dropout=0.0,
    )
    train = dataclasses.replace(TrainConfig(batch_size=16, lr=2e-3, workers=0,
                                            synthetic_samples=160), val_fraction=0.2)
    return RunConfig(model, train.with_epochs(10))


def preset(name: str) -> RunConfig:
    """The preset called `name` (paper, small or tiny)."""
    builders = {"paper": paper, "small": small, "tiny": tiny}
    if name not in builders:
        raise BidError(f"unknown preset {name!r}; use one of {', '.join(PRESETS)}")
    return builders[name]()
