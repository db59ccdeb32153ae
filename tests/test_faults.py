"""Faults the simulator injects (sim/faults.py): a turned camera as the renderer and the RSU see it, a
clock offset and a capture latency on the frames of the live world, and the scenario and command-line
forms of them."""
import json
import math

import cv2
import numpy as np
import pytest
from conftest import REPO

from sim.faults import Drift, RsuFault, faults_from_options, parse_drift, seen_pose, turned
from sim.image_model import ImageModel
from sim.scenario import bundled_scenario_path, load_scenario
from sim.scene import rsu_camera
from sim.world import World
from toptag.inputs import InputError
from toptag.rsu.pipeline import RsuPipeline

pytestmark = pytest.mark.unit

DEMO = REPO / "toptag" / "data" / "demo"
MS = 1_000_000


def test_a_turned_camera_keeps_its_centre_and_sees_the_world_move_the_other_way():
    cam = rsu_camera("sw")
    p = np.array([[0.0, 0.0, 3.0]])
    u0 = cam.project(p, distort=False)[0]
    left = turned(cam, math.radians(1.0))  # turned counter-clockwise seen from above
    down = turned(cam, 0.0, math.radians(1.0))  # tilted further down
    assert np.allclose(left.center, cam.center) and np.allclose(down.center, cam.center)
    assert left.project(p, distort=False)[0][0] > u0[0] + 5  # the scene moves right in the image
    assert down.project(p, distort=False)[0][1] < u0[1] - 5  # and up when it tilts down
    assert turned(cam, 0.0) is cam


def test_seen_pose_turns_the_bus_about_the_pole():
    cam = rsu_camera("sw")
    x, y, yaw = seen_pose(cam, turned(cam, math.radians(0.2)), 0.0, 0.0, 0.3, 3.0)
    c = cam.center[:2]
    a = -math.radians(0.2)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    assert np.allclose([x, y], c + R @ (np.zeros(2) - c), atol=1e-9)
    assert math.isclose(yaw, 0.3 - math.radians(0.2), abs_tol=1e-9)


@pytest.fixture(scope="module")
def drifted_world():
    sc = load_scenario(bundled_scenario_path())
    sc = sc.model_copy(update={"image_model": ImageModel.ideal(), "faults": {
        "rsu-sw": RsuFault(drift=Drift(yaw_deg=0.5, at_s=0.0)),
        "rsu-ne": RsuFault(clock_offset_ms=30.0, capture_latency_ms=40.0)}})
    w = World(sc)
    w.start(0)
    return w


def _in_view(world: World, rsu: str, bus: str) -> int:
    for t in range(0, world.legs_end_ns, 100 * MS):
        if len(world.tags_in_view(rsu, t).get(bus, [])) == 2:
            st = world.state(bus, t)
            if math.hypot(st.x - world.camera(rsu).center[0], st.y - world.camera(rsu).center[1]) < 16:
                return t
    raise AssertionError(f"{bus} never in {rsu}'s view")


def test_the_rsu_with_its_surveyed_camera_sees_a_turned_camera_frame_turned_about_its_pole(drifted_world):
    """The live world renders rsu-sw's frames with the turned camera; the RSU pipeline, holding the
    surveyed camera file, reports the bus turned about the pole by -0.5 deg: what seen_pose predicts
    (the fusion study's drift model), and far from the truth."""
    w = drifted_world
    t = _in_view(w, "rsu-sw", "bus-42")
    jpeg, stamp = w.capture("rsu-sw", t)
    assert stamp == t
    gray = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    surveyed = w.camera("rsu-sw")
    pipe = RsuPipeline(surveyed)
    pipe.add_vehicle(w.vehicle("bus-42"))
    fix = pipe.process(gray, stamp, 0).vehicles["bus-42"].fix
    st = w.state("bus-42", t)
    expected = seen_pose(surveyed, w.actual_camera("rsu-sw", t), st.x, st.y, st.yaw, st.z)
    truth_err = math.hypot(fix.x - st.x, fix.y - st.y)
    assert math.hypot(fix.x - expected[0], fix.y - expected[1]) < 0.02 < 0.5 * truth_err
    assert abs(math.remainder(fix.yaw - expected[2], 2 * math.pi)) < math.radians(0.1)


def test_clock_offset_and_capture_latency_on_the_frames(drifted_world):
    """rsu-ne: 40 ms latency (the frame shows the scene 40 ms before its tick) and a clock 30 ms off
    (stamped 30 ms after its tick)."""
    w = drifted_world
    t = _in_view(w, "rsu-ne", "bus-17")
    jpeg, stamp = w.capture("rsu-ne", t)
    assert stamp == t + 30 * MS
    assert jpeg == w.render_jpeg("rsu-ne", t - 40 * MS)  # an ideal image model: no noise, same bytes
    assert jpeg != w.render_jpeg("rsu-ne", t)
    assert w.actual_camera("rsu-ne", t) is w.camera("rsu-ne")


