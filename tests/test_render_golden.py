"""Golden images: hand-built Town02 scenes under several weathers, compared with stored PNGs
in tests/golden/ within a tolerance (small drawing differences between OpenCV builds pass;
a moved object, a lost layer or a changed colour does not).

After an intended change to the renderer, look at the new images, then regenerate them:

    BID_REGEN_GOLDEN=1 .venv/bin/pytest tests/test_render_golden.py
"""

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from render_scenes import facing_head, snapshot, street_scene

from bid_sim.render import Renderer
from bid_sim.render.view import write_png
from bid_sim.snapshot import RED
from bid_sim.town_map import load_town_map

GOLDEN = Path(__file__).parent / "golden"
REGEN = os.environ.get("BID_REGEN_GOLDEN") == "1"
MEAN_ABS_MAX = 1.0  # mean |difference| per channel, 0–255
FAR_OFF_SHARE_MAX = 0.005  # share of pixels off by more than 40 in some channel

CASES = [
    ("street", "ClearNoon"),
    ("street", "HardRainNoon"),
    ("street", "WetSunset"),
    ("signal", "ClearSunset"),
    ("signal", "SoftRainSunset"),
    ("signal", "WetNoon"),
]


def scene(tmap, name: str):
    if name == "street":
        return street_scene(tmap, step=11)
    x, y, yaw = facing_head(tmap, 0, 25.0)
    return snapshot(tmap, x, y, yaw, light=RED, step=11)


@pytest.mark.parametrize(("scene_name", "weather"), CASES)
def test_golden(town02, scene_name, weather):
    tmap = load_town_map(town02)
    frame = Renderer(tmap, weather=weather, seed=0).render(scene(tmap, scene_name))
    path = GOLDEN / f"{scene_name}_{weather}.png"
    if REGEN:
        write_png(frame, path)
        pytest.skip(f"regenerated {path.name}")
    assert path.exists(), f"{path} is missing; regenerate: BID_REGEN_GOLDEN=1 pytest {Path(__file__).name}"
    want = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    assert want.shape == frame.shape
    diff = np.abs(frame.astype(int) - want.astype(int))
    mean = diff.mean()
    far = (diff.max(axis=2) > 40).mean()
    assert mean <= MEAN_ABS_MAX and far <= FAR_OFF_SHARE_MAX, (
        f"{path.name}: mean |diff| {mean:.2f}, {100 * far:.2f}% pixels far off; if intended, "
        "look at the new frame and regenerate (see this module's docstring)")
