"""The BID network ("Brain-inspired driving"): visual cortex → prefrontal cortex → control.

    frame t ──▶ V1 ─▶ V2 ─▶ V4 ─▶ IT ──E_V──▶ VPC ─┐
    frame t−1 ─▶ V1 ─┴──────▶ MT/MST ──E_S──▶ DPC ─┼─▶ MPC ─▶ CPC ─▶ (steer, accel)
    command ─────────────────────────────────▶ OFC ─┘

With `config.forecast_s` a small head beside CPC also forecasts the speed those seconds
ahead from MPC's tokens: an auxiliary training target (`forward(..., forecast=True)`) that
asks the decision network to see a slowdown coming (a corner, a red light, a queue) before
the expert's braking starts; driving never reads it. With `config.hazard` another says how
far ahead the nearest pedestrian and vehicle in the ego's path are, and the stop line of a red
light on its route (bid_model.hazards), also
from MPC's tokens (`forward(..., hazard=True)`): it asks the network to tell a pedestrian in
its path from one beside it. Driving never reads it either. With `config.hazard_sc` SC, a
shallow pathway on frames t and t−1 at the full input size that never sees the speed
(areas.SC), says it too, and the pedestrian's and the vehicle's nearness are the larger of
the two: a person 10 m off is 3 pixels of a 64×192 frame, gone by IT's grid, and the head on
MPC's tokens learnt that at 10 m/s nothing is near (docs/experiments.md). With
`config.sc_fine` a second SC on finer frames, grafted from another checkpoint, adds its
pedestrian (`BID.merge_hazard`).

`BID.forward_features` returns every area's output by name; `forward_head` is CPC. Any area
can be lesioned at inference (`set_lesions`, `lesioned`): its output is replaced by zeros or
by its mean activation, a running mean kept during training.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping

import torch
from torch import nn

from bid_model.areas import CPC, DPC, IT, MPC, MT, OFC, SC, V1, V2, V4, VPC, GridTokens, half
from bid_model.config import PATH_KINDS, ModelConfig
from bid_sim.errors import BidError

AREAS = ("V1", "V2", "V4", "IT", "MT", "VPC", "DPC", "OFC", "MPC", "CPC")
LESION_MODES = ("zero", "mean")
SPEED_SCALE_MPS = 10.0  # speed is fed as speed_mps / 10, about unit scale

# Mean and spread of pixel values (0..1) the network sees after normalisation.
_PIXEL_MEAN, _PIXEL_STD = 0.45, 0.25


def grid_hw(frame_hw: tuple[int, int]) -> dict[str, tuple[int, int]]:
    """(rows, cols) of the feature grid of each perception area for input `frame_hw`."""
    h, w = frame_hw
    grids = {"V1": (half(half(h)), half(half(w)))}
    for name, prev in (("V2", "V1"), ("V4", "V2"), ("IT", "V4")):
        grids[name] = (half(grids[prev][0]), half(grids[prev][1]))
    grids["MT"] = grids["IT"]
    return grids


def hazard_kinds(config: ModelConfig) -> int:
    """How many of bid_model.config.KINDS a model of `config` has its hazard head say (0: none)."""
    return (2 + config.hazard_light + config.hazard_crossing) if config.hazard else 0


class AttendingHazardHead(nn.Module):
    """The hazard head of config.hazard_attend: a learned query per kind attends, with `heads`
    heads, over V2's and V4's feature grids (projected to the token width, with a positional
    embedding each) and MPC's tokens; an MLP reads each kind's pooled vector. A person 10 m off
    is 2–3 pixels of a 64×192 frame: a cell of V2's grid, averaged away in MPC's 26 tokens."""

    def __init__(self, grids: Mapping[str, tuple[int, int, int]], width: int, hidden: int, kinds: int,
                 heads: int = 4):
        super().__init__()
        self.levels = tuple(grids)
        self.project = nn.ModuleDict({name: nn.Linear(ch, width) for name, (ch, _, _) in grids.items()})
        self.position = nn.ParameterDict({name: nn.Parameter(torch.randn(h * w, width) * 0.02)
                                          for name, (_, h, w) in grids.items()})
        self.query = nn.Parameter(torch.randn(kinds, width) * 0.02)
        self.attend = nn.MultiheadAttention(width, heads, batch_first=True)
        self.hidden = nn.Linear(width, hidden)
        self.out_weight = nn.Parameter(torch.zeros(kinds, hidden))
        self.out_bias = nn.Parameter(torch.zeros(kinds))

    def forward(self, features: Mapping[str, torch.Tensor]) -> torch.Tensor:
        tokens = [self.project[name](features[name].flatten(2).transpose(1, 2)) + self.position[name]
                  for name in self.levels]
        tokens = torch.cat([*tokens, features["MPC"]], dim=1)
        query = self.query.to(tokens.dtype).expand(tokens.shape[0], -1, -1)
        pooled, _ = self.attend(query, tokens, tokens, need_weights=False)  # (B, kinds, width)
        h = torch.relu(self.hidden(pooled))
        return (h * self.out_weight).sum(-1) + self.out_bias


class PresenceHazardHead(nn.Sequential):
    """The hazard head of config.head_presence: MPC's mean token → hidden layer → the nearness per
    kind (the plain head's layers, under the same names) and, from the same hidden layer, a logit
    that a pedestrian is in the path at SEEN_NEARNESS or nearer, its last column. Fitted apart
    (train.head_presence_loss), the pedestrian's nearness is how near she is given that she is
    there: an L1 fit on both reads an unsure sighting as far off."""

    def __init__(self, width: int, hidden: int, kinds: int):
        super().__init__(nn.Linear(width, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, kinds))
        self.presence = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self[1](self[0](x))
        return torch.cat([self[2](h), self.presence(h)], dim=1)


def resize_grid_tokens(state: Mapping[str, torch.Tensor], from_hw: tuple[int, int],
                       model: nn.Module) -> dict[str, torch.Tensor]:
    """`state` (of a model with input `from_hw`) with the positional embeddings of its token
    grids (VPC, DPC, the dorsal tokens) resized, bilinearly, to `model`'s IT grid, so a
    network trained at one input size can start one at another (`bid train --init
    --frame-hw`). Every other tensor is passed through as it is."""
    rows, cols = grid_hw(from_hw)["IT"]
    new_rows, new_cols = grid_hw(model.config.frame_hw)["IT"]
    own = model.state_dict()
    out = dict(state)
    for name, module in model.named_modules():
        key = f"{name}.pos_embed" if name else "pos_embed"
        if not isinstance(module, GridTokens) or key not in state or state[key].shape == own[key].shape:
            continue
        src = state[key]
        if src.shape[1] != rows * cols:
            raise BidError(f"{key} holds {src.shape[1]} tokens, not the {rows}×{cols} grid of a "
                           f"{from_hw[0]}×{from_hw[1]} input")
        grid = src.reshape(1, rows, cols, -1).permute(0, 3, 1, 2)
        grid = nn.functional.interpolate(grid, size=(new_rows, new_cols), mode="bilinear",
                                         align_corners=False)
        out[key] = grid.permute(0, 2, 3, 1).reshape(1, new_rows * new_cols, -1).contiguous()
    return out


class BID(nn.Module):
    """The whole network; which streams exist follows `config` (the paper's variants)."""

    def __init__(self, config: ModelConfig):
        """Build the areas of `config`'s variant; widths, input size and steps come from it."""
        super().__init__()
        self.config = c = config
        w, d = c.widths, c.width
        areas: dict[str, nn.Module] = {
            "V1": V1(w[0]),
            "V2": V2(w[0], w[1], c.times[0], c.expansion, c.depthwise),
            "V4": V4(w[1], w[2], c.times[1], c.expansion, c.depthwise),
            "IT": IT(w[2], w[3], c.times[2], c.expansion, c.depthwise),
        }
        n_tokens = self.grid_hw()["IT"][0] * self.grid_hw()["IT"][1]
        if c.dorsal:
            areas["MT"] = MT(w, c.mt_kernel, c.mt_groups)
        areas["VPC"] = VPC(n_tokens, d)
        if c.relations:
            areas["DPC"] = DPC(d, n_tokens, c.dpc_kernel, c.dpc_groups)
        if c.navigation:
            areas["OFC"] = OFC(c.n_commands, d)
        areas["MPC"] = MPC(d, c.mpc_layers, c.mpc_heads, c.mpc_ff_mult, c.dropout)
        areas["CPC"] = CPC(d, c.cpc_hidden)
        self.areas = nn.ModuleDict(areas)
        # The direct MT → MPC pathway of the +dorsal variants without DPC.
        self.dorsal_tokens = GridTokens(n_tokens, d) if c.dorsal and not c.relations else None
        # Measured speed as an extra token: an option, not part of the paper's model.
        self.speed_token = nn.Linear(1, d) if c.speed_input else None
        # Auxiliary speed forecast, in units of SPEED_SCALE_MPS; not an area (no lesions).
        self.forecast_head = (nn.Sequential(nn.Linear(d, c.cpc_hidden[1]), nn.ReLU(inplace=True),
                                            nn.Linear(c.cpc_hidden[1], len(c.forecast_s)))
                              if c.forecast_s else None)
        # Auxiliary hazard head: (pedestrian, vehicle[, red light]) nearness in the path, 1 −
        # distance / HAZARD_AHEAD_M (0: none within it); not an area (no lesions).
        # With config.hazard_attend it attends over V2's and V4's grids as well (AttendingHazardHead).
        # With config.head_presence it says also whether a pedestrian is in the path (PresenceHazardHead).
        self.hazard_head = self._new_hazard_head(c.head_presence) if c.hazard else None
        # With config.hazard_sc SC says it too, from the frames alone: forward_hazard reads the nearer.
        self.hazard_sc = (SC(c.scaled_hw(c.sc_scale), c.n_commands, len(PATH_KINDS), presence=c.sc_presence)
                          if c.hazard_sc else None)
        # With config.sc_fine a second SC, with presence, on frames sc_fine times finer: its
        # pedestrian joins the merge (merge_hazard).
        self.hazard_sc_fine = (SC(c.scaled_hw(c.sc_fine), c.n_commands, len(PATH_KINDS), presence=True)
                               if c.sc_fine else None)
        # With config.hazard_crossing a second SC map of its own, one kind: how near the next crossing
        # on the path with a pedestrian on it is (the fourth hazard output; warm_start_crossing).
        self.hazard_crossing = SC(c.scaled_hw(c.sc_scale), c.n_commands, 1) if c.hazard_crossing else None
        # With config.move_off_head a second hazard head, alike, reading MPC without the speed token
        # (with config.move_off_speed with it).
        self.hazard_move_off = self._new_hazard_head() if c.move_off_head else None

        for name, shape in self.output_shapes().items():
            self.register_buffer(f"mean_{name}", torch.zeros(shape), persistent=True)
        self.register_buffer("mean_batches", torch.zeros((), dtype=torch.long))
        self.lesions: dict[str, str] = {}

    def _new_hazard_head(self, presence: bool = False) -> nn.Module:
        """A hazard head: MPC's mean token (with config.hazard_attend all its tokens and V2's
        and V4's grids, AttendingHazardHead) → (pedestrian, vehicle[, red light]) nearness; with
        `presence` then the pedestrian's presence logit (PresenceHazardHead)."""
        c, d = self.config, self.config.width
        if presence:
            return PresenceHazardHead(d, c.cpc_hidden[1], 2 + c.hazard_light)
        if c.hazard_attend:
            grids = {name: (c.widths[i], *self.grid_hw()[name]) for i, name in ((1, "V2"), (2, "V4"))}
            return AttendingHazardHead(grids, d, c.cpc_hidden[1], 2 + c.hazard_light)
        return nn.Sequential(nn.Linear(d, c.cpc_hidden[1]), nn.ReLU(inplace=True),
                             nn.Linear(c.cpc_hidden[1], 2 + c.hazard_light))

    # --- shapes ---------------------------------------------------------------------------

    def hazard_kinds(self) -> int:
        """How many of bid_model.config.KINDS the hazard head says (0: no head)."""
        return hazard_kinds(self.config)

    def head_columns(self) -> int:
        """The hazard head's columns in forward_hazard(apart=True): its kinds' nearness, then with
        config.head_presence the pedestrian's presence logit."""
        return 2 + int(self.config.hazard_light) + int(self.config.head_presence)

    def gate_head(self, head: torch.Tensor) -> torch.Tensor:
        """The hazard head's columns (head_columns) as driving reads them: with config.head_presence
        the pedestrian's nearness only where its logit says she is in the path, else 0."""
        if not self.config.head_presence:
            return head
        n = self.head_columns() - 1  # the logit's column, after the kinds' nearness
        pedestrian = torch.where(head[:, n] > 0, head[:, 0], torch.zeros_like(head[:, 0]))
        return torch.cat([pedestrian[:, None], head[:, 1:n]], dim=1)

    def grid_hw(self) -> dict[str, tuple[int, int]]:
        """(rows, cols) of the feature grid of each perception area."""
        return grid_hw(self.config.frame_hw)

    def output_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-sample output shape of each area present in this variant."""
        g, w, d = self.grid_hw(), self.config.widths, self.config.width
        n = g["IT"][0] * g["IT"][1]
        n_all = n * (1 + self.config.dorsal) + self.config.navigation + self.config.speed_input
        shapes = {"V1": (w[0], *g["V1"]), "V2": (w[1], *g["V2"]), "V4": (w[2], *g["V4"]),
                  "IT": (d, *g["IT"]), "MT": (d, *g["MT"]), "VPC": (n, d), "DPC": (n, d),
                  "OFC": (1, d), "MPC": (n_all, d), "CPC": (2,)}
        return {name: shapes[name] for name in AREAS if name in self.areas}

    # --- lesions --------------------------------------------------------------------------

    def set_lesions(self, lesions: Mapping[str, str]) -> None:
        """Switch areas off from now on: {"IT": "zero", "MT": "mean", ...}; {} restores all."""
        for name, mode in lesions.items():
            if name not in self.areas:
                raise BidError(f"cannot lesion {name!r}: this {self.config.variant} model has "
                               f"areas {', '.join(self.areas)}")
            if mode not in LESION_MODES:
                raise BidError(f"lesion mode {mode!r} for {name}; use 'zero' or 'mean'")
        self.lesions = dict(lesions)

    def _area(self, name: str, *inputs: torch.Tensor | dict) -> torch.Tensor:
        """Run area `name`; apply its lesion, or (training) update its mean activation."""
        out = self.areas[name](*inputs)
        mode = self.lesions.get(name)
        mean: torch.Tensor = getattr(self, f"mean_{name}")
        if mode == "zero":
            return torch.zeros_like(out)
        if mode == "mean":
            return mean.to(out.dtype).expand_as(out).clone()
        if self.areas[name].training:  # not while frozen (bid train --train-only)
            with torch.no_grad():
                # Cumulative average at first, then an exponential one that follows training. The
                # weight stays a tensor: reading mean_batches on the host would make every area of
                # a GPU step wait for the GPU to finish the areas before it.
                m = (self.mean_batches + 1).reciprocal().clamp(min=self.config.lesion_momentum)
                mean.mul_(1 - m).add_(out.detach().mean(0, dtype=torch.float32) * m)
        return out

    # --- forward --------------------------------------------------------------------------

    def check_inputs(self, frame_t: torch.Tensor, frame_prev: torch.Tensor,
                     command_onehot: torch.Tensor, speed_mps: torch.Tensor | None) -> None:
        """Raise BidError naming the problem if the inputs do not fit this model."""
        c = self.config
        hw = c.input_hw
        for name, x in (("frame_t", frame_t), ("frame_prev", frame_prev)):
            if x.ndim != 4 or x.shape[1] != 3 or tuple(x.shape[2:]) != hw:
                raise BidError(f"{name} has shape {tuple(x.shape)} but the {c.preset!r} preset "
                               f"expects (batch, 3, {hw[0]}, {hw[1]}); resize frames with "
                               "bid_model.data.prepare_frame")
        if frame_prev.shape[0] != frame_t.shape[0]:
            raise BidError(f"frame_prev has batch {frame_prev.shape[0]}, frame_t {frame_t.shape[0]}")
        if tuple(command_onehot.shape) != (frame_t.shape[0], c.n_commands):
            raise BidError(f"command must be a one-hot of shape (batch, {c.n_commands}), got "
                           f"{tuple(command_onehot.shape)}; build it with "
                           "bid_model.data.command_one_hot")
        if c.speed_input and (speed_mps is None or speed_mps.numel() != frame_t.shape[0]):
            raise BidError("this model takes the measured speed as input: pass speed_mps (batch,)")

    @staticmethod
    def _normalise(frame: torch.Tensor) -> torch.Tensor:
        """uint8 RGB (0..255), or float already in 0..1, to the network's input scale."""
        x = frame.float() / 255.0 if frame.dtype == torch.uint8 else frame.float()
        return (x - _PIXEL_MEAN) / _PIXEL_STD

    def forward_features(self, frame_t: torch.Tensor, frame_prev: torch.Tensor,
                         command_onehot: torch.Tensor,
                         speed_mps: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Every area's output by name (V1's for frame t), up to MPC's tokens."""
        self.check_inputs(frame_t, frame_prev, command_onehot, speed_mps)
        c, b = self.config, frame_t.shape[0]
        feats: dict[str, torch.Tensor] = {}
        seen_t, seen_prev = self._normalise(frame_t), self._normalise(frame_prev)

        def at_scale(scale: int) -> tuple[torch.Tensor, torch.Tensor]:
            """Frames t and t−1 area-averaged down to frame_hw × scale."""
            down = c.input_scale // scale
            if down == 1:
                return seen_t, seen_prev
            return nn.functional.avg_pool2d(seen_t, down), nn.functional.avg_pool2d(seen_prev, down)

        cortex_t, cortex_prev = at_scale(1)  # what the cortex read before any SC read finer frames
        if c.dorsal:  # one V1 pass over both frames
            v1_both = self._area("V1", torch.cat([cortex_t, cortex_prev]))
            feats["V1"], v1_prev = v1_both.split(b)
        else:
            feats["V1"] = self._area("V1", cortex_t)
        feats["V2"] = self._area("V2", feats["V1"])
        feats["V4"] = self._area("V4", feats["V2"])
        feats["IT"] = self._area("IT", feats["V4"])
        streams = {"ventral": self._area("VPC", feats["IT"])}
        feats["VPC"] = streams["ventral"]
        if c.dorsal:
            feats["MT"] = self._area("MT", feats["V1"], v1_prev)
            if c.relations:
                feats["DPC"] = streams["dorsal"] = self._area("DPC", feats["MT"], feats["IT"])
            else:
                streams["dorsal"] = self.dorsal_tokens(feats["MT"])
        if c.navigation:
            feats["OFC"] = streams["navigation"] = self._area("OFC", command_onehot.float())
        if self.speed_token is not None:
            speed = speed_mps.reshape(b, 1, 1).float() / SPEED_SCALE_MPS
            streams["speed"] = self.speed_token(speed)
        feats["MPC"] = self._area("MPC", streams)
        if c.hazard_speedless or (c.move_off_head and not c.move_off_speed):  # for a hazard head alone
            feats["MPC_speedless"] = self._speedless_mpc({k: v for k, v in streams.items() if k != "speed"})
        if self.hazard_sc is not None:
            sc_t, sc_prev = at_scale(c.sc_scale)
            feats["SC"] = self.hazard_sc(sc_t, sc_t if c.sc_still else sc_prev, command_onehot.float())
            if self.hazard_crossing is not None:
                feats["crossing"] = self.hazard_crossing(sc_t, sc_prev, command_onehot.float())
        if self.hazard_sc_fine is not None:
            feats["SC_fine"] = self.hazard_sc_fine(*at_scale(c.sc_fine), command_onehot.float())
        if self.training:
            self.mean_batches += 1
        return feats

    def _speedless_mpc(self, streams: dict[str, torch.Tensor]) -> torch.Tensor:
        """MPC's tokens merged from the streams without the speed token (config.hazard_speedless),
        under MPC's lesion: zeros, or MPC's mean token in place of every token. It leaves MPC's
        mean activation alone (that is of the tokens with the speed)."""
        out = self.areas["MPC"](streams)
        mode = self.lesions.get("MPC")
        if mode == "zero":
            return torch.zeros_like(out)
        if mode == "mean":
            return self.mean_MPC.mean(0).to(out.dtype).expand_as(out).clone()
        return out

    def forward_head(self, features: dict[str, torch.Tensor]) -> torch.Tensor:
        """CPC: MPC's tokens → (batch, 2) = (steer, accel), each in [−1, 1]."""
        return self._area("CPC", features["MPC"])

    def forward_forecast(self, features: dict[str, torch.Tensor]) -> torch.Tensor:
        """(batch, len(forecast_s)): the speed forecast, m/s, from MPC's tokens."""
        if self.forecast_head is None:
            raise BidError("this model has no speed forecast; train it with --forecast")
        return self.forecast_head(features["MPC"].mean(dim=1)) * SPEED_SCALE_MPS

    def forward_hazard(self, features: dict[str, torch.Tensor], apart: bool = False,
                       move_off: bool = False, speed_mps: torch.Tensor | None = None) -> torch.Tensor:
        """(batch, hazard_kinds()): nearness of the nearest (pedestrian, vehicle) in the path and,
        with config.hazard_light, of a red light's stop line, from MPC's tokens (and with
        config.hazard_attend from V2's and V4's grids too; with config.hazard_sc the
        pedestrian's and the vehicle's are the larger of the head's and SC's, SC's with
        config.sc_presence only where its logit says one is in the path; with `apart` the head's
        outputs then SC's, (batch, hazard_kinds() + 2), with config.sc_presence + 4 (SC's nearness,
        then its logits), so that training fits each alone, and with config.sc_fine the fine SC's
        four after them; merged, its pedestrian with config.fine_moving only where `speed_mps`
        is config.fine_speed or more: merge_hazard); with config.hazard_crossing the last
        column is how near an occupied crossing is (its own SC map's), both ways. With
        config.head_presence the head's pedestrian counts only where its presence logit says she
        is in the path (gate_head); `apart` gives the logit after the head's nearness. `move_off`:
        the same from the second head (config.move_off_head), which reads MPC without the speed
        (config.move_off_speed: with it)."""
        if self.hazard_head is None:
            raise BidError("this model has no hazard head; train it with --hazard")
        if move_off and self.hazard_move_off is None:
            raise BidError("this model has no move-off head; train one with --move-off-head")
        head = self.hazard_move_off if move_off else self.hazard_head
        speedless = not self.config.move_off_speed if move_off else self.config.hazard_speedless
        mpc = features["MPC_speedless"] if speedless else features["MPC"]
        if self.config.hazard_attend:
            near = head({**features, "MPC": mpc})
        else:
            near = head(mpc.mean(dim=1))
        if self.hazard_sc is None:  # head_presence needs SC: nothing to gate here
            return near
        # what either sees in the path
        sc = [features[name].to(near.dtype) for name in ("SC", "SC_fine", "crossing") if name in features]
        near = torch.cat([near, *sc], dim=1)
        return near if apart else self.merge_hazard(near, speed_mps)

    def sc_columns(self, apart: torch.Tensor, fine: bool = False) -> torch.Tensor:
        """SC's own columns out of forward_hazard(apart=True)'s (a model with SC): its (pedestrian,
        vehicle) nearness, then with config.sc_presence their logits; `fine`: the fine SC's
        (config.sc_fine), nearness then logits, after them."""
        k = len(PATH_KINDS)
        start, width = self.head_columns(), k * (2 if self.config.sc_presence else 1)
        if fine:
            start, width = start + width, 2 * k if self.config.sc_fine else 0
        return apart[:, start:start + width]

    def sc_near(self, apart: torch.Tensor, fine: bool = False) -> torch.Tensor:
        """(batch, 2): SC's own (pedestrian, vehicle) nearness out of forward_hazard(apart=True)'s
        columns (a model with SC; `fine`: the fine SC's); with presence logits only where the
        kind's says one is in the path (above 0; the pedestrian above config.sc_logit, the fine
        SC's above config.fine_logit), else 0."""
        k = len(PATH_KINDS)
        sc = self.sc_columns(apart, fine)
        if fine or self.config.sc_presence:
            at = torch.zeros(k, dtype=sc.dtype, device=sc.device)
            at[PATH_KINDS.index("pedestrian")] = self.config.fine_logit if fine else self.config.sc_logit
            sc = torch.where(sc[:, k:] > at, sc[:, :k], torch.zeros_like(sc[:, :k]))
        return sc

    def merge_hazard(self, apart: torch.Tensor, speed_mps: torch.Tensor | None = None,
                     fine: bool = True) -> torch.Tensor:
        """forward_hazard(apart=True)'s columns (a model with SC) as forward_hazard gives them: the
        pedestrian's and the vehicle's nearness the larger of the head's and SC's (sc_near), with
        config.sc_fine the pedestrian's also of the fine SC's (with config.fine_moving only where
        `speed_mps`, (batch,), is config.fine_speed or more), then the head's others, then the crossing
        map's; the head's pedestrian with config.head_presence only where it says she is in the
        path (gate_head). `fine` False leaves the fine SC out (fine_near reads it apart)."""
        k, n = len(PATH_KINDS), self.head_columns()
        crossing = apart[:, n + self.sc_columns(apart).shape[1] + self.sc_columns(apart, fine=True).shape[1]:]
        head = self.gate_head(apart[:, :n])
        near = torch.maximum(head[:, :k], self.sc_near(apart))
        if self.config.sc_fine and fine:
            at = PATH_KINDS.index("pedestrian")
            near = near.clone()
            near[:, at] = torch.maximum(near[:, at], self.fine_near(apart, speed_mps))
        return torch.cat([near, head[:, k:], crossing], dim=1)

    def fine_near(self, apart: torch.Tensor, speed_mps: torch.Tensor | None = None) -> torch.Tensor:
        """(batch,): the fine SC's pedestrian nearness out of forward_hazard(apart=True)'s columns
        (config.sc_fine), gated by its logit (sc_near) and, with config.fine_moving, 0 where
        `speed_mps` (batch,) is below config.fine_speed: what merge_hazard merges."""
        fine = self.sc_near(apart, fine=True)[:, PATH_KINDS.index("pedestrian")]
        if self.config.fine_moving:
            if speed_mps is None:
                raise BidError("this model reads its fine SC only while the ego moves: pass speed_mps")
            moving = speed_mps.reshape(-1).to(fine.device) >= self.config.fine_speed
            fine = torch.where(moving, fine, torch.zeros_like(fine))
        return fine

    def forward(self, frame_t: torch.Tensor, frame_prev: torch.Tensor,
                command_onehot: torch.Tensor, speed_mps: torch.Tensor | None = None,
                forecast: bool = False, hazard: bool = False,
                hazard_apart: bool = False, move_off: bool = False) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """(steer, accel) for a batch: frames (B, 3, rows, cols) uint8, command one-hot (B, 6), the
        measured speed (B,) m/s (read with config.speed_input, and by the merge with config.sc_fine);
        with `forecast`, `hazard` and/or `move_off`, ((steer, accel), then the forecast speeds (B,
        len(forecast_s)) in m/s, then the hazard nearness (B, hazard_kinds()), then the move-off
        head's, those asked for, in that order; `hazard_apart`: forward_hazard(apart=True), both heads)."""
        feats = self.forward_features(frame_t, frame_prev, command_onehot, speed_mps)
        control = self.forward_head(feats)
        extra = (([self.forward_forecast(feats)] if forecast else [])
                 + ([self.forward_hazard(feats, apart=hazard_apart, speed_mps=speed_mps)] if hazard else [])
                 + ([self.forward_hazard(feats, apart=hazard_apart, move_off=True, speed_mps=speed_mps)]
                    if move_off else []))
        return (control, *extra) if extra else control

    def parts(self) -> dict[str, nn.Module]:
        """Every area by name, then the optional extra pathways this model has: dorsal_tokens,
        speed, forecast, hazard, SC, SC_fine, crossing, move_off (the names of parameter_counts and
        `bid train --train-only`)."""
        extra = (("dorsal_tokens", self.dorsal_tokens), ("speed", self.speed_token),
                 ("forecast", self.forecast_head), ("hazard", self.hazard_head), ("SC", self.hazard_sc),
                 ("SC_fine", self.hazard_sc_fine),
                 ("crossing", self.hazard_crossing), ("move_off", self.hazard_move_off))
        return {**self.areas, **{name: module for name, module in extra if module is not None}}

    def parameter_counts(self) -> dict[str, int]:
        """Number of parameters of each area (and of the optional extra pathways)."""
        return {name: sum(p.numel() for p in part.parameters()) for name, part in self.parts().items()}


def compile_each_area(model: BID) -> None:
    """torch.compile every area in place, for fixed shapes. Compiling the whole BID instead
    recompiles per area (`BID._area` dispatches by name) and stops at dynamo's recompile limit;
    per area, the paper preset's step ran 1.49× faster than eager channels-last on an H200
    (555 against 372 samples/s at batch 100, benchmarks/bench_model.py --gpu-only, 2026-12-04).
    V2, V4 and IT share RecurrentArea's code: with torch's default (dynamic=None) the second
    area's shapes recompiled it for symbolic sizes, which ran at 512 samples/s and took minutes
    to compile; with dynamic=False each area has its own static graph (about 40 s in all)."""
    # A graph per area, batch size and mode: V2, V4 and IT share one code object, and a training
    # run meets the full and the last batch, training and evaluating (12 graphs; the limit is 8).
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 32)
    for area in model.areas.values():
        area.compile(dynamic=False)


@contextlib.contextmanager
def lesioned(model: BID, lesions: Mapping[str, str]) -> Iterator[BID]:
    """`with lesioned(model, {"IT": "mean"}):` the model with those areas switched off."""
    before = dict(model.lesions)
    model.set_lesions({**before, **lesions})
    try:
        yield model
    finally:
        model.lesions = before