def test_a_ramp_turns_the_camera_gradually():
    d = Drift(yaw_deg=0.4, at_s=10.0, ramp_s=20.0)
    assert [d.fraction(t) for t in (5.0, 10.0, 20.0, 30.0, 99.0)] == [0.0, 0.0, 0.5, 1.0, 1.0]
    assert math.isclose(d.angles(20.0)[0], math.radians(0.2))


def test_the_bundled_faults_scenario_loads():
    sc = load_scenario(DEMO / "scenario-faults.json")
    w = World(sc)
    assert sc.faults["rsu-ne"].clock_offset_ms == 40 and sc.faults["rsu-sw"].drift.yaw_deg == 1.0
    # its buses' settings: a busy machine's, a file that loads, with a 10 cm / 0.3 deg box (the camera
    # turns by 1 deg); the filter's defaults are 3 cm / 0.1 deg with the view-dependent error weighed
    from services.bus.agent import BusSettings
    from toptag.fusion.filter import FilterConfig
    from toptag.settings import load_settings
    f = load_settings(sc.bus_config, BusSettings).filter
    assert (f.drift_min_pos_m, f.drift_min_yaw_deg) == (0.10, 0.3)
    assert (f.drift_window_s, f.drift_min_fixes) == (30.0, 6.0)
    d = FilterConfig()
    assert (d.drift_min_pos_m, d.drift_min_yaw_deg, d.drift_view_bias_share, d.drift_view_corr_m) == \
        (0.03, 0.1, 0.76, 6.35)
    assert f.drift_view_bias_share == d.drift_view_bias_share
    # the 0.2 deg scenario's buses run the filter's defaults (no bus settings file), as a user's do
    assert load_scenario(DEMO / "scenario-drift02.json").bus_config is None
    assert not w.faults[w.rsu_ids.index("rsu-ne")].clock_disciplined
    assert w.faults[w.rsu_ids.index("rsu-se")] == RsuFault()


def test_faults_on_unknown_rsus_or_out_of_range_are_refused(tmp_path):
    data = json.loads((DEMO / "scenario-faults.json").read_text())
    data["map"] = str(DEMO / "map.json")
    data["rsus"] = [str(DEMO / r) for r in data["rsus"]]
    data["buses"][0]["vehicle"] = str(DEMO / "bus-17.json")
    for faults, says in (({"rsu-xx": {"clock_offset_ms": 5}}, "faults name RSUs it does not have: rsu-xx"),
                         ({"rsu-ne": {"clock_offset_ms": 5000}}, "faults.rsu-ne.clock_offset_ms"),
                         ({"rsu-ne": {"drift": {"yaw_deg": 1, "when": 3}}}, "faults.rsu-ne.drift.when")):
        p = tmp_path / "s.json"
        p.write_text(json.dumps(dict(data, faults=faults)))
        with pytest.raises(InputError, match=says.replace(".", r"\.")):
            World(load_scenario(p))


def test_command_line_forms():
    f = faults_from_options("rsu-se=30,rsu-ne=-12.5", "rsu-nw=40", "rsu-se=0.2@30,rsu-sw=0.5@10/60")
    assert f["rsu-se"].clock_offset_ms == 30 and f["rsu-se"].drift == Drift(yaw_deg=0.2, at_s=30)
    assert f["rsu-ne"].time_offset_ns == -12_500_000 and not f["rsu-ne"].clock_disciplined
    assert f["rsu-nw"].clock_disciplined and f["rsu-nw"].time_offset_ns == 40 * MS
    assert f["rsu-sw"].drift.ramp_s == 60
    assert parse_drift("rsu-se=0.2") == {"rsu-se": Drift(yaw_deg=0.2)}
    for bad in ("rsu-se", "=3", "rsu-se=x"):
        with pytest.raises(InputError, match="--clock-offset-ms: expected RSU=MS"):
            faults_from_options(clock_offset_ms=bad)
    with pytest.raises(InputError, match="fault of rsu-se"):
        faults_from_options(capture_latency_ms="rsu-se=-5")


def test_livefix_names_a_bad_bus(capsys):
    """`toptag eval livefix` (the live pipeline's bias per RSU; its run is the figure in
    docs/figures/time-trust/livefix, minutes of rendering): an unknown bus is a one-line error."""
    from sim.studies.livefix import main
    assert main(["--bus", "bus-99"]) == 2
    assert "--bus bus-99: not in the scenario" in capsys.readouterr().err
