"""Shared test helpers: free ports, real zenoh sessions (peer, multicast scouting off, explicit
tcp/127.0.0.1 endpoints), and a process launcher that stops every process it started, by PID."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from tiers import pytest_collection_modifyitems  # noqa: F401  (the hook: one tier per test)

from services.processes import free_port as _free_port
from services.processes import stop_process
from toptag.waiting import wait_until

REPO = Path(__file__).resolve().parents[1]

# A line a test wants printed in the terminal summary (figures of a system test, such as timings):
# request.node.user_properties.append((f"{SUMMARY}:<name>", line)); the last line of each name is printed.
# User properties travel with the test reports, so this works under pytest-xdist as well.
SUMMARY = "summary"


def pytest_configure(config):
    """The solvers', the bus filter's and the renderer's compiled kernels into numba's on-disk cache once,
    before any test (or process a test starts) solves, filters or renders: a process without the cache
    compiles them on its first call, seconds of CPU (toptag/solvers/warmup.py, sim/render_kernels.py). xdist's workers start after the controller's configure."""
    if not hasattr(config, "workerinput"):
        from sim.render_kernels import warm_up as warm_up_renderer
        from toptag.solvers.warmup import warm_up_all

        warm_up_all()
        warm_up_renderer()


def pytest_xdist_auto_num_workers(config):
    """`-n auto` (make test): a worker per core, and one more for the system tests. They run one after
    another on one worker (tests/tiers.py), which mostly waits while the whole system runs in its child
    processes (the demo takes ~0.7 cores, README); with a worker per core the rest of the suite had the
    other core only and the run left CPU unused: on 2 cores, the suite without its system tests used 1.08
    cores on 2 workers (273 s) and 1.40 on 3 (228 s), load average 3.5-4.0 from the other engineers
    (2026-11-24). PYTEST_XDIST_AUTO_NUM_WORKERS still sets the number (xdist's own hook reads it)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return len(os.sched_getaffinity(0)) + 1


def pytest_terminal_summary(terminalreporter, config):
    lines: dict[str, str] = {}
    for reports in terminalreporter.stats.values():
        for rep in reports:
            for name, value in getattr(rep, "user_properties", ()):
                if isinstance(name, str) and name.startswith(SUMMARY + ":"):
                    lines[name] = value
    for line in lines.values():
        terminalreporter.write_line(line)


@pytest.fixture
def free_port():
    """free_port() -> int."""
    return _free_port


# ---- zenoh sessions ---------------------------------------------------------------------------

@pytest.fixture
def zenoh_session():
    """zenoh_session(mode="peer", listen=[...], connect=[...]) -> zenoh.Session; all closed at teardown."""
    from protocol.transport import open_session

    sessions = []

    def make(mode: str = "peer", listen=(), connect=(), **extra):
        s = open_session(mode=mode, listen=list(listen), connect=list(connect), multicast_scouting=False,
                         extra=extra or None)
        sessions.append(s)
        return s

    yield make
    for s in reversed(sessions):
        try:
            s.close()
        except Exception:
            pass


@pytest.fixture
def peer_pair(zenoh_session, free_port):
    """Two peer sessions joined over tcp/127.0.0.1:<free port>: (listener, connector)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh_session("peer", listen=[ep])
    b = zenoh_session("peer", connect=[ep])
    assert wait_until(lambda: len(b.info.peers_zid()) > 0, 60), "peers did not connect"
    return a, b


# ---- processes --------------------------------------------------------------------------------

def assert_fused_claims_hold(bus: str, b: dict) -> None:
    """A bus's fused poses in the monitor's report hold what they claim (services.monitor): "ok" poses within
    their 3 sigma, and those claiming cm-level accuracy within 8 cm RMS. Not the RMS of every "ok" pose: a
    filter is "ok" up to 0.5 m sigma, and on a busy machine, with few fixes, honestly so (bus-17's "ok" poses
    were 13.7 cm RMS once at load 27, with 34 fixes in 150 s)."""
    assert b["fused_ok_samples"] > 0, (bus, b)
    assert b["fused_ok_held_fraction"] >= 0.9, (bus, b)
    assert b["fused_confident_pos_rms_m"] is None or b["fused_confident_pos_rms_m"] < 0.08, (bus, b)


class DemoRun:
    """`toptag demo ARGS` as a user runs it: its stdout (the live table) read as it comes, its stderr into a
    file (a pipe nobody reads while the demo runs would fill and block it); stopped with Ctrl-C."""

    def __init__(self, args: list[str], tmp_path: Path):
        self.err_path = tmp_path / "demo.stderr"
        with open(self.err_path, "w") as err:
            self.proc = subprocess.Popen([sys.executable, "-m", "toptag", "demo", *args], cwd=REPO, env=clean_env(),
                                         stdout=subprocess.PIPE, stderr=err, text=True)
        self._out: list[str] = []
        self._reader = threading.Thread(target=lambda: self._out.extend(self.proc.stdout), daemon=True)
        self._reader.start()

    def stdout(self) -> str:
        return "".join(self._out)

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def stop(self) -> int:
        """Ctrl-C (every service stopped, the report written) and the exit code."""
        code = stop_process(self.proc, signal.SIGINT, grace_s=120)
        self._reader.join(10)
        return code

    def run_until(self, shown: Callable[[], bool], timeout_s: float) -> str:
        """Wait (looking every second) until `shown()` (what the live table shows), then Ctrl-C; asserts that
        it was shown while the demo ran and that the demo exited 0; its stdout."""
        try:
            assert wait_until(lambda: shown() or self.proc.poll() is not None, timeout_s, 1), self.stdout()[-4000:]
            assert self.proc.poll() is None, self.stdout()[-3000:] + self.stderr()[-3000:]
        finally:
            code = self.stop()
        assert code == 0, self.stdout()[-3000:] + self.stderr()[-3000:]
        return self.stdout()


def clean_env(extra: dict | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TOPTAG_ZENOH_", "ZENOH_"))}
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


class Launched:
    def __init__(self, proc: subprocess.Popen, log_path: Path):
        self.proc = proc
        self.pid = proc.pid
        self.log_path = log_path

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def wait_for(self, text: str, timeout: float = 60.0) -> bool:
        """Wait until ``text`` appears in the process's combined stdout/stderr (False if it exits or
        the timeout passes first)."""
        def seen():
            return text in self.output() or self.proc.poll() is not None
        wait_until(seen, timeout, 0.02)
        return text in self.output()

    def stop(self, sig=signal.SIGTERM, timeout: float = 20.0) -> int:
        """Send ``sig`` to this PID, wait; SIGKILL if it does not exit. Returns the exit code."""
        return stop_process(self.proc, sig, timeout)


@pytest.fixture
def launch(tmp_path):
    """launch(args, env=None, ready=None, timeout=60) -> Launched. ``args`` follow sys.executable
    (e.g. ["-m", "services.router", ...]). If ``ready`` is given, wait for that text in the output.
    Every launched process is stopped by PID at teardown (SIGTERM, then SIGKILL)."""
    started: list[Launched] = []

    def start(args, env: dict | None = None, ready: str | None = None, timeout: float = 60.0) -> Launched:
        log_path = tmp_path / f"proc-{len(started)}.log"
        with open(log_path, "wb") as out:
            proc = subprocess.Popen([sys.executable, *args], cwd=REPO, env=clean_env(env), stdout=out,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        p = Launched(proc, log_path)
        started.append(p)
        if ready is not None and not p.wait_for(ready, timeout):
            raise AssertionError(f"process {args} not ready ({ready!r} not seen); exit code "
                                 f"{proc.poll()}; output:\n{p.output()[-2000:]}")
        return p

    yield start
    for p in reversed(started):
        p.stop()


@pytest.fixture
def router(launch, free_port):
    """A real `python -m services.router` subprocess on tcp/127.0.0.1:<free port>; yields its endpoint."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    proc = launch(["-m", "services.router", "--listen", ep], ready="router listening on")
    yield ep
    proc.stop()


