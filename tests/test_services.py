"""The networked system with real processes over Zenoh: an RSU and a bus agent as subprocesses of a
router, the test acting as camera (rendered frames) and as the bus's GNSS."""
import struct
import threading
import time

import numpy as np
import pytest

from protocol import codec, keys
from protocol.messages import Frame, GnssFix, Imu, PoseFix, RsuStatus
from protocol.transport import MessagePublisher, subscribe_messages
from sim.render import PlacedVehicle, render_jpeg
from sim.scenario import bundled_scenario_path
from sim.scene import bundled_vehicle
from toptag.camera import Camera
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration

SITE = bundled_scenario_path().parent
CAMERA = SITE / "corners" / "rsu-sw.json"  # SPEC's corner pole: the frames below lie in the middle of its view
BUS = SITE / "bus-17.json"
MAP = SITE / "corners" / "map.json"
# The approach radius of x1 is 45 m there. Inside, the satellite position is where the frames show the bus (the
# middle of its pass): the bus announces it, and the RSU searches only where it can be.
INSIDE, OUTSIDE = (-1.0, -1.85), (-80.0, -1.85)


@pytest.fixture(scope="module")
def pass_frames():
    """JPEG frames of bus-17 driving through rsu-sw's view, with the truth of each."""
    camera = Camera.load(CAMERA)
    bus = bundled_vehicle("bus_double")
    rng = np.random.default_rng(4)
    out = []
    for i in range(30):
        x, y, yaw = -6.0 + 0.35 * i, -1.85, 0.0
        pv = PlacedVehicle(bus, x, y, yaw, 3.0 + 0.05 * np.sin(i), speed=3.5)
        out.append(((x, y), render_jpeg(camera, [pv], rng=rng)))
    return camera, out


class Camera10Hz:
    """Publishes the rendered frames as rsu-sw's camera at 10 Hz, remembering each frame's truth."""

    def __init__(self, session, camera, frames):
        self.pub = MessagePublisher(session, keys.frame(camera.id), Frame)
        self.camera, self.frames = camera, frames
        self.truth: dict[int, tuple[float, float]] = {}
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        seq = 0
        while not self._stop.is_set():
            truth, jpeg = self.frames[seq % len(self.frames)]
            t = time.time_ns()
            self.truth[t] = truth
            self.pub.put(Frame(rsu_id=self.camera.id, capture_time_ns=t, seq=seq, encoding="jpeg",
                               width=self.camera.width, height=self.camera.height, image=jpeg))
            seq += 1
            self._stop.wait(0.1)

    def close(self):
        self._stop.set()
        self.thread.join(2)
        self.pub.close()


class Gnss:
    """The bus's satellite position, as the simulator would publish it, at 5 Hz."""

    def __init__(self, session, bus_id, where):
        self.pub = MessagePublisher(session, keys.gnss(bus_id), GnssFix)
        self.bus_id, self.where = bus_id, where
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self._stop.is_set():
            x, y = self.where
            self.pub.put(GnssFix(bus_id=self.bus_id, t_ns=time.time_ns(), x=x, y=y, sigma_m=2.0))
            self._stop.wait(0.2)

    def close(self):
        self._stop.set()
        self.thread.join(2)
        self.pub.close()


class Watch:
    """What the test sees on the network: RSU heartbeats and PoseFixes."""

    def __init__(self, session):
        self.status: list[RsuStatus] = []
        self.fixes: list[tuple[int, PoseFix]] = []
        self.subs = [
            subscribe_messages(session, keys.rsu_status(keys.ANY), RsuStatus, self.status.append),
            subscribe_messages(session, keys.pose_fix("x1", keys.ANY, keys.ANY), PoseFix,
                               lambda m: self.fixes.append((time.time_ns(), m))),
        ]

    def latest(self) -> RsuStatus | None:
        return self.status[-1] if self.status else None

    def active(self) -> list[str]:
        s = self.latest()
        return [] if s is None else s.active_buses

    def close(self):
        for s in self.subs:
            s.close()


