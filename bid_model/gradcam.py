"""Sign-aware Grad-CAM of the BID model, and per-camera overlays as PNG.

Grad-CAM weights an area's feature maps by the spatial mean of the output's gradient. For a
regression output whose sign means a direction (steer < 0 = left, accel < 0 = brake), the
map explains the output *as it is*: the gradient of sign(y)·y, so a left turn highlights
what pushes the car left, a brake what makes it brake (as in the paper).

We use captum's `LayerGradCam` (PyTorch's own interpretability library, no dependencies
beyond torch and numpy) rather than pytorch-grad-cam, which requires torchvision. It is
hooked on the area module's output, after its recurrent loop, not inside it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from bid_model.model import BID
from bid_sim.errors import BidError

TARGETS = {"steer": 0, "accel": 1}
GRID_AREAS = ("V1", "V2", "V4", "IT", "MT")  # areas whose output is a spatial grid
CAMERAS = ("left", "centre", "right")
OVERLAY_CAMERA_PX = 300  # each camera is drawn at the renderer's 300×300


def gradcam(model: BID, frame_t: torch.Tensor, frame_prev: torch.Tensor,
            command_onehot: torch.Tensor, speed_mps: torch.Tensor | None = None,
            area: str = "IT", target: str = "steer") -> torch.Tensor:
    """Sign-aware Grad-CAM maps (B, rows, cols) in [0, 1] at the input frame's size."""
    from captum.attr import LayerAttribution, LayerGradCam

    if area not in GRID_AREAS or area not in model.areas:
        present = [a for a in GRID_AREAS if a in model.areas]
        raise BidError(f"Grad-CAM needs an area with a spatial grid; choose one of "
                       f"{', '.join(present)} (got {area!r})")
    if target not in TARGETS:
        raise BidError(f"Grad-CAM target {target!r}; use steer or accel")
    index = TARGETS[target]
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            sign = torch.sign(model(frame_t, frame_prev, command_onehot, speed_mps))
        sign[sign == 0] = 1.0

        def signed(*inputs: torch.Tensor) -> torch.Tensor:
            return model(*inputs) * sign

        cam = LayerGradCam(signed, model.areas[area])
        attr = cam.attribute((frame_t, frame_prev, command_onehot), target=index,
                             additional_forward_args=(speed_mps,), relu_attributions=True)
    finally:
        model.train(was_training)
    attr = attr[: frame_t.shape[0]].detach().float()  # V1 also sees frame t−1 when dorsal
    maps = LayerAttribution.interpolate(attr, tuple(frame_t.shape[2:]), "bilinear")[:, 0]
    peak = maps.flatten(1).amax(1).clamp_min(1e-12)
    return (maps / peak[:, None, None]).clamp(0, 1)


def overlay(frame: np.ndarray, cam: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """An RGB uint8 frame (rows, cols, 3) with a [0, 1] map (rows, cols) blended as a heat map."""
    heat = cv2.applyColorMap((cam * 255).astype(np.uint8), cv2.COLORMAP_JET)[..., ::-1]
    return cv2.addWeighted(frame, 1 - alpha, heat, alpha, 0)


def write_overlays(frame: torch.Tensor, cam: torch.Tensor, out: Path, stem: str) -> list[Path]:
    """PNGs of one sample: STEM_left/centre/right.png (each camera at 300×300) and STEM.png.

    frame: uint8 (3, rows, cols), three cameras side by side; cam: (rows, cols) in [0, 1].
    """
    rgb = frame.permute(1, 2, 0).cpu().numpy()
    heat = cam.cpu().numpy().astype(np.float32)
    w = rgb.shape[1] // 3
    px = OVERLAY_CAMERA_PX
    panels = []
    paths = []
    for i, name in enumerate(CAMERAS):
        f = cv2.resize(np.ascontiguousarray(rgb[:, i * w:(i + 1) * w]), (px, px),
                       interpolation=cv2.INTER_LINEAR)
        c = cv2.resize(np.ascontiguousarray(heat[:, i * w:(i + 1) * w]), (px, px),
                       interpolation=cv2.INTER_LINEAR)
        panel = overlay(f, np.clip(c, 0, 1))
        panels.append(panel)
        paths.append(out / f"{stem}_{name}.png")
        _write_png(paths[-1], panel)
    paths.append(out / f"{stem}.png")
    _write_png(paths[-1], np.concatenate(panels, axis=1))
    return paths


def _write_png(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise BidError(f"cannot write {path}; is the folder writable?")


def run_gradcam(checkpoint: Path, out: Path, *, data: Path | None = None, synthetic: bool = False,
                area: str = "IT", targets: tuple[str, ...] = ("steer",), samples: int = 6,
                preset: str | None = None) -> list[Path]:
    """`bid gradcam`: overlays for `samples` validation frames spread over the split."""
    from bid_model.checkpoint import load_model
    from bid_model.train import batch_inputs, open_data

    if samples < 1:
        raise BidError(f"--samples must be at least 1, got {samples}")
    model, config = load_model(checkpoint, preset)
    _, val_set, _ = open_data(config, data, synthetic)
    if len(val_set) == 0:
        raise BidError("the validation split is empty: Grad-CAM needs at least two episodes")
    out.mkdir(parents=True, exist_ok=True)
    picks = np.linspace(0, len(val_set) - 1, min(samples, len(val_set))).round().astype(int)
    items = [val_set[int(i)] for i in picks]
    batch = torch.utils.data.default_collate(items)
    inputs, _ = batch_inputs(batch, torch.device("cpu"))
    with torch.no_grad():
        pred = model(*inputs)
    paths = []
    for target in targets:
        maps = gradcam(model, *inputs, area=area, target=target)
        for j, item in enumerate(items):
            value = float(pred[j, TARGETS[target]])
            stem = f"{j:03d}_ep{item['episode']}_step{item['step']}_{target}{value:+.2f}_{area}"
            paths += write_overlays(item["frame"], maps[j], out, stem)
    return paths
