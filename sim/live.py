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
- every bus on the road: its IMU samples at imu_hz (gyro_z, accel_x/y gravity-compensated, wheel_speed,
  seq +1 per sample), imu_per_message to an ImuBatch on keys.imu_batch sent at its newest sample's time (a
  sensor window's last batch may hold fewer; with 1, an Imu per sample on keys.imu), GroundTruth at
  truth_hz (keys.ground_truth; z = roof height), GnssFix at gnss_hz (keys.gnss; N(0, gnss_sigma_m) per
  axis, none inside the map's gnss_shadow_radius). Samples lie on fixed grids from the start time and are
  published once their time has come.
A bus exists only during its legs (see sim.world): between legs nothing is published for it.

Processes and honest timing: the frames are rendered in a render process (multiprocessing, spawn
context: the simulator's Zenoh session and threads are never forked), which builds the same World from
the scenario and renders every RSU's frames earliest tick first, each up to 5 s ahead of its tick
(RENDER_AHEAD_NS; the same frames, seeds, faults and schedule as one process would render: the World
draws each camera's noise from its own stream, in its frames' order), as long as the frames not yet
due hold less than RENDER_AHEAD_BYTES (64 MB: large frames are rendered less far ahead), and hands the
JPEG over a pipe to the simulator's process. Its publishing thread sends each frame at its tick (not before: nothing
downstream sees a frame before its capture time) along with the sensor samples (computed per bus in
0.5 s windows ahead of their time). So the renderer's time is not counted as the camera's latency, no
renderer holds the publishing process's GIL, and the frames of a bus crossing, expensive to render while
the RSUs want the cores too, are rendered in the quiet seconds before it. If the renderer falls behind
anyway, late ticks (more than half a period, at most 50 ms) are skipped and counted, never rendered late
in a backlog; the schedule never drifts. The clock starts 100 ms after the render process is ready. Only
the main process opens a Zenoh session, so the Zenoh options are its own. A render process ends when the
simulator says stop, when the simulator's end of its pipe closes, or when the simulator dies
(PR_SET_PDEATHSIG); the simulator kills one that has not ended RENDER_STOP_S after stop, so none outlives
it; one that fails or exits stops the simulator (exit 1). A progress line every 5 s: frames per RSU,
achieved fps, render+encode ms p50/p90 (wall) and their hand-over to the publishing thread, skipped
ticks, the frames' sending after their tick (p50/p99), sensor counts; the last line adds the renders'
CPU and says how long after their tick the frames were sent over the whole run (p50/p99, all cameras).

Measured (`toptag bench demo --duration 60`, nproc 2, AMD EPYC, shared with two other engineers, load
3-9; docs/architecture.md "The simulator's processes"): frames sent p99 80-104 ms after their tick and
27-105 ticks skipped, against 126-157 ms and 211-398 with rendering in the loop thread 100 ms ahead; the
renders' CPU per frame is unchanged, but the demo's CPU rose (1.30 against ~1.04 cores there): nothing is
skipped any more, and a stopped run has rendered 5 s of frames it never sends.

Exit 0 after --duration or on SIGINT/SIGTERM (session closed); 2 with one line on stderr for a bad
scenario (or camera, vehicle, map file); 1 if the Zenoh session cannot be opened or the render process
fails. Without --duration
the cameras keep streaming after a non-looping scenario's last leg (an empty intersection).
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import multiprocessing as mp
import multiprocessing.connection as mp_connection
import os
import signal
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable

import cv2
import numpy as np

from protocol import keys
from protocol.messages import ClockInfo, Frame, GnssFix, GroundTruth, Imu, ImuBatch
from protocol.transport import MessagePublisher, imu_publisher
from protocol.transport.runner import add_service_arguments, run_service, setup_logging
from sim.scenario import bundled_scenario_path, load_scenario
from sim.world import World
from toptag.inputs import InputError
from toptag.units import NS_PER_S, ms_from_ns

log = logging.getLogger(__name__)

PROGRESS_S = 5.0
MAX_LATE_S = 0.05  # a tick rendered later than min(half a period, this) is skipped
# A frame is rendered (in a render process) up to this long before its tick and published at the tick by
# the publishing thread (SensorLoop): the scene at a future instant is known, and a real camera's frame does
# not wait for a renderer. Seconds, not a period: the renders are cheap on an empty road (~2 ms) and
# expensive while buses cross (15-60 ms), when the RSUs want both cores too; rendered ahead in the quiet
# seconds before, the frames are ready when the crossing comes (docs/architecture.md, "The simulator's
# processes"). At most RENDER_AHEAD_BYTES of frames wait for their tick: the demo's 4 RSUs x 10 fps x 5 s x
# 150-220 kB are 30-45 MB, but 3200x2400 JPEGs of ~1.5 MB would be ~300 MB; the budget keeps those ~1 s ahead.
START_LEAD_NS = 100_000_000  # the clock starts this long after the render processes are ready
RENDER_AHEAD_NS = 5 * NS_PER_S
RENDER_AHEAD_BYTES = 64 * 1024 * 1024


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
        self.imu = {b: imu_publisher(session, b, world.scenario.imu_per_message) for b in world.bus_ids}
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
    """The publishing thread: IMU, ground truth and GNSS of every bus, and the frames the render
    process renders ahead (post_frame), each published as soon as its time has come, none after `end_ns`
    (the run's end: a starved main loop may notice it late). Sensor samples are computed SENSOR_WINDOW_NS at a
    time, ahead of their time (the world's sensor windows move forward as before)."""

    def __init__(self, world: World, pubs: _Publishers, stop: threading.Event, end_ns: int | None = None):
        super().__init__(name="sim-sensors", daemon=True)
        self.world, self.pubs, self.stop_event, self.end_ns = world, pubs, stop, end_ns
        self.counts: dict[str, int] = defaultdict(int)  # sent by kind: messages, IMU samples
        self._imu_batches: dict[str, int] = defaultdict(int)  # ImuBatch seq per bus
        self.max_delay_ns = 0  # worst publish delay of an IMU sample behind its time, since last read
        self.frame_delays_ns: list[int] = []  # each frame's publication behind its tick, over the run
        self.error: BaseException | None = None
        # Computed, not yet published: (publisher, count key, [(t_ns, message)] in time order, next index).
        self._queues: list[list] = []
        self._computed_ns = world.t0_ns - 1  # samples up to this time are computed
        self._incoming: deque = deque()  # frames posted by the main loop: (tick, publisher, Frame)
        self._frame_queues: dict[str, list] = {}  # per frame key: its entry of _queues
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
            q = self._frame_queues.get(pub.key)
            if q is None:  # one queue per camera for the whole run: its frames come in tick order
                q = self._frame_queues[pub.key] = [pub, "frame", [], 0]
                self._queues.append(q)
            q[2].append((t, frame))

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
        per_message = w.scenario.imu_per_message
        for bus in w.bus_ids:
            b = w.imu_between(bus, t_from, t_to)
            samples = [Imu(bus_id=bus, t_ns=int(b.t_ns[i]), gyro_z=float(b.gyro_z[i]), accel_x=float(b.accel_x[i]),
                           accel_y=float(b.accel_y[i]), wheel_speed=float(b.wheel_speed[i]), seq=int(b.seq[i]))
                       for i in range(len(b))]
            if per_message == 1:
                imu = [(s.t_ns, s) for s in samples]
            else:  # each batch at its newest sample's time
                imu = []
                for k in range(0, len(samples), per_message):
                    batch = samples[k:k + per_message]
                    self._imu_batches[bus] += 1
                    imu.append((batch[-1].t_ns, ImuBatch(bus_id=bus, samples=batch, seq=self._imu_batches[bus])))
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
                if kind == "frame":
                    self.frame_delays_ns.append(time.time_ns() - items[j][0])
                    self.frame_published(items[j][1].rsu_id)
                j += 1
            if j > i and kind == "imu":  # counted in samples, one or several to a message
                self.counts[kind] += sum(len(m.samples) if isinstance(m, ImuBatch) else 1 for _, m in items[i:j])
                self.max_delay_ns = max(self.max_delay_ns, time.time_ns() - items[j - 1][0])
            elif j > i:
                self.counts[kind] += j - i
            q[3] = j
            if j < len(items):
                wake = min(wake, items[j][0])
            if kind == "frame" and j:
                del items[:j]  # a camera's queue lives on: what is sent leaves it
                q[3] = 0
        self._queues = [q for q in self._queues if q[1] == "frame" or q[3] < len(q[2])]
        return wake


class FrameStats:
    def __init__(self, rsu_ids: list[str]):
        self.published = {r: 0 for r in rsu_ids}
        self.skipped = {r: 0 for r in rsu_ids}
        self.render_ms: list[float] = []  # since the last progress line
        self.render_cpu_ms: list[float] = []  # the renders' thread CPU, over the run
        self.handover_ms: list[float] = []  # from a render's end to the simulator's, since the last line
        self.all_render_ms: list[float] = []

    def sent(self, rsu_id: str) -> None:
        self.published[rsu_id] += 1

    def line(self, elapsed_s: float, since: dict[str, int], window_s: float) -> str:
        parts = []
        for r, n in self.published.items():
            fps = (n - since.get(r, 0)) / window_s if window_s > 0 else 0.0
            parts.append(f"{r} {n} ({fps:.1f} fps)")
        ms = np.asarray(self.render_ms) if self.render_ms else np.zeros(1)
        ho = np.asarray(self.handover_ms) if self.handover_ms else np.zeros(1)
        return (f"t=+{elapsed_s:.0f} s frames {', '.join(parts)}; render+encode p50 "
                f"{np.percentile(ms, 50):.1f} ms p90 {np.percentile(ms, 90):.1f} ms, handed over p50 "
                f"{np.percentile(ho, 50):.1f} / p99 {np.percentile(ho, 99):.1f} ms; "
                f"skipped {sum(self.skipped.values())}")


def world_from_file(path: str) -> World:
    """The World of a scenario file (the render processes' `make_world`, with functools.partial)."""
    return World(load_scenario(path))


# A render process's messages to the simulator (multiprocessing.connection, pickled tuples):
#   ("ready",)                                   its World is built and its cameras' caches are warm
#   ("frame", r, k, tick_ns, stamp_ns, jpeg, ms, cpu_ms, done_ns)
#                                 RSU r's frame k, rendered RENDER_AHEAD_NS or less before its tick (wall and
#                                 thread CPU ms; done_ns: when the render ended)
#   ("skip", r, k_from, k_to)                    RSU r's ticks k_from..k_to-1 came too late to render: skipped
#   ("error", text)                              it failed (then exits)
# and the simulator's to it: ("start", t0_ns, end_ns | None), then ("stop",). It stops at "stop", at the
# end of its pipe (the simulator is gone) or with the simulator's death (PR_SET_PDEATHSIG).
# One render process for every camera, rendering the earliest tick first: with one process per camera
# they shared the CPU on a busy moment and made every camera late at once (docs/architecture.md).
RENDER_PROCESSES = 1
RENDER_READY_S = 120.0  # how long a render process may take to start (imports, caches) on a busy machine
RENDER_STOP_S = 3.0  # after "stop": how long it may take to finish its frame and exit before it is killed


def _die_with_parent() -> None:
    """Linux: this process gets SIGKILL when its parent dies (a render process is never orphaned)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the end of the pipe still stops it
        pass


def render_process(conn, make_world: Callable[[], World], rsus: list[int], log_level: str,
                   parent_pid: int) -> None:
    """The entry of a render process (multiprocessing, spawn) for the RSUs `rsus` (indices): builds its
    World, warms those cameras, then renders their frames in tick order, each from RENDER_AHEAD_NS before
    its tick on, and hands them to the simulator, which publishes each at its tick; late ticks are
    skipped as the contract says (see the module docstring)."""
    # Stopped by the simulator (a Ctrl-C at the terminal reaches the whole process group, not only it).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    if os.getppid() != parent_pid:  # the simulator died before the line above
        return
    setup_logging(log_level)
    try:
        cv2.setNumThreads(1)
        c0 = time.perf_counter()
        world = make_world()
        world.warm_up(rsus)
        log.info("render process %d (%s): caches built in %.2f s", os.getpid(),
                 ", ".join(world.rsu_ids[r] for r in rsus), time.perf_counter() - c0)
        conn.send(("ready",))
        msg = conn.recv()
        if msg[0] != "start":
            return
        world.start(msg[1])
        _render_frames(world, rsus, conn, msg[2])
        conn.recv()  # after the last tick of the run: until the simulator says stop
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return  # the simulator is gone
    except BaseException as e:  # noqa: BLE001 - the simulator reports it and stops
        log.exception("render process %d failed", os.getpid())
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(e).__name__}: {e}"))


def _render_frames(world: World, rsus: list[int], conn, end_ns: int | None,
                   ahead_bytes: int = RENDER_AHEAD_BYTES) -> None:
    """The frames of RSUs `rsus`, earliest tick first (so that a busy moment makes the fewest frames
    late), each rendered from RENDER_AHEAD_NS before its tick on, while the frames sent and not yet due
    hold less than `ahead_bytes`, and sent on `conn`; returns at "stop" (or the end of the pipe) or once
    every next tick is at or after end_ns."""
    late_limit = {r: int(min(0.5 * NS_PER_S / world.fps[r], MAX_LATE_S * NS_PER_S)) for r in rsus}
    next_k = dict.fromkeys(rsus, 0)
    waiting: deque[tuple[int, int]] = deque()  # (tick, JPEG bytes) of the frames sent, earliest tick first
    waiting_bytes = 0
    while not conn.poll():  # anything from the simulator now is "stop" (or the end of the pipe)
        r = min(rsus, key=lambda i: world.frame_time(i, next_k[i]))
        k = next_k[r]
        t = world.frame_time(r, k)
        if end_ns is not None and t >= end_ns:
            return
        now = time.time_ns()
        while waiting and waiting[0][0] <= now:
            waiting_bytes -= waiting.popleft()[1]
        full = bool(waiting) and waiting_bytes >= ahead_bytes
        start_ns = max(t - RENDER_AHEAD_NS, waiting[0][0] if full else now)  # full: after the next frame goes out
        if start_ns > now:
            conn.poll((start_ns - now) / NS_PER_S)
            continue
        if now - t > late_limit[r]:
            next_k[r] = world.frame_index_from(r, now - late_limit[r] + 1)
            conn.send(("skip", r, k, next_k[r]))
            continue
        c0, cpu0 = time.perf_counter(), time.thread_time()
        jpeg, stamp = world.capture(r, t)
        conn.send(("frame", r, k, t, stamp, jpeg, (time.perf_counter() - c0) * 1e3,
                   (time.thread_time() - cpu0) * 1e3, time.time_ns()))
        waiting.append((t, len(jpeg)))
        waiting_bytes += len(jpeg)
        next_k[r] = k + 1


class RenderProcesses:
    """The simulator's render processes (multiprocessing's spawn context: the simulator's Zenoh session
    and threads are never forked), `count` of them, RSU i rendered by process i % count. They render in
    their own interpreters, so that the publishing thread never waits for a renderer's GIL."""

    def __init__(self, make_world: Callable[[], World], rsu_ids: list[str], count: int = 1):
        self.rsu_ids = list(rsu_ids)
        n = len(self.rsu_ids)
        self.groups = [list(range(i, n, max(1, count))) for i in range(min(max(1, count), n))]
        ctx = mp.get_context("spawn")
        self.conns = []
        self.procs = []
        level = logging.getLevelName(logging.getLogger().getEffectiveLevel())
        try:
            for rsus in self.groups:
                ours, theirs = ctx.Pipe()
                p = ctx.Process(target=render_process, args=(theirs, make_world, rsus, level, os.getpid()),
                                name=f"sim-render-{'-'.join(self.rsu_ids[r] for r in rsus)}", daemon=True)
                p.start()
                theirs.close()  # so that its end of the pipe closes with the process
                self.conns.append(ours)
                self.procs.append(p)
        except BaseException:
            self.close()
            raise

    def describe(self) -> str:
        """'pid 123 (rsu-sw, rsu-se), ...' for the log."""
        return ", ".join(f"pid {p.pid} ({', '.join(self.rsu_ids[r] for r in rsus)})"
                         for p, rsus in zip(self.procs, self.groups, strict=True))

    def wait_ready(self, stop: threading.Event) -> bool:
        """Until every render process is ready (True), or `stop` is set (False). RuntimeError if one
        fails or takes longer than RENDER_READY_S."""
        waiting = set(range(len(self.conns)))
        deadline = time.monotonic() + RENDER_READY_S
        while waiting:
            if stop.is_set():
                return False
            if time.monotonic() > deadline:
                raise RuntimeError(f"render processes not ready after {RENDER_READY_S:.0f} s: "
                                   f"{', '.join(self.procs[i].name for i in sorted(waiting))}")
            for c in mp_connection.wait([self.conns[i] for i in waiting], 0.1):
                i = self.conns.index(c)
                if self._recv(i)[0] == "ready":
                    waiting.discard(i)
        return True

    def begin(self, t0_ns: int, end_ns: int | None) -> None:
        for c in self.conns:
            c.send(("start", t0_ns, end_ns))

    def receive(self, timeout: float) -> list[tuple]:
        """The "frame" and "skip" messages the render processes sent, waiting up to `timeout` s for one.
        RuntimeError if one failed or exited."""
        out = []
        for c in mp_connection.wait(self.conns, timeout):
            i = self.conns.index(c)
            while c.poll():
                out.append(self._recv(i))
        return out

    def _recv(self, i: int) -> tuple:
        try:
            msg = self.conns[i].recv()
        except (EOFError, OSError):
            self.procs[i].join(1.0)
            raise RuntimeError(f"render process {self.procs[i].name} exited "
                               f"(exit code {self.procs[i].exitcode})") from None
        if msg[0] == "error":
            raise RuntimeError(f"render process {self.procs[i].name} failed: {msg[1]}")
        return msg

    def stop(self) -> list[tuple]:
        """Says stop to every render process and returns the frames and skips each sent before it
        exited; a failure here is logged by the process, not raised."""
        for c in self.conns:
            with contextlib.suppress(OSError):
                c.send(("stop",))
        out = []
        deadline = time.monotonic() + RENDER_STOP_S
        for c in self.conns:
            try:
                while c.poll(max(0.0, deadline - time.monotonic())):
                    msg = c.recv()
                    if msg[0] in ("frame", "skip"):
                        out.append(msg)
            except (EOFError, OSError):
                pass  # it has exited
        return out

    def close(self) -> None:
        """Every render process ends here: asked to, then killed if it has not exited in time."""
        for c in self.conns:
            with contextlib.suppress(OSError):
                c.send(("stop",))
        deadline = time.monotonic() + RENDER_STOP_S
        for p in self.procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                log.warning("render process %s (pid %d) did not stop: killed", p.name, p.pid)
                p.kill()
                p.join(5.0)
        for c in self.conns:
            c.close()


