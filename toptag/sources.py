"""Camera sources for the RSU and `toptag locate`: IP camera streams, video files, V4L2 devices and
folders of images, read with OpenCV's VideoCapture (its FFmpeg backend) without any network layer of
toptag's own, so that the offline shell and the RSU service share them.

SOURCE (`parse_source`):
    zenoh                       the simulator's frames over Zenoh (handled by the RSU service itself)
    rtsp://…, rtsps://…, http://…, https://…, rtmp://…, srt://…, udp://…   a network stream
    /dev/videoN (or N)          a V4L2 camera
    DIR                         a folder of images (a camera that uploads stills), read in name order
    FILE                        a video file (mp4, mkv, ts, avi, …)

Capture time, per source (the time a PoseFix carries; SPEC: integer ns since the epoch):
    file      the file's own presentation timestamps, from `start_ns` (locate: --start-ns, default 0;
              the RSU replays the file in real time from the moment it opens it)
    stream    receive time minus `capture_latency_ns`: OpenCV does not expose RTP/RTCP wall-clock
              times, so the camera-to-RSU latency (exposure, encoding, network, decoding) is measured
              once at installation and configured (README: installing at a site). The receive time is
              that of the frame's place in the stream (`StreamClock`): a frame that waited in a buffer
              while its reader was busy keeps the spacing of the stream's own timestamps
    device    receive time minus `capture_latency_ns` (the driver's buffering and readout)
    folder    the image file's modification time minus `capture_latency_ns` (the upload delay)

`LatestFrameReader` runs a source on its own thread and keeps only the newest frame: a consumer that
falls behind gets the latest one and the frames it never saw are counted as dropped; a stream that
breaks or cannot be opened is reopened with exponential backoff; it reports fps, drops, reconnects and
the last error. Bad input (a source that cannot be opened, an unreadable image) is one line.
"""
from __future__ import annotations

import os
import re
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.errors import InputError

STREAM_SCHEMES = ("rtsp", "rtsps", "http", "https", "rtmp", "srt", "udp", "tcp")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mkv", ".mov", ".avi", ".ts", ".m2ts", ".mts", ".webm", ".h264", ".264",
                  ".h265", ".265", ".hevc", ".mjpeg", ".mjpg", ".flv", ".mpg", ".mpeg")
OPEN_TIMEOUT_S = 10.0
READ_TIMEOUT_S = 5.0
LIVE_FFMPEG_OPTIONS = "analyzeduration;200000|probesize;65536|fflags;nobuffer"


class StreamClock:
    """The receive time a live stream's frame would have had with no wait in the reader's buffers: its
    presentation timestamp plus the smallest receive-minus-timestamp delay seen over the last
    `window_s` of the stream. Without it a reader that falls behind (a busy machine, a slow first
    detection) stamps a backlog of frames 100 ms apart with receive times a few ms apart, and every
    motion between them looks instantaneous. The window follows a camera clock that drifts against
    the host's; a timestamp that does not increase (a restarted stream, or none at all) starts afresh,
    so a stream without timestamps is stamped with its receive times."""

    def __init__(self, window_s: float = 10.0):
        self.window_ns = int(window_s * 1e9)
        self._delays: deque[tuple[int, int]] = deque()  # (pts, receive - pts), delays increasing
        self._last_pts: int | None = None

    def stamp(self, pts_ns: int, received_ns: int) -> int:
        if self._last_pts is not None and pts_ns <= self._last_pts:
            self._delays.clear()
        self._last_pts = pts_ns
        delay = received_ns - pts_ns
        while self._delays and self._delays[-1][1] >= delay:
            self._delays.pop()
        self._delays.append((pts_ns, delay))
        while self._delays[0][0] < pts_ns - self.window_ns:
            self._delays.popleft()
        return pts_ns + self._delays[0][1]


