"""Real camera streams: a rendered drive recorded as H.264 (`toptag sim record`), located offline as a
video and as images, served over RTSP on loopback by Debian's gst-rtsp-server, and an RSU process
reading that stream, including a stream that drops and comes back. Also the newest-frame reader and the
source parsing on their own."""
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.processes import free_port, stop_process
from toptag.waiting import wait_until

REPO = Path(__file__).resolve().parents[1]
SYSTEM_PYTHON = "/usr/bin/python3"
# One worker for the module: under pytest-xdist each worker would record the drive (~30 s) for itself.
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("streams")]


def _gst_rtsp_available() -> str | None:
    """None when the system python can run gst-rtsp-server, else why not."""
    if not Path(SYSTEM_PYTHON).exists():
        return f"{SYSTEM_PYTHON} not found"
    r = subprocess.run([SYSTEM_PYTHON, "-c", "import gi; gi.require_version('GstRtspServer', '1.0'); "
                        "from gi.repository import Gst, GstRtspServer; Gst.init(None); "
                        "assert all(Gst.ElementFactory.find(e) for e in ('qtdemux', 'h264parse', 'rtph264pay'))"],
                       capture_output=True, text=True)
    return None if r.returncode == 0 else "gst-rtsp-server not usable (make stream-tools installs it): " + \
        (r.stderr.strip().splitlines() or ["?"])[-1]


needs_ffmpeg = pytest.mark.skipif(shutil.which("ffmpeg") is None,
                                  reason="ffmpeg not installed (make stream-tools installs it)")


