"""`toptag view`: the intersection live in a browser, drawn by Rerun's web viewer.

    toptag view [--connect ENDPOINT] [--bind 127.0.0.1:PORT] [--scenario FILE | --map MAP --camera CAM...]

Subscribes to toptag/v1/** and shows:
- the map (y up, north at the top): roads, each RSU and its view footprint at roof height;
- each bus: its true outline and trail (when the simulator publishes truth, green), each RSU's fixes
  of the last second (one colour per RSU), the fused outline, trail and 95 % covariance ellipse
  (magenta), its fusion status;
- each RSU's camera image, grey and downscaled, a few times a second, with the tags the RSU detected
  in that very frame drawn over it (corners and ids; yellow: used by the solver, red: screened out);
- RSU status (sessions, frame rate, frames behind, clock, flags) and bus status as a table;
- plots over time: fix latency (capture to arrival here), fix and fused error against the truth, RSU
  detection time.

Rerun's own serve functions bind every interface, so the bundled `rerun` binary is started bound to
--bind's address (default loopback), on a free gRPC port; the view logs to it and prints the URL to
open. Updates are capped (--hz, default 5; images --image-hz, default 2 per RSU) and sent in chunks
once a second: the web viewer fell behind at 50 Hz, and on a loaded 2-core machine in software
rendering even at 10 Hz. Needs the optional extra: pip install 'toptag[view]'.
"""
from __future__ import annotations

import argparse
import datetime
import logging
import threading
import time
from collections import defaultdict, deque

import cv2
import numpy as np

from protocol import keys
from protocol.codec import ProtocolError
from protocol.images import frame_to_gray
from protocol.messages import (
    Approach,
    Frame,
    FusedPose,
    GroundTruth,
    PoseFix,
    RsuStatus,
    TagDetections,
)
from protocol.transport import MessageCounters, subscribe_messages
from protocol.transport.runner import add_service_arguments, run_service
from services.monitor import Monitor
from services.view.rerun_server import RerunServer, ViewerError, parse_bind, rerun_binary
from services.view.site import SiteMap, load_site
from toptag.errors import InputError
from toptag.geometry import vehicle_to_world
from toptag.vehicle import Vehicle

log = logging.getLogger(__name__)

GREY, LANE, CENTRE = (70, 70, 70), (200, 200, 200), (230, 200, 60)
RSU_COLOUR = (255, 150, 0)
TRUTH, FUSED = (40, 210, 40), (235, 0, 235)
USED_TAG, DROPPED_TAG = (255, 235, 0), (255, 40, 40)
FIX_COLOURS = [(0, 170, 255), (0, 230, 200), (150, 120, 255), (255, 110, 160), (120, 200, 255), (200, 255, 120)]
TRAIL_S = 15.0  # truth and fused trails
FIXES_S = 1.0  # fixes shown on the map
STALE_S = 3.0  # a bus not heard of for this long is taken off the map
ELLIPSE_K = float(np.sqrt(5.991))  # 95 % of a 2-D Gaussian
STATUS_PERIOD_S = 1.0
TRAIL_PERIOD_S = 1.0


def _flip(xy) -> np.ndarray:
    """World (y north) to the 2-D view (y down): the map is drawn with north at the top."""
    return np.asarray(xy, dtype=float).reshape(-1, 2) * np.array([1.0, -1.0])


def _outline(vehicle: Vehicle | None, x: float, y: float, yaw: float) -> np.ndarray:
    fp = vehicle.footprint() if vehicle is not None else np.array([[6.0, 1.25], [6.0, -1.25], [-6.0, -1.25],
                                                                   [-6.0, 1.25]])
    pts = vehicle_to_world(np.column_stack([fp, np.zeros(4)]), x, y, yaw, 0.0)[:, :2]
    return np.vstack([pts, pts[:1]])


def covariance_ellipse(x: float, y: float, cov_xy: np.ndarray, k: float = ELLIPSE_K, n: int = 48) -> np.ndarray:
    vals, vecs = np.linalg.eigh(0.5 * (cov_xy + cov_xy.T))
    a = np.linspace(0, 2 * np.pi, n + 1)
    circle = np.column_stack([np.cos(a), np.sin(a)]) * (k * np.sqrt(np.maximum(vals, 0.0)))
    return circle @ vecs.T + np.array([x, y])