# ---- sample messages --------------------------------------------------------------------------

def make_samples() -> dict:
    """One valid instance of every protocol message type, keyed by type name."""
    import json

    from protocol import (
        ActiveSessions,
        Approach,
        ClockInfo,
        Frame,
        FusedPose,
        FusionHealth,
        GnssFix,
        GroundTruth,
        Imu,
        ImuBatch,
        Leave,
        PoseFix,
        RsuDiagnosis,
        RsuStatus,
        TagDetections,
    )
    from protocol.messages import DetectedTag
    from toptag.vehicle import VehicleFile

    vehicle = VehicleFile.model_validate(json.loads((REPO / "toptag/data/bus_double.json").read_text()))
    t = 1_763_700_000_000_000_000
    cov = [[0.01, 0.001, 0.0], [0.001, 0.02, 0.0], [0.0, 0.0, 0.0004]]
    approach = Approach(bus_id=vehicle.id, intersection_id="x1", vehicle=vehicle, reference_time_ns=t,
                        clock=ClockInfo(source="ptp", sync_uncertainty_ns=50_000), seq=3)
    diagnosis = RsuDiagnosis(bus_id=vehicle.id, rsu_id="rsu-sw", intersection_id="x1", reference_time_ns=t,
                             time_offset_ns=-31_000_000, time_offset_sigma_ns=1_200_000, clock_known=False,
                             drift_flagged=True, flagged_since_ns=t - 4 * 10**9, disagreement_m=0.052,
                             disagreement_yaw_rad=-0.0035, disagreement_statistic=88.0, fixes_accepted=40,
                             fixes_gated=3, advice="check its calibration: toptag calibrate check ...")
    samples = [
        approach,
        Leave(bus_id=vehicle.id, intersection_id="x1", reference_time_ns=t + 9, reason="passed"),
        ActiveSessions(intersection_id="x1", responder_id=vehicle.id, reference_time_ns=t, sessions=[approach]),
        PoseFix(bus_id=vehicle.id, rsu_id="rsu-sw", intersection_id="x1", capture_time_ns=t,
                publish_time_ns=t + 35_000_000, x=3.25, y=-7.5, z=3.02, yaw=0.7, covariance=cov,
                method="s_opt", tags_used=[3, 7], reprojection_rms_px=0.41, frame_seq=1234,
                clock=ClockInfo(source="system")),
        diagnosis,
        RsuStatus(rsu_id="rsu-sw", intersection_id="x1", reference_time_ns=t, started_ns=t - 10**9,
                  active_buses=[vehicle.id], frames_received=100, frames_processed=90, frames_skipped=10,
                  fixes_published=80, messages_rejected=1, detection_ns_mean=21_000_000,
                  detection_ns_max=40_000_000, clock=ClockInfo(source="ntp", sync_uncertainty_ns=800_000),
                  diagnoses=[diagnosis], drift_flagged=True),
        TagDetections(rsu_id="rsu-sw", capture_time_ns=t, frame_seq=1234, width=960, height=720,
                      tags=[DetectedTag(bus_id=vehicle.id, tag_id=3, corners=[(10.5, 20.0), (40.0, 21.0), (39.5, 50.0),
                                                                               (11.0, 49.0)]),
                            DetectedTag(bus_id=vehicle.id, tag_id=7, corners=[(60.0, 20.0), (90.0, 21.0), (89.5, 50.0),
                                                                               (61.0, 49.0)], used=False)],
                      modes={vehicle.id: "tracked"}, processing_ns=7_000_000),
        Frame(rsu_id="rsu-sw", capture_time_ns=t, seq=7, encoding="jpeg", width=960, height=720,
              image=b"\xff\xd8" + bytes(range(256)) * 40 + b"\xff\xd9"),
        Imu(bus_id=vehicle.id, t_ns=t, gyro_x=0.001, gyro_y=-0.002, gyro_z=0.05, accel_x=0.3, accel_y=0.01,
            accel_z=9.81, wheel_speed=5.5, seq=99),
        ImuBatch(bus_id=vehicle.id, seq=24, samples=[
            Imu(bus_id=vehicle.id, t_ns=t + 10_000_000 * k, gyro_z=0.05 + 0.01 * k, accel_x=0.3, accel_y=-0.01 * k,
                wheel_speed=None if k == 2 else 5.5, seq=None if k == 1 else 96 + k) for k in range(4)]),
        GroundTruth(bus_id=vehicle.id, t_ns=t, x=1.0, y=2.0, z=3.0, yaw=-3.0, speed=5.0, yaw_rate=0.1),
        GnssFix(bus_id=vehicle.id, t_ns=t, x=-41.0, y=-1.5, sigma_m=2.0),
        FusedPose(bus_id=vehicle.id, t_ns=t, x=1.0, y=2.0, yaw=0.1, speed=5.0, yaw_rate=0.05, covariance=cov,
                  health=FusionHealth(accepted_fixes=10, rejected_fixes=2, since_last_fix_ns=80_000_000,
                                      last_fix_delay_ns=35_000_000, last_fix_rsu="rsu-sw", too_old_fixes=1,
                                      flagged_rsu_fixes=4, unknown_clock_fixes=12, flagged_rsus=["rsu-sw"])),
    ]
    return {type(m).__name__: m for m in samples}


def key_for(msg) -> str:
    """The key a sample message is published on."""
    from protocol import keys
    return keys.key_of(msg)


@pytest.fixture
def samples() -> dict:
    return make_samples()
