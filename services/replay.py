"""`toptag replay`: republish a recording (`toptag record`) with its original pacing.

    toptag replay RUN.mcap [--speed X] [--shift-to-now] [--keys EXPR]... [--skip EXPR]... [zenoh options]

Each message goes out on its recorded key with its recorded Zenoh encoding and the QoS of its type,
at its recorded reception time relative to the first message (divided by --speed). Without
--shift-to-now the payloads are the recorded bytes. With --shift-to-now every timestamp in every
message (protocol.timeshift) moves by one offset, so the recording's first message is "now": services
that compare timestamps with their clock (the bus filter, latency figures) take the replay for a live
run. To re-run a recorded drive through new RSU and bus code, replay only the simulator's outputs
(--sensors: frames, IMU, GNSS, truth) into fresh `toptag rsu` and `toptag bus` processes.

At the end (or Ctrl-C) prints how many messages were sent and how late each was against its schedule
(p50 / p99 / max): the pacing tolerance of this replay on this machine.
"""
from __future__ import annotations

import argparse
import logging
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from protocol import codec, keys
from protocol.codec import ProtocolError
from protocol.timeshift import shift_times
from protocol.transport import Qos, qos_for, wait_matching
from protocol.transport.runner import add_service_arguments, run_service
from services.recording import Recorded, read_recording, recording_channels

log = logging.getLogger(__name__)

# What the simulator publishes: a recorded drive's inputs to the RSUs and buses.
SENSOR_KEYS = [keys.frame(keys.ANY), keys.imu(keys.ANY), keys.imu_batch(keys.ANY), keys.gnss(keys.ANY),
               keys.ground_truth(keys.ANY)]
PROGRESS_S = 5.0


