"""A loopback RTSP server for the camera-stream tests: serves an H.264 MP4 file the way an IP camera
streams (RTP over RTSP, real-time pace, the file repeated), with Debian's gst-rtsp-server.

Run by the *system* python3 (python3-gi and gir1.2-gst-rtsp-server-1.0 from Debian, installed by
`make stream-tools`), not the project's venv:

    /usr/bin/python3 tests/rtsp_server.py --port PORT --path /cam --video FILE.mp4

Prints "rtsp server ready rtsp://127.0.0.1:PORT/cam" when it listens; stops on SIGTERM/SIGINT.
"""
import argparse
import signal
import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--path", default="/cam")
    p.add_argument("--video", required=True)
    args = p.parse_args()
    Gst.init(None)
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(args.port))
    factory = GstRtspServer.RTSPMediaFactory()
    # multifilesrc loop=true would not loop an MP4; instead each client gets the file from its start
    # and the file is long enough for a test. config-interval=-1 repeats SPS/PPS with every key frame.
    factory.set_launch(f"( filesrc location={args.video} ! qtdemux ! h264parse "
                       f"! rtph264pay name=pay0 pt=96 config-interval=-1 )")
    factory.set_shared(True)
    server.get_mount_points().add_factory(args.path, factory)
    if server.attach(None) == 0:
        print(f"rtsp server: cannot listen on 127.0.0.1:{args.port}", file=sys.stderr, flush=True)
        return 1
    loop = GLib.MainLoop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        GLib.unix_signal_add(GLib.PRIORITY_DEFAULT, sig, loop.quit)
    print(f"rtsp server ready rtsp://127.0.0.1:{args.port}{args.path}", flush=True)
    loop.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
