"""A site in files: the demo site is a valid site folder; `toptag site check` names every problem of a
broken one in one line, warns of an intersection no camera covers and draws the top view."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.render import PlacedVehicle
from sim.sampling import DECODABLE_CELL_PX, PLATE_MARGIN_PX, in_some_view, tags_seen, visible_tags
from sim.scene import rsu_camera, rsu_cameras
from sim.site_check import SiteCheck
from sim.scenario import bundled_scenario_path
from toptag.camera import Camera
from toptag.inputs import InputError
from toptag.rsu.regions import thinnest_cell_px
from toptag.site import load_site_file
from toptag.vehicle import Vehicle

DEMO = bundled_scenario_path().parent


@pytest.mark.integration
def test_the_demo_site_is_a_valid_site_folder(tmp_path):
    site = load_site_file(DEMO)
    assert [r.camera for r in site.rsus] == ["rsu-sw.json", "rsu-se.json", "rsu-ne.json", "rsu-nw.json"]
    out = tmp_path / "top.png"
    r = subprocess.run([sys.executable, "-m", "toptag", "site", "check", str(DEMO), "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "x1: cameras rsu-sw, rsu-se, rsu-ne, rsu-nw" in r.stdout and "by one camera 100 %" in r.stdout
    assert "valid" in r.stdout and "warning" not in r.stderr
    assert out.stat().st_size > 20_000
    # The demo's poles see tags decodably on the roads up to its 18 m approach radius: no note of a
    # session the cameras cannot follow.
    assert "roads within the approach radius by one 97 % (90 % up to 18 m from the centre)" in r.stdout
    assert "of its roads within the approach radius" not in r.stdout
    for bus in ("bus-17", "bus-42"):
        assert f"{bus}: with an approach radius of 18 m 97 %" in r.stdout


def spec_corner_site(folder: Path, radius: float = 45.0) -> Path:
    """The demo site with SPEC's four corner RSUs (the paper study's arrangement, sim.scene) and the
    approach radius and GNSS shadow the demo had with them."""
    shutil.copytree(DEMO, folder, ignore=shutil.ignore_patterns("__init__.py", "__pycache__"))
    for cam in rsu_cameras(960, 720, dist=Camera.load(DEMO / "rsu-sw.json").dist):
        (folder / f"{cam.id}.json").write_text(cam.to_json())
    m = json.loads((DEMO / "map.json").read_text())
    m["intersections"][0].update(radius=radius, leave_margin=5.0, gnss_shadow_radius=30.0)
    (folder / "map.json").write_text(json.dumps(m))
    return folder


@pytest.mark.integration
def test_site_check_scores_the_scenarios_drive_and_finds_its_blind_spot(tmp_path):
    """On SPEC's corner poles, per bus, the share of its session with two tags decodable in some camera
    rises as the approach radius shrinks (what bounds "fused ok while in session"); bus-17's right turn
    from the east runs in the curb lane (y 5.5 m), which no corner camera sees from ~14 to ~8 m out.
    The demo site's poles keep both buses decodable through their sessions."""
    check = SiteCheck(spec_corner_site(tmp_path / "spec")).run()
    drive = check.coverage["x1"]["drive"]
    assert drive["duration_s"] > 40
    for bus, b in drive["buses"].items():
        shares = [b["in_view_in_session"][r] for r in (45.0, 35.0, 25.0, 20.0, 15.0)]
        assert all(a < c for a, c in zip(shares, shares[1:])), (bus, shares)
        assert 0.15 < shares[0] < 0.5 and shares[-1] < 0.9, (bus, shares)  # the site, not the software
    b17 = drive["buses"]["bus-17"]
    assert b17["longest_unseen_within_reach_s"] >= 1.0
    (x0, y0), (x1, y1) = b17["unseen_from_to"]
    assert x0 > x1 > 5 and abs(y0 - 5.5) < 0.5, b17
    assert any("in the scenario's drive a bus has two tags decodable" in n for n in check.notes)
    demo = SiteCheck(DEMO).run()
    for bus, b in demo.coverage["x1"]["drive"]["buses"].items():
        assert b["in_view_in_session"][18.0] > 0.96 and b["longest_unseen_within_reach_s"] <= 0.5, (bus, b)
    assert not any("in the scenario's drive" in n for n in demo.notes)


