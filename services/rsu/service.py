"""`toptag rsu`: the RSU service for one camera.

Frames come from --source: `zenoh` (the simulator's frames, the default) or a camera source of
toptag.sources (an RTSP/HTTP stream, a video file, /dev/videoN, a folder of images), read on its own
thread that keeps only the newest frame (older ones are dropped and counted), reopens a lost stream
with backoff while the RSU keeps serving its sessions, and stamps each frame with its capture time
(the source's own timestamps where it has them, else the receive time minus --capture-latency-ms).

Idle while no bus is in session: frames arrive and are dropped undecoded. A bus's Approach (or, for an
RSU started late, the answer to a session query) adds its code bag to the pipeline; the RSU then
detects only those tags and publishes one PoseFix per bus per frame, stamped with the frame's capture
time. An acquisition search (for a bus not yet found) is begun with its frame and run on a thread of
lower priority (SEARCH_NICE) while the next frames are processed, so that a tracked bus's frame never
waits for it, here or (the other RSUs' searches being niced too) on another RSU of the host; its fix is
stamped with the capture time of the frame it searched. Leave, or the bus's liveliness token vanishing,
ends the session. RsuStatus every second, with
the host's clock (toptag.hostclock) and what the buses think of this RSU (their RsuDiagnosis on
keys.rsu_diagnosis: its time offset, and whether its camera is flagged for drift).
"""
from __future__ import annotations

import argparse
import logging
import os
import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from protocol import keys
from protocol.codec import ProtocolError
from protocol.convert import clock_to_message, fix_to_message, reported_position
from protocol.images import frame_to_gray
from protocol.messages import Approach, DetectedTag, Frame, Leave, PoseFix, RsuDiagnosis, RsuStatus, TagDetections
from protocol.transport import (
    MISSING,
    REJECTED,
    SKIPPED,
    MessageCounters,
    MessagePublisher,
    latest_receiver,
    query_sessions,
    subscribe_messages,
    watch_buses,
)
from protocol.transport.runner import ServiceSettings, add_service_arguments, run_service
from toptag.camera import Camera
from toptag.hostclock import HostClockProbe
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.solvers import METHODS
from toptag.sources import LatestFrameReader, SourceSettings, open_source, parse_source
from toptag.solvers.warmup import warm_up
from toptag.vehicle import Vehicle, VehicleFile

log = logging.getLogger(__name__)

# An acquisition search (tens of ms of CPU, searched for as long as a bus is announced but not found) runs
# on a thread this much nicer than the RSU's frames, so that every tracked frame on the host, this RSU's
# and the others', takes the cores first: the search is what may wait (its bus is acquired a little
# later on a busy host), not the tracked buses' fixes.
SEARCH_NICE = 10
DIAGNOSIS_SHOWN_S = 10.0  # a bus's diagnosis of this RSU is shown in RsuStatus this long after it came


class RsuSettings(ServiceSettings):
    """`toptag rsu --config FILE`: [zenoh], [pipeline] (toptag.rsu.pipeline.PipelineSettings) and [camera]
    (toptag.sources.SourceSettings: source, capture_latency_ms, rtsp_transport)."""

    pipeline: PipelineSettings = PipelineSettings()
    camera: SourceSettings = SourceSettings()


@dataclass
class RsuCounters:
    frames_received: int = 0
    frames_processed: int = 0
    frames_idle: int = 0
    frames_bad: int = 0
    frames_with_fix: int = 0
    fixes_published: int = 0
    active_s: float = 0.0
    detect_ns: list[int] = field(default_factory=list)  # since the last status
    # Zenoh frames in session, over the run (logged at the end): from the capture stamp to the frame's
    # arrival here, and from its arrival to the frame loop taking it: where a fix's age before its
    # processing goes.
    delivery_ns: list[int] = field(default_factory=list)
    wait_ns: list[int] = field(default_factory=list)


