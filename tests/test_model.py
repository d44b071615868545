"""The BID network on the tiny preset: shapes, recurrence, gradients, lesions, bad input."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from bid_model.areas import dynamic_filter
from bid_model.config import (
    VARIANTS,
    ModelConfig,
    RunConfig,
    preset,
    scaled_milestones,
    tiny,
    with_variant,
)
from bid_model.data import SyntheticDriving, check_sample, command_one_hot, synthetic_split
from bid_model.model import BID, lesioned
from bid_model.train import l1_loss, make_optimizer
from bid_sim.errors import BidError

B = 4


pytestmark = pytest.mark.usefixtures("one_thread")


def tiny_model(variant: str = "full", **changes) -> BID:
    torch.manual_seed(0)
    return BID(dataclasses.replace(with_variant(tiny().model, variant), **changes))


def inputs(model: BID, batch: int = B, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    h, w = model.config.frame_hw
    frame = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    prev = torch.randint(0, 256, (batch, 3, h, w), dtype=torch.uint8, generator=g)
    command = command_one_hot(torch.randint(1, 7, (batch,), generator=g))
    speed = torch.rand(batch, generator=g) * 10
    return frame, prev, command, speed


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_forward_shapes_per_variant(variant):
    model = tiny_model(variant).eval()
    x = inputs(model)
    feats = model.forward_features(*x)
    expected = {"V1", "V2", "V4", "IT", "VPC", "MPC"}
    expected |= {"MT"} if VARIANTS[variant]["dorsal"] else set()
    expected |= {"DPC"} if VARIANTS[variant]["relations"] else set()
    expected |= {"OFC"} if VARIANTS[variant]["navigation"] else set()
    assert set(feats) == expected
    assert set(model.areas) == expected | {"CPC"}
    shapes = model.output_shapes()
    for name, out in feats.items():
        assert tuple(out.shape) == (B, *shapes[name]), name
    grids = model.grid_hw()
    assert feats["IT"].shape[1] == model.config.width
    assert feats["VPC"].shape[1] == grids["IT"][0] * grids["IT"][1]
    out = model(*x)
    assert out.shape == (B, 2) and bool((out.abs() <= 1).all())
    assert torch.equal(out, model.forward_head(feats))


def test_speed_input_is_an_extra_token():
    model = tiny_model(speed_input=True).eval()
    frame, prev, command, speed = inputs(model)
    out = model(frame, prev, command, speed)
    assert out.shape == (B, 2)
    assert not torch.equal(out, model(frame, prev, command, speed + 5))
    with pytest.raises(BidError, match="speed"):
        model(frame, prev, command)


def test_paper_preset_matches_the_paper():
    m = preset("paper").model
    assert m.frame_hw == (300, 900) and m.widths == (64, 128, 256, 512)
    assert m.times == (2, 4, 2) and (m.mpc_layers, m.mpc_heads) == (4, 4)
    assert not m.speed_input and m.variant == "full"
    t = preset("paper").train
    assert (t.epochs, t.milestones, t.batch_size, t.lr, t.weight_decay) == (100, (25, 45, 70), 100, 2e-4, 0.02)
    assert (t.lambda_steer, t.lambda_accel) == (0.5, 0.5)
    assert scaled_milestones(20) == (5, 9, 14)


@pytest.mark.parametrize("depthwise", [False, True])
def test_recurrence_counts(depthwise):
    model = tiny_model(depthwise=depthwise).eval()
    steps = {"V2": 0, "V4": 0, "IT": 0}
    calls = dict.fromkeys(steps, 0)

    def count(table, name):
        def hook(module, args, output):
            table[name] += 1
        return hook

    for name in steps:
        model.areas[name].bottleneck.register_forward_hook(count(steps, name))
        model.areas[name].register_forward_hook(count(calls, name))
    model(*inputs(model))
    assert steps == {"V2": 2, "V4": 4, "IT": 2}
    assert calls == {"V2": 1, "V4": 1, "IT": 1}


def test_recurrent_area_shares_weights_not_norms():
    area = tiny_model().areas["V4"]
    assert len(area.bottleneck.norms) == 4
    assert len({id(n[0]) for n in area.bottleneck.norms}) == 4
    assert sum(isinstance(m, torch.nn.Conv2d) for m in area.modules()) == 5  # input, skip, 3 shared


def test_dynamic_filter_matches_a_plain_reference():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4, 3, 5, dtype=torch.float64, generator=g, requires_grad=True)
    f = torch.randn(1, 2, 9, 3, 5, dtype=torch.float64, generator=g, requires_grad=True)
    cols = torch.nn.functional.unfold(x, 3, padding=1).reshape(1, 2, 2, 9, 3, 5)
    reference = (cols * f[:, :, None]).sum(3).reshape(1, 4, 3, 5)
    assert torch.allclose(dynamic_filter(x, f), reference)
    assert torch.autograd.gradcheck(dynamic_filter, (x, f))


def test_gradients_reach_every_area():
    model = tiny_model(speed_input=True).train()
    frame, prev, command, speed = inputs(model)
    target = torch.rand(B, 2) * 2 - 1
    l1_loss(model(frame, prev, command, speed), target, tiny().train).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
    for name, area in model.areas.items():
        assert any(float(p.grad.abs().sum()) > 0 for p in area.parameters()), name


def test_mean_activations_average_the_first_batches_then_follow_training():
    model = tiny_model().train()
    batches = [inputs(model, seed=s) for s in range(3)]
    it_means = []
    for x in batches:
        it_means.append(model.forward_features(*x)["IT"].detach().mean(0))
    # The cumulative average of the first batches (weights 1, 1/2, 1/3 > lesion_momentum).
    assert torch.allclose(model.mean_IT, torch.stack(it_means).mean(0), atol=1e-6)
    model.mean_batches.fill_(1000)  # later: an exponential average with the configured weight
    before = model.mean_IT.clone()
    now = model.forward_features(*batches[0])["IT"].detach().mean(0)
    m = model.config.lesion_momentum
    assert torch.allclose(model.mean_IT, before * (1 - m) + now * m, atol=1e-6)


def test_lesions_change_outputs_and_are_restored():
    model = tiny_model()
    x = inputs(model)
    opt = make_optimizer(model, tiny().train)
    model.train()
    for _ in range(3):  # a few steps so that mean activations exist
        loss = model(*x).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    intact = model(*x)
    assert int(model.mean_batches) == 3
    for name in model.areas:
        for mode in ("zero", "mean"):
            with lesioned(model, {name: mode}):
                out = model(*x)
            assert not torch.allclose(out, intact), (name, mode)
    assert model.lesions == {}
    assert torch.equal(model(*x), intact)
    with lesioned(model, {"IT": "zero"}):
        assert torch.count_nonzero(model.forward_features(*x)["IT"]) == 0
    with pytest.raises(BidError, match="areas"):
        model.set_lesions({"FEF": "zero"})
    with pytest.raises(BidError, match="mode"):
        model.set_lesions({"IT": "half"})
    with pytest.raises(BidError, match="baseline"):
        tiny_model("baseline").set_lesions({"MT": "zero"})


def test_weight_decay_only_on_weights():
    model = tiny_model()
    decay, keep = make_optimizer(model, tiny().train).param_groups
    assert decay["weight_decay"] == 0.02 and keep["weight_decay"] == 0.0
    names = {id(p): n for n, p in model.named_parameters()}
    assert all(p.ndim >= 2 for p in decay["params"])
    kept = {names[id(p)] for p in keep["params"]}
    assert any(n.endswith("bias") for n in kept) and any("norm" in n for n in kept)
    assert "areas.VPC.pos_embed" in kept
    assert "areas.V1.conv1.0.weight" in {names[id(p)] for p in decay["params"]}


def test_bad_inputs_are_named():
    model = tiny_model().eval()
    frame, prev, command, _ = inputs(model)
    with pytest.raises(BidError, match=r"frame_t .*tiny.*prepare_frame"):
        model(torch.zeros(B, 3, 300, 900, dtype=torch.uint8), prev, command)
    with pytest.raises(BidError, match="frame_prev"):
        model(frame, prev[:, :, :-1], command)
    with pytest.raises(BidError, match="one-hot"):
        model(frame, prev, command[:, :4])
    with pytest.raises(BidError, match="command 7 out of range"):
        command_one_hot([4, 7])
    with pytest.raises(BidError, match="command 0 out of range"):
        command_one_hot(0)
    with pytest.raises(BidError, match="unknown preset"):
        preset("huge")
    with pytest.raises(BidError, match="unknown variant"):
        with_variant(tiny().model, "dorsalx")
    with pytest.raises(ValueError, match="dorsal"):
        ModelConfig(dorsal=False, relations=True)


def test_synthetic_data_keeps_the_contract():
    hw = tiny().model.frame_hw
    data = SyntheticDriving(60, hw, seed=1)
    for i in (0, 1, 59):
        check_sample(data[i], hw)
    assert torch.equal(data[5]["frame"], SyntheticDriving(60, hw, seed=1)[5]["frame"])
    assert torch.equal(data[21]["prev_frame"], data[20]["frame"])
    train, val, desc = synthetic_split(200, hw, 0.2, seed=0)
    train_eps = {train[i]["episode"] for i in range(len(train))}
    val_eps = {val[i]["episode"] for i in range(len(val))}
    assert train_eps and val_eps and not train_eps & val_eps
    assert desc["train_samples"] + desc["val_samples"] == 200
    bad = dict(data[0], frame=data[0]["frame"][:, :-1])
    with pytest.raises(BidError, match="prepare_frame"):
        check_sample(bad, hw)


def test_run_config_round_trips_through_json():
    import json

    run = RunConfig(with_variant(tiny().model, "both"), tiny().train.with_epochs(7))
    assert RunConfig.from_dict(json.loads(json.dumps(run.to_dict()))) == run


def test_the_network_trains_and_is_timed_without_the_simulator_installed():
    # A GPU node that times training steps (benchmarks/bench_model.py --gpu-profile) has
    # torch but neither SUMO nor the recordings' libraries: the network, its loss and the
    # benchmark must import without them. Each is made unimportable in a child process.
    root = Path(__file__).resolve().parents[1]
    code = f"""
