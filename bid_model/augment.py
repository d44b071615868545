"""Photometric augmentation of training frames (`bid train --augment SHARE`).

The BID trains on four weathers and is tested on two others. On the same 25 Town02 routes
without traffic the DAgger-round-3 `small` BID succeeded on 64 % under ClearSunset but 12 % under
WetSunset, which differs from it by a darker, shinier road: lane keeping hangs on the exact
brightness and colour of road and kerb. A share of the training samples therefore gets a
random change of brightness, contrast, saturation and colour balance. Frame t and frame t−1
of a sample get the same change, so the motion between them is what it was.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# Ranges of the per-sample factors (1 leaves the frame as it is).
BRIGHTNESS = (0.65, 1.35)
CONTRAST = (0.65, 1.35)
SATURATION = (0.5, 1.5)
CHANNEL_GAIN = (0.85, 1.15)  # per RGB channel: noon's blue-white vs sunset's orange light
_GREY = (0.299, 0.587, 0.114)  # ITU-R 601 luma weights


def _uniform(n: int, bounds: tuple[float, float], device: torch.device,
             generator: torch.Generator | None, channels: int = 1) -> torch.Tensor:
    lo, hi = bounds
    u = torch.rand((n, channels, 1, 1), generator=generator).to(device)
    return lo + (hi - lo) * u


def photometric(frame: torch.Tensor, prev: torch.Tensor, share: float,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(frame, prev) uint8 (B, 3, H, W) with a random lighting change on a share of the samples.

    The factors are drawn from `generator` (the global torch RNG by default, which training
    reseeds per epoch), the same number of draws whatever `share` is.
    """
    if frame.shape != prev.shape or frame.ndim != 4 or frame.shape[1] != 3:
        raise ValueError(f"photometric wants two (B, 3, H, W) batches, got {tuple(frame.shape)} "
                         f"and {tuple(prev.shape)}")
    n, dev = frame.shape[0], frame.device
    on = (torch.rand((n, 1, 1, 1), generator=generator) < share).to(dev)
    brightness = _uniform(n, BRIGHTNESS, dev, generator)
    contrast = _uniform(n, CONTRAST, dev, generator)
    saturation = _uniform(n, SATURATION, dev, generator)
    gain = _uniform(n, CHANNEL_GAIN, dev, generator, channels=3)
    if share <= 0.0:
        return frame, prev
    grey_w = torch.tensor(_GREY, device=dev).view(1, 3, 1, 1)
    # The contrast pivots on frame t's mean grey level, for both frames alike.
    pivot = (frame.float() * grey_w).sum(1, keepdim=True).mean((2, 3), keepdim=True)

    def change(x: torch.Tensor) -> torch.Tensor:
        y = x.float() * gain
        grey = (y * grey_w).sum(1, keepdim=True)
        y = grey + (y - grey) * saturation
        y = pivot + (y - pivot) * contrast
        y = (y * brightness).clamp(0.0, 255.0).round().to(torch.uint8)
        return torch.where(on, y, x)

    return change(frame), change(prev)


# Command one-hot columns (bid_sim.routes: LEFT 1, RIGHT 2, STRAIGHT 3, LANEFOLLOW 4,
# CHANGELANELEFT 5, CHANGELANERIGHT 6, less one) as a mirror image of the world reads them.
MIRRORED_COMMAND = (1, 0, 2, 3, 5, 4)


def mirror(frame: torch.Tensor, prev: torch.Tensor, command: torch.Tensor, target: torch.Tensor, share: float,
           generator: torch.Generator | None = None
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(frame, prev, command one-hot, (steer, accel) target) with a share of the samples
    mirrored left to right (`bid train --mirror SHARE`): the three-camera frame flipped
    (left camera ↔ right, each mirrored) is the mirror image of the world, in which a left
    turn is a right one and steering changes sign; what stands in the path and how near
    stays. The town drives on the right and its mirror on the left, so this is meant for
    fitting a detector (`--train-only SC`), not for lane keeping. No draws when share is 0."""
    if share <= 0.0:
        return frame, prev, command, target
    n, dev = frame.shape[0], frame.device
    on = (torch.rand(n, generator=generator) < share).to(dev)
    flip = on.view(n, 1, 1, 1)
    frame = torch.where(flip, frame.flip(-1), frame)
    prev = torch.where(flip, prev.flip(-1), prev)
    command = torch.where(on.view(n, 1), command[:, list(MIRRORED_COMMAND)], command)
    target = torch.where(on.view(n, 1), target * torch.tensor([-1.0, 1.0], device=dev), target)
    return frame, prev, command, target


def shift(frame: torch.Tensor, prev: torch.Tensor, pixels: int,
          generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(frame, prev) uint8 (B, 3, H, W), each sample moved by its own whole number of pixels,
    up to `pixels` each way, down or up and sideways, the edge rows and columns repeated into
    what is uncovered (`bid train --shift PIXELS`). Frame t and t−1 move alike, so the motion
    between them is what it was. A camera pitched or turned a little: the shipped SC lost a car
    standing 2 m ahead that it saw in the same frame moved up by 4 rows (docs/experiments.md),
    a detector of where things are in Town01's pictures rather than of what they are. No draws
    when `pixels` is 0."""
    if pixels <= 0:
        return frame, prev
    n, _, h, w = frame.shape
    dy = torch.randint(-pixels, pixels + 1, (n,), generator=generator).tolist()
    dx = torch.randint(-pixels, pixels + 1, (n,), generator=generator).tolist()
    both = F.pad(torch.cat([frame, prev], dim=1).float(), (pixels,) * 4, mode="replicate")
    out = torch.stack([both[i, :, pixels - dy[i]:pixels - dy[i] + h, pixels - dx[i]:pixels - dx[i] + w]
                       for i in range(n)]).to(torch.uint8)
    return out[:, :3].contiguous(), out[:, 3:].contiguous()