class ViewState:
    """What the view knows, filled by Zenoh callbacks, read by the drawing loop (one lock)."""

    def __init__(self, site: SiteMap):
        self.lock = threading.Lock()
        self.vehicles: dict[str, Vehicle] = dict(site.vehicles)
        self.truth: dict[str, deque] = defaultdict(lambda: deque(maxlen=int(TRAIL_S * 50)))
        self.fused: dict[str, deque] = defaultdict(lambda: deque(maxlen=int(TRAIL_S * 50)))
        self.fixes: dict[str, deque] = defaultdict(lambda: deque(maxlen=400))
        self.frames: dict[str, deque] = defaultdict(lambda: deque(maxlen=8))
        self.detections: dict[str, deque] = defaultdict(lambda: deque(maxlen=8))
        self.status: dict[str, RsuStatus] = {}
        self.heard: dict[str, float] = {}  # bus -> monotonic time of its last truth or fused pose
        self.newest_ns = 0  # newest message time seen: "now" on the view's timeline

    def _now(self, t_ns: int) -> None:
        self.newest_ns = max(self.newest_ns, t_ns)

    def on_truth(self, m: GroundTruth) -> None:
        with self.lock:
            self.truth[m.bus_id].append(m)
            self.heard[m.bus_id] = time.monotonic()
            self._now(m.t_ns)

    def on_fused(self, m: FusedPose) -> None:
        with self.lock:
            self.fused[m.bus_id].append(m)
            self.heard[m.bus_id] = time.monotonic()
            self._now(m.t_ns)

    def on_fix(self, m: PoseFix) -> None:
        with self.lock:
            self.fixes[m.bus_id].append(m)

    def on_frame(self, m: Frame) -> None:
        with self.lock:
            self.frames[m.rsu_id].append(m)

    def on_detections(self, m: TagDetections) -> None:
        with self.lock:
            self.detections[m.rsu_id].append(m)

    def on_status(self, m: RsuStatus) -> None:
        with self.lock:
            self.status[m.rsu_id] = m

    def on_approach(self, m: Approach) -> None:
        with self.lock:
            if m.bus_id not in self.vehicles:
                try:
                    self.vehicles[m.bus_id] = Vehicle(m.vehicle)
                except Exception:  # an unusable bag: drawn with a default outline
                    pass


