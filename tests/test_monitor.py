"""`toptag monitor --duration`: the span it watches starts with the buses' traffic, not with its own start
(a monitor started before the simulator and the buses, as in docker compose, must not run out first)."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from conftest import key_for, make_samples

from protocol import GroundTruth, RsuStatus
from protocol.transport import publish
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration


def test_monitor_duration_counts_from_the_first_bus_message(router, launch, zenoh_session, tmp_path):
    report = tmp_path / "report.json"
    mon = launch(["-m", "toptag", "monitor", "--duration", "1", "--period", "0.2", "--report", str(report)],
                 env={"TOPTAG_ZENOH_MODE": "client", "TOPTAG_ZENOH_CONNECT": router})
    s = zenoh_session("client", connect=[router])
    status: RsuStatus = make_samples()["RsuStatus"].model_copy(update={
        "source": "stream rtsp://127.0.0.1:8554/cam", "source_connected": False, "source_fps": 0.0,
        "source_reconnects": 3, "source_last_error": "no stream answered at rtsp://127.0.0.1:8554/cam"})
    source_line = "source stream rtsp://127.0.0.1:8554/cam LOST 0.0 fps reconnects 3 last error: no stream answered"

    def heartbeat() -> bool:
        publish(s, key_for(status), status)
        time.sleep(0.2)
        return source_line in mon.output()

    # Until the monitor shows the RSU (it is subscribed: on a busy machine that takes a while), then on:
    # RSU heartbeats alone are not traffic, several times --duration later the monitor still watches.
    assert wait_until(heartbeat, 60), mon.output()[-2000:]
    for _ in range(15):
        heartbeat()
    assert mon.proc.poll() is None, mon.output()[-2000:]
    assert not report.exists()
    truth = GroundTruth(bus_id="bus-17", t_ns=time.time_ns(), x=1.0, y=2.0, yaw=0.0)

    def bus_message() -> bool:  # the first that arrives: 1 s later it reports and exits 0 (truth goes out
        publish(s, key_for(truth), truth)  # with DROP: on a busy machine one put alone can be shed)
        return mon.proc.poll() is not None
    assert wait_until(bus_message, 30, 0.3), mon.output()[-2000:]
    assert mon.proc.returncode == 0
    summary = json.loads(report.read_text())
    assert "bus-17" in summary["buses"] and status.rsu_id in summary["rsus"]
    # the camera source as the RSU reports it: in the summary and on the progress table
    rsu = summary["rsus"][status.rsu_id]
    assert rsu["source_connected"] is False and rsu["source_reconnects"] == 3


def test_fused_ok_is_also_counted_where_a_camera_can_see_the_bus(zenoh_session):
    """With the scenario's cameras (ViewCoverage), the summary splits the fused samples in session into those
    taken while two of the bus's tags were decodable in some camera's image (its true pose at the sample's time) and
    says how many of those were ok: a bus out of every view is "degraded" there by design."""
    from services.monitor import Monitor, ViewCoverage
    from sim.scenario import bundled_scenario_path, load_scenario

    views = ViewCoverage(load_scenario(bundled_scenario_path()))
    # the eastbound lane past the centre (two cameras; roof at the bus's height), and far away
    assert views("bus-42", [(5.0, -1.9, 0.0, np.nan), (120.0, 0.0, 0.0, 3.2)]).tolist() == [True, False]
    assert views("bus-99", [(0.0, 0.0, 0.0, np.nan)]) is None  # not a bus of the scenario
    samples = make_samples()
    monitor = Monitor(zenoh_session("peer"), in_view=views)
    try:
        monitor._on_approach(samples["Approach"].model_copy(update={"bus_id": "bus-42"}))
        t0 = 1_000_000_000_000
        fused = samples["FusedPose"]
        for k, (x, status) in enumerate(((5.0, "ok"), (120.0, "degraded"), (5.5, "degraded"), (121.0, "ok"))):
            t = t0 + k * 1_000_000_000
            for dt in (0, 100_000_000):
                monitor._on_truth(GroundTruth(bus_id="bus-42", t_ns=t + dt, x=x, y=-1.9, z=3.2, yaw=0.0))
            monitor._on_fused(fused.model_copy(update={
                "bus_id": "bus-42", "t_ns": t + 50_000_000, "x": x, "y": -1.9,
                "health": fused.health.model_copy(update={"status": status})}))
        bus = monitor.summary()["buses"]["bus-42"]
        assert bus["fused_in_session_samples"] == 4 and bus["fused_in_session_ok_fraction"] == 0.5
        assert bus["fused_in_view_samples"] == 2 and bus["fused_in_view_ok_fraction"] == 0.5
    finally:
        monitor.close()
    blind = Monitor(zenoh_session("peer"))  # no cameras given: nothing said about views
    try:
        assert blind.summary()["all_buses"]["fused_in_view_samples"] is None
    finally:
        blind.close()