class RsuService:
    """Wires one RsuPipeline to Zenoh. Session changes arrive on Zenoh threads and are applied by the
    frame loop between frames, so the pipeline is only ever touched by one thread."""

    def __init__(self, session, camera: Camera, intersection: str, settings: PipelineSettings | None = None,
                 source: LatestFrameReader | None = None):
        self.session = session
        self.source = source  # None: frames from Zenoh
        self.camera = camera
        self.rsu_id = camera.id
        self.intersection = intersection
        self.pipeline = RsuPipeline(camera, settings)
        self._prepared: set[tuple[str, ...]] = set()
        self._searcher = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"search-{self.rsu_id}",
                                            initializer=_lower_priority, initargs=(SEARCH_NICE,))
        self._search_run: Future | None = None  # the deferred search's work, on self._searcher
        # What the first frames of the first session would otherwise wait for: the solvers' kernels
        # (loaded from numba's cache: a few tenths of a second, seconds on a loaded machine) and the
        # detectors of the usual tag family.
        warm_up()
        self._prepare({VehicleFile.model_fields["family"].default})
        self.counters = RsuCounters()
        self.msg_counters = MessageCounters()
        self.started_ns = time.time_ns()
        self._changes: queue.Queue = queue.Queue()
        self._sessions: dict[str, Approach] = {}  # bus id -> its Approach (owned by the frame loop)
        self._stop = threading.Event()
        self._fix_pubs: dict[str, MessagePublisher] = {}
        self._status_pub = MessagePublisher(session, keys.rsu_status(self.rsu_id), RsuStatus)
        self._detections_pub = MessagePublisher(session, keys.detections(self.rsu_id), TagDetections)
        self.clock = HostClockProbe().start()
        self._diagnoses: dict[str, tuple[RsuDiagnosis, float]] = {}  # bus -> (latest, monotonic arrival)
        self._subs = [
            subscribe_messages(session, keys.approach(intersection, keys.ANY), Approach,
                               lambda m: self._changes.put(("approach", m)), self.msg_counters, log),
            subscribe_messages(session, keys.leave(intersection, keys.ANY), Leave,
                               lambda m: self._changes.put(("leave", m.bus_id, "leave")), self.msg_counters, log),
            # The other RSUs' fixes say where a bus is: search there, or not at all when it is out of view.
            subscribe_messages(session, keys.pose_fix(intersection, keys.ANY, keys.ANY), PoseFix,
                               self._on_peer_fix, self.msg_counters, log),
            subscribe_messages(session, keys.rsu_diagnosis(intersection, self.rsu_id, keys.ANY), RsuDiagnosis,
                               self._on_diagnosis, self.msg_counters, log),
        ]
        self._frames = (latest_receiver(session, keys.frame(self.rsu_id), Frame, self.msg_counters, log)
                        if source is None else None)
        self._bad_logged = 0
        self._search_frame = None  # (processing start, clock, seq, modes) of the frame whose search is deferred
        self._watch = watch_buses(session, intersection,
                                  on_appear=lambda bus: self._changes.put(("appear", bus)),
                                  on_vanish=lambda bus: self._changes.put(("leave", bus, "liveliness lost")),
                                  logger=log)
        self._changes.put(("query", None))

    def _prepare(self, families: set[str]) -> None:
        """The detectors of buses of these families built before a frame needs them: the frame loop's and
        the detection workers' here, the search thread's on it (queued before any search)."""
        key = tuple(sorted(families))
        if key not in self._prepared:
            self._prepared.add(key)
            self._searcher.submit(self.pipeline.prepare(key))

    def _on_diagnosis(self, m: RsuDiagnosis) -> None:
        before = self._diagnoses.get(m.bus_id)
        if m.drift_flagged and (before is None or not before[0].drift_flagged):
            log.warning("bus %s flags this camera for drift: %s", m.bus_id, m.advice)
        elif before is not None and before[0].drift_flagged and not m.drift_flagged:
            log.info("bus %s no longer flags this camera", m.bus_id)
        self._diagnoses[m.bus_id] = (m, time.monotonic())

    def _on_peer_fix(self, m: PoseFix) -> None:
        if m.rsu_id != self.rsu_id:
            self._changes.put(("hint", m))

    # ---- sessions -----------------------------------------------------------------------------
    def _apply_changes(self) -> None:
        while True:
            try:
                change = self._changes.get_nowait()
            except queue.Empty:
                return
            kind = change[0]
            if kind == "approach":
                self._start_session(change[1])
            elif kind == "leave":
                self._end_session(change[1], change[2])
            elif kind == "hint":
                m = change[1]
                self.pipeline.hint(m.bus_id, m.capture_time_ns, m.x, m.y, m.yaw, m.z, m.rsu_id)
            elif kind in ("appear", "query"):
                # A bus we have no bag for (we started late or missed its Approach): ask for it.
                if kind == "query" or change[1] not in self._sessions:
                    self._query_sessions()

    def _query_sessions(self) -> None:
        found = query_sessions(self.session, self.intersection, timeout=1.0, counters=self.msg_counters, logger=log)
        alive = {k.rsplit("/", 1)[-1] for k in self._watch.alive}
        for bus, approach in found.items():
            if bus in alive:
                self._start_session(approach)

    def _start_session(self, a: Approach) -> None:
        self._note_position(a)
        known = self._sessions.get(a.bus_id)
        if known is not None and known.vehicle == a.vehicle:
            self._sessions[a.bus_id] = a  # a repeated Approach: nothing changes
            return
        try:
            vehicle = Vehicle(a.vehicle)
        except Exception as e:  # the bag passed the wire schema but is unusable
            self.msg_counters.inc(REJECTED, "Approach", keys.approach(self.intersection, a.bus_id), reason="bag",
                                  error=str(e))
            log.warning("bus %s: unusable code bag: %s", a.bus_id, e)
            return
        clash = {(vehicle.family, t) for t in vehicle.tag_ids} & {
            (v.family, t) for b, v in self.pipeline.vehicles.items() if b != a.bus_id for t in v.tag_ids}
        if clash:
            log.warning("bus %s shares tag ids %s with a bus already in session: those tags are ambiguous and "
                        "will not be used for either", a.bus_id, sorted(t for _, t in clash))
        self._sessions[a.bus_id] = a
        self.pipeline.add_vehicle(vehicle)
        self._prepare({v.family for v in self.pipeline.vehicles.values()})
        self._note_position(a)
        self._fix_pubs.setdefault(a.bus_id, MessagePublisher(
            self.session, keys.pose_fix(self.intersection, a.bus_id, self.rsu_id), PoseFix))
        log.info("session start: bus %s (tags %s)", a.bus_id, vehicle.tag_ids)

    def _note_position(self, a: Approach) -> None:
        p = a.position
        if p is not None:
            self.pipeline.report_position(a.bus_id, reported_position(p))

    def _end_session(self, bus: str, why: str) -> None:
        if self._sessions.pop(bus, None) is None:
            return
        self.pipeline.remove_vehicle(bus)
        pub = self._fix_pubs.pop(bus, None)
        if pub is not None:
            pub.close()
        log.info("session end: bus %s (%s)", bus, why)

    # ---- frames -------------------------------------------------------------------------------
    def handle_frame(self, frame: Frame) -> None:
        """A Zenoh frame: decoded only while a bus is in session, and only when the pipeline searches some
        region of it."""
        self.counters.frames_received += 1
        if not self._sessions:
            self.counters.frames_idle += 1  # no bus announced: no decoding, no detection
            return
        arrival = self._frames.taken_arrival_ns
        self.counters.delivery_ns.append(arrival - frame.capture_time_ns)
        self.counters.wait_ns.append(time.time_ns() - arrival)
        self.process_gray(lambda: frame_to_gray(frame), frame.capture_time_ns, frame.seq, frame.clock)

    def handle_captured(self, frame) -> None:
        """A frame of a camera source (toptag.sources.CapturedFrame), already decoded by the reader."""
        self.counters.frames_received += 1
        if not self._sessions:
            self.counters.frames_idle += 1
            return
        self.process_gray(frame.gray, frame.capture_time_ns, frame.index)

    def _bad_frame(self, message: str, reason: str = "frame") -> None:
        self.counters.frames_bad += 1
        self.msg_counters.inc(REJECTED, "Frame", keys.frame(self.rsu_id), reason=reason, error=message)
        # one line per bad frame, but a stream that goes on sending bad frames is not allowed to flood the log
        if self._bad_logged < 20 or self.counters.frames_bad % 100 == 0:
            log.warning("dropped frame: %s", message)
            self._bad_logged += 1

    def process_gray(self, image, capture_time_ns: int, seq: int, clock=None) -> None:
        """Detect and publish. image: the gray frame, or a function that decodes it (called only when some
        region is searched). clock: the clock that stamped capture_time_ns (a Zenoh frame's, when the
        sender says); None: this host's (a camera source's frames are stamped on receipt here)."""
        c = self.counters

        def checked() -> np.ndarray:
            try:
                gray = image() if callable(image) else image
            except ProtocolError as e:
                raise ProtocolError(f"frame {seq}: {e}", e.reason) from None
            if gray.shape != (self.camera.height, self.camera.width):
                raise ProtocolError(f"frame {seq}: {gray.shape[1]}x{gray.shape[0]} from a "
                                    f"{self.camera.width}x{self.camera.height} camera", "frame")
            return gray

        t0 = time.perf_counter_ns()
        clock = clock or clock_to_message(self.clock.current())  # the clock of the capture stamp
        publish, published = self._publisher(t0, clock)
        try:
            # A due search is only begun here, and run between frames (continue_search): never before the
            # next frame's tracked buses.
            result = self.pipeline.process(checked, capture_time_ns, seq, on_vehicle=publish, defer_search=True)
        except ProtocolError as e:
            self._bad_frame(str(e), e.reason)
            return
        processing_ns = time.perf_counter_ns() - t0
        c.detect_ns.append(processing_ns)
        c.frames_processed += 1
        c.fixes_published += len(published)
        c.frames_with_fix += bool(published)
        self._detections_pub.put(self.detections(capture_time_ns, seq, result, processing_ns))
        if result.search_deferred:
            self._search_frame = (t0, clock, seq, {bus: vr.mode for bus, vr in result.vehicles.items()})

    def _publisher(self, t0: int, clock):
        """(publish, published): publish(vr) sends a bus's fix as soon as the pipeline has it, its processing
        counted from t0 (the start of its frame's processing); published lists the buses sent."""
        published = []

        def publish(vr) -> None:
            if vr.fix is not None and vr.vehicle_id in self._fix_pubs:
                self._fix_pubs[vr.vehicle_id].put(fix_to_message(
                    vr.fix, vr.vehicle_id, self.intersection, time.time_ns(), time.perf_counter_ns() - t0, clock))
                published.append(vr.vehicle_id)

        return publish, published

    def step_search(self) -> None:
        """The deferred search: its work handed to the search thread, or, once that has run, ended here (the
        pipeline's thread)."""
        run = self._search_run
        if run is not None:
            if not run.done():
                return
            self._search_run = None
            if run.exception() is not None:
                log.error("acquisition search failed: %s", run.exception())
                self.pipeline.drop_search()
            elif self.pipeline.search_ready:
                self.continue_search()
        work = self.pipeline.search_work()
        if work is not None:
            self._search_run = self._searcher.submit(work)

    def continue_search(self) -> None:
        """End the deferred search whose work has run on the search thread: publish its fixes and its
        frame's detections again with the searched buses' modes (its processing counted from the frame's
        start: the frames tracked in between included)."""
        t0, clock, seq, modes = self._search_frame
        publish, published = self._publisher(t0, clock)
        try:
            result = self.pipeline.continue_search(on_vehicle=publish)
        except Exception as e:  # a bug in one search must not stop the RSU, nor leave it searching forever
            log.exception("acquisition search of frame %s failed: %s", seq, e)
            self.pipeline.drop_search()
            return
        if result is None:
            return
        self.counters.fixes_published += len(published)
        self.counters.frames_with_fix += bool(published)
        self._detections_pub.put(self.detections(result.t_ns, seq, result, time.perf_counter_ns() - t0, modes))

    def detections(self, capture_time_ns: int, seq: int, result, processing_ns: int,
                   modes: dict[str, str] | None = None) -> TagDetections:
        """The tags found in this frame, corners as observed (for a view to draw over the image). modes: the
        frame's other buses' modes (a deferred search's result has only the buses it sought)."""
        tags = []
        for bus, vr in result.vehicles.items():
            used = set(vr.solution.tags) if vr.solution is not None and vr.solution.ok else set()
            for ob in vr.observations:
                corners = ob.raw_corners if ob.raw_corners is not None else ob.corners
                tags.append(DetectedTag(bus_id=bus, tag_id=int(ob.tag_id), used=int(ob.tag_id) in used,
                                        corners=[(float(u), float(v)) for u, v in corners]))
        return TagDetections(rsu_id=self.rsu_id, capture_time_ns=capture_time_ns, frame_seq=seq,
                             width=self.camera.width, height=self.camera.height, tags=tags,
                             modes={**(modes or {}), **{bus: vr.mode for bus, vr in result.vehicles.items()}},
                             processing_ns=processing_ns)

    def status(self) -> RsuStatus:
        c = self.counters
        det = c.detect_ns
        fields = {"frames_skipped": self.msg_counters.get(SKIPPED, "Frame"),
                  "frames_missing": self.msg_counters.get(MISSING, "Frame"), **self._source_status()}
        msg = RsuStatus(rsu_id=self.rsu_id, intersection_id=self.intersection, reference_time_ns=time.time_ns(),
                        started_ns=self.started_ns, active_buses=sorted(self._sessions),
                        frames_received=c.frames_received, frames_processed=c.frames_processed, frames_idle=c.frames_idle,
                        frames_with_fix=c.frames_with_fix, fixes_published=c.fixes_published,
                        active_s=c.active_s, messages_rejected=self.msg_counters.get(REJECTED),
                        detection_ns_mean=int(np.mean(det)) if det else None,
                        detection_ns_max=int(np.max(det)) if det else None,
                        clock=clock_to_message(self.clock.current()), **self._trust(), **fields)
        c.detect_ns = []
        return msg

    def _trust(self) -> dict:
        """The buses' recent diagnoses of this RSU, for its RsuStatus."""
        now = time.monotonic()
        recent = [m for m, t in list(self._diagnoses.values()) if now - t <= DIAGNOSIS_SHOWN_S]
        return {"diagnoses": recent, "drift_flagged": any(m.drift_flagged for m in recent)}

    def _source_status(self) -> dict:
        if self.source is None:
            return {}
        st = self.source.stats()
        return {"source": self.source.source.spec.describe()[:300], "source_connected": st.connected,
                "source_fps": round(st.fps, 3), "source_reconnects": st.reconnects,
                "source_last_error": None if st.last_error is None else st.last_error[:500],
                "frames_skipped": self.msg_counters.get(SKIPPED, "Frame") + st.frames_dropped}

    # ---- loop ---------------------------------------------------------------------------------
    def run(self, duration: float | None = None, status_period: float = 1.0) -> None:
        t_end = None if duration is None else time.monotonic() + duration
        next_status = time.monotonic() + status_period
        last = time.monotonic()
        while not self._stop.is_set() and (t_end is None or time.monotonic() < t_end):
            self._apply_changes()
            self.step_search()
            wait = 0.01 if self._search_run is not None else 0.05  # a search that ends is concluded soon
            if self.source is None:
                frame, handle = self._frames.recv(timeout=wait), self.handle_frame
            else:
                frame, handle = self.source.get(timeout=wait), self.handle_captured
            now = time.monotonic()
            if self._sessions:
                self.counters.active_s += now - last
            last = now
            if frame is not None:
                try:
                    handle(frame)
                except Exception as e:  # a bug on one frame must not stop the RSU
                    log.exception("frame %s failed: %s", getattr(frame, "seq", getattr(frame, "index", "?")), e)
            if now >= next_status:
                next_status = now + status_period
                self._status_pub.put(self.status())

    def stop(self) -> None:
        self._stop.set()
        if self.source is not None:
            self.source.stop()

    def close(self) -> None:
        c = self.counters
        if c.delivery_ns:
            (d50, d99), (w50, w99) = (np.percentile(v, [50, 99]) / 1e6 for v in (c.delivery_ns, c.wait_ns))
            log.info("%d frames in session: arrived p50 %.1f / p99 %.1f ms after their capture stamp, waited "
                     "p50 %.1f / p99 %.1f ms for the frame loop", len(c.delivery_ns), d50, d99, w50, w99)
        self._searcher.shutdown(wait=True, cancel_futures=True)
        for s in self._subs:
            s.close()
        if self._frames is not None:
            self._frames.close()
        if self.source is not None:
            self.source.close()
        self._watch.close()
        for p in self._fix_pubs.values():
            p.close()
        self._status_pub.close()
        self._detections_pub.close()
        self.clock.close()


