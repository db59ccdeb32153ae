"""`toptag eval replay`: the bus fusion re-run offline on a recording is bit-for-bit repeatable, scores
against the recorded truth, and takes filter settings from a TOML file (unknown keys refused)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from protocol import codec, keys
from protocol.messages import GroundTruth, Imu, ImuBatch, PoseFix
from protocol.transport import encoding_for
from services.recording import McapLog
from services.replay_eval import evaluate, load_filter_config
from sim.scenario import bundled_scenario_path, load_scenario
from sim.world import World
from toptag.errors import InputError

T0 = 1_800_000_000_000_000_000
BUS = "bus-42"
FIX_SIGMA = 0.02


def _put(log: McapLog, msg, at_ns: int) -> None:
    log.add(keys.key_of(msg), str(encoding_for(type(msg))), codec.encode(msg), log_time_ns=at_ns)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """8 s of bus-42 crossing the demo intersection: IMU 100 Hz, truth 20 Hz, and fixes from two RSUs
    every 100 ms (truth + 2 cm noise) arriving 40-70 ms late, written as a recorder writes them."""
    return _write_drive(tmp_path_factory.mktemp("drive") / "drive.mcap")


def _write_drive(path, imu_per_message: int = 1):
    """The drive of the fixture `drive`; its IMU samples imu_per_message to an ImuBatch, each batch received
    with its newest sample, when more than one."""
    world = World(load_scenario(bundled_scenario_path()))
    world.start(T0)
    rng = np.random.default_rng(5)
    events = []  # (arrival ns, order, message)
    step = 10_000_000
    for k in range(800):
        t0, t1 = T0 + k * step, T0 + (k + 1) * step
        b = world.imu_between(BUS, t0, t1)
        for i in range(len(b)):
            events.append((int(b.t_ns[i]) + 1_000_000, 0, Imu(bus_id=BUS, t_ns=int(b.t_ns[i]), gyro_z=float(b.gyro_z[i]),
                                                            accel_x=float(b.accel_x[i]), accel_y=float(b.accel_y[i]),
                                                            wheel_speed=float(b.wheel_speed[i]), seq=int(b.seq[i]))))
        for s in world.truth_between(BUS, t0, t1):
            events.append((s.t_ns + 2_000_000, 1, GroundTruth(bus_id=BUS, t_ns=s.t_ns, x=s.x, y=s.y, z=s.z, yaw=s.yaw)))
            if (s.t_ns - T0) % 100_000_000 == 0:
                for j, rsu in enumerate(("rsu-sw", "rsu-ne")):
                    dx, dy, da = rng.normal(0, [FIX_SIGMA, FIX_SIGMA, 0.003])
                    cov = np.diag([FIX_SIGMA ** 2, FIX_SIGMA ** 2, 0.003 ** 2]).tolist()
                    fix = PoseFix(bus_id=BUS, rsu_id=rsu, intersection_id="x1", capture_time_ns=s.t_ns,
                                  publish_time_ns=s.t_ns + 30_000_000, x=s.x + dx, y=s.y + dy, z=s.z, yaw=s.yaw + da,
                                  covariance=cov, method="level", tags_used=[1], reprojection_rms_px=0.1,
                                  frame_seq=int((s.t_ns - T0) // 100_000_000))
                    events.append((s.t_ns + 40_000_000 + j * 30_000_000, 2, fix))
    if imu_per_message > 1:
        samples = [m for _, _, m in events if isinstance(m, Imu)]
        events = [e for e in events if not isinstance(e[2], Imu)]
        for k in range(0, len(samples), imu_per_message):
            batch = samples[k:k + imu_per_message]
            events.append((batch[-1].t_ns + 1_000_000, 0, ImuBatch(bus_id=BUS, samples=batch)))
    log = McapLog(path)
    for at, _, msg in sorted(events, key=lambda e: (e[0], e[1])):
        _put(log, msg, at)
    log.close()
    return path


@pytest.mark.unit
def test_offline_fusion_is_bit_for_bit_repeatable_and_scored_against_truth(drive):
    a = evaluate(drive, BUS, load_filter_config(None))
    b = evaluate(drive, BUS, load_filter_config(None))
    assert a == b  # every figure and the digest of every estimate
    assert a["imu_samples"] == 800 and a["fixes"] == 160
    f = a["fused_vs_truth"]
    assert f["n"] > 100 and f["rms_m"] < FIX_SIGMA  # fusing two RSUs beats one fix
    assert 0.5 * FIX_SIGMA < a["fixes_vs_truth"]["rms_m"] < 2 * FIX_SIGMA


@pytest.mark.unit
def test_imu_samples_several_to_a_message_are_fused_as_one_by_one(drive, tmp_path):
    """A recording of ImuBatches (as the simulator sends them) gives the filter the same samples: re-timed
    at their own stamps, the same estimates to the last bit."""
    batched = _write_drive(tmp_path / "batched.mcap", imu_per_message=4)
    one, four = (evaluate(p, BUS, load_filter_config(None), fix_latency_ms=30) for p in (drive, batched))
    assert four["imu_samples"] == one["imu_samples"] == 800
    assert {**four, "recording": None} == {**one, "recording": None}
    assert evaluate(batched, BUS, load_filter_config(None))["imu_samples"] == 800  # as the recorder received them


@pytest.mark.unit
def test_filter_settings_from_toml_change_the_result_and_unknown_keys_are_refused(drive, tmp_path):
    base = evaluate(drive, BUS, load_filter_config(None))
    cfg = tmp_path / "bus.toml"
    cfg.write_text("[filter]\ngate_probability = 0.95\npos_noise_density = 0.05\n")
    changed = evaluate(drive, BUS, load_filter_config(cfg))
    assert changed["digest"] != base["digest"]
    bad = tmp_path / "bad.toml"
    bad.write_text("[filter]\ngate_probabilty = 0.9\n")
    with pytest.raises(InputError, match="filter.gate_probabilty: unknown key"):
        load_filter_config(bad)


@pytest.mark.unit
def test_fixes_can_be_re_timed_as_a_quiet_machine_would_deliver_them(drive):
    """--fix-latency-ms: every fix arrives that long after its capture (here 40-70 ms as recorded, re-timed
    to 10 ms): the same fixes and IMU, another result; with a latency past the 2 s buffer most fixes are
    too old (those after the last IMU sample are not). No RSU is flagged for drift on these healthy fixes (the report lists flags)."""
    recorded = evaluate(drive, BUS, load_filter_config(None))
    quick = evaluate(drive, BUS, load_filter_config(None), fix_latency_ms=10)
    assert quick["fix_latency_ms"] == 10 and recorded["fix_latency_ms"] is None
    assert (quick["fixes"], quick["imu_samples"]) == (recorded["fixes"], recorded["imu_samples"])
    assert quick["digest"] != recorded["digest"] and quick["drift_flags"] == recorded["drift_flags"] == []
    late = evaluate(drive, BUS, load_filter_config(None), fix_latency_ms=3000)
    assert quick["filter"]["too_old"] == 0 and late["filter"]["too_old"] > late["fixes"] / 2


@pytest.mark.integration
def test_eval_replay_command(drive, tmp_path):
    out = tmp_path / "r.json"
    p = subprocess.run([sys.executable, "-m", "toptag", "eval", "replay", str(drive), "--bus", BUS, "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "fused vs truth" in p.stdout and json.loads(out.read_text())["digest"] in p.stdout
    p = subprocess.run([sys.executable, "-m", "toptag", "eval", "replay", str(drive), "--bus", "bus-99"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "no IMU samples of bus 'bus-99'" in p.stderr
