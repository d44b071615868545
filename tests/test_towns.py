import json
import shutil

import pytest

from bid_sim.cli import main
from bid_sim.errors import BidError
from bid_sim.towns import describe_town, resolve_town

# (town, junctions, T, four-way, signalised, lanes per direction, width, height, street km)
EXPECTED = {
    "01": (12, 12, 0, 12, [1], 394, 329, 2.48),
    "02": (8, 8, 0, 8, [1], 197, 197, 1.06),
    "05": (21, 8, 13, 15, [1, 2, 3], 473, 399, 3.85),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_town_figures_match_carla(name):
    d = describe_town(resolve_town(name))
    junctions, t, four, signals, lanes, w, h, km = EXPECTED[name]
    assert (d["junctions"], d["t_junctions"], d["four_way"], d["signalised"]) == (junctions, t, four, signals)
    assert d["lanes_per_direction"] == lanes
    assert d["width_m"] == pytest.approx(w, rel=0.03)
    assert d["height_m"] == pytest.approx(h, rel=0.03)
    assert d["street_length_m"] / 1000 == pytest.approx(km, rel=0.08)


@pytest.mark.parametrize("name", ["01", "02", "05"])
def test_every_street_has_sidewalks_and_signalised_junctions_have_crossings(name):
    import sumolib

    net = sumolib.net.readNet(str(resolve_town(name).net_file), withInternal=True, withPrograms=True)
    for e in net.getEdges():
        if e.getFunction() == "":
            assert e.getLanes()[0].allows("pedestrian") and not e.getLanes()[0].allows("passenger"), e.getID()
    crossings = {e.getFromNode().getID() for e in net.getEdges() if e.getFunction() == "crossing"}
    for tl in net.getTrafficLights():
        node = tl.getID()
        assert node in crossings
        states = [ph.state for p in tl.getPrograms().values() for ph in p.getPhases()]
        # Pedestrian phases: crossing links turn green while some vehicle links are red.
        assert any("G" in s and "r" in s for s in states)


def test_speed_limit_town02(town02):
    import sumolib

    net = sumolib.net.readNet(str(town02.net_file))
    speeds = {round(lane.getSpeed(), 2) for e in net.getEdges() for lane in e.getLanes() if lane.allows("passenger")}
    assert speeds == {11.18}


def test_towns_json_keys(capsys):
    assert main(["towns", "--json", "02"]) == 0
    row = json.loads(capsys.readouterr().out)[0]
    for key in ("town", "width_m", "height_m", "junctions", "t_junctions", "four_way", "signalised", "street_length_m"):
        assert key in row
    assert (row["crossing_width_m"], row["zebra_width_m"]) == (2.0, 4.0)


@pytest.mark.parametrize("spec", ["07", "town9", "/no/such/folder"])
def test_unknown_town_is_one_line_exit_2(spec, capsys):
    assert main(["towns", spec]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown town")


def test_folder_without_network(tmp_path):
    with pytest.raises(BidError, match="has no network"):
        resolve_town(tmp_path)


def test_user_folder_plain_xml_is_built_and_rebuilt_on_change(tmp_path, monkeypatch):
    from bid_sim import towns

    monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
    src = resolve_town("02").folder
    mine = tmp_path / "mytown"
    mine.mkdir()
    for f in ("town.nod.xml", "town.edg.xml"):
        shutil.copy(src / f, mine / f)
    town = resolve_town(mine)
    net = town.net_file
    assert net.exists() and describe_town(town)["junctions"] == 8
    first = net.stat().st_mtime_ns
    assert towns.build_net(town) == net and net.stat().st_mtime_ns == first  # cached
    edg = mine / "town.edg.xml"
    edg.write_text(edg.read_text().replace('speed="11.18"', 'speed="8.33"'))
    towns.build_net(resolve_town(mine))
    assert net.stat().st_mtime_ns != first


def test_user_folder_with_net_xml(tmp_path):
    shutil.copy(resolve_town("02").net_file, tmp_path / "city.net.xml")
    town = resolve_town(tmp_path)
    assert town.net_file == tmp_path / "city.net.xml"
    assert describe_town(town)["signalised"] == 8


def test_broken_plain_xml_is_a_bid_error(tmp_path, monkeypatch):
    from bid_sim import towns

    monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
    (tmp_path / "bad.nod.xml").write_text("<nodes><node id='a' x='0' y='0'/></nodes>")
    (tmp_path / "bad.edg.xml").write_text("<edges><edge id='e' from='a' to='zz'/></edges>")
    with pytest.raises(BidError, match="netconvert failed"):
        _ = resolve_town(tmp_path).net_file
    assert not list((tmp_path / "build").rglob("*.net.xml"))


def test_workers_that_build_a_missing_net_at_once_all_get_it(tmp_path, monkeypatch):
    """Evaluation and recording workers on a fresh clone each find no net and build it."""
    from concurrent.futures import ThreadPoolExecutor

    from bid_sim import towns

    monkeypatch.setattr(towns, "BUILD", tmp_path / "build")
    town = resolve_town("02")
    with ThreadPoolExecutor(3) as pool:
        nets = list(pool.map(lambda _: towns.build_net(town), range(3)))
    assert len(set(nets)) == 1 and nets[0].parent == tmp_path / "build" / town.folder.name
    assert describe_town(resolve_town(nets[0].parent))["signalised"] == 8
    assert sorted(p.name for p in nets[0].parent.iterdir()) == ["net.sha", nets[0].name]  # no temporaries left


def _waiting_places_in_turning_paths(net_file) -> list[tuple[str, float, float]]:
    """Places where people wait for the light (six across each end of each crossing, from
    half a SUMO stripe, 0.32 m, in from either side) that lie outside every walking area and
    sidewalk and within the ego's half width plus a person's half size of an internal car
    lane's centre line."""
    import numpy as np
    import shapely
    import sumolib
    from shapely.geometry import LineString, Point, Polygon

    from bid_sim.ego import EgoParams

    net = sumolib.net.readNet(str(net_file), withInternal=True, withPedestrianConnections=True)
    walk, turns, crossings = [], [], []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = lane.getShape()
            if edge.getFunction() == "walkingarea":
                walk.append(Polygon(shape).buffer(0))
            elif edge.getFunction() == "crossing":
                crossings.append((edge.getID(), shape, lane.getWidth()))
            elif lane.allows("passenger"):
                if edge.getFunction() == "internal":
                    turns.append(LineString(shape))
            elif lane.allows("pedestrian"):
                walk.append(LineString(shape).buffer(lane.getWidth() / 2, cap_style="flat"))
    paved = shapely.union_all(walk).buffer(0.05)
    reach = EgoParams().width_m / 2 + 0.24
    found = []
    for cid, shape, width in crossings:
        along = np.subtract(shape[-1], shape[0])
        across = np.array([-along[1], along[0]]) / np.linalg.norm(along)
        for end in (shape[0], shape[-1]):
            for off in np.linspace(-width / 2 + 0.32, width / 2 - 0.32, 6):
                p = Point(*(np.asarray(end) + across * off))
                if not paved.contains(p) and min(t.distance(p) for t in turns) < reach:
                    found.append((cid, round(p.x, 2), round(p.y, 2)))
    return found


@pytest.mark.parametrize("name", ["01", "02", "05"])
def test_people_waiting_at_2_m_crossings_stand_clear_of_turning_cars(name, town_with_crossings):
    # netconvert's 4 m crossings (the built-in towns' until 2026-12-05) leave the outer stripe of
    # each end in the carriageway beside the walking area's rounded corner, where right-turning
    # cars pass; the built-in towns' 2 m crossings do not.
    town = resolve_town(name)
    assert (town.crossing_width_m, town.zebra_width_m) == (2.0, 4.0)
    assert _waiting_places_in_turning_paths(town.net_file) == []
    assert _waiting_places_in_turning_paths(town_with_crossings(name, 4.0).net_file)


def test_crossing_width_comes_from_town_toml_and_is_checked(tmp_path):
    folder = tmp_path / "mytown"  # resolving a town does not build its net
    shutil.copytree(resolve_town("02").folder, folder)
    (folder / "town.toml").unlink()
    assert (resolve_town(folder).crossing_width_m, resolve_town(folder).zebra_width_m) == (4.0, None)
    (folder / "town.toml").write_text('name = "Mine"\ncrossing_width_m = 2.5\n')
    assert resolve_town(folder).crossing_width_m == 2.5
    (folder / "town.toml").write_text('crossing_width_m = "wide"\n')
    with pytest.raises(BidError, match="crossing_width_m"):
        resolve_town(folder)
    (folder / "town.toml").write_text("crossing_width_m = 2\nzebra_width_m = 4\n")
    assert resolve_town(folder).zebra_width_m == 4.0
    (folder / "town.toml").write_text("crossing_width_m = 2\nzebra_width_m = 2\n")
    assert resolve_town(folder).zebra_width_m is None  # as wide as the crossings
    (folder / "town.toml").write_text("zebra_width_m = 9\n")
    with pytest.raises(BidError, match="zebra_width_m"):
        resolve_town(folder)


def test_2_m_crossings_painted_4_m_wide_look_as_the_4_m_ones(town_with_crossings):
    import numpy as np

    from bid_sim.town_map import build_town_map
    from bid_sim.towns import net_tag

    wide, narrow = town_with_crossings("02", 4.0), town_with_crossings("02", 2.0)
    painted = resolve_town("02")  # the built-in town: 2 m crossings painted 4 m wide
    assert (painted.crossing_width_m, painted.zebra_width_m) == (2.0, 4.0)
    assert net_tag(painted) != net_tag(narrow)  # results of the two pictures do not mix

    def bars(net, zebra=None):
        stripes = build_town_map(net, "Town02", zebra).crossing_stripes
        return np.array(sorted(np.round(np.asarray(r), 3).ravel().tolist() for r in stripes))

    as_4m, as_2m = bars(wide.net_file), bars(narrow.net_file)
    assert as_4m.shape != as_2m.shape or not np.allclose(as_4m, as_2m, atol=0.01)
    painted_bars = bars(painted.net_file, painted.zebra_width_m)
    assert painted_bars.shape == as_4m.shape and np.allclose(painted_bars, as_4m, atol=0.01)