@pytest.fixture
def system(router, launch, zenoh_session, pass_frames):
    """Router + RSU process + the test session as camera and observer; start_bus() adds a bus agent."""
    client = ["--zenoh-mode", "client", "--connect", router]
    rsu = launch(["-m", "toptag", "rsu", "--camera", str(CAMERA), "--intersection", "x1", *client],
                 ready="ready", timeout=60)
    session = zenoh_session("client", connect=[router])
    watch = Watch(session)
    camera, frames = pass_frames
    cam = Camera10Hz(session, camera, frames)
    gnss = Gnss(session, "bus-17", OUTSIDE)

    def start_bus():
        return launch(["-m", "toptag", "bus", "--vehicle", str(BUS), "--map", str(MAP), *client],
                      ready="ready", timeout=60)

    def start_rsu():
        return launch(["-m", "toptag", "rsu", "--camera", str(CAMERA), "--intersection", "x1", *client],
                      ready="ready", timeout=60)

    yield {"rsu": rsu, "session": session, "watch": watch, "camera": cam, "gnss": gnss,
           "start_bus": start_bus, "start_rsu": start_rsu, "client": client}
    cam.close()
    gnss.close()
    watch.close()


def test_detects_only_between_approach_and_leave(system):
    watch, gnss, cam = system["watch"], system["gnss"], system["camera"]
    bus = system["start_bus"]()
    assert wait_until(lambda: watch.latest() is not None and watch.latest().frames_received >= 20, 60)
    before = watch.latest()
    assert before.frames_processed == 0 and before.frames_idle >= 20 and not watch.fixes  # no bus, no detection

    gnss.where = INSIDE  # the bus enters the approach radius: it announces itself
    assert wait_until(lambda: "bus-17" in watch.active() and len(watch.fixes) >= 15, 60), watch.latest()
    for arrival, fix in watch.fixes:
        truth = cam.truth[fix.capture_time_ns]  # stamped with the frame's capture time, unchanged
        assert np.hypot(fix.x - truth[0], fix.y - truth[1]) < 0.10
        assert fix.rsu_id == "rsu-sw" and fix.bus_id == "bus-17" and arrival > fix.publish_time_ns >= fix.capture_time_ns

    gnss.where = OUTSIDE  # and leaves
    assert wait_until(lambda: "bus-17" not in watch.active(), 30)
    ended = watch.latest()  # the first heartbeat without the bus; the next one comes after every fix
    assert wait_until(lambda: watch.latest().frames_received > ended.frames_received, 30)
    n_fixes, after = len(watch.fixes), watch.latest()
    assert wait_until(lambda: watch.latest().frames_received >= after.frames_received + 15, 60)  # frames come ...
    now = watch.latest()
    assert now.frames_processed == after.frames_processed and len(watch.fixes) == n_fixes  # ... and are dropped
    assert bus.proc.poll() is None


def test_killed_bus_ends_its_session(system):
    import signal

    watch, gnss = system["watch"], system["gnss"]
    bus = system["start_bus"]()
    gnss.where = INSIDE
    assert wait_until(lambda: "bus-17" in watch.active() and len(watch.fixes) > 5, 30)
    gnss.close()  # no more positions: nothing can revive the killed bus
    bus.stop(signal.SIGKILL)
    # No Leave is sent: the liveliness token goes with the bus's TCP connection, and the RSU ends the
    # session on that alone. Frames keep coming; a session still open would keep producing fixes.
    assert wait_until(lambda: "bus-17" not in watch.active(), 60), watch.latest()
    ended = watch.latest()
    assert wait_until(lambda: watch.latest().frames_received > ended.frames_received, 30)
    n_fixes, after = len(watch.fixes), watch.latest()
    assert wait_until(lambda: watch.latest().frames_received >= after.frames_received + 15, 60)
    assert len(watch.fixes) == n_fixes and watch.latest().frames_processed == after.frames_processed


def test_restarted_rsu_resumes_the_active_session(system):
    watch, gnss = system["watch"], system["gnss"]
    system["start_bus"]()
    gnss.where = INSIDE
    assert wait_until(lambda: "bus-17" in watch.active() and watch.fixes, 60)
    assert system["rsu"].stop() == 0  # SIGTERM: a clean exit
    watch.status.clear()
    n = len(watch.fixes)
    system["start_rsu"]()
    assert wait_until(lambda: "bus-17" in watch.active() and len(watch.fixes) > n + 5, 60)