class SourceSettings(BaseModel):
    """Where an RSU's frames come from (the [camera] table of `toptag rsu --config`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: str = Field(default="zenoh", description="zenoh, a stream URL, a video file, /dev/videoN or a folder")
    capture_latency_ms: float = Field(default=0.0, ge=0, description="camera-to-receiver latency (streams, devices, "
                                                                     "folders)")
    rtsp_transport: Literal["tcp", "udp"] = "tcp"


class SourceError(InputError):
    """A camera source cannot be opened or read; str(e) names the source and the problem."""


class SourceEnded(Exception):
    """A finite source (a video file, a folder with no new image) has no more frames."""


@dataclass(frozen=True)
class SourceSpec:
    kind: str  # "zenoh" | "stream" | "device" | "folder" | "file"
    target: str

    @property
    def live(self) -> bool:
        """Frames keep coming (and a lost source is worth reopening)."""
        return self.kind in ("stream", "device", "folder")

    def describe(self) -> str:
        return f"{self.kind} {redact(self.target)}" if self.kind != "zenoh" else "zenoh frames"


def redact(url: str) -> str:
    """The URL without a password (IP camera URLs often carry user:password@)."""
    return re.sub(r"(://[^:/@]+):[^@/]*@", r"\1:***@", url)


def is_video_path(path: str) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def is_stream_url(text: str) -> bool:
    return urlsplit(text).scheme.lower() in STREAM_SCHEMES and "://" in text


def parse_source(text: str) -> SourceSpec:
    """SourceSpec of a --source argument, or SourceError naming what is wrong."""
    t = (text or "").strip()
    if not t:
        raise SourceError("source: empty (give zenoh, a stream URL, a video file, /dev/videoN or a folder)")
    if t == "zenoh":
        return SourceSpec("zenoh", t)
    scheme = urlsplit(t).scheme.lower()
    if "://" in t:
        if scheme not in STREAM_SCHEMES:
            raise SourceError(f"source {redact(t)}: unsupported scheme {scheme!r} "
                              f"(known: {', '.join(STREAM_SCHEMES)})")
        if not urlsplit(t).hostname:
            raise SourceError(f"source {redact(t)}: no host in the URL")
        return SourceSpec("stream", t)
    if t.isdigit() or re.fullmatch(r"/dev/video\d+", t):
        return SourceSpec("device", t)
    p = Path(t)
    if p.is_dir():
        return SourceSpec("folder", t)
    if p.is_file():
        if p.suffix.lower() in IMAGE_SUFFIXES:
            raise SourceError(f"source {t}: a single image is not a camera source (give its folder)")
        return SourceSpec("file", t)
    if t.startswith("/dev/"):
        raise SourceError(f"source {t}: no such device (V4L2 cameras are /dev/videoN)")
    raise SourceError(f"source {t}: no such file or folder, and not a stream URL (rtsp://, http://)")


@dataclass
class CapturedFrame:
    index: int  # frames delivered by this source since it was created (across reconnects)
    capture_time_ns: int
    receive_time_ns: int
    gray: np.ndarray
    name: str = ""  # the image file of a folder source


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 2:
        return frame
    if frame.shape[2] == 1:
        return frame[:, :, 0]
    return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)


class VideoSource:
    """A stream, device or video file through cv2.VideoCapture (FFmpeg backend; V4L2 for devices).

    realtime: deliver a file's frames at their own pace (the RSU replaying a recording); False reads
    as fast as asked (locate). start_ns: the wall time of the file's timestamp 0 (None: when opened)."""

    def __init__(self, spec: SourceSpec, *, capture_latency_ns: int = 0, start_ns: int | None = None,
                 realtime: bool = False, rtsp_transport: str = "tcp", open_timeout_s: float = OPEN_TIMEOUT_S,
                 read_timeout_s: float = READ_TIMEOUT_S):
        if spec.kind not in ("stream", "device", "file"):
            raise ValueError(f"VideoSource cannot read a {spec.kind} source")
        self.spec = spec
        self.capture_latency_ns = int(capture_latency_ns)
        self.start_ns = start_ns
        self.realtime = realtime
        self.rtsp_transport = rtsp_transport
        self.open_timeout_s, self.read_timeout_s = open_timeout_s, read_timeout_s
        self._cap = None
        self._index = 0
        self._t0_ns: int | None = None
        self._wall0: float | None = None
        self.fps_declared = 0.0
        self.size: tuple[int, int] | None = None

    @property
    def live(self) -> bool:
        return self.spec.live

    @property
    def frames_read(self) -> int:
        return self._index

    def open(self) -> None:
        import cv2

        # OpenCV's FFmpeg backend reads its demuxer options from this variable at every open. A live
        # stream is probed briefly (FFmpeg's default reads seconds of it, which then arrive as a stale
        # burst) and not buffered; RTSP runs over TCP by default (no torn frames from lost packets).
        if self.spec.kind == "stream":
            opts = LIVE_FFMPEG_OPTIONS
            if urlsplit(self.spec.target).scheme.lower().startswith("rtsp"):
                opts += f"|rtsp_transport;{self.rtsp_transport}"
            os.environ["OPENCV_FFMPEG_CAPTURE_OPTIONS"] = opts
        else:
            os.environ.pop("OPENCV_FFMPEG_CAPTURE_OPTIONS", None)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(self.open_timeout_s * 1000),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self.read_timeout_s * 1000)]
        if self.spec.kind == "file" and not Path(self.spec.target).is_file():
            raise SourceError(f"source {self.spec.target}: no such file")
        if self.spec.kind == "device":
            t = self.spec.target
            index = int(t) if t.isdigit() else int(t.removeprefix("/dev/video"))
            cap = cv2.VideoCapture(index, cv2.CAP_V4L2)
        else:
            cap = cv2.VideoCapture(self.spec.target, cv2.CAP_FFMPEG, params)
        if not cap.isOpened():
            cap.release()
            why = {"stream": "no stream answered (connection refused, wrong path, or a codec FFmpeg cannot "
                             "decode)",
                   "device": "the device cannot be opened (missing, busy, or no permission)",
                   "file": "not a video OpenCV's FFmpeg can decode"}[self.spec.kind]
            raise SourceError(f"source {redact(self.spec.target)}: {why}")
        self._cap = cap
        self._clock = StreamClock()
        self.fps_declared = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.size = (w, h) if w > 0 and h > 0 else None
        if self.spec.kind == "file":
            self._t0_ns = time.time_ns() if self.start_ns is None else int(self.start_ns)
            self._wall0 = time.monotonic()
            self._file_frame = 0

    def read(self) -> CapturedFrame:
        import cv2

        if self._cap is None:
            raise SourceError(f"source {redact(self.spec.target)}: not open")
        ok, frame = self._cap.read()
        received = time.time_ns()
        if not ok or frame is None:
            if self.spec.kind == "file":
                raise SourceEnded(self.spec.target)
            raise SourceError(f"source {redact(self.spec.target)}: stream lost (no frame within "
                              f"{self.read_timeout_s:g} s, or the sender closed it)")
        if self.spec.kind == "file":
            pts_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC))
            if not np.isfinite(pts_ms) or pts_ms < 0 or (pts_ms == 0 and self._file_frame > 0):
                pts_ms = 1e3 * self._file_frame / (self.fps_declared or 10.0)  # no timestamps: the frame rate
            self._file_frame += 1
            capture = self._t0_ns + int(round(pts_ms * 1e6))
            if self.realtime:
                wait = self._wall0 + pts_ms / 1e3 - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                received = time.time_ns()
        elif self.spec.kind == "stream":
            pts_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC))
            placed = received if not np.isfinite(pts_ms) else self._clock.stamp(int(round(pts_ms * 1e6)), received)
            capture = placed - self.capture_latency_ns
        else:
            capture = received - self.capture_latency_ns
        out = CapturedFrame(self._index, capture, received, _gray(frame))
        self._index += 1
        return out

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderSource:
    """Images appearing in a folder (a camera uploading stills), in name order, each once. A corrupt or
    unreadable image is skipped with a one-line error (SourceError from read, the source goes on)."""

    def __init__(self, spec: SourceSpec, *, capture_latency_ns: int = 0, poll_s: float = 0.05,
                 follow: bool = True):
        self.spec = spec
        self.folder = Path(spec.target)
        self.capture_latency_ns = int(capture_latency_ns)
        self.poll_s = poll_s
        self.follow = follow  # wait for new images (RSU) rather than end when all are read (locate)
        self._seen: set[str] = set()
        self._index = 0
        self._pending: deque[Path] = deque()

    live = True

    def open(self) -> None:
        if not self.folder.is_dir():
            raise SourceError(f"source {self.folder}: not a folder")

    def _scan(self) -> None:
        try:
            names = sorted(p.name for p in self.folder.iterdir()
                           if p.suffix.lower() in IMAGE_SUFFIXES and p.name not in self._seen)
        except OSError as e:
            raise SourceError(f"source {self.folder}: cannot list ({e.strerror or e})") from None
        for n in names:
            self._seen.add(n)
            self._pending.append(self.folder / n)

    def read(self) -> CapturedFrame:
        from toptag.images import read_gray

        while not self._pending:
            self._scan()
            if self._pending:
                break
            if not self.follow:
                raise SourceEnded(str(self.folder))
            time.sleep(self.poll_s)
        path = self._pending.popleft()
        try:
            mtime = path.stat().st_mtime_ns
            gray = read_gray(path)
        except FileNotFoundError:
            raise SourceError(f"image {path}: removed before it was read") from None
        except InputError as e:
            raise SourceError(str(e)) from None
        received = time.time_ns()
        out = CapturedFrame(self._index, mtime - self.capture_latency_ns, received, gray, name=path.name)
        self._index += 1
        return out

    def close(self) -> None:
        pass