class Replayer:
    def __init__(self, session: zenoh.Session, path: Path, *, speed: float = 1.0, shift_to_now: bool = False,
                 key_exprs: list[str] | None = None, skip: list[str] | None = None, wait_s: float = 3.0):
        self.session = session
        self.path = path
        self.speed = speed
        self.shift_to_now = shift_to_now
        self.key_exprs, self.skip = key_exprs, skip
        self.wait_s = wait_s
        self._stop = threading.Event()
        self._pubs: dict[tuple[str, str], zenoh.Publisher] = {}
        self.sent = 0
        self.unshifted = 0  # payloads that are not toptag messages: sent as recorded
        self.lateness_ns: list[int] = []
        self.offset_ns = 0

    def _publisher(self, m: Recorded) -> zenoh.Publisher:
        pub = self._pubs.get((m.key, m.encoding))
        if pub is None:
            q = qos_for(m.message_type) if m.message_type is not None else Qos()
            pub = self.session.declare_publisher(m.key, encoding=zenoh.Encoding(m.encoding),
                                                 congestion_control=q.congestion_control, priority=q.priority,
                                                 express=q.express)
            self._pubs[(m.key, m.encoding)] = pub
        return pub

    def _declare_all(self) -> int:
        """Declare every publisher before the first message, then wait (up to wait_s) until one has a
        subscriber: routes to a new publisher take a moment, and a put before them is lost."""
        channels = recording_channels(self.path, self.key_exprs, self.skip)
        for m in channels:
            self._publisher(m)
        if not channels:
            return 0
        first_log = min(m.log_time_ns for m in channels)
        deadline = time.monotonic() + self.wait_s
        for pub in self._pubs.values():
            if not wait_matching(pub, timeout=max(0.0, deadline - time.monotonic())):
                continue
            break
        else:
            log.warning("no subscriber for any replayed key after %.1f s: replaying anyway", self.wait_s)
        return first_log

    def _payload(self, m: Recorded) -> bytes:
        if not self.shift_to_now:
            return m.payload
        if m.message_type is None:
            self.unshifted += 1
            return m.payload
        try:
            msg = codec.decode(m.payload, m.message_type)
        except ProtocolError:
            self.unshifted += 1  # recorded as received, bad payloads included: replayed as they were
            return m.payload
        return codec.encode_as(shift_times(msg, self.offset_ns), m.payload)

    def run(self, duration: float | None = None) -> None:
        first_log = self._declare_all()
        if not first_log:
            log.warning("%s: nothing to replay", self.path)
            return
        t0_mono = time.monotonic_ns()
        self.offset_ns = time.time_ns() - first_log
        t_end = None if duration is None else t0_mono + int(duration * 1e9)
        last_progress = time.monotonic()
        log.info("replaying %s at %gx%s", self.path, self.speed,
                 f", timestamps shifted by {self.offset_ns / 1e9:+.3f} s" if self.shift_to_now else "")
        for m in read_recording(self.path, self.key_exprs, self.skip):
            planned = t0_mono + int((m.log_time_ns - first_log) / self.speed)
            if t_end is not None and planned > t_end:
                break
            payload = self._payload(m)  # prepared before the wait: the put itself is on time
            wait = (planned - time.monotonic_ns()) * 1e-9
            if wait > 0 and self._stop.wait(wait):
                break
            if self._stop.is_set():
                break
            self._pubs[(m.key, m.encoding)].put(payload)
            self.lateness_ns.append(time.monotonic_ns() - planned)
            self.sent += 1
            if time.monotonic() - last_progress >= PROGRESS_S:
                last_progress = time.monotonic()
                log.info("replay: %d messages sent, %.1f s of the recording", self.sent,
                         (m.log_time_ns - first_log) * 1e-9)
        log.info("replay done: %s", self.summary())

    def pacing(self) -> dict:
        late = np.asarray(self.lateness_ns, dtype=float) * 1e-6
        if late.size == 0:
            return {"messages": 0}
        return {"messages": int(late.size), "late_ms_p50": round(float(np.percentile(late, 50)), 3),
                "late_ms_p99": round(float(np.percentile(late, 99)), 3), "late_ms_max": round(float(late.max()), 3)}

    def summary(self) -> str:
        p = self.pacing()
        if not p["messages"]:
            return "0 messages sent"
        extra = f"; {self.unshifted} sent unshifted (not toptag messages)" if self.unshifted else ""
        return (f"{p['messages']} messages sent; lateness against the recorded pacing p50 {p['late_ms_p50']:.2f} ms, "
                f"p99 {p['late_ms_p99']:.2f} ms, max {p['late_ms_max']:.2f} ms{extra}")

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except Exception:
                pass


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag replay", description=__doc__.split("\n\n")[0])
    p.add_argument("recording", metavar="RUN.mcap")
    p.add_argument("--speed", type=float, default=1.0, help="pacing factor (2: twice as fast); default 1")
    p.add_argument("--shift-to-now", action="store_true",
                   help="move every timestamp so that the recording starts now (for live services)")
    p.add_argument("--keys", action="append", default=None, metavar="EXPR",
                   help="replay only keys intersecting EXPR (repeatable; default all)")
    p.add_argument("--sensors", action="store_true",
                   help="replay only the simulator's outputs (frames, IMU, GNSS, truth): "
                        "a drive for fresh RSU and bus processes")
    p.add_argument("--skip", action="append", default=None, metavar="EXPR", help="do not replay keys intersecting EXPR")
    p.add_argument("--wait-subscribers", type=float, default=3.0, metavar="S",
                   help="wait up to S seconds for a subscriber before the first message (default 3)")
    add_service_arguments(p)
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    key_exprs = (args.keys or []) + (SENSOR_KEYS if args.sensors else [])

    def load() -> Path:
        if not args.speed > 0:
            raise ValueError("--speed must be positive")
        for k in key_exprs + (args.skip or []):
            try:
                zenoh.KeyExpr(k)
            except Exception:
                raise ValueError(f"key expression {k!r} is not valid") from None
        path = Path(args.recording)
        recording_channels(path)  # raises ValueError if unreadable
        if args.shift_to_now and args.speed != 1.0:
            log.warning("--shift-to-now with --speed %g: timestamps keep their recorded spacing, so services "
                        "see sensor time run at 1/%g of their clock", args.speed, args.speed)
        return path

    return run_service("replay", args, load,
                       lambda session, path: Replayer(session, path, speed=args.speed, shift_to_now=args.shift_to_now,
                                                      key_exprs=key_exprs or None, skip=args.skip,
                                                      wait_s=args.wait_subscribers),
                       lambda path: f"replay of {path}")