def _toptag(*args, timeout=600, cwd=None):
    return subprocess.run([sys.executable, "-m", "toptag", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd or REPO)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """6 s of rsu-ne's view of bus-17 turning right past its pole, H.264 and PNG frames, with the truth file."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg not installed (make stream-tools installs it)")
    d = tmp_path_factory.mktemp("drive")
    r = _toptag("sim", "record", "--out", d / "drive.mp4", "--rsu", "rsu-ne", "--start", "42.5", "--duration", "6",
                "--images", d / "frames")
    assert r.returncode == 0, r.stderr
    truth = json.loads((d / "drive.truth.json").read_text())
    (d / "camera.json").write_text(json.dumps(truth["camera"]))
    (d / "bus-17.json").write_text(json.dumps(truth["vehicles"]["bus-17"]))
    return d, truth


def _errors(lines, truth) -> np.ndarray:
    frames = truth["frames"]
    out = []
    for i, line in enumerate(lines):
        d = json.loads(line)
        t = frames[d.get("frame", i)]["vehicles"]["bus-17"]
        out.append(np.hypot(d["x"] - t["x"], d["y"] - t["y"]) if d["ok"] else np.nan)
    return np.array(out)


@needs_ffmpeg
def test_sim_record_writes_h264_and_truth(drive):
    d, truth = drive
    assert len(truth["frames"]) == 60 and truth["codec"] == "h264" and truth["fps"] == 10
    assert all(f["vehicles"]["bus-17"]["tags_in_view"] for f in truth["frames"])
    probe = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries",
                            "stream=codec_name,width,height,nb_frames", "-of", "json", str(d / "drive.mp4")],
                           capture_output=True, text=True)
    s = json.loads(probe.stdout)["streams"][0]
    assert (s["codec_name"], s["width"], s["height"], int(s["nb_frames"])) == ("h264", 960, 720, 60)
    assert len(list((d / "frames").glob("frame-*.png"))) == 60


@needs_ffmpeg
def test_locate_on_a_video_is_as_accurate_as_on_its_frames_as_images(drive):
    d, truth = drive
    video = _toptag("locate", "--camera", d / "camera.json", "--vehicle", d / "bus-17.json", d / "drive.mp4",
                    "--start-ns", truth["frames"][0]["t_ns"])
    assert video.returncode == 0, video.stderr
    lines = video.stdout.splitlines()
    assert len(lines) == 60
    heads = [json.loads(x) for x in lines]
    assert [h["frame"] for h in heads] == list(range(60))
    # the file's own timestamps: frame k at start + k / 10 s
    assert [h["capture_time_ns"] for h in heads] == [f["t_ns"] for f in truth["frames"]]
    images = _toptag("locate", "--camera", d / "camera.json", "--vehicle", d / "bus-17.json",
                     *sorted((d / "frames").glob("frame-*.png")))
    assert images.returncode == 0, images.stderr
    ev, ei = _errors(lines, truth), _errors(images.stdout.splitlines(), truth)
    assert np.isfinite(ev).sum() >= 57 and np.isfinite(ei).sum() >= 57
    rms_v, rms_i = (float(np.sqrt(np.nanmean(e ** 2))) for e in (ev, ei))
    print(f"position RMS: H.264 video {100 * rms_v:.2f} cm, the same frames as PNG {100 * rms_i:.2f} cm")
    assert rms_i < 0.05 and rms_v < 0.05
    assert rms_v <= 1.3 * rms_i + 0.003  # the same accuracy: within 30 % (+3 mm) of the lossless frames


# ---- RTSP ---------------------------------------------------------------------------------------
class RtspServer:
    """tests/rtsp_server.py under the system python, on a fixed port, restartable."""

    def __init__(self, video: Path, port: int, log_dir: Path):
        self.video, self.port, self.log_dir = video, port, log_dir
        self.proc = None
        self.url = f"rtsp://127.0.0.1:{port}/cam"

    def start(self):
        log = open(self.log_dir / f"rtsp-{time.monotonic_ns()}.log", "wb")
        self.proc = subprocess.Popen([SYSTEM_PYTHON, str(REPO / "tests" / "rtsp_server.py"), "--port", str(self.port),
                                      "--video", str(self.video)], stdout=log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL)
        path = Path(log.name)
        assert wait_until(lambda: b"ready" in path.read_bytes() or self.proc.poll() is not None, 30), "rtsp server"
        assert self.proc.poll() is None, path.read_text()

    def kill(self):
        if self.proc is not None:
            stop_process(self.proc, sig=9)
            self.proc = None


@pytest.fixture
def rtsp(drive, tmp_path):
    why = _gst_rtsp_available()
    if why:
        pytest.skip(why)
    d, _ = drive
    server = RtspServer(d / "drive.mp4", free_port(), tmp_path)
    server.start()
    yield server
    server.kill()


def test_locate_reads_an_rtsp_stream(drive, rtsp):
    d, _ = drive
    r = _toptag("locate", "--camera", d / "camera.json", "--vehicle", d / "bus-17.json", rtsp.url,
                "--max-frames", "15", "--capture-latency-ms", "120", timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert [x["frame"] for x in lines] == list(range(15))
    assert sum(x["ok"] for x in lines) >= 12
    now = time.time_ns()
    assert all(now - 120e9 < x["capture_time_ns"] < now for x in lines)  # receive time minus the latency


def test_frames_read_late_from_a_stream_keep_the_stream_s_spacing(rtsp):
    from toptag.sources import SourceSpec, VideoSource

    source = VideoSource(SourceSpec("stream", rtsp.url), capture_latency_ns=50_000_000)
    source.open()
    try:
        frames = [source.read()]
        time.sleep(1.0)  # a busy reader: ten frames wait in the buffers
        frames += [source.read() for _ in range(6)]
    finally:
        source.close()
    gaps_ms = np.diff([f.capture_time_ns for f in frames]) / 1e6
    assert np.allclose(gaps_ms[1:], 100.0, atol=1.0), gaps_ms  # 10 fps, whatever the reader's delays
    assert gaps_ms[0] >= 99.0, gaps_ms
    assert all(f.capture_time_ns <= f.receive_time_ns - 50_000_000 for f in frames)


def test_rsu_serves_fixes_from_an_rtsp_stream_that_drops_and_comes_back(drive, rtsp, router, launch, zenoh_session):
    from protocol import keys
    from protocol.messages import Approach, PoseFix, RsuStatus, TagDetections
    from protocol.transport import MessagePublisher, subscribe_messages
    from toptag.vehicle import VehicleFile

    d, truth = drive
    rsu = launch(["-m", "toptag", "rsu", "--camera", str(d / "camera.json"), "--intersection", "x1", "--source",
                  rtsp.url, "--capture-latency-ms", "80", "--zenoh-mode", "client", "--connect", router],
                 ready="ready", timeout=60)
    session = zenoh_session("client", connect=[router])
    fixes: list[tuple[int, PoseFix]] = []
    status: list[RsuStatus] = []
    subs = [subscribe_messages(session, keys.pose_fix("x1", keys.ANY, keys.ANY), PoseFix,
                               lambda m: fixes.append((time.time_ns(), m))),
            subscribe_messages(session, keys.rsu_status("rsu-ne"), RsuStatus, status.append)]
    detections: list[TagDetections] = []
    subs.append(subscribe_messages(session, keys.detections("rsu-ne"), TagDetections, detections.append))
    vehicle = VehicleFile.model_validate(truth["vehicles"]["bus-17"])
    pub = MessagePublisher(session, keys.approach("x1", "bus-17"), Approach)
    stop = threading.Event()

    def announce():  # the bus repeats its Approach every second, as the bus agent does
        seq = 0
        while not stop.is_set():
            pub.put(Approach(bus_id="bus-17", intersection_id="x1", vehicle=vehicle, reference_time_ns=time.time_ns(),
                             seq=seq))
            seq += 1
            stop.wait(1.0)

    t = threading.Thread(target=announce, daemon=True)
    t.start()
    try:
        assert wait_until(lambda: len(fixes) >= 10, 90), f"no fixes from the stream; RSU log:\n{rsu.output()[-3000:]}"
        path = np.array([[f["vehicles"]["bus-17"]["x"], f["vehicles"]["bus-17"]["y"]] for f in truth["frames"]])
        for arrival, fix in fixes[:10]:
            assert np.min(np.hypot(*(path - [fix.x, fix.y]).T)) < 0.15  # on the recorded drive
            assert fix.capture_time_ns <= arrival and arrival - fix.capture_time_ns < 30e9
        # and the tags it found, for a live view to draw over the stream's frames
        assert wait_until(lambda: any(m.tags for m in detections), 30), rsu.output()[-3000:]
        m = next(m for m in detections if m.tags)
        assert (m.width, m.height) == (960, 720) and m.tags[0].bus_id == "bus-17"
        assert "Traceback" not in rsu.output()  # no frame failed
        assert wait_until(lambda: status and status[-1].source_connected and status[-1].source_fps, 30)
        s = status[-1]
        assert s.source.startswith("stream rtsp://127.0.0.1") and 2 < s.source_fps < 30

        # the camera drops off the network: the RSU keeps running and says so
        rtsp.kill()
        n_status = len(status)
        assert wait_until(lambda: len(status) > n_status + 2 and not status[-1].source_connected
                          and status[-1].source_last_error, 60), rsu.output()[-3000:]
        assert "no stream answered" in status[-1].source_last_error or "lost" in status[-1].source_last_error
        reconnects_before = status[-1].source_reconnects
        n_fixes = len(fixes)
        assert rsu.proc.poll() is None

        # it comes back: the RSU reopens it (backoff) and serves fixes again
        rtsp.start()
        assert wait_until(lambda: len(fixes) >= n_fixes + 5, 90), rsu.output()[-3000:]
        assert wait_until(lambda: status[-1].source_reconnects > reconnects_before and status[-1].source_connected, 30)
        assert rsu.proc.poll() is None
    finally:
        stop.set()
        t.join(3)
        pub.close()
        for sub in subs:
            sub.close()