@pytest.mark.integration
def test_site_check_says_how_much_of_a_session_the_cameras_can_see(tmp_path):
    """The share of the approach roads where tags are decodable follows the approach radius; the note goes
    once it is small enough for the cameras to see nearly all of it (the demo's poles: ~22 m; SPEC's
    corner poles, whose far rows show a tag a few px tall: ~13 m)."""
    site = tmp_path / "site"
    shutil.copytree(DEMO, site, ignore=shutil.ignore_patterns("__init__.py", "__pycache__"))
    shares = {}
    for radius in (45.0, 25.0, 14.0):
        m = json.loads((DEMO / "map.json").read_text())
        m["intersections"][0]["radius"] = radius
        (site / "map.json").write_text(json.dumps(m))
        check = SiteCheck(site).run()
        cov = check.coverage["x1"]
        shares[radius] = cov["approach"]
        assert min(radius, 18) <= cov["covered_radius_m"] <= min(radius, 24), (radius, cov)
        assert any("of its roads within the approach radius" in n for n in check.notes) == (cov["approach"] < 0.9)
    assert shares[45.0] < shares[25.0] < shares[14.0] and shares[14.0] >= 0.9, shares
    spec = SiteCheck(spec_corner_site(tmp_path / "spec", radius=25.0)).run().coverage["x1"]
    assert spec["covered_radius_m"] <= 14 and spec["approach"] < 0.5, spec


@pytest.mark.unit
def test_a_tag_whole_in_the_image_but_few_pixels_across_is_not_decodable():
    """sim.sampling's rule: a bus far out near the side of a corner camera's (barrel-distorted) image has
    both plates inside it, but its tags' cells are under DECODABLE_CELL_PX tall in it;
    near, they count."""
    cam = rsu_camera("sw", dist=Camera.load(DEMO / "rsu-sw.json").dist)
    bus = Vehicle.load(DEMO / "bus-17.json")
    far = PlacedVehicle(bus, 17.0, -1.0, np.radians(135.0))  # ~28 m from the pole
    near = PlacedVehicle(bus, -2.0, -2.0, np.radians(45.0))
    assert len(visible_tags(cam, far, min_cell_px=0.0)) == 2
    cells = [thinnest_cell_px(cam.project(far.tag_corners_world(t))) for t in bus.tag_ids]
    assert max(cells) < DECODABLE_CELL_PX, cells
    assert visible_tags(cam, far, min_cell_px=DECODABLE_CELL_PX) == [] and not in_some_view([cam], far)
    assert in_some_view([cam], near)


@pytest.mark.unit
def test_a_tag_is_seen_with_its_whole_plate_inside_the_margin_and_cells_tall_enough():
    """sim.sampling.tags_seen, the rule visible_tags and in_some_view_many both ask, at its edges: a plate
    corner just inside or just outside PLATE_MARGIN_PX, cells just over or under DECODABLE_CELL_PX, a
    plate behind the camera that projects into the image all the same."""
    cam = rsu_camera("sw", dist=Camera.load(DEMO / "rsu-sw.json").dist)

    def world(centre, half):  # corners on the roof plane z = 3 m seen at a pixel square
        px = np.asarray(centre) + half * np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]])
        return cam.backproject_to_plane(px, 3.0)

    left = -0.5 + PLATE_MARGIN_PX
    inside = world((left + 0.01 + 20, 300), 20)
    outside = world((left - 0.01 + 20, 300), 20)
    c = cam.center
    behind = 2 * c - world((480, 360), 20)
    tall, short = world((400, 300), 4 * (DECODABLE_CELL_PX + 0.01)), world((400, 300), 4 * (DECODABLE_CELL_PX - 0.01))
    assert np.abs(cam.project(inside)[:, 0].min() - (left + 0.01)) < 1e-6  # the corners are where we meant
    plates = np.stack([inside, outside, behind, world((400, 300), 30), world((400, 300), 30)])
    tags = np.stack([tall, tall, tall, tall, short])
    assert tags_seen(cam, plates, tags).tolist() == [True, False, False, True, False]
    assert tags_seen(cam, plates, tags, min_cell_px=0.0).tolist() == [True, False, False, True, True]
    assert tags_seen(cam, plates[None], tags[None]).shape == (1, 5)


