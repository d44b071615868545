"""The brain areas of the BID network ("Brain-inspired driving"), one `nn.Module` each.

Perception (visual cortex): V1 → ventral stream V2 → V4 → IT (CORnet-S-style recurrent
areas, appearance embedding E_V) and dorsal stream MT/MST (dynamic filters on motion, motion
embedding E_S). Decision (prefrontal cortex): VPC, DPC, OFC merged by MPC, read out by CPC.
Beside the cortex, optionally, SC (superior colliculus): pedestrians and vehicles in the path.
Grids are (batch, channels, rows, cols); token sequences are (batch, tokens, width).
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import nn


def conv_bn_relu(c_in: int, c_out: int, kernel: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, kernel, stride, kernel // 2, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


def half(n: int) -> int:
    """Grid size after one stride-2 stage (3×3 or 7×7 conv, or 3×3 max pool, 'same' padding)."""
    return (n + 1) // 2


class _DynamicFilter(torch.autograd.Function):
    """Position-specific filtering with a hand-written backward.

    Autograd through k·k slices of a padded tensor allocates a padded-size gradient per slice;
    accumulating into one buffer instead makes forward + backward about 3× faster on CPU and
    keeps memory at two copies of the input.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, filters: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        groups, kk = filters.shape[1], filters.shape[2]
        k = round(kk**0.5)
        pad = k // 2
        ctx.k, ctx.filter_dtype = k, filters.dtype
        filters = filters.to(x.dtype)  # bf16 features with fp32 softmax kernels under autocast
        xp = F.pad(x, (pad, pad, pad, pad)).reshape(b, groups, c // groups, h + 2 * pad,
                                                    w + 2 * pad)
        out = x.new_zeros(b, groups, c // groups, h, w)
        for j in range(kk):
            dy, dx = divmod(j, k)
            out.addcmul_(xp[..., dy:dy + h, dx:dx + w], filters[:, :, j:j + 1])
        ctx.save_for_backward(xp, filters)
        return out.reshape(b, c, h, w)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        xp, filters = ctx.saved_tensors
        k = ctx.k
        pad = k // 2
        b, groups, per_group, hp, wp = xp.shape
        h, w = hp - 2 * pad, wp - 2 * pad
        grad = grad.reshape(b, groups, per_group, h, w).to(xp.dtype)
        grad_xp = torch.zeros_like(xp) if ctx.needs_input_grad[0] else None
        grad_f = torch.empty_like(filters) if ctx.needs_input_grad[1] else None
        for j in range(k * k):
            dy, dx = divmod(j, k)
            if grad_xp is not None:
                grad_xp[..., dy:dy + h, dx:dx + w].addcmul_(grad, filters[:, :, j:j + 1])
            if grad_f is not None:
                grad_f[:, :, j] = (grad * xp[..., dy:dy + h, dx:dx + w]).sum(2)
        grad_x = None
        if grad_xp is not None:
            grad_x = grad_xp[..., pad:pad + h, pad:pad + w].reshape(b, groups * per_group, h, w)
        return grad_x, None if grad_f is None else grad_f.to(ctx.filter_dtype)


def dynamic_filter(x: torch.Tensor, filters: torch.Tensor) -> torch.Tensor:
    """Position-specific filtering: each output pixel uses its own k×k kernel.

    x (B, C, H, W); filters (B, G, k·k, H, W), one kernel per position and channel group
    (C divisible by G): out[b, c, y, x] = Σ_j filters[b, group(c), j, y, x] · x[b, c, (y, x) + offset_j].
    """
    return _DynamicFilter.apply(x, filters)


class FilterGenerator(nn.Module):
    """Kernels for `dynamic_filter` from a feature grid: (B, C, H, W) → (B, G, k·k, H, W)."""

    def __init__(self, channels: int, groups: int, kernel: int):
        super().__init__()
        self.groups, self.kernel = groups, kernel
        self.net = nn.Sequential(conv_bn_relu(channels, channels, 3),
                                 nn.Conv2d(channels, groups * kernel * kernel, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        logits = self.net(x).reshape(b, self.groups, self.kernel**2, h, w)
        # Softmax over the taps: each kernel is a weighting of the neighbourhood, which keeps
        # the filtered response on the scale of its input whatever the generator outputs.
        return logits.softmax(dim=2)


class GridTokens(nn.Module):
    """A feature grid flattened to tokens, plus a learned 1-D positional embedding."""

    def __init__(self, n_tokens: int, width: int):
        super().__init__()
        self.pos_embed = nn.Parameter(torch.randn(1, n_tokens, width) * 0.02)

    def forward(self, grid: torch.Tensor) -> torch.Tensor:
        return grid.flatten(2).transpose(1, 2) + self.pos_embed


# --- perception ---------------------------------------------------------------------------


class V1(nn.Module):
    """Primary visual cortex: local edges and colour, 7×7 conv (stride 2), pool, 3×3 conv."""

    def __init__(self, width: int):
        super().__init__()
        self.conv1 = conv_bn_relu(3, width, 7, stride=2)
        self.pool = nn.MaxPool2d(3, 2, 1)
        self.conv2 = conv_bn_relu(width, width, 3)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.pool(self.conv1(image)))


class Bottleneck(nn.Module):
    """One recurrent step of a ventral area: 1×1 → 3×3 (expanded) → 1×1.

    The convolutions are shared by all steps; the norms are not (one set per step). Only the
    first step downsamples. Called once per step, so a forward hook counts the steps.
    """

    def __init__(self, width: int, expansion: int, times: int, depthwise: bool):
        super().__init__()
        inner = width * expansion
        self.groups = inner if depthwise else 1
        self.conv1 = nn.Conv2d(width, inner, 1, bias=False)
        self.conv2 = nn.Conv2d(inner, inner, 3, padding=1, groups=self.groups, bias=False)
        self.conv3 = nn.Conv2d(inner, width, 1, bias=False)
        self.norms = nn.ModuleList(
            nn.ModuleList([nn.BatchNorm2d(inner), nn.BatchNorm2d(inner), nn.BatchNorm2d(width)])
            for _ in range(times)
        )

    def forward(self, x: torch.Tensor, step: int) -> torch.Tensor:
        n1, n2, n3 = self.norms[step]
        x = F.relu(n1(self.conv1(x)), inplace=True)
        # The shared 3×3 weights run at stride 2 on the first step only.
        x = F.conv2d(x, self.conv2.weight, None, 2 if step == 0 else 1, 1, 1, self.groups)
        x = F.relu(n2(x), inplace=True)
        return n3(self.conv3(x))


class RecurrentArea(nn.Module):
    """CORnet-S area: input 1×1 conv, then `times` bottleneck steps fed back into the area."""

    def __init__(self, c_in: int, c_out: int, times: int, expansion: int, depthwise: bool):
        super().__init__()
        self.times = times
        self.conv_input = nn.Conv2d(c_in, c_out, 1, bias=False)
        self.skip = nn.Conv2d(c_out, c_out, 1, stride=2, bias=False)
        self.skip_norm = nn.BatchNorm2d(c_out)
        self.bottleneck = Bottleneck(c_out, expansion, times, depthwise)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv_input(x)
        for step in range(self.times):
            skip = self.skip_norm(self.skip(x)) if step == 0 else x
            x = F.relu(self.bottleneck(x, step) + skip, inplace=True)
        return x


class V2(RecurrentArea):
    """Secondary visual cortex: contours and textures, recurrent (2 steps in the paper)."""


class V4(RecurrentArea):
    """Visual area V4: shapes and object parts, recurrent (4 steps in the paper)."""


class IT(RecurrentArea):
    """Inferior temporal cortex: objects, recurrent (2 steps); its grid is E_V."""


class MT(nn.Module):
    """MT/MST, the dorsal stream: motion of frame t−1 → t filtered by kernels generated from
    frame t's appearance, then pooled to the IT grid as the motion embedding E_S."""

    def __init__(self, widths: tuple[int, int, int, int], kernel: int, groups: int):
        super().__init__()
        self.generate = FilterGenerator(widths[0], groups, kernel)
        # MST: larger receptive fields, down to the IT grid so E_S and E_V align.
        self.mst = nn.Sequential(*(conv_bn_relu(a, b, 3, stride=2)
                                   for a, b in itertools.pairwise(widths)))

    def forward(self, v1_now: torch.Tensor, v1_prev: torch.Tensor) -> torch.Tensor:
        motion = v1_now - v1_prev
        return self.mst(dynamic_filter(motion, self.generate(v1_now)))


# --- decision ------------------------------------------------------------------------------


class VPC(GridTokens):
    """Ventrolateral prefrontal cortex: E_V as tokens with a 1-D positional embedding."""


class DPC(nn.Module):
    """Dorsolateral prefrontal cortex: relates the moving foreground (E_S) to the scene
    around it (E_V) with filters generated from the motion; one token per grid cell."""

    def __init__(self, width: int, n_tokens: int, kernel: int, groups: int):
        super().__init__()
        self.generate = FilterGenerator(width, groups, kernel)
        self.merge = nn.Conv2d(2 * width, width, 1)
        self.tokens = GridTokens(n_tokens, width)

    def forward(self, motion: torch.Tensor, appearance: torch.Tensor) -> torch.Tensor:
        context = dynamic_filter(appearance, self.generate(motion))
        return self.tokens(self.merge(torch.cat([motion, context], dim=1)))


class OFC(nn.Module):
    """Orbitofrontal cortex: the navigation command (one-hot) as one token E_N."""

    def __init__(self, n_commands: int, width: int):
        super().__init__()
        self.fc = nn.Linear(n_commands, width)

    def forward(self, command_onehot: torch.Tensor) -> torch.Tensor:
        return self.fc(command_onehot).unsqueeze(1)


class MPC(nn.Module):
    """Medial prefrontal cortex: a transformer encoder merging the streams' tokens."""

    STREAMS = ("ventral", "dorsal", "navigation", "speed")

    def __init__(self, width: int, layers: int, heads: int, ff_mult: int, dropout: float):
        super().__init__()
        self.stream_embed = nn.Parameter(torch.randn(len(self.STREAMS), width) * 0.02)
        layer = nn.TransformerEncoderLayer(width, heads, ff_mult * width, dropout,
                                           activation="gelu", batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(width)

    def forward(self, streams: dict[str, torch.Tensor]) -> torch.Tensor:
        tokens = torch.cat([t + self.stream_embed[self.STREAMS.index(name)]
                            for name, t in streams.items()], dim=1)
        return self.norm(self.encoder(tokens))


class CPC(nn.Module):
    """Caudal prefrontal cortex: token average → 3 FC → (steer, accel), tanh-bounded to [−1, 1]."""

    def __init__(self, width: int, hidden: tuple[int, int]):
        super().__init__()
        self.head = nn.Sequential(nn.Linear(width, hidden[0]), nn.ReLU(inplace=True),
                                  nn.Linear(hidden[0], hidden[1]), nn.ReLU(inplace=True),
                                  nn.Linear(hidden[1], 2))

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.head(tokens.mean(dim=1)))


class SC(nn.Module):
    """Superior colliculus: a shallow, full-resolution retinal pathway beside the cortex; a
    priority map per kind of frame t and its change since t−1, read at its peak: how near a
    pedestrian and a vehicle in the path are (with ModelConfig.hazard_sc the hazard head's first
    two outputs are the nearer of its own and these). It never sees the speed, so it cannot read
    "fast, so nothing near". With `presence`, a second map per kind says whether one is in the
    path there (a logit), and the nearness is read where that map peaks."""

    def __init__(self, frame_hw: tuple[int, int], n_commands: int, kinds: int = 2,
                 widths: tuple[int, int, int] = (16, 32, 64), presence: bool = False):
        super().__init__()
        a, b, c = widths
        self.kinds, self.presence = kinds, presence
        # 5×5 stride 2, then two stride-2 stages each with a 3×3 after: an eighth of the input,
        # a grid cell of 8×8 pixels (a person 10 m off is 3 pixels wide in a 64×192 frame).
        self.retina = nn.Sequential(
            conv_bn_relu(6, a, 5, 2),
            conv_bn_relu(a, b, 3, 2), conv_bn_relu(b, b, 3),
            conv_bn_relu(b, c, 3, 2), conv_bn_relu(c, c, 3),
        )
        rows, cols = half(half(half(frame_hw[0]))), half(half(half(frame_hw[1])))
        self.position = nn.Parameter(torch.zeros(1, c, rows, cols))
        self.command = nn.Linear(n_commands, c)  # where the path goes depends on the command
        maps = kinds * (2 if presence else 1)
        self.priority = nn.Sequential(nn.Conv2d(c, c, 1), nn.ReLU(inplace=True), nn.Conv2d(c, maps, 1))

    def priority_map(self, frame_t: torch.Tensor, frame_prev: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """(B, kinds, rows, cols): the nearness each cell of the grid reads (normalised frames in);
        with `presence` (B, 2·kinds, rows, cols): the nearness maps, then the presence logits'."""
        x = self.retina(torch.cat([frame_t, frame_t - frame_prev], dim=1))
        x = torch.relu(x + self.position + self.command(command)[:, :, None, None])
        return self.priority(x)

    def forward(self, frame_t: torch.Tensor, frame_prev: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """(B, kinds): each priority map's peak; with `presence` (B, 2·kinds): the nearness read
        where each kind's presence map peaks, then that peak, the logit that one is in the path."""
        maps = self.priority_map(frame_t, frame_prev, command).flatten(2)
        if not self.presence:
            return maps.amax(dim=2)
        near, logit = maps[:, :self.kinds], maps[:, self.kinds:]
        peak, where = logit.max(dim=2, keepdim=True)
        return torch.cat([near.gather(2, where).squeeze(2), peak.squeeze(2)], dim=1)
