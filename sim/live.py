"""`toptag sim run`: the live simulator that drives the running system's cameras and bus sensors.

    toptag sim run [--scenario FILE] [--duration S] [zenoh options: --connect/--listen/--zenoh-mode ...]

Plays a scenario (sim.scenario; default: the bundled toptag/data/demo/scenario.json) on the wall clock
(simulator time = wall-clock time, integer ns since the epoch) and publishes through Zenoh:
- every RSU: a Frame (JPEG of sim.render at the scenario's image model) every 1/fps s on
  keys.frame(rsu_id). RSUs are staggered within the period to spread the CPU load. A frame's
  capture_time_ns is its scheduled tick, which is also the instant of the truth used to render it; seq
  is the tick index (a skipped tick leaves a gap in seq). Its clock is "sim" (exact). The scenario's
  faults (sim.faults; World.capture) change that for one RSU: a clock offset moves the stamp (and the
  clock is "system", undisciplined), a capture latency renders an earlier instant, a drift renders
  with the turned camera.
- every bus on the road: Imu at imu_hz (keys.imu; gyro_z, accel_x/y gravity-compensated, wheel_speed,
  seq +1 per sample), GroundTruth at truth_hz (keys.ground_truth; z = roof height), GnssFix at gnss_hz
  (keys.gnss; N(0, gnss_sigma_m) per axis, none inside the map's gnss_shadow_radius). Samples lie on
  fixed grids from the start time and are published once their time has come.
A bus exists only during its legs (see sim.world): between legs nothing is published for it.

Honest timing: a frame is rendered up to 100 ms ahead of its tick and published at the tick (not
before: nothing downstream sees a frame before its capture time) by the publishing thread, which also
sends the sensor samples (computed per bus in 0.5 s windows ahead of their time), so that the renderer's
own time is not counted as the camera's latency and an expensive frame does not make the next late. If
rendering falls behind, late ticks (more than half a period, at most 50 ms) are skipped and counted,
never rendered late in a backlog; the schedule never drifts. A progress line every 5 s: frames per RSU,
achieved fps, render+encode ms p50/p90, skipped ticks, sensor counts.

Exit 0 after --duration or on SIGINT/SIGTERM (session closed); 2 with one line on stderr for a bad
scenario (or camera, vehicle, map file); 1 if the Zenoh session cannot be opened. Without --duration
the cameras keep streaming after a non-looping scenario's last leg (an empty intersection).
"""
from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable

import cv2
import numpy as np

from protocol import keys
from protocol.messages import ClockInfo, Frame, GnssFix, GroundTruth, Imu
from protocol.transport import MessagePublisher
from protocol.transport.runner import add_service_arguments, run_service
from sim.scenario import bundled_scenario_path, load_scenario
from sim.world import World
from toptag.inputs import InputError
from toptag.units import NS_PER_S, ms_from_ns

log = logging.getLogger(__name__)

PROGRESS_S = 5.0
MAX_LATE_S = 0.05  # a tick rendered later than min(half a period, this) is skipped
# A frame is rendered up to this long before its tick and published at the tick by the publishing
# thread (SensorLoop): the scene at a future instant is known, and a real camera's frame does not wait
# for a renderer. One period at the demo's 10 fps, so that an expensive frame (a bus close to a camera,
# or the machine busy) delays the frames after it without making them late.
RENDER_AHEAD_NS = 100_000_000


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag sim run", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, metavar="FILE",
                   help="scenario file (default: the bundled demo, toptag/data/demo/scenario.json)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds of simulated (= wall-clock) time; default: run until signalled")
    add_service_arguments(p, duration=False)
    return p


class _Publishers:
    def __init__(self, session, world: World):
        self.frames = {r: MessagePublisher(session, keys.frame(r), Frame) for r in world.rsu_ids}
        self.imu = {b: MessagePublisher(session, keys.imu(b), Imu) for b in world.bus_ids}
        self.truth = {b: MessagePublisher(session, keys.ground_truth(b), GroundTruth) for b in world.bus_ids}
        self.gnss = {b: MessagePublisher(session, keys.gnss(b), GnssFix) for b in world.bus_ids}

    def close(self) -> None:
        for group in (self.frames, self.imu, self.truth, self.gnss):
            for p in group.values():
                p.close()