def run(world: World, session, stop: threading.Event, duration_s: float | None = None, *,
        make_world: Callable[[], World]) -> FrameStats:
    """The real-time loop (the caller opens/closes the session): starts the render process(es), each
    with its own World from `make_world` (a picklable callable: the same scenario as `world`), starts the
    clock once they are ready, and publishes until `stop` is set or `duration_s` has passed."""
    n = len(world.rsu_ids)
    stats = FrameStats(world.rsu_ids)
    cams = RenderProcesses(make_world, world.rsu_ids, RENDER_PROCESSES)
    pubs: _Publishers | None = None
    sensors: SensorLoop | None = None
    next_k = [0] * n
    try:
        if not cams.wait_ready(stop):
            return stats  # stopped while the cameras started
        pubs = _Publishers(session, world)
        world.start(time.time_ns() + START_LEAD_NS)  # so that the first frames too are rendered ahead
        t0 = world.t0_ns
        end = t0 + int(duration_s * NS_PER_S) if duration_s is not None else None
        cams.begin(t0, end)
        # The clock that stamps each RSU's frames: the simulator's, exact, unless the scenario puts it off.
        clocks = [ClockInfo(source="sim", sync_uncertainty_ns=0) if f.clock_disciplined
                  else ClockInfo(source="system") for f in world.faults]

        def take(msg: tuple) -> None:
            r = msg[1]
            rid = world.rsu_ids[r]
            if msg[0] == "frame":
                _, _, k, tick, stamp, jpeg, ms, cpu_ms, done_ns = msg
                stats.render_ms.append(ms)
                stats.render_cpu_ms.append(cpu_ms)
                stats.handover_ms.append((time.time_ns() - done_ns) / 1e6)
                cam = world.cameras[r]
                # A camera's frame exists from its capture time on: the publishing thread sends it at its tick.
                sensors.post_frame(tick, pubs.frames[rid], Frame(
                    rsu_id=rid, capture_time_ns=stamp, seq=k, encoding="jpeg", width=cam.width,
                    height=cam.height, image=jpeg, clock=clocks[r]))
                next_k[r] = k + 1
            elif msg[0] == "skip":
                _, _, k_from, k_to = msg
                stats.skipped[rid] += k_to - k_from
                next_k[r] = k_to

        sensors = SensorLoop(world, pubs, stop, end)
        sensors.frame_published = stats.sent
        sensors.start()
        log.info("sim running: t0_ns=%d, %d RSUs at %s fps, buses %s, %s%s; render processes: %s", t0, n,
                 "/".join(f"{f:g}" for f in world.fps), ", ".join(world.bus_ids) or "(none)",
                 f"loop every {world.period_ns / NS_PER_S:.1f} s" if world.period_ns else "no loop",
                 f", for {duration_s:g} s" if duration_s is not None else "",
                 cams.describe())
        last_progress, since, sent_since = time.monotonic(), dict(stats.published), 0
        try:
            while not stop.is_set():
                mono = time.monotonic()
                if mono - last_progress >= PROGRESS_S:
                    window = sensors.frame_delays_ns[sent_since:]
                    sent = np.asarray(window or [0]) / 1e6
                    log.info("%s; sent p50 %.1f / p99 %.1f ms after the tick; imu %d truth %d gnss %d "
                             "(imu delay max %.1f ms); on the road: %s",
                             stats.line((time.time_ns() - t0) / NS_PER_S, since, mono - last_progress),
                             np.percentile(sent, 50), np.percentile(sent, 99),
                             sensors.counts["imu"], sensors.counts["truth"], sensors.counts["gnss"],
                             ms_from_ns(sensors.max_delay_ns),
                             ", ".join(world.truth_at(time.time_ns())) or "nobody")
                    sensors.max_delay_ns = 0
                    stats.all_render_ms.extend(stats.render_ms)
                    stats.render_ms = []
                    stats.handover_ms = []
                    last_progress, since = mono, dict(stats.published)
                    sent_since += len(window)
                now = time.time_ns()
                if end is not None and now >= end:
                    break
                wait_s = PROGRESS_S - (time.monotonic() - last_progress)
                if end is not None:
                    wait_s = min(wait_s, (end - now) / NS_PER_S)
                for msg in cams.receive(max(0.0, min(wait_s, 0.5))):
                    take(msg)
        finally:
            stop.set()
            sensors.wake()
            t_stop = time.time_ns() if end is None else min(time.time_ns(), end)
            for msg in cams.stop():  # what they rendered before they saw the stop
                take(msg)
            # Ticks that came due and were neither rendered nor skipped by their camera: skipped, and counted.
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
            cpu = np.asarray(stats.render_cpu_ms or [0])
            log.info("sim stopped after %.1f s: frames %s; skipped %d; render+encode p50 %.1f ms p90 %.1f ms "
                     "(CPU p50 %.1f / p90 %.1f / mean %.1f ms); frames sent p50 %.1f / p99 %.1f ms after their "
                     "tick; imu %d truth %d gnss %d",
                     (t_stop - t0) / NS_PER_S, ", ".join(f"{r} {k}" for r, k in stats.published.items()),
                     sum(stats.skipped.values()), np.percentile(ms, 50), np.percentile(ms, 90),
                     np.percentile(cpu, 50), np.percentile(cpu, 90), cpu.mean(),
                     np.percentile(late, 50), np.percentile(late, 99), sensors.counts["imu"],
                     sensors.counts["truth"], sensors.counts["gnss"])
    finally:
        cams.close()  # never leaves a render process behind, whatever happened
        if pubs is not None:
            pubs.close()
    if sensors is not None and sensors.error is not None:
        raise RuntimeError(f"sensor loop failed: {sensors.error}")
    return stats


class LiveSimulator:
    """`toptag sim run` as a service: the real-time loop on one session until stopped."""

    def __init__(self, world: World, session, make_world: Callable[[], World]):
        self.world, self.session, self.make_world = world, session, make_world
        self._stop = threading.Event()

    def run(self, duration: float | None = None) -> None:
        run(self.world, self.session, self._stop, duration, make_world=self.make_world)

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
        world = world_from_file(str(path))  # checks the scenario and its files; cameras render elsewhere
        log.info("scenario %s: %d RSUs, %d buses, %d trucks; image model: %s", path, len(world.cameras),
                 len(world.buses), len(world.trucks), world.model.describe())
        return world

    make_world = functools.partial(world_from_file, str(path))
    return run_service("sim run", args, load, lambda session, world: LiveSimulator(world, session, make_world),
                       lambda world: f"simulator ({len(world.cameras)} RSUs, {len(world.buses)} buses)")


if __name__ == "__main__":
    sys.exit(main())