import sys
for name in ("libsumo", "traci", "sumolib", "mcap", "mcap_protobuf", "shapely", "zstandard", "lz4"):
    sys.modules[name] = None
sys.path.insert(0, {str(root / "benchmarks")!r})
import torch
import bench_model
step = bench_model.TrainStep("tiny", 2, torch.device("cpu"))
print(len(step.seconds(1)), bench_model.kernel_family("sm90_xmma_wgrad_implicit_gemm"))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=root)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["1", "conv", "weight", "grad"]


def test_compiled_areas_keep_one_static_graph_per_batch_size_and_mode():
    # `bid train --compile` (CUDA): every area through torch.compile with static shapes. A run
    # meets the full and the last batch, training and evaluating; V2, V4 and IT share one code
    # object, so without a raised limit dynamo gives up on IT's graphs and runs it eagerly. The
    # eager backend checks dynamo's graphs and guards without a GPU or a C compiler.
    code = """
import torch
from unittest import mock
from torch._dynamo.utils import counters
from bid_model.config import tiny
from bid_model.data import command_one_hot
from bid_model.model import BID, compile_each_area
torch.manual_seed(0)
model = BID(tiny().model)
compile_module = torch.nn.Module.compile
with mock.patch.object(torch.nn.Module, "compile", lambda m, **kw: compile_module(m, backend="eager", **kw)):
    compile_each_area(model)
h, w = model.config.frame_hw
for mode in ("train", "eval"):
    getattr(model, mode)()
    for b in (4, 3, 4, 3):
        frames = torch.randint(0, 256, (b, 3, h, w), dtype=torch.uint8)
        out = model(frames, frames, command_one_hot(torch.ones(b, dtype=torch.long)), torch.rand(b))
        if mode == "train":
            out.sum().backward()
print(counters["stats"]["unique_graphs"], sorted(counters["unimplemented"]))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]
    graphs, gave_up = done.stdout.split(" ", 1)
    assert gave_up.strip() == "[]", gave_up  # no "recompile limit exceeded"
    # Each area once per (batch size, mode) at most: 4 combinations of the tiny model's areas.
    assert 0 < int(graphs) <= 4 * len(tiny_model().areas)


def test_sc_scale_gives_sc_finer_frames_and_the_cortex_the_same_ones_averaged_down():
    """sc_scale 2: the network takes frames twice as fine; SC reads them so (a grid twice as
    fine), and the cortex reads them area-averaged down: a frame whose every pixel is a 2×2 block
    drives it exactly as the coarse frame drives the same cortex at sc_scale 1."""
    coarse_cfg = dataclasses.replace(tiny().model, hazard=True, hazard_light=True, hazard_sc=True)
    fine_cfg = dataclasses.replace(coarse_cfg, sc_scale=2)
    assert fine_cfg.input_hw == (64, 192) and coarse_cfg.input_hw == coarse_cfg.frame_hw
    torch.manual_seed(0)
    coarse, fine = BID(coarse_cfg).eval(), BID(fine_cfg).eval()
    assert fine.hazard_sc.position.shape[2:] == (8, 24) and coarse.hazard_sc.position.shape[2:] == (4, 12)
    fine.load_state_dict({k: v for k, v in coarse.state_dict().items() if not k.startswith("hazard_sc.")},
                         strict=False)
    frame, prev = (torch.randint(0, 256, (2, 3, 32, 96), dtype=torch.uint8) for _ in range(2))
    cmd, speed = torch.eye(6)[[1, 4]], None
    blocks = [x.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3) for x in (frame, prev)]
    with torch.no_grad():
        want = coarse(frame, prev, cmd, speed, hazard=True, hazard_apart=True)
        got = fine(*blocks, cmd, speed, hazard=True, hazard_apart=True)
    assert torch.allclose(got[0], want[0], atol=1e-6)  # steer, accel
    assert torch.allclose(got[1][:, :3], want[1][:, :3], atol=1e-6)  # the head's own outputs
    with pytest.raises(BidError, match=r"expects \(batch, 3, 64, 192\)"):
        fine(frame, prev, cmd)
    for bad, why in (({"sc_scale": 2, "hazard_sc": False}, "needs hazard_sc"), ({"sc_scale": 0}, "whole factor")):
        with pytest.raises(ValueError, match=why):
            dataclasses.replace(coarse_cfg, **bad)


def test_sc_fine_is_a_second_sc_on_finer_frames_whose_pedestrian_counts_while_moving():
    """sc_fine 2 beside an SC at 1×: the network takes frames twice as fine; the cortex and the
    first SC read them area-averaged down, so a frame of 2×2 blocks drives them exactly as the
    coarse frame drives the model without the fine SC; the fine SC reads the fine frame as a
    model with SC at sc_scale 2 and presence does. Merged, its pedestrian joins the first's only
    where the ego moves; the vehicle stays the head's and the first SC's."""
    base_cfg = dataclasses.replace(tiny().model, hazard=True, hazard_light=True, hazard_sc=True)
    fine_cfg = dataclasses.replace(base_cfg, sc_fine=2)
    donor_cfg = dataclasses.replace(base_cfg, sc_scale=2, sc_presence=True)
    assert fine_cfg.input_hw == (64, 192) and fine_cfg.scaled_hw(fine_cfg.sc_scale) == (32, 96)
    torch.manual_seed(0)
    base, donor, fine = BID(base_cfg).eval(), BID(donor_cfg).eval(), BID(fine_cfg).eval()
    assert "SC_fine" in fine.parts() and "SC_fine" not in base.parts()
    fine.load_state_dict({**base.state_dict(), **{"hazard_sc_fine." + k.removeprefix("hazard_sc."): v
                                                  for k, v in donor.state_dict().items() if k.startswith("hazard_sc.")}})
    frame, prev = (torch.randint(0, 256, (4, 3, 32, 96), dtype=torch.uint8) for _ in range(2))
    cmd = torch.eye(6)[[1, 4, 2, 3]]
    blocks = [x.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3) for x in (frame, prev)]
    with torch.no_grad():
        want = base(frame, prev, cmd, hazard=True, hazard_apart=True)
        theirs = donor(*blocks, cmd, hazard=True, hazard_apart=True)[1]
        control, apart = fine(*blocks, cmd, hazard=True, hazard_apart=True)
    assert torch.allclose(control, want[0], atol=1e-6)
    assert apart.shape[1] == want[1].shape[1] + 4  # the head's 3, SC's 2, then the fine SC's 4
    assert torch.allclose(apart[:, :5], want[1], atol=1e-6)
    assert torch.equal(fine.sc_columns(apart, fine=True), apart[:, 5:9])
    assert torch.allclose(fine.sc_columns(apart, fine=True), donor.sc_columns(theirs), atol=1e-6)
    assert torch.allclose(fine.sc_near(apart, fine=True), donor.sc_near(theirs), atol=1e-6)
    # Give the fine SC a pedestrian in every row (its logit made positive, its nearness high).
    apart[:, 5], apart[:, 7] = 0.9, 1.0
    speed = torch.tensor([0.0, 0.29, 0.3, 5.0])
    merged, before = fine.merge_hazard(apart, speed), base.merge_hazard(apart[:, :5])
    moving = speed >= 0.3
    assert torch.equal(merged[~moving], before[~moving])
    assert torch.equal(merged[moving, 0], torch.full((2,), 0.9)) and torch.equal(merged[:, 1:], before[:, 1:])
    always = BID(dataclasses.replace(fine_cfg, fine_moving=False))
    assert torch.equal(always.merge_hazard(apart)[:, 0], torch.full((4,), 0.9))
    with pytest.raises(BidError, match="pass speed_mps"):
        fine.merge_hazard(apart)
    for bad, why in (({"sc_fine": 2, "hazard_sc": False}, "needs hazard_sc"), ({"sc_fine": 5}, "whole factor"),
                     ({"sc_fine": 2, "sc_scale": 3}, "one must divide the other")):
        with pytest.raises(ValueError, match=why):
            dataclasses.replace(base_cfg, **bad)