class LiveView:
    """Subscriptions, and a drawing step (tick) that logs what changed to a Rerun recording stream."""

    def __init__(self, session, rec, site: SiteMap, *, hz: float = 5.0, image_hz: float = 2.0,
                 image_width: int = 480):
        self.rec = rec
        self.site = site
        self.period = 1.0 / hz
        self.image_period = 1.0 / image_hz
        self.image_width = image_width
        self.state = ViewState(site)
        self.counters = MessageCounters()
        self.monitor = Monitor(session)
        self._stop = threading.Event()
        self._rsus: list[str] = [r.id for r in site.rsus]
        self._shown_image: dict[str, tuple[float, int]] = {}  # rsu -> (monotonic time, frame seq) last drawn
        self._scored: dict[tuple[str, str], int] = {}
        self._cleared: set[str] = set()
        self._trails: dict[str, float] = {}
        self._last_status = 0.0
        self._frames_seen: dict[str, tuple[float, int]] = {}
        self.images_drawn = 0
        self.overlays_drawn = 0
        st = self.state
        a = keys.ANY
        subs = [(keys.ground_truth(a), GroundTruth, st.on_truth), (keys.fused_pose(a), FusedPose, st.on_fused),
                (keys.pose_fix(a, a, a), PoseFix, st.on_fix), (keys.frame(a), Frame, st.on_frame),
                (keys.detections(a), TagDetections, st.on_detections), (keys.rsu_status(a), RsuStatus, st.on_status),
                (keys.approach(a, a), Approach, st.on_approach)]
        self._subs = [subscribe_messages(session, k, t, h, self.counters, log) for k, t, h in subs]
        self._send_blueprint()
        self._draw_map()

    # ---- static ---------------------------------------------------------------------------------
    def _blueprint(self):
        import rerun.blueprint as rrb

        (x0, x1), (y0, y1) = self.site.extent
        cams = [rrb.Spatial2DView(origin=f"cameras/{r}", name=f"{r} camera") for r in self._rsus]
        last_minute = rrb.VisibleTimeRange("time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-60.0),
                                           end=rrb.TimeRangeBoundary.cursor_relative())
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin="map", name="intersection (north up)",
                                      visual_bounds=rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])),
                    rrb.TextDocumentView(origin="status", name="status"),
                    row_shares=[3, 1]),
                rrb.Vertical(
                    rrb.Grid(*cams, grid_columns=2 if len(cams) > 1 else 1) if cams else rrb.Grid(),
                    rrb.TimeSeriesView(origin="plots/latency", name="fix latency, capture to arrival (ms)",
                                       time_ranges=last_minute),
                    rrb.TimeSeriesView(origin="plots/error", name="error vs truth (cm)", time_ranges=last_minute),
                    rrb.TimeSeriesView(origin="plots/rsu", name="RSU detection and solve (ms)", time_ranges=last_minute),
                    row_shares=[4, 1, 1, 1]),
                column_shares=[1, 1]),
            collapse_panels=True)

    def _send_blueprint(self) -> None:
        self.rec.send_blueprint(self._blueprint())

    def _draw_map(self) -> None:
        import rerun as rr

        rec, site = self.rec, self.site
        from sim.scene import ROAD_HALF_WIDTH

        by_kind = defaultdict(list)
        for road in site.roads:
            by_kind[road.kind].append(_flip(road.points))
        rec.log("map/roads/surface", rr.LineStrips2D(by_kind["surface"], radii=ROAD_HALF_WIDTH, colors=GREY,
                                                     draw_order=0.0), static=True)
        rec.log("map/roads/centre", rr.LineStrips2D(by_kind["centre"], radii=0.12, colors=CENTRE, draw_order=1.0),
                static=True)
        rec.log("map/roads/lanes", rr.LineStrips2D(by_kind["lane"], radii=0.08, colors=LANE, draw_order=1.0),
                static=True)
        for r in site.rsus:
            rec.log(f"map/rsus/{r.id}", rr.Points2D(_flip(r.position), radii=0.8, colors=RSU_COLOUR, labels=[r.id],
                                                    draw_order=5.0), static=True)
            rec.log(f"map/rsus/{r.id}/footprint", rr.LineStrips2D([_flip(r.footprint)], radii=0.12,
                                                                   colors=RSU_COLOUR, draw_order=2.0), static=True)

    # ---- per tick -------------------------------------------------------------------------------
    def _at(self, t_ns: int) -> None:
        self.rec.set_time("time", timestamp=np.datetime64(int(t_ns), "ns"))

    def _draw_buses(self) -> None:
        import rerun as rr

        st, rec = self.state, self.rec
        with st.lock:
            buses = sorted(set(st.truth) | set(st.fused))
            snap = {b: (list(st.truth[b]), list(st.fused[b]), list(st.fixes[b]), st.vehicles.get(b), st.heard.get(b, 0.0))
                    for b in buses}
        now = time.monotonic()
        for bus, (truth, fused, fixes, vehicle, heard) in snap.items():
            base = f"map/buses/{bus}"
            if now - heard > STALE_S:
                if bus not in self._cleared:
                    self._at(max(st.newest_ns, 1))
                    rec.log(base, rr.Clear(recursive=True))
                    self._cleared.add(bus)
                continue
            self._cleared.discard(bus)
            if truth:
                t = truth[-1]
                self._at(t.t_ns)
                # Wider than the fused outline and beneath it: a green rim shows where the truth is.
                rec.log(f"{base}/truth", rr.LineStrips2D([_flip(_outline(vehicle, t.x, t.y, t.yaw))], radii=0.4,
                                                         colors=TRUTH, draw_order=6.0))
                self._trail(f"{base}/truth_trail", truth, TRUTH, 3.0)
            if fused:
                f = fused[-1]
                self._at(f.t_ns)
                cov = f.covariance_matrix()[:2, :2]
                sigma_cm = 100 * float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))
                label = f"{bus} {f.health.status or '-'} ±{sigma_cm:.1f} cm"
                rec.log(f"{base}/fused", rr.LineStrips2D([_flip(_outline(vehicle, f.x, f.y, f.yaw))], radii=0.18,
                                                         colors=FUSED, labels=[label], draw_order=7.0))
                rec.log(f"{base}/fused_ellipse", rr.LineStrips2D([_flip(covariance_ellipse(f.x, f.y, cov))], radii=0.05,
                                                                 colors=FUSED, draw_order=8.0))
                self._trail(f"{base}/fused_trail", fused, FUSED, 3.5)
            if fixes:
                newest = fixes[-1].capture_time_ns
                recent = [m for m in fixes if (newest - m.capture_time_ns) * 1e-9 <= FIXES_S]
                self._at(newest)
                rec.log(f"{base}/fixes", rr.Points2D(_flip([(m.x, m.y) for m in recent]), radii=0.3,
                                                     colors=[self._rsu_colour(m.rsu_id) for m in recent], draw_order=9.0))

    def _trail(self, entity: str, poses: list, colour, draw_order: float) -> None:
        """The last TRAIL_S seconds of poses (truth or fused) as a line; hundreds of points, so redrawn
        once a second, not every tick."""
        import rerun as rr

        now = time.monotonic()
        if now - self._trails.get(entity, 0.0) < TRAIL_PERIOD_S:
            return
        self._trails[entity] = now
        newest = poses[-1].t_ns
        trail = [(m.x, m.y) for m in poses if (newest - m.t_ns) * 1e-9 <= TRAIL_S]
        self.rec.log(entity, rr.LineStrips2D([_flip(trail)], radii=0.07, colors=colour, draw_order=draw_order))

    def _rsu_colour(self, rsu: str) -> tuple[int, int, int]:
        if rsu not in self._rsus:
            self._rsus.append(rsu)
            self._send_blueprint()
        return FIX_COLOURS[self._rsus.index(rsu) % len(FIX_COLOURS)]

    def _pick_frame(self, rsu: str) -> tuple[Frame | None, TagDetections | None]:
        """The newest frame whose detections have arrived (so the overlay is that frame's), or, when
        the RSU has not processed recent frames (no bus in session), the newest frame alone."""
        with self.state.lock:
            frames = list(self.state.frames.get(rsu, ()))
            dets = list(self.state.detections.get(rsu, ()))
        if not frames:
            return None, None
        by_seq = {f.seq: f for f in frames}
        for d in reversed(dets):
            if d.frame_seq in by_seq:
                return by_seq[d.frame_seq], d
        newest = frames[-1]
        if dets and (newest.capture_time_ns - dets[-1].capture_time_ns) * 1e-9 < 1.0:
            return None, None  # detections lag behind: wait for the frame they belong to
        return newest, None

    def _draw_cameras(self) -> None:
        import rerun as rr

        now = time.monotonic()
        for rsu in list(self._rsus) + [r for r in self.state.frames if r not in self._rsus]:
            shown = self._shown_image.get(rsu)
            if shown is not None and now - shown[0] < self.image_period:
                continue
            frame, det = self._pick_frame(rsu)
            if frame is None or (shown is not None and frame.seq == shown[1]):
                continue
            try:
                gray = frame_to_gray(frame)
            except ProtocolError as e:
                log.warning("camera %s: %s", rsu, e)
                self._shown_image[rsu] = (now, frame.seq)
                continue
            if rsu not in self._rsus:
                self._rsus.append(rsu)
                self._send_blueprint()
            scale = min(1.0, self.image_width / gray.shape[1])
            small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray
            base = f"cameras/{rsu}"
            self._at(frame.capture_time_ns)
            self.rec.log(f"{base}/image", rr.Image(small))
            if det is not None and det.tags:
                s = np.array([small.shape[1] / det.width, small.shape[0] / det.height])
                # corners are pixel centres (OpenCV); the image's pixel i spans [i, i+1] in the view
                polys = [np.vstack([np.asarray(t.corners) * s, np.asarray(t.corners[:1]) * s]) + 0.5 * s for t in det.tags]
                self.rec.log(f"{base}/tags", rr.LineStrips2D(
                    polys, radii=rr.Radius.ui_points(2.0), colors=[USED_TAG if t.used else DROPPED_TAG for t in det.tags],
                    labels=[f"{t.bus_id} #{t.tag_id}" for t in det.tags], draw_order=10.0))
                self.overlays_drawn += 1
                if self.overlays_drawn == 1:
                    log.info("view: first camera image with detections drawn (%s, %d tags)", rsu, len(det.tags))
            else:
                self.rec.log(f"{base}/tags", rr.Clear(recursive=False))
            self.images_drawn += 1
            self._shown_image[rsu] = (now, frame.seq)

    def _plot(self, path: str, value: float | None) -> None:
        import rerun as rr

        if value is not None and np.isfinite(value):
            self.rec.log(path, rr.Scalars(float(value)))

    def _draw_plots(self) -> None:
        mon = self.monitor
        summary = mon.summary()  # scores what the truth now covers
        self._at(max(self.state.newest_ns, 1))
        for bus, b in list(mon.buses.items()):
            for name, stats, scale in (("latency", b.latency_ms, 1.0), ("error/fix", b.fix_err, 100.0),
                                       ("error/fused", b.fused_err, 100.0)):
                if stats.n != self._scored.get((bus, name), 0):
                    self._scored[(bus, name)] = stats.n
                    path = f"plots/latency/{bus}" if name == "latency" else f"plots/{name.split('/')[0]}/{bus}/{name.split('/')[1]}"
                    self._plot(path, stats.last * scale)
        return summary

    def _draw_status(self, summary: dict) -> None:
        import rerun as rr

        now = time.monotonic()
        lines = ["| RSU | buses in session | fps | processed | behind | detect ms | fixes | clock | flags |",
                 "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        with self.state.lock:
            status = dict(self.state.status)
        for rid, s in sorted(status.items()):
            prev = self._frames_seen.get(rid)
            fps = None
            if prev is not None and now > prev[0] and s.frames_received >= prev[1]:
                fps = (s.frames_received - prev[1]) / (now - prev[0])
            if prev is None or now - prev[0] >= 2.0:
                self._frames_seen[rid] = (now, s.frames_received)
            det = None if s.detection_ns_mean is None else s.detection_ns_mean * 1e-6
            self._plot(f"plots/rsu/{rid}", det)
            flags = [f for f, on in (("rejected input", s.messages_rejected > 0), ("behind", s.frames_skipped > 0)) if on]
            clock = s.clock.source + ("" if s.clock.sync_uncertainty_ns is None else f" ±{s.clock.sync_uncertainty_ns / 1e6:g} ms")
            lines.append(f"| {rid} | {', '.join(s.active_buses) or '-'} | {'-' if fps is None else f'{fps:.1f}'} | "
                         f"{s.frames_processed} | {s.frames_skipped} | {'-' if det is None else f'{det:.1f}'} | "
                         f"{s.fixes_published} | {clock} | {', '.join(flags) or 'ok'} |")
        lines += ["", "| bus | status | fixes | by RSU | fix err | fused err | latency p50 |", "| --- | --- | --- | --- | --- | --- | --- |"]
        for bus, b in summary["buses"].items():
            def cm(v):
                return "-" if v is None else f"{100 * v:.1f} cm"
            lat = "-" if b["latency_ms_p50"] is None else f"{b['latency_ms_p50']:.0f} ms"
            lines.append(f"| {bus} | {b['last_fused_status'] or '-'} | {b['fixes_received']} | "
                         f"{', '.join(f'{r} {n}' for r, n in b['fixes_by_rsu'].items()) or '-'} | {cm(b['last_fix_err_m'])} | "
                         f"{cm(b['last_fused_err_m'])} | {lat} |")
        self.rec.log("status", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN))

    def tick(self) -> None:
        self._draw_buses()
        self._draw_cameras()
        summary = self._draw_plots()
        if time.monotonic() - self._last_status >= STATUS_PERIOD_S:
            self._last_status = time.monotonic()
            self._draw_status(summary)

    def run(self, duration: float | None = None) -> None:
        t_end = None if duration is None else time.monotonic() + duration
        next_t = time.monotonic()
        last_note = time.monotonic()
        while not self._stop.is_set() and (t_end is None or time.monotonic() < t_end):
            try:
                self.tick()
            except Exception as e:  # a drawing bug must not end the view
                log.exception("view tick failed: %s", e)
            if time.monotonic() - last_note >= 10.0:
                last_note = time.monotonic()
                log.info("view: %d camera images drawn (%d with detections)", self.images_drawn, self.overlays_drawn)
            next_t += self.period
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        for s in self._subs:
            s.close()
        self.monitor.close()
        log.info("view: %d camera images drawn (%d with detections)", self.images_drawn, self.overlays_drawn)


