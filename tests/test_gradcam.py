"""Sign-aware Grad-CAM (captum's LayerGradCam) on the tiny preset, and `bid gradcam`."""

import cv2
import numpy as np
import pytest
import torch

from bid_model.checkpoint import save_checkpoint
from bid_model.config import tiny
from bid_model.data import command_one_hot
from bid_model.gradcam import GRID_AREAS, gradcam, write_overlays
from bid_model.model import BID
from bid_sim.cli import main as bid
from bid_sim.errors import BidError

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def model_and_inputs():
    torch.manual_seed(0)
    model = BID(tiny().model)
    h, w = model.config.frame_hw
    g = torch.Generator().manual_seed(1)
    frame = torch.randint(0, 256, (3, 3, h, w), dtype=torch.uint8, generator=g)
    prev = torch.randint(0, 256, (3, 3, h, w), dtype=torch.uint8, generator=g)
    return model, (frame, prev, command_one_hot([1, 4, 2]))


@pytest.mark.parametrize("area", GRID_AREAS)
@pytest.mark.parametrize("target", ["steer", "accel"])
def test_maps_have_the_frame_shape(model_and_inputs, area, target):
    model, x = model_and_inputs
    maps = gradcam(model, *x, area=area, target=target)
    assert maps.shape == (3, *model.config.frame_hw)
    assert bool(torch.isfinite(maps).all()) and float(maps.min()) >= 0 and float(maps.max()) <= 1
    assert model.training  # the model's mode is restored


def test_the_sign_of_the_output_sets_the_gradient_sign(model_and_inputs):
    model, x = model_and_inputs
    model.eval()
    steer = model(*x)[:, 0]
    # Flipping the last layer's steer row flips the output's sign; a sign-aware map, which
    # explains sign(y)·y, stays the same.
    head = model.areas["CPC"].head[-1]
    flipped_model = BID(model.config).eval()
    flipped_model.load_state_dict(model.state_dict())
    with torch.no_grad():
        flipped = flipped_model.areas["CPC"].head[-1]
        flipped.weight[0].neg_()
        flipped.bias[0].neg_()
        assert torch.allclose(flipped_model(*x)[:, 0], -steer, atol=1e-6)
    assert head.weight[0, 0] == -flipped.weight[0, 0]
    a = gradcam(model, *x, area="IT")
    b = gradcam(flipped_model, *x, area="IT")
    assert torch.allclose(a, b, atol=1e-5)
    model.train()


def test_bad_area_is_named(model_and_inputs):
    model, x = model_and_inputs
    with pytest.raises(BidError, match="spatial grid"):
        gradcam(model, *x, area="MPC")
    with pytest.raises(BidError, match="target"):
        gradcam(model, *x, target="brake")


def test_overlays_per_camera(tmp_path, model_and_inputs):
    model, x = model_and_inputs
    maps = gradcam(model, *x)
    paths = write_overlays(x[0][0], maps[0], tmp_path, "s0")
    assert [p.name for p in paths] == ["s0_left.png", "s0_centre.png", "s0_right.png", "s0.png"]
    assert cv2.imread(str(paths[0])).shape == (300, 300, 3)
    assert cv2.imread(str(paths[3])).shape == (300, 900, 3)


def test_bid_gradcam_writes_pngs(tmp_path, capsys):
    torch.manual_seed(0)
    run = tiny()
    ckpt = tmp_path / "last.pt"
    save_checkpoint(ckpt, {"config": run.to_dict(), "model": BID(run.model).state_dict()})
    out = tmp_path / "cam"
    rc = bid(["gradcam", "--checkpoint", str(ckpt), "--out", str(out), "--synthetic",
              "--samples", "2", "--target", "both"])
    assert rc == 0, capsys.readouterr().err
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 2 * 2 * 4  # samples × targets × (3 cameras + strip)
    assert any("_steer" in p.name for p in pngs) and any("_accel" in p.name for p in pngs)
    img = cv2.imread(str(pngs[0]))
    assert img is not None and np.asarray(img).std() > 0
    assert bid(["gradcam", "--checkpoint", str(ckpt), "--out", str(out), "--synthetic",
                "--preset", "small"]) == 2
    assert "'tiny' preset, not 'small'" in capsys.readouterr().err
