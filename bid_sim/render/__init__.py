"""Software rasterizer: three pinhole cameras turn a Snapshot into a 300×900 RGB frame.

Painter's algorithm with numpy + OpenCV (no OpenGL): the ground is drawn first as batched
polygon layers, then walls, vehicles, pedestrians and signals far to near, then the
weather's screen-space effects. See ../shared/DESIGN.md sections 3–5 and 10.
"""

from bid_sim.render.camera import CameraRig
from bid_sim.render.presets import PRESETS, WeatherPreset, preset
from bid_sim.render.renderer import Renderer

__all__ = ["PRESETS", "CameraRig", "Renderer", "WeatherPreset", "preset"]