@pytest.mark.integration
def test_site_check_names_each_problem_and_warns_of_uncovered_intersections(tmp_path):
    site = tmp_path / "site"
    shutil.copytree(DEMO, site, ignore=shutil.ignore_patterns("__init__.py", "__pycache__"))
    doc = json.loads((site / "site.json").read_text())
    doc["rsus"][1]["intersection"] = "x9"  # not on the map
    doc["rsus"][2]["camera"] = "rsu-missing.json"
    doc["vehicles"] += ["bus-17.json", "bus-99.json"]  # listed twice; another bus with bus-17's tags
    bus = json.loads((site / "bus-17.json").read_text())
    (site / "bus-99.json").write_text(json.dumps({**bus, "id": "bus-99"}))
    (site / "site.json").write_text(json.dumps(doc))
    m = json.loads((site / "map.json").read_text())
    m["intersections"].append({"id": "x2", "center": [400.0, 0.0]})  # no camera there
    (site / "map.json").write_text(json.dumps(m))
    cam = json.loads((site / "rsu-nw.json").read_text())
    cam["K"][2] = [0, 0, 2]
    (site / "rsu-nw.json").write_text(json.dumps(cam))

    check = SiteCheck(site).run()
    text = "\n".join(check.errors)
    assert "RSU rsu-se serves intersection 'x9', which the map does not have" in text
    assert "rsu-missing.json: no such file" in text
    assert "rsu-nw.json: (top level): K: last row must be [0, 0, 1]" in text
    assert "vehicle id 'bus-17' already in bus-17.json" in text
    assert "bus-99.json: tag tag36h11 3 is also on bus-17" in text
    assert all("\n" not in e for e in check.errors)
    assert any("intersection x2: no camera covers it" in w for w in check.warnings)
    cov = check.coverage["x1"]  # rsu-sw alone is left at x1: its quarter of the junction box
    assert cov["cameras"] == ["rsu-sw"] and 0.2 < cov["one"] < 0.9 and cov["two"] == 0.0, cov
    assert any("intersection x1: only" in w for w in check.warnings)
    r = subprocess.run([sys.executable, "-m", "toptag", "site", "check", str(site)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "6 error(s)" in r.stderr
    assert (site / "site-check.png").exists()


@pytest.mark.unit
def test_a_folder_without_site_json_is_one_line(tmp_path):
    with pytest.raises(InputError, match=r"site\.json: no such file"):
        load_site_file(tmp_path)
    (tmp_path / "site.json").write_text('{"rsus": [{"camera": "a.json"}]}')
    with pytest.raises(InputError, match=r"rsus\.0\.intersection: Field required"):
        load_site_file(Path(tmp_path))


@pytest.mark.unit
def test_many_poses_are_placed_in_the_views_as_one_at_a_time():
    """in_some_view_many (the monitor's "in view" over seconds of poses at once) says what each pose's own
    projection of every plate says (visible_tags, one pose at a time: whole in the image, and decodable), at
    the views' edges too."""
    import numpy as np

    from sim.render import PlacedVehicle
    from sim.sampling import DECODABLE_CELL_PX, in_some_view_many, visible_tags
    from sim.scenario import load_scenario
    from sim.world import World

    world = World(load_scenario(bundled_scenario_path()))
    rng = np.random.default_rng(7)
    for bus in world.buses:
        v = bus.vehicle
        n = 1500
        poses = np.c_[rng.uniform(-45, 45, n), rng.uniform(-45, 45, n), rng.uniform(-np.pi, np.pi, n),
                      v.height + rng.uniform(-0.1, 0.1, n)]
        poses[: n // 2, 1] = rng.uniform(-4, 4, n // 2)  # on the road through the views
        for min_tags, min_cell_px in ((1, 0.0), (2, 0.0), (2, DECODABLE_CELL_PX)):
            expected = [any(len(visible_tags(c, PlacedVehicle(v, *p), 2.0, min_cell_px)) >= min_tags
                            for c in world.cameras) for p in poses]
            got = in_some_view_many(world.cameras, v, poses, min_tags, 2.0, min_cell_px)
            assert got.tolist() == expected
            assert 0.05 < np.mean(expected) < 0.95  # both answers, many times
