"""`toptag demo` as a user runs it: every service its own process, a report at the end."""
import json
import subprocess
import sys


def test_demo_runs_two_buses_through_four_rsus_and_reports(tmp_path):
    report = tmp_path / "report.json"
    p = subprocess.run([sys.executable, "-m", "toptag", "demo", "--duration", "28", "--report", str(report),
                        "--logs", str(tmp_path / "logs")], capture_output=True, text=True, timeout=150)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    r = json.loads(report.read_text())
    assert set(r["rsus"]) == {"rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"}
    assert all(v == 0 for v in r["exit_codes"].values()), r["exit_codes"]
    for rsu in r["rsus"].values():
        assert rsu["frames"] > 100 and rsu["seconds_active"] > 5
    assert sum(rsu["frames_detected"] for rsu in r["rsus"].values()) > 100
    for bus in ("bus-17", "bus-42"):
        b = r["buses"][bus]
        assert b["fixes_received"] > 40 and len(b["fixes_by_rsu"]) >= 2, b
        assert b["fix_pos_rms_m"] < 0.10, b
        assert b["fused_ok_samples"] > 50 and b["fused_pos_rms_m"] < 0.05, b
        assert b["latency_ms_p50"] < 300
    assert "t=" in p.stdout and "fused err" in p.stdout  # live progress was shown