class ViewService:
    """The Rerun server, the recording stream connected to it, and the LiveView: started and stopped
    together (the server by its PID)."""

    def __init__(self, session, site: SiteMap, server: RerunServer, **view_kw):
        import rerun as rr

        self.server = server
        server.start()
        # Fewer, larger chunks (one per entity a second instead of every 0.2 s): the web viewer ingests
        # chunk by chunk and fell behind real time on a loaded machine (measured: 0.2 s ticks and 10 Hz
        # updates lagged ~5x; 0.5 s ticks and trails at 1 Hz halved the lag).
        batch = rr.ChunkBatcherConfig(flush_tick=datetime.timedelta(seconds=1.0))
        self.rec = rr.RecordingStream("toptag", recording_id=f"toptag-live-{time.time_ns()}", batcher_config=batch)
        self.rec.connect_grpc(server.grpc_url)
        self.view = LiveView(session, self.rec, site, **view_kw)
        print(f"toptag view: open {server.url}", flush=True)

    def run(self, duration: float | None = None) -> None:
        self.view.run(duration)

    def stop(self) -> None:
        self.view.stop()

    def close(self) -> None:
        self.view.close()
        try:
            self.rec.flush(timeout_sec=1.0)  # a live view may lose its last second, never hang on exit
        except Exception:
            pass
        self.server.stop()
        try:
            self.rec.disconnect()
        except Exception:
            pass


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag view", description=__doc__.split("\n\n")[0])
    p.add_argument("--bind", default="127.0.0.1:0", metavar="ADDR:PORT",
                   help="where the web viewer listens (default 127.0.0.1, a free port); the URL is printed")
    p.add_argument("--scenario", default=None, metavar="FILE",
                   help="site files (map, cameras, vehicles) from a scenario (default: the bundled demo)")
    p.add_argument("--map", default=None, metavar="MAP", help="map file of intersections (instead of a scenario)")
    p.add_argument("--camera", action="append", default=None, metavar="CAM", help="RSU camera file (repeatable)")
    p.add_argument("--vehicle", action="append", default=None, metavar="VEH", help="vehicle file (repeatable)")
    p.add_argument("--hz", type=float, default=5.0, help="map and plot updates per second (default 5, at most 30)")
    p.add_argument("--image-hz", type=float, default=2.0, help="camera images per second per RSU (default 2)")
    p.add_argument("--image-width", type=int, default=480, help="camera images downscaled to this width")
    add_service_arguments(p)
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)

    def load() -> tuple[SiteMap, RerunServer]:
        from sim.scenario import bundled_scenario_path, load_scenario

        if not (0 < args.hz <= 30 and 0 < args.image_hz <= args.hz and args.image_width >= 64):
            raise InputError("need 0 < --image-hz <= --hz <= 30 and --image-width >= 64")
        try:
            host, port = parse_bind(args.bind)
        except ViewerError as e:
            raise InputError(str(e)) from None
        if args.map:
            site = load_site(args.map, args.camera or [], args.vehicle or [])
        else:
            sc = load_scenario(args.scenario or bundled_scenario_path())
            site = load_site(sc.map_path(), sc.camera_paths(), sc.vehicle_paths())
        rerun_binary()  # rerun-sdk installed, its viewer binary there (else SetupError: exit 1)
        return site, RerunServer(host, port)

    def build(session, inputs):
        site, server = inputs
        return ViewService(session, site, server, hz=args.hz, image_hz=args.image_hz, image_width=args.image_width)

    return run_service("view", args, load, build, lambda inputs: f"live view ({len(inputs[0].rsus)} RSUs on the map)")