def _lower_priority(nice: int) -> None:
    """Make the calling thread `nice` steps nicer (Linux: a thread's own nice value; the detector threads
    it starts inherit it)."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (AttributeError, OSError) as e:  # not Linux, or not allowed: the search runs at the RSU's priority
        log.info("search thread keeps the RSU's priority: %s", e)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag rsu", description=__doc__.split("\n\n")[0])
    p.add_argument("--camera", required=True, help="camera calibration JSON; its id is the RSU id")
    p.add_argument("--intersection", required=True, help="intersection id (as in the map file)")
    p.add_argument("--method", choices=METHODS, default=None,
                   help=f"solver (default: the settings file's pipeline.method, else {PipelineSettings().method})")
    p.add_argument("--source", default=None,
                   help="zenoh (the simulator's frames, default), a stream URL (rtsp://, http://), a video file, "
                        "/dev/videoN or a folder of images (default: the settings file's camera.source)")
    p.add_argument("--capture-latency-ms", type=float, default=None,
                   help="streams, devices, folders: camera-to-RSU latency subtracted from the receive time to give "
                        "the capture time (measure it once: README, installing at a site); default 0")
    p.add_argument("--rtsp-transport", choices=("tcp", "udp"), default=None, help="RTSP transport (default tcp)")
    add_service_arguments(p)
    return p


def _reader(settings: SourceSettings) -> LatestFrameReader | None:
    spec = parse_source(settings.source)
    if spec.kind == "zenoh":
        return None
    if spec.kind in ("stream", "device") and settings.capture_latency_ms == 0:
        log.warning("capture latency 0 ms assumed for %s: measure it and set --capture-latency-ms", spec.describe())
    src = open_source(spec, capture_latency_ns=int(round(settings.capture_latency_ms * 1e6)), realtime=True,
                      rtsp_transport=settings.rtsp_transport)
    return LatestFrameReader(src, log=log).start()


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)

    def load() -> tuple[Camera, PipelineSettings, SourceSettings]:
        camera = Camera.load(args.camera).require_extrinsics(f"camera file {args.camera}:")
        keys.frame(camera.id)  # the camera id must be usable as an RSU id on the wire
        keys.approach(args.intersection, "x")
        pipeline = args.settings.pipeline
        if args.method is not None:  # the command line overrides the settings file
            pipeline = pipeline.model_copy(update={"method": args.method})
        given = {"source": args.source, "capture_latency_ms": args.capture_latency_ms,
                 "rtsp_transport": args.rtsp_transport}
        camera_source = SourceSettings.model_validate(
            {**args.settings.camera.model_dump(), **{k: v for k, v in given.items() if v is not None}})
        parse_source(camera_source.source)  # one line naming what is wrong, before the session opens
        return camera, pipeline, camera_source

    return run_service(
        "rsu", args, load,
        lambda session, inputs: RsuService(session, inputs[0], args.intersection, inputs[1],
                                           source=_reader(inputs[2])),
        lambda inputs: f"RSU {inputs[0].id} at intersection {args.intersection} "
                       f"({inputs[0].width}x{inputs[0].height}, {inputs[1].method} solver), frames from "
                       f"{parse_source(inputs[2].source).describe()}",
        settings=RsuSettings)