def test_malformed_messages_on_every_key_are_counted_and_services_keep_working(system):
    watch, gnss, session = system["watch"], system["gnss"], system["session"]
    bus = system["start_bus"]()
    gnss.where = INSIDE
    assert wait_until(lambda: "bus-17" in watch.active() and watch.fixes, 60)
    imu = codec.encode(Imu(bus_id="bus-17", t_ns=time.time_ns(), gyro_z=0.0, seq=1))  # a binary layout (codec)
    garbage = [b"", b"\x00\xff", b"{not json", b'{"version": 99, "type": "approach"}', b"[1, 2, 3]",
               b'{"version": 1, "type": "pose_fix", "bus_id": "bus-17"}', imu[:-1],
               imu[:14] + struct.pack(">d", float("nan")) + imu[22:]]
    targets = [keys.approach("x1", "bus-17"), keys.leave("x1", "bus-17"), keys.frame("rsu-sw"),
               keys.pose_fix("x1", "bus-17", "rsu-evil"), keys.imu("bus-17"), keys.gnss("bus-17")]
    rejected_before = watch.latest().messages_rejected
    for key in targets:
        for payload in garbage:
            session.put(key, payload)
    # A JPEG that does not decode, in an otherwise valid frame.
    session.put(keys.frame("rsu-sw"), codec.encode(
        Frame(rsu_id="rsu-sw", capture_time_ns=time.time_ns(), seq=10**6, encoding="jpeg", width=960, height=720,
              image=b"\xff\xd8garbage\xff\xd9")))
    assert wait_until(lambda: watch.latest().messages_rejected >= rejected_before + 3 * len(garbage), 60), \
        watch.latest()
    n = len(watch.fixes)
    assert wait_until(lambda: len(watch.fixes) > n + 10, 60)  # the RSU goes on
    assert "bus-17" in watch.active() and bus.proc.poll() is None
    assert "rejected payload" in bus.output()  # the bus logged what it refused
    assert "Imu: binary payload of 85 bytes, expected 86" in bus.output()
    assert "Imu: gyro_x: must be a finite number, got nan" in bus.output()
    assert system["rsu"].proc.poll() is None


def test_the_bus_diagnoses_the_rsu_and_the_rsu_shows_it_with_its_clock(system):
    """The bus assesses rsu-sw on keys.rsu_diagnosis, rsu-sw shows that in its RsuStatus; both carry
    this host's clock (the test camera's frames say none, so the RSU stamps with its host's). The bus
    gets no IMU here: its filter starts from a fix and every later fix is counted as from the future."""
    from protocol.convert import clock_to_message
    from protocol.messages import FusedPose
    from toptag.hostclock import probe

    watch, gnss, session = system["watch"], system["gnss"], system["session"]
    fused: list[FusedPose] = []
    sub = subscribe_messages(session, keys.fused_pose("bus-17"), FusedPose, fused.append)
    try:
        system["start_bus"]()
        gnss.where = INSIDE

        def diagnosed():
            s = watch.latest()
            return s is not None and any(d.bus_id == "bus-17" for d in s.diagnoses)
        assert wait_until(lambda: diagnosed() and fused and fused[-1].health.future_fixes >= 3, 60), watch.latest()
    finally:
        sub.close()
    host = clock_to_message(probe())
    s = watch.latest()
    d = next(d for d in s.diagnoses if d.bus_id == "bus-17")
    assert s.clock == host and all(f.clock == host for _, f in watch.fixes)
    assert d.rsu_id == "rsu-sw" and d.intersection_id == "x1" and d.clock_known == (host.sync_uncertainty_ns is not None)
    assert not d.drift_flagged and not s.drift_flagged and d.advice is None
    h = fused[-1].health
    assert h.unknown_clock_fixes == (0 if d.clock_known else h.accepted_fixes + h.future_fixes + h.other_fixes
                                     + h.rejected_fixes + h.too_old_fixes)