# Sensor samples are computed in windows of this length, ahead of their time (the next window once the
# last one has less than half of it left), and each is published when its time has come: one
# vectorised state and noise evaluation per bus and window instead of one per 10 ms wake-up.
SENSOR_WINDOW_NS = 500_000_000


class SensorLoop(threading.Thread):
    """The publishing thread: IMU, ground truth and GNSS of every bus, and the frames the main loop
    renders ahead (post_frame), each published as soon as its time has come, none after `end_ns` (the
    run's end: a starved main loop may notice it late). Sensor samples are computed SENSOR_WINDOW_NS at a
    time, ahead of their time (the world's sensor windows move forward as before)."""

    def __init__(self, world: World, pubs: _Publishers, stop: threading.Event, end_ns: int | None = None):
        super().__init__(name="sim-sensors", daemon=True)
        self.world, self.pubs, self.stop_event, self.end_ns = world, pubs, stop, end_ns
        self.counts: dict[str, int] = defaultdict(int)
        self.max_delay_ns = 0  # worst publish delay of an IMU sample behind its time, since last read
        self.frame_delays_ns: list[int] = []  # each frame's publication behind its tick, over the run
        self.error: BaseException | None = None
        # Computed, not yet published: (publisher, count key, [(t_ns, message)] in time order, next index).
        self._queues: list[list] = []
        self._computed_ns = world.t0_ns - 1  # samples up to this time are computed
        self._incoming: deque = deque()  # frames posted by the main loop: (tick, publisher, Frame)
        self._wake = threading.Event()
        self.frame_published: Callable[[str], None] = lambda rsu_id: None

    def post_frame(self, tick_ns: int, pub: MessagePublisher, frame: Frame) -> None:
        """Publish this frame at tick_ns (at once if that has passed)."""
        self._incoming.append((tick_ns, pub, frame))
        self._wake.set()

    def wake(self) -> None:
        self._wake.set()

    def flush(self, t_ns: int) -> None:
        """After the thread has stopped: publishes what is queued for times <= t_ns."""
        self._take_posted()
        self.publish_due(t_ns)

    def _take_posted(self) -> None:
        while self._incoming:
            t, pub, frame = self._incoming.popleft()
            self._queues.append([pub, "frame", [(t, frame)], 0])

    def run(self) -> None:
        try:
            while not self.stop_event.is_set():
                now = time.time_ns()
                if self.end_ns is not None:
                    now = min(now, self.end_ns)
                if now + SENSOR_WINDOW_NS // 2 > self._computed_ns and (
                        self.end_ns is None or self._computed_ns < self.end_ns):
                    until = now + SENSOR_WINDOW_NS
                    until = until if self.end_ns is None else min(until, self.end_ns)
                    self.compute(self._computed_ns, until)
                    self._computed_ns = until
                self._take_posted()
                wake = self.publish_due(now)
                if self.end_ns is not None and now >= self.end_ns:
                    break
                if self.end_ns is None or self._computed_ns < self.end_ns:
                    wake = min(wake, self._computed_ns - SENSOR_WINDOW_NS // 2)
                if self.end_ns is not None:
                    wake = min(wake, self.end_ns)
                self._wake.wait(max(0.0, (wake - time.time_ns()) / NS_PER_S) + 2e-4)
                self._wake.clear()
        except BaseException as e:  # noqa: BLE001 - reported by the main loop
            self.error = e
            log.exception("sensor loop failed")
            self.stop_event.set()

    def compute(self, t_from: int, t_to: int) -> None:
        """The samples of (t_from, t_to], queued as messages for their times."""
        w, p = self.world, self.pubs
        for bus in w.bus_ids:
            b = w.imu_between(bus, t_from, t_to)
            imu = [(int(b.t_ns[i]), Imu(bus_id=bus, t_ns=int(b.t_ns[i]), gyro_z=float(b.gyro_z[i]),
                                        accel_x=float(b.accel_x[i]), accel_y=float(b.accel_y[i]),
                                        wheel_speed=float(b.wheel_speed[i]), seq=int(b.seq[i])))
                   for i in range(len(b))]
            truth = [(s.t_ns, GroundTruth(bus_id=bus, t_ns=s.t_ns, x=s.x, y=s.y, z=s.z, yaw=s.yaw, speed=s.speed,
                                          yaw_rate=s.yaw_rate)) for s in w.truth_between(bus, t_from, t_to)]
            gnss = [(g.t_ns, GnssFix(bus_id=bus, t_ns=g.t_ns, x=g.x, y=g.y, sigma_m=g.sigma_m))
                    for g in w.gnss_between(bus, t_from, t_to)]
            for pub, kind, items in ((p.imu[bus], "imu", imu), (p.truth[bus], "truth", truth),
                                     (p.gnss[bus], "gnss", gnss)):
                if items:
                    self._queues.append([pub, kind, items, 0])

    def publish_due(self, now: int) -> int:
        """Publishes every queued sample whose time is <= now; returns the time of the next one."""
        wake = now + SENSOR_WINDOW_NS
        for q in self._queues:
            pub, kind, items, i = q
            j = i
            while j < len(items) and items[j][0] <= now:
                pub.put(items[j][1])
                j += 1
            if j > i:
                self.counts[kind] += j - i
                if kind == "frame":
                    self.frame_published(items[i][1].rsu_id)
                    self.frame_delays_ns.append(time.time_ns() - items[i][0])
                elif kind == "imu":
                    self.max_delay_ns = max(self.max_delay_ns, time.time_ns() - items[j - 1][0])
            q[3] = j
            if j < len(items):
                wake = min(wake, items[j][0])
        self._queues = [q for q in self._queues if q[3] < len(q[2])]
        return wake


class FrameStats:
    def __init__(self, rsu_ids: list[str]):
        self.published = {r: 0 for r in rsu_ids}
        self.skipped = {r: 0 for r in rsu_ids}
        self.render_ms: list[float] = []  # since the last progress line
        self.all_render_ms: list[float] = []

    def sent(self, rsu_id: str) -> None:
        self.published[rsu_id] += 1

    def line(self, elapsed_s: float, since: dict[str, int], window_s: float) -> str:
        parts = []
        for r, n in self.published.items():
            fps = (n - since.get(r, 0)) / window_s if window_s > 0 else 0.0
            parts.append(f"{r} {n} ({fps:.1f} fps)")
        ms = np.asarray(self.render_ms) if self.render_ms else np.zeros(1)
        return (f"t=+{elapsed_s:.0f} s frames {', '.join(parts)}; render+encode p50 "
                f"{np.percentile(ms, 50):.1f} ms p90 {np.percentile(ms, 90):.1f} ms; "
                f"skipped {sum(self.skipped.values())}")


def run(world: World, session, stop: threading.Event, duration_s: float | None = None) -> FrameStats:
    """The real-time loop (the caller has warmed the world up and opens/closes the session): starts
    the clock now, renders and publishes until `stop` is set or `duration_s` has passed."""
    pubs = _Publishers(session, world)
    world.start(time.time_ns())
    t0 = world.t0_ns
    end = t0 + int(duration_s * NS_PER_S) if duration_s is not None else None
    n = len(world.rsu_ids)
    next_k = [0] * n
    stats = FrameStats(world.rsu_ids)
    # The clock that stamps each RSU's frames: the simulator's, exact, unless the scenario puts it off.
    clocks = [ClockInfo(source="sim", sync_uncertainty_ns=0) if f.clock_disciplined else ClockInfo(source="system")
              for f in world.faults]
    sensors = SensorLoop(world, pubs, stop, end)
    sensors.frame_published = stats.sent
    sensors.start()
    log.info("sim running: t0_ns=%d, %d RSUs at %s fps, buses %s, %s%s", t0, n,
             "/".join(f"{f:g}" for f in world.fps), ", ".join(world.bus_ids) or "(none)",
             f"loop every {world.period_ns / NS_PER_S:.1f} s" if world.period_ns else "no loop",
             f", for {duration_s:g} s" if duration_s is not None else "")
    last_progress, since = time.monotonic(), dict(stats.published)
    try:
        while not stop.is_set():
            mono = time.monotonic()
            if mono - last_progress >= PROGRESS_S:
                log.info("%s; imu %d truth %d gnss %d (imu delay max %.1f ms); on the road: %s",
                         stats.line((time.time_ns() - t0) / NS_PER_S, since, mono - last_progress),
                         sensors.counts["imu"], sensors.counts["truth"], sensors.counts["gnss"],
                         ms_from_ns(sensors.max_delay_ns), ", ".join(world.truth_at(time.time_ns())) or "nobody")
                sensors.max_delay_ns = 0
                stats.all_render_ms.extend(stats.render_ms)
                stats.render_ms = []
                last_progress, since = mono, dict(stats.published)
            now = time.time_ns()
            if end is not None and now >= end:
                break
            ticks = [world.frame_time(r, next_k[r]) for r in range(n)]
            r = int(np.argmin(ticks))
            t = ticks[r]
            if end is not None and t >= end:
                stop.wait((end - now) / NS_PER_S)
                break
            if t - RENDER_AHEAD_NS > now:
                stop.wait((t - RENDER_AHEAD_NS - now) / NS_PER_S)
                continue
            late_limit = min(0.5 * NS_PER_S / world.fps[r], MAX_LATE_S * NS_PER_S)
            if now - t > late_limit:
                k = world.frame_index_from(r, now - int(late_limit) + 1)
                stats.skipped[world.rsu_ids[r]] += k - next_k[r]
                next_k[r] = k
                continue
            c0 = time.perf_counter()
            jpeg, stamp = world.capture(r, t)
            stats.render_ms.append((time.perf_counter() - c0) * 1e3)
            cam = world.cameras[r]
            # A camera's frame exists from its capture time on: the publishing thread sends it at its tick.
            sensors.post_frame(t, pubs.frames[cam.id], Frame(
                rsu_id=cam.id, capture_time_ns=stamp, seq=next_k[r], encoding="jpeg", width=cam.width,
                height=cam.height, image=jpeg, clock=clocks[r]))
            next_k[r] += 1
    finally:
        stop.set()
        sensors.wake()
        # Ticks that came due while the loop was behind and are not rendered now: skipped, and counted.
        t_stop = time.time_ns() if end is None else min(time.time_ns(), end)
        for r in range(n):
            due = world.frame_index_from(r, t_stop)
            if due > next_k[r]:
                stats.skipped[world.rsu_ids[r]] += due - next_k[r]
                next_k[r] = due
        sensors.join(timeout=2.0)
        if not sensors.is_alive():
            sensors.flush(t_stop)  # frames rendered for ticks before the stop that it had not sent yet
        stats.all_render_ms.extend(stats.render_ms)
        ms = np.asarray(stats.all_render_ms) if stats.all_render_ms else np.zeros(1)
        late = np.asarray(sensors.frame_delays_ns or [0]) / 1e6
        log.info("sim stopped after %.1f s: frames %s; skipped %d; render+encode p50 %.1f ms p90 %.1f ms; "
                 "frames sent p50 %.1f / p99 %.1f ms after their tick; imu %d truth %d gnss %d",
                 (time.time_ns() - t0) / NS_PER_S, ", ".join(f"{r} {k}" for r, k in stats.published.items()),
                 sum(stats.skipped.values()), np.percentile(ms, 50), np.percentile(ms, 90),
                 np.percentile(late, 50), np.percentile(late, 99), sensors.counts["imu"], sensors.counts["truth"],
                 sensors.counts["gnss"])
        pubs.close()
    if sensors.error is not None:
        raise RuntimeError(f"sensor loop failed: {sensors.error}")
    return stats


class LiveSimulator:
    """`toptag sim run` as a service: the real-time loop on one session until stopped."""

    def __init__(self, world: World, session):
        self.world, self.session = world, session
        self._stop = threading.Event()

    def run(self, duration: float | None = None) -> None:
        run(self.world, self.session, self._stop, duration)

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    path = args.scenario or bundled_scenario_path()

    def load() -> World:
        if args.duration is not None and not args.duration > 0:
            raise InputError("--duration must be positive")
        world = World(load_scenario(path))
        cv2.setNumThreads(1)
        c0 = time.perf_counter()
        world.warm_up()
        log.info("scenario %s: %d RSUs, %d buses, %d trucks; camera caches built in %.2f s; image model: %s",
                 path, len(world.cameras), len(world.buses), len(world.trucks), time.perf_counter() - c0,
                 world.model.describe())
        return world

    return run_service("sim run", args, load, lambda session, world: LiveSimulator(world, session),
                       lambda world: f"simulator ({len(world.cameras)} RSUs, {len(world.buses)} buses)")


if __name__ == "__main__":
    sys.exit(main())
