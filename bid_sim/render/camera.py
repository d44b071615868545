"""The camera rig (pinhole cameras sharing one centre) and the maths that poses, clips and
projects points into a camera's canvas.

Camera coordinates: x right, y down, z forward (m). A canvas is the camera image with a
margin of MARGIN_PX on every side (polygons with corners far off-screen leave stray border
pixels otherwise); projected points are fixed point with SHIFT fractional bits, as OpenCV's
fill functions take them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bid_sim.errors import BidError

MARGIN_PX = 8
SHIFT = 2  # fixed-point fractional bits of projected coordinates
ONE = 1 << SHIFT
NEAR_M = 0.1


@dataclass(frozen=True)
class CameraRig:
    """Cameras side by side in the frame, left to right, all at one point on the ego."""

    width_px: int = 300
    height_px: int = 300
    fov_deg: float = 60.0  # horizontal field of view of each camera
    yaws_deg: tuple[float, ...] = (60.0, 0.0, -60.0)  # relative to the ego, + = left
    height_m: float = 1.6
    forward_m: float = 0.8  # ahead of the ego's box centre

    def __post_init__(self) -> None:
        if not (0.0 < self.fov_deg < 170.0) or not math.isfinite(self.fov_deg):
            raise BidError(f"camera field of view {self.fov_deg}° is unusable; use 0 < fov < 170 (default 60)")
        if self.width_px < 8 or self.height_px < 8:
            raise BidError(f"camera size {self.width_px}×{self.height_px} px is too small; use at least 8×8 (default 300×300)")
        if not self.yaws_deg:
            raise BidError("a camera rig needs at least one camera yaw")
        if not (0.2 <= self.height_m <= 10.0):
            raise BidError(f"camera height {self.height_m} m is off; use 0.2–10 m (default 1.6)")

    @property
    def focal_px(self) -> float:
        return (self.width_px / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        return (self.height_px, self.width_px * len(self.yaws_deg), 3)

    @property
    def canvas_shape(self) -> tuple[int, int, int]:
        return (self.height_px + 2 * MARGIN_PX, self.width_px + 2 * MARGIN_PX, 3)

    @property
    def cx(self) -> float:
        """Principal point column in the canvas (pixel centres at integers)."""
        return (self.width_px - 1) / 2.0 + MARGIN_PX

    @property
    def cy(self) -> float:
        return (self.height_px - 1) / 2.0 + MARGIN_PX


@dataclass(frozen=True)
class Pose:
    """One camera's pose for one frame: centre (m) and horizontal axes in the world frame."""

    x: float
    y: float
    z: float
    fwd: tuple[float, float]  # unit forward (world x, y)
    right: tuple[float, float]  # unit right


def camera_poses(rig: CameraRig, x: float, y: float, yaw: float) -> list[Pose]:
    """Poses of the rig's cameras for an ego box centre (x, y) and yaw (rad)."""
    cxw = x + rig.forward_m * math.cos(yaw)
    cyw = y + rig.forward_m * math.sin(yaw)
    poses = []
    for yd in rig.yaws_deg:
        t = yaw + math.radians(yd)
        c, s = math.cos(t), math.sin(t)
        poses.append(Pose(cxw, cyw, rig.height_m, (c, s), (s, -c)))
    return poses


def project(rig: CameraRig, cam: np.ndarray) -> np.ndarray:
    """Camera points (..., 3) with z >= NEAR_M to fixed-point canvas pixels (..., 2) int32."""
    f = rig.focal_px * ONE
    inv = 1.0 / cam[..., 2]
    out = np.empty((*cam.shape[:-1], 2), dtype=np.int32)
    # Clamp so that far off-screen corners (near the near plane) stay inside int32 after
    # OpenCV's own fixed-point arithmetic; the visible part of the polygon is unchanged
    # at this size because the clamp is > 1000 image widths away.
    lim = 2.0e6
    out[..., 0] = np.clip(rig.cx * ONE + f * cam[..., 0] * inv, -lim, lim)
    out[..., 1] = np.clip(rig.cy * ONE + f * cam[..., 1] * inv, -lim, lim)
    return out


def clip_near(pts: np.ndarray, starts: np.ndarray, near: float = NEAR_M) -> tuple[np.ndarray, np.ndarray]:
    """Clips many polygons at once to z >= near (Sutherland–Hodgman against one plane).

    pts (N, 3) camera points of R polygons, polygon i being pts[starts[i]:starts[i + 1]]
    (each with >= 3 corners). Returns the clipped points and their (R + 1,) offsets; a
    polygon wholly behind the plane comes back empty. Concave rings work too: the edges
    added along the near plane lie far off-screen.
    """
    n = len(pts)
    if n == 0:
        return pts, starts
    z = pts[:, 2]
    inside = z >= near
    if inside.all():
        return pts, starts
    nxt = np.arange(1, n + 1)
    nxt[starts[1:] - 1] = starts[:-1]  # each polygon's last corner joins its first
    cross = inside != inside[nxt]
    ci = np.flatnonzero(cross)  # edges that cross the plane: one new point each
    a = pts.take(ci, axis=0)  # take, not fancy indexing: several times faster on rows
    b = pts.take(nxt[ci], axis=0)
    hit = a + ((near - a[:, 2]) / (b[:, 2] - a[:, 2]))[:, None] * (b - a)
    hit[:, 2] = near
    # Per corner, in order: the corner itself if inside, then its edge's crossing if any.
    emitted = inside.astype(np.int64) + cross
    end = np.cumsum(emitted)
    src = np.empty(int(end[-1]), np.int64)  # output point -> row of [pts; hit]
    keep = np.flatnonzero(inside)
    src[end[keep] - emitted[keep]] = keep
    src[end[ci] - 1] = n + np.arange(len(ci))
    out = np.concatenate([pts, hit]).take(src, axis=0)
    out_starts = np.zeros(len(starts), dtype=np.int64)
    np.cumsum(np.add.reduceat(emitted, starts[:-1]), out=out_starts[1:])
    return out, out_starts