def open_source(spec: SourceSpec, *, capture_latency_ns: int = 0, realtime: bool = True,
                start_ns: int | None = None, follow: bool = True, rtsp_transport: str = "tcp"):
    """The reader object of a non-zenoh source (not yet opened)."""
    if spec.kind == "folder":
        return FolderSource(spec, capture_latency_ns=capture_latency_ns, follow=follow)
    return VideoSource(spec, capture_latency_ns=capture_latency_ns, start_ns=start_ns, realtime=realtime,
                       rtsp_transport=rtsp_transport)


@dataclass
class SourceStats:
    frames_read: int = 0
    frames_dropped: int = 0  # read but replaced by a newer one before the consumer took it
    frames_bad: int = 0  # unreadable images of a folder source
    reconnects: int = 0  # successful reopenings after a loss
    open_failures: int = 0
    fps: float = 0.0  # frames read per second over the last few seconds
    connected: bool = False
    ended: bool = False
    last_error: str | None = None


class LatestFrameReader:
    """Reads a source on its own thread, keeping only the newest frame (see the module docstring).

    backoff: first and longest wait (s) before reopening a lost or unopenable source, doubling between."""

    def __init__(self, source, *, backoff: tuple[float, float] = (0.5, 8.0), log=None,
                 fps_window_s: float = 3.0):
        self.source = source
        self.backoff = backoff
        self.log = log
        self.fps_window_s = fps_window_s
        self._stats = SourceStats()
        self._cond = threading.Condition()
        self._slot: CapturedFrame | None = None
        self._stop = threading.Event()
        self._arrivals: deque[float] = deque()
        self._thread = threading.Thread(target=self._run, name="camera-source", daemon=True)

    def start(self) -> "LatestFrameReader":
        self._thread.start()
        return self

    # ---- consumer side ------------------------------------------------------------------------
    def get(self, timeout: float | None = None) -> CapturedFrame | None:
        """The newest frame not yet taken (waiting up to `timeout` s for one), or None."""
        with self._cond:
            if self._slot is None and timeout:
                self._cond.wait_for(lambda: self._slot is not None or self._stop.is_set(), timeout)
            frame, self._slot = self._slot, None
            return frame

    def stats(self) -> SourceStats:
        with self._cond:
            s = SourceStats(**vars(self._stats))
            now = time.monotonic()
            recent = [t for t in self._arrivals if now - t <= self.fps_window_s]
            s.fps = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) >= 2 and recent[-1] > recent[0] else 0.0
            return s

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    def close(self, timeout: float = 10.0) -> None:
        self.stop()
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.source.close()

    # ---- reader thread ------------------------------------------------------------------------
    def _note_error(self, message: str) -> None:
        with self._cond:
            self._stats.last_error = message
        if self.log is not None:
            self.log.warning("%s", message)

    def _run(self) -> None:
        wait = self.backoff[0]
        opened_before = False
        while not self._stop.is_set():
            try:
                self.source.open()
            except SourceError as e:
                with self._cond:
                    self._stats.open_failures += 1
                self._note_error(f"{e}; retrying in {wait:g} s")
                if self._stop.wait(wait):
                    break
                wait = min(2 * wait, self.backoff[1])
                continue
            with self._cond:
                self._stats.connected = True
                if opened_before:
                    self._stats.reconnects += 1
            if self.log is not None:
                self.log.info("camera source %s %s", self.source.spec.describe(),
                              "reopened" if opened_before else "opened")
            opened_before = True
            lost = self._read_until_lost()
            if lost == "lost":
                wait = self.backoff[0]  # it worked until now: retry soon
            self.source.close()
            with self._cond:
                self._stats.connected = False
            if not lost:
                break  # stopped, or a finite source ended
            if self._stop.wait(wait):
                break
            wait = min(2 * wait, self.backoff[1])

    def _read_until_lost(self) -> str | None:
        """'lost' (after frames) / 'failed' (none read) to reopen; None when stopped or ended."""
        got_any = False
        while not self._stop.is_set():
            try:
                frame = self.source.read()
            except SourceEnded:
                with self._cond:
                    self._stats.ended = True
                if self.log is not None:
                    self.log.info("camera source %s ended", self.source.spec.describe())
                return None
            except SourceError as e:
                if self.source.spec.kind == "folder":  # one bad image: skip it, the folder goes on
                    with self._cond:
                        self._stats.frames_bad += 1
                    self._note_error(str(e))
                    continue
                self._note_error(f"{e}; reopening")
                return "lost" if got_any else "failed"
            except Exception as e:  # OpenCV errors on a damaged stream: reopen rather than die
                self._note_error(f"source {self.source.spec.describe()}: read failed ({e}); reopening")
                return "lost" if got_any else "failed"
            got_any = True
            with self._cond:
                self._stats.frames_read += 1
                if self._slot is not None:
                    self._stats.frames_dropped += 1
                self._slot = frame
                now = time.monotonic()
                self._arrivals.append(now)
                while self._arrivals and now - self._arrivals[0] > self.fps_window_s:
                    self._arrivals.popleft()
                self._cond.notify_all()
        return None
