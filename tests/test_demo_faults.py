"""`toptag demo` on the demo site's faults scenario (toptag/data/demo/scenario-faults.json), as a user
runs it: rsu-ne's clock is 40 ms off (and undisciplined), rsu-sw's camera is turned by 1 deg; every
service is its own process, the buses with the scenario's bus settings (the drift thresholds for the
live pipeline, toptag/data/demo/bus-faults.toml). The demo runs until its live table shows bus-17's estimate of rsu-ne's
offset settled and rsu-sw flagged for drift, then gets Ctrl-C; the report must carry the estimate
near 40 ms and flags on rsu-sw only. The checks count outcomes and wait on what the table shows, never
on the clock, so a busy machine only makes the test wait longer."""
import json
import re

import pytest

from conftest import REPO, DemoRun

pytestmark = pytest.mark.system

SCENARIO = REPO / "toptag" / "data" / "demo" / "scenario-faults.json"
OFFSET_RSU, OFFSET_MS = "rsu-ne", 40.0
DRIFT_RSU = "rsu-sw"
SETTLED_SIGMA_MS = 5.0
GENEROUS_MS = 15.0  # live fixes from rendered images, on a machine others share


# Issue 13. A healthy RSU used to be flagged after the turned one, and on a very busy machine (each RSU under
# 0.2 fixes a second) the turned camera went unflagged for the 600 s the test waits (a pass brought too few
# fixes to decide); the detector now weighs disagreements against each RSU's constant bias and adds an RSU's
# deviation from the others up over the bus's passes (docs/time-and-trust.md, "Drifted cameras").
def test_demo_estimates_the_injected_offset_and_flags_only_the_turned_camera(tmp_path):
    report = tmp_path / "report.json"
    demo = DemoRun(["--scenario", str(SCENARIO), "--duration", "900", "--period", "1", "--report", str(report),
                    "--logs", str(tmp_path / "logs")], tmp_path)
    offset_line = re.compile(rf"{OFFSET_RSU} .* offset bus-17 ([+-]\d+\.\d)±(\d+\.\d) ms")

    def settled() -> bool:  # the live table: rsu-ne's offset known to 5 ms, rsu-sw flagged
        text = demo.stdout()
        est = offset_line.findall(text)
        flagged = re.search(rf"{DRIFT_RSU} .* DRIFT \(bus-17", text)
        return bool(est) and float(est[-1][1]) <= SETTLED_SIGMA_MS and flagged is not None

    stdout = demo.run_until(settled, 600)
    r = json.loads(report.read_text())
    offset = r["rsus"][OFFSET_RSU]["time_offset_ms"]["bus-17"]
    assert abs(offset["estimate"] - OFFSET_MS) < GENEROUS_MS and offset["sigma"] <= 2 * SETTLED_SIGMA_MS, offset
    assert not offset["clock_known"]  # its frames said its clock is undisciplined
    for rsu, v in r["rsus"].items():  # the healthy RSUs: offsets near zero, never flagged
        est = v.get("time_offset_ms", {}).get("bus-17")
        if "bus-17" in v.get("flagged_by", ()):  # flagged: its offset is no estimate (its bias passed for one)
            assert est is None or est["estimate"] is None, (rsu, est)
        elif rsu != OFFSET_RSU and est is not None and est["sigma"] <= SETTLED_SIGMA_MS:
            assert abs(est["estimate"]) < GENEROUS_MS, (rsu, est)
        assert bool(v.get("ever_flagged_by")) == (rsu == DRIFT_RSU), (rsu, v.get("ever_flagged_by"))
    assert f"{DRIFT_RSU}" in stdout and "DRIFT (bus-17: run toptag calibrate check)" in stdout
    paths = r["buses"]["bus-17"]["fix_paths"]
    assert paths["unknown_clock"] > 0 and paths["from_flagged_rsu"] > 0 and paths["accepted"] > 0
