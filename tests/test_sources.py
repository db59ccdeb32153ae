"""Camera sources on their own (toptag.sources): parsing a --source, one-line errors for what cannot be
opened or read, a folder of images, and the newest-frame reader (drops, reopening, fps) on an in-memory
source. The real streams are in test_streams.py."""
import os
import time

import numpy as np
import pytest

from services.processes import free_port
from toptag.errors import InputError
from toptag.sources import (
    FolderSource,
    LatestFrameReader,
    SourceEnded,
    SourceError,
    SourceSpec,
    StreamClock,
    VideoSource,
    parse_source,
)
from toptag.waiting import wait_until

pytestmark = pytest.mark.unit


def test_source_parsing_names_what_is_wrong(tmp_path):
    assert parse_source("zenoh").kind == "zenoh"
    assert parse_source("rtsp://user:pw@10.0.0.5:554/stream1").kind == "stream"
    assert "pw" not in parse_source("rtsp://user:pw@10.0.0.5:554/stream1").describe()
    assert parse_source("/dev/video0").kind == "device"
    assert parse_source(str(tmp_path)).kind == "folder"
    (tmp_path / "v.mp4").write_bytes(b"x")
    assert parse_source(str(tmp_path / "v.mp4")).kind == "file"
    for bad, msg in (("ftp://host/x", "unsupported scheme 'ftp'"), ("rtsp:///nohost", "no host"),
                     (str(tmp_path / "missing.mp4"), "no such file or folder"), ("", "empty")):
        with pytest.raises(InputError, match=msg):
            parse_source(bad)


def test_unopenable_and_corrupt_sources_are_one_line_errors(tmp_path):
    (tmp_path / "junk.mp4").write_bytes(os.urandom(5000))
    src = VideoSource(parse_source(str(tmp_path / "junk.mp4")))
    with pytest.raises(SourceError, match="junk.mp4: not a video"):
        src.open()
    port = free_port()  # nothing listens there
    s = VideoSource(SourceSpec("stream", f"rtsp://127.0.0.1:{port}/cam"), open_timeout_s=3)
    with pytest.raises(SourceError) as e:
        s.open()
    assert "no stream answered" in str(e.value) and "\n" not in str(e.value)


def test_folder_source_reads_new_images_in_order_and_skips_corrupt_ones(tmp_path):
    import cv2

    img = np.full((48, 64), 128, np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    (tmp_path / "b.jpg").write_bytes(b"\xff\xd8 truncated")
    cv2.imwrite(str(tmp_path / "c.png"), img)
    src = FolderSource(SourceSpec("folder", str(tmp_path)), capture_latency_ns=10_000_000, follow=False)
    src.open()
    first = src.read()
    assert first.name == "a.png"
    assert first.capture_time_ns == (tmp_path / "a.png").stat().st_mtime_ns - 10_000_000
    with pytest.raises(SourceError, match="b.jpg: corrupt or truncated"):
        src.read()
    assert src.read().name == "c.png"
    with pytest.raises(SourceEnded):
        src.read()


class _Counting:
    """A fake-free, in-memory source: frames as fast as asked, a loss after `lose_after` frames."""

    def __init__(self, lose_after: int | None = None):
        self.spec = SourceSpec("stream", "rtsp://test/cam")
        self.opened, self.n, self.lose_after = 0, 0, lose_after
        self.live = True

    def open(self):
        self.opened += 1

    def read(self):
        from toptag.sources import CapturedFrame

        if self.lose_after is not None and self.n == self.lose_after:
            self.lose_after = None
            raise SourceError("source rtsp://test/cam: stream lost")
        self.n += 1
        time.sleep(0.002)
        return CapturedFrame(self.n, time.time_ns(), time.time_ns(), np.zeros((2, 2), np.uint8))

    def close(self):
        pass


def test_latest_frame_reader_keeps_the_newest_counts_drops_and_reopens():
    src = _Counting(lose_after=50)
    reader = LatestFrameReader(src, backoff=(0.05, 0.2)).start()
    try:
        assert wait_until(lambda: reader.stats().frames_read >= 200, 30)
        time.sleep(0.05)
        newest = reader.get(timeout=1.0)
        st = reader.stats()
        assert newest is not None and newest.index >= st.frames_read - 2  # the newest, not a queued old one
        assert st.frames_dropped >= st.frames_read - 5  # nobody consumed: all but the newest dropped
        assert st.reconnects == 1 and src.opened == 2 and "stream lost" in st.last_error
        assert st.fps > 0
    finally:
        reader.close()


def test_stream_clock_places_a_backlog_of_frames_by_their_own_timestamps():
    clock = StreamClock(window_s=10.0)
    ms = 1_000_000
    # 10 fps; frames 0-1 arrive 40 ms after their time, then the reader is busy for 3 s and frames 2-5
    # come out of its buffer a few ms apart
    assert clock.stamp(0, 1_000 * ms + 40 * ms) == 1_040 * ms
    assert clock.stamp(100 * ms, 1_140 * ms) == 1_140 * ms
    late = [clock.stamp(k * 100 * ms, 4_000 * ms + k * ms) for k in range(2, 6)]
    assert late == [1_040 * ms + k * 100 * ms for k in range(2, 6)]
    # a frame faster than any before sets the delay for those after it
    assert clock.stamp(600 * ms, 1_630 * ms) == 1_630 * ms
    assert clock.stamp(700 * ms, 1_760 * ms) == 1_730 * ms
    # the smallest delay is forgotten after the window (a camera clock drifting against the host's)
    assert clock.stamp(700 * ms + 11_000 * ms, 12_760 * ms) == 12_760 * ms
    # timestamps that do not increase: a restarted stream, or none (every frame then at its receive time)
    assert clock.stamp(0, 20_000 * ms) == 20_000 * ms
    assert clock.stamp(0, 20_100 * ms) == 20_100 * ms
