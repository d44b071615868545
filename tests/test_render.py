"""Renderer: geometry (where things land in the three cameras), occlusion, lamps, weather,
determinism, bad input, the worker pool and `bid view`."""

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from render_scenes import (
    STREET_XY,
    STREET_YAW,
    facing_head,
    local,
    snapshot,
    street_scene,
)

from bid_sim.cli import main
from bid_sim.errors import BidError
from bid_sim.render import PRESETS, CameraRig, Renderer
from bid_sim.render.camera import MARGIN_PX, NEAR_M, clip_near
from bid_sim.render.pool import RenderPool
from bid_sim.snapshot import GREEN, OFF, RED, YELLOW
from bid_sim.town_map import load_town_map

W = 300  # one camera's width


@pytest.fixture(scope="module")
def tmap(town02):
    return load_town_map(town02)


@pytest.fixture(scope="module")
def clear(tmap):
    return Renderer(tmap, weather="ClearNoon")


def changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows and columns of the pixels that differ between two frames."""
    return np.argwhere(np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 0)


def with_car(tmap, ahead: float, left: float = 0.0, colour: int = 0, peds=()):
    x, y = STREET_XY
    return snapshot(tmap, x, y, STREET_YAW, [(*local(x, y, STREET_YAW, ahead, left), STREET_YAW, colour)], peds)


def empty_street(tmap):
    return snapshot(tmap, *STREET_XY, STREET_YAW)


def test_frame_shape_and_type(clear, tmap):
    frame = clear.render(street_scene(tmap))
    assert frame.shape == (300, 900, 3)
    assert frame.dtype == np.uint8
    assert frame.std() > 20  # a scene, not a flat colour


def test_car_straight_ahead_lands_in_the_middle_of_the_centre_camera(clear, tmap):
    base = clear.render(empty_street(tmap))
    px = changed(clear.render(with_car(tmap, 15.0)), base)
    assert len(px) > 500
    cols = px[:, 1]
    assert cols.min() >= W and cols.max() < 2 * W  # centre camera only
    assert abs(np.median(cols) - 1.5 * W) < 10
    # It stands on the ground below the horizon (camera at 1.6 m, car 1.5 m tall).
    assert np.median(px[:, 0]) > 150


def test_car_to_the_left_lands_in_the_left_camera(clear, tmap):
    base = clear.render(empty_street(tmap))
    # 60° left: the left camera's axis.
    d = 12.0
    px = changed(clear.render(with_car(tmap, d * math.cos(math.radians(60)), d * math.sin(math.radians(60)))), base)
    assert len(px) > 300
    assert px[:, 1].max() < W
    assert abs(np.median(px[:, 1]) - 0.5 * W) < 25
    # 90° left: the left camera's left edge.
    px = changed(clear.render(with_car(tmap, 0.8, 9.0)), base)
    assert len(px) > 100
    assert px[:, 1].max() < W
    assert np.median(px[:, 1]) < 0.3 * W


def test_car_to_the_right_lands_in_the_right_camera(clear, tmap):
    base = clear.render(empty_street(tmap))
    px = changed(clear.render(with_car(tmap, 4.0, -5.0)), base)
    assert len(px) > 300
    assert px[:, 1].min() >= 2 * W


def test_car_behind_is_not_drawn(clear, tmap):
    base = clear.render(empty_street(tmap))
    assert len(changed(clear.render(with_car(tmap, -12.0)), base)) == 0


@pytest.mark.parametrize("yaws", [(60.0, 0.0, -60.0), (0.0, 180.0), (150.0, -150.0), (0.0,)])
def test_view_cull_matches_the_cameras_fields_of_view(tmap, yaws):
    """The renderer drops actors and walls outside every camera's horizontal field of view
    before building their faces; it must keep exactly the discs some camera can see."""
    r = Renderer(tmap, CameraRig(width_px=120, height_px=90, yaws_deg=yaws))
    rng = np.random.default_rng(7)
    n = 4000
    rel = rng.uniform(-30, 30, (n, 2))
    rad = rng.uniform(0.1, 8.0, n)
    ego_yaw = 0.7
    d2 = (rel ** 2).sum(axis=1)
    got = r._in_view(rel, d2, rad, [(math.cos(ego_yaw + a), math.sin(ego_yaw + a)) for a in r._fov_mid])
    # Brute force, camera by camera: the angle from the camera's axis to the disc's centre
    # is at most the half field of view (canvas margin included) plus the disc's angular radius.
    half = math.atan((r.rig.width_px / 2 + MARGIN_PX) / r.rig.focal_px)
    d = np.sqrt(d2)
    grow = np.where(d > rad, np.arcsin(np.minimum(rad / np.maximum(d, 1e-9), 1.0)), np.pi)
    slack = np.full(n, -np.inf)
    for y in yaws:
        off = np.arctan2(rel[:, 1], rel[:, 0]) - (ego_yaw + math.radians(y))
        ang = np.abs((off + np.pi) % (2 * np.pi) - np.pi)
        slack = np.maximum(slack, half + grow - ang)
    clear_cut = np.abs(slack) > 1e-6
    assert clear_cut.sum() > 0.99 * n
    assert (got[clear_cut] == (slack[clear_cut] > 0)).all()
    assert 0 < got.sum() < n


def test_clip_near_matches_clipping_polygon_by_polygon():
    """The batched near-plane clip gives, polygon by polygon, what Sutherland–Hodgman gives
    one polygon at a time: corners in front kept in order, a crossing point on each edge
    that crosses, nothing for a polygon wholly behind."""
    rng = np.random.default_rng(3)
    sizes = rng.integers(3, 8, 60)
    pts = rng.uniform(-2, 3, (int(sizes.sum()), 3))
    pts[: sizes[0], 2] = rng.uniform(0.5, 3, sizes[0])  # one wholly in front
    pts[sizes[0]: sizes[0] + sizes[1], 2] = rng.uniform(-2, 0, sizes[1])  # one wholly behind
    starts = np.concatenate([[0], np.cumsum(sizes)])
    out, offs = clip_near(pts, starts, near=NEAR_M)
    for i in range(len(sizes)):
        poly = pts[starts[i]:starts[i + 1]]
        want = []
        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            if a[2] >= NEAR_M:
                want.append(a)
            if (a[2] >= NEAR_M) != (b[2] >= NEAR_M):
                t = (NEAR_M - a[2]) / (b[2] - a[2])
                want.append(a + t * (b - a))
        got = out[offs[i]:offs[i + 1]]
        assert len(got) == len(want)
        if want:
            np.testing.assert_allclose(got, np.array(want), atol=1e-12)
    assert offs[2] - offs[1] == 0 and offs[1] - offs[0] == sizes[0]
    front = pts.copy()
    front[:, 2] = np.abs(front[:, 2]) + 1.0
    assert clip_near(front, starts)[0] is front  # nothing to clip: returned as is


def test_car_beyond_view_range_is_not_drawn(clear, tmap):
    base = clear.render(empty_street(tmap))
    assert len(changed(clear.render(with_car(tmap, clear.view_m + 20.0)), base)) == 0


def test_near_car_hides_the_far_one(clear, tmap):
    x, y = STREET_XY
    near = (*local(x, y, 0.0, 10.0), 0.0, 0)  # red
    far = (*local(x, y, 0.0, 25.0), 0.0, 1)  # blue
    base = clear.render(empty_street(tmap))
    only_near = clear.render(snapshot(tmap, x, y, 0.0, [near]))
    both = clear.render(snapshot(tmap, x, y, 0.0, [far, near]))
    covered = changed(only_near, base)
    r, c = covered[:, 0], covered[:, 1]
    np.testing.assert_array_equal(both[r, c], only_near[r, c])
    assert len(changed(both, only_near)) > 0  # the far car shows beside or above it


def test_pedestrian_behind_a_building_is_hidden(clear, tmap):
    b = max(tmap.buildings, key=lambda b: b.height_m)
    fp = np.asarray(b.footprint)
    centre = fp.mean(axis=0)
    # Stand 15 m outside the middle of the first wall, looking at the building's centre.
    mid = 0.5 * (fp[0] + fp[1])
    out = mid - centre
    eye = mid + 15.0 * out / np.linalg.norm(out)
    yaw = math.atan2(centre[1] - eye[1], centre[0] - eye[0])
    base = clear.render(snapshot(tmap, eye[0], eye[1], yaw))
    hidden = clear.render(snapshot(tmap, eye[0], eye[1], yaw, pedestrians=[(*centre, 0.0, 0)]))
    assert len(changed(hidden, base)) == 0
    front = mid + 4.0 * out / np.linalg.norm(out)  # in front of the wall: seen
    seen = clear.render(snapshot(tmap, eye[0], eye[1], yaw, pedestrians=[(*front, 0.0, 0)]))
    assert len(changed(seen, base)) > 50


def test_car_straddling_the_camera_is_clipped_not_dropped(clear, tmap):
    base = clear.render(empty_street(tmap))
    frame = clear.render(with_car(tmap, 1.0))  # its rear is behind the camera
    assert len(changed(frame, base)) > 20_000


def lamp_pixels(frame: np.ndarray, state: int, where: np.ndarray) -> int:
    """Pixels clearly of the lamp colour among those marked in `where`."""
    c = frame.astype(int)
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    if state == RED:
        m = (r > 170) & (g < 110) & (b < 110)
    elif state == YELLOW:
        m = (r > 170) & (g > 130) & (b < 100)
    else:
        m = (g > 170) & (r < 140) & (b > 60) & (b < 190)
    return int((m & where).sum())


@pytest.mark.parametrize("dist", [20.0, 40.0])
def test_lamp_state_is_legible_in_the_centre_camera(clear, tmap, dist):
    x, y, yaw = facing_head(tmap, 0, dist)
    frames = {}
    for s in (RED, YELLOW, GREEN):
        lights = np.full(len(tmap.signal_heads), OFF, np.uint8)  # only head 0 lit
        lights[0] = s
        frames[s] = clear.render(replace(snapshot(tmap, x, y, yaw), light_states=lights))
    # Where the states differ: the lamps, and only in the centre camera.
    lit = np.zeros(frames[RED].shape[:2], bool)
    for a in frames.values():
        for b in frames.values():
            lit |= np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 0
    cols = np.flatnonzero(lit.any(axis=0))
    assert len(cols) and cols.min() >= W and cols.max() < 2 * W
    for s, frame in frames.items():
        n = lamp_pixels(frame, s, lit)
        assert n >= 3, f"state {s} at {dist} m: {n} lit pixels"
        for o in frames:
            if o != s:
                assert lamp_pixels(frame, o, lit) < n / 3


def test_lamps_are_dark_from_behind(clear, tmap):
    x, y, yaw = facing_head(tmap, 0, -20.0)  # 20 m behind head 0 ...
    toward = yaw + math.pi  # ... looking at its back
    lights = np.full(len(tmap.signal_heads), GREEN, np.uint8)
    green = clear.render(snapshot(tmap, x, y, toward))
    lights[0] = RED
    red = clear.render(replace(snapshot(tmap, x, y, toward), light_states=lights))
    np.testing.assert_array_equal(red, green)
    # From the front the same change shows.
    fx, fy, fyaw = facing_head(tmap, 0, 20.0)
    front = snapshot(tmap, fx, fy, fyaw)
    assert not np.array_equal(clear.render(front), clear.render(replace(front, light_states=lights)))


def test_weathers_differ_and_are_deterministic(tmap):
    snap = street_scene(tmap, step=7)
    frames = {}
    for name in PRESETS:
        a = Renderer(tmap, weather=name, seed=3).render(snap)
        b = Renderer(tmap, weather=name, seed=3).render(snap)
        np.testing.assert_array_equal(a, b)
        frames[name] = a
    names = list(frames)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.abs(frames[a].astype(int) - frames[b].astype(int)).mean() > 2.0, (a, b)
    # Sunset is warmer than noon; rain is greyer (less saturated) than clear.
    sky = slice(0, 40)
    noon, sunset = frames["ClearNoon"][sky, W:2 * W].mean((0, 1)), frames["ClearSunset"][sky, W:2 * W].mean((0, 1))
    assert noon[2] > noon[0] and sunset[0] / sunset[2] > noon[0] / noon[2]
    sat = {k: (f.max(2).astype(int) - f.min(2)).mean() for k, f in frames.items()}
    assert sat["HardRainNoon"] < sat["ClearNoon"]


def test_rain_pattern_follows_seed_and_step(tmap):
    snap = street_scene(tmap, step=4)
    r0, r1 = Renderer(tmap, weather="HardRainNoon", seed=0), Renderer(tmap, weather="HardRainNoon", seed=1)
    assert not np.array_equal(r0.render(snap), r1.render(snap))
    assert not np.array_equal(r0.render(snap), r0.render(replace(snap, step=5)))
    c0, c1 = Renderer(tmap, weather="ClearNoon", seed=0), Renderer(tmap, weather="ClearNoon", seed=1)
    np.testing.assert_array_equal(c0.render(snap), c1.render(snap))


def test_wet_road_is_darker_near_and_shinier_far(tmap):
    snap = empty_street(tmap)
    dry, wet = Renderer(tmap, weather="ClearNoon").render(snap), Renderer(tmap, weather="WetNoon").render(snap)
    near_road = (slice(280, 300), slice(W + 120, W + 180))
    assert wet[near_road].mean() < dry[near_road].mean()


def test_unknown_weather_names_the_choices(tmap):
    with pytest.raises(BidError, match="ClearNoon"):
        Renderer(tmap, weather="Foggy")


def test_zero_fov_rig_is_refused():
    with pytest.raises(BidError, match="field of view"):
        CameraRig(fov_deg=0.0)
    with pytest.raises(BidError):
        CameraRig(width_px=0)


def test_nan_and_out_of_town_snapshots_are_refused(clear, tmap):
    snap = empty_street(tmap)
    with pytest.raises(BidError, match="not finite"):
        clear.render(replace(snap, ego=replace(snap.ego, x_m=float("nan"))))
    with pytest.raises(BidError, match="outside Town02"):
        clear.render(replace(snap, ego=replace(snap.ego, x_m=5000.0)))
    bad = with_car(tmap, 10.0)
    xy = bad.vehicles.xy.copy()
    xy[0, 1] = np.inf
    with pytest.raises(BidError, match="vehicle 'a0'"):
        clear.render(replace(bad, vehicles=replace(bad.vehicles, xy=xy)))
    with pytest.raises(BidError, match="signal heads"):
        clear.render(replace(snap, light_states=np.zeros(3, np.uint8)))


def test_smaller_rig(tmap):
    rig = CameraRig(width_px=64, height_px=48, fov_deg=90.0, yaws_deg=(0.0,))
    frame = Renderer(tmap, rig).render(street_scene(tmap))
    assert frame.shape == (48, 64, 3)


def test_pool_matches_in_process_rendering(tmap, town02):
    snaps = [street_scene(tmap, step=s) for s in range(6)]
    expected = [Renderer(tmap, weather="SoftRainSunset", seed=2).render(s) for s in snaps]
    with RenderPool(town02, "SoftRainSunset", workers=2, seed=2) as pool:
        got = list(pool.map(snaps))
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_pool_reports_bad_snapshots(tmap, town02):
    snap = empty_street(tmap)
    bad = replace(snap, ego=replace(snap.ego, y_m=float("nan")))
    with RenderPool(town02, "ClearNoon", workers=2) as pool, pytest.raises(BidError, match="not finite"):
        list(pool.map([snap, bad]))


def test_view_writes_png_and_mp4(tmp_path, capsys):
    png = tmp_path / "v.png"
    assert main(["view", "--town", "02", "--density", "none", "--step", "3", "--out", str(png)]) == 0
    img = cv2.imread(str(png))
    assert img.shape == (300, 900, 3)
    grid = tmp_path / "all.png"
    assert main(["view", "--town", "02", "--density", "none", "--step", "2", "--weather", "all",
                 "--out", str(grid)]) == 0
    assert cv2.imread(str(grid)).shape == (1800, 900, 3)
    mp4 = tmp_path / "v.mp4"
    assert main(["view", "--town", "02", "--density", "none", "--steps", "8", "--out", str(mp4)]) == 0
    cap = cv2.VideoCapture(str(mp4))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 8
    assert "8 frames" in capsys.readouterr().out


def test_bench_render_prints_its_figures(capsys):
    """`bid bench render` on a few frames: frames/s, the stage costs, the 700-vs-70 ratio and
    the machine-speed reference, as one line and as JSON."""
    assert main(["bench", "render", "--town", "02", "--frames", "6"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "frames/s per core" in line and "700 vs 70 vehicles" in line and "machine speed" in line
    assert main(["bench", "render", "--town", "02", "--frames", "6", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == 6 and res["render_fps_per_core"] > 0
    assert set(res["stage_ms_per_frame"]) == {"transform", "clip", "sort", "fill", "effects"}
    assert res["render_cost_ratio_700_vs_70"] > 0 and res["machine_numpy_mul_1k_us"] > 0


def test_view_bad_output_is_one_error_line(tmp_path, capsys):
    assert main(["view", "--town", "02", "--out", str(tmp_path / "v.gif")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and ".png" in err and "\n" not in err
    assert main(["view", "--town", "02", "--weather", "Foggy", "--out", str(tmp_path / "v.png")]) == 2
