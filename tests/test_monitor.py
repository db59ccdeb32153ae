"""`toptag monitor --duration`: the span it watches starts with the buses' traffic, not with its own start
(a monitor started before the simulator and the buses, as in docker compose, must not run out first)."""
from __future__ import annotations

import json
import time

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
