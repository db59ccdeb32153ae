"""The live view's geometry and settings, without a browser: footprints, covariance ellipses, the
viewer's bind address, and the Rerun server started and stopped by its PID."""
import numpy as np
import pytest
from matplotlib.path import Path as Polygon

from services.view.app import _flip, covariance_ellipse
from services.view.rerun_server import RerunServer, ViewerError, parse_bind
from services.view.site import camera_footprint, load_site
from sim.scenario import bundled_scenario_path, load_scenario

@pytest.fixture(scope="module")
def site():
    sc = load_scenario(bundled_scenario_path())
    return load_site(sc.map_path(), sc.camera_paths(), sc.vehicle_paths())


@pytest.mark.unit
def test_a_footprint_holds_exactly_the_roof_points_its_camera_sees(site):
    from toptag.camera import Camera

    sc = load_scenario(bundled_scenario_path())
    cam = Camera.load(sc.camera_paths()[0])
    poly = Polygon(camera_footprint(cam, site.roof_height, max_range=200.0))
    rng = np.random.default_rng(1)
    pts = rng.uniform(-40, 40, (4000, 2))
    world = np.column_stack([pts, np.full(len(pts), site.roof_height)])
    in_front = cam.to_camera(world)[:, 2] > 0
    seen = in_front & cam.in_image(cam.project(world), margin=2.0)
    inside = poly.contains_points(pts)
    near_edge = in_front & cam.in_image(cam.project(world), margin=-4.0) & ~cam.in_image(cam.project(world), margin=6.0)
    assert seen.sum() > 200
    assert np.all(inside[seen & ~near_edge]) and not np.any(inside[~seen & ~near_edge & in_front])


@pytest.mark.unit
def test_the_map_has_every_rsu_and_north_up(site):
    assert [r.id for r in site.rsus] == ["rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"]
    ne = next(r for r in site.rsus if r.id == "rsu-ne")
    assert ne.position[0] > 0 and ne.position[1] > 0
    assert _flip(ne.position)[0, 1] < 0  # north of the centre is up in the view (y down)


@pytest.mark.unit
def test_covariance_ellipse_axes():
    cov = np.array([[0.04, 0.0], [0.0, 0.01]])  # sigma 20 cm along x, 10 cm along y
    e = covariance_ellipse(1.0, 2.0, cov)
    half = (e.max(axis=0) - e.min(axis=0)) / 2
    assert np.allclose(half, np.sqrt(5.991) * np.array([0.2, 0.1]), rtol=1e-3)
    assert np.allclose(e.mean(axis=0), [1.0, 2.0], atol=1e-2)


@pytest.mark.unit
def test_bind_address_is_checked():
    assert parse_bind("127.0.0.1:9090") == ("127.0.0.1", 9090)
    assert parse_bind("127.0.0.1") == ("127.0.0.1", 0)
    for bad in ("localhost:x", "example:80", "127.0.0.1:70000"):
        with pytest.raises(ViewerError):
            parse_bind(bad)


@pytest.mark.integration
def test_rerun_server_listens_on_loopback_and_stops_by_pid():
    import socket

    server = RerunServer("127.0.0.1")
    server.start()
    try:
        assert server.proc.poll() is None
        with socket.create_connection(("127.0.0.1", server.web_port), timeout=2):
            pass
        assert server.url.startswith(f"http://127.0.0.1:{server.web_port}/?url=rerun%2Bhttp")
    finally:
        server.stop()
    assert server.proc.poll() is not None


@pytest.mark.integration
def test_rerun_server_dies_with_its_parent_even_when_killed(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from toptag.waiting import wait_until

    script = ("from services.view.rerun_server import RerunServer\n"
              "import time\ns = RerunServer('127.0.0.1'); s.start(); print(s.proc.pid, flush=True); time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)

        def gone():
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                return True
            with open(f"/proc/{child}/stat") as f:  # a zombie until its reaper collects it
                return f.read().split()[2] == "Z"
        assert wait_until(gone, 10), "the rerun server outlived the view"
    finally:
        if parent.poll() is None:
            parent.kill()


@pytest.mark.integration
def test_a_tick_draws_every_panel(site, zenoh_session):
    """The drawing step on a state filled by hand (as the subscriptions fill it): map, camera with
    overlay, plots and status go to a Rerun recording without error."""
    import cv2
    import rerun as rr
    from conftest import make_samples

    from services.view.app import LiveView

    rec = rr.RecordingStream("toptag-test")
    rec.memory_recording()
    view = LiveView(zenoh_session("peer"), rec, site)
    s = make_samples()
    t = s["GroundTruth"].t_ns
    fused = s["FusedPose"].model_copy(update={"bus_id": "bus-17", "t_ns": t})
    for k in range(3):
        view.state.on_truth(s["GroundTruth"].model_copy(update={"bus_id": "bus-17", "t_ns": t + k * 50_000_000}))
        view.state.on_fused(fused.model_copy(update={"t_ns": t + k * 20_000_000}))
    view.state.on_fix(s["PoseFix"].model_copy(update={"bus_id": "bus-17"}))
    ok, jpeg = cv2.imencode(".jpg", np.full((720, 960), 128, np.uint8))
    view.state.on_frame(s["Frame"].model_copy(update={"image": jpeg.tobytes(), "seq": 1234}))
    view.state.on_detections(s["TagDetections"].model_copy(update={"frame_seq": 1234}))
    view.tick()
    view.close()
    assert view.images_drawn == 1 and view.overlays_drawn == 1
    assert "bus-17" not in view._cleared
