"""`toptag bus`: the bus agent.

Knows the map of intersections. From its position (GNSS when it has one, its fused pose otherwise) it
announces itself (Approach with its code bag, repeated every 0.2 s with where the bus is, a liveliness
token and an answer to session queries) when it enters an intersection's approach radius, and leaves (Leave, token
withdrawn) when it exits. It fuses its IMU/odometry with the RSUs' PoseFixes, each applied at its
capture time, and publishes FusedPose at 50 Hz with covariance and health. Once a second it publishes
its assessment of every RSU it has heard from lately (RsuDiagnosis: the RSU's estimated time offset,
its drift flag and disagreement) on keys.rsu_diagnosis, which the RSUs and the monitor read. Its
Approach carries its host's clock (toptag.hostclock).

One thread does the work: its IMU samples, GNSS fixes and PoseFixes wait in Zenoh's channels (filled
without Python) and each filter cycle takes them in (IMU, then GNSS in arrival order, then fixes) before it
estimates. A cycle is every --filter-every-th output step (default 2: 25 Hz at the 50 Hz output); it publishes
its estimate of now and predicts the outputs of the steps before the next cycle, which publish those
predictions at their instants (a step that wakes late runs a cycle instead). On this VM each wake-up runs its
Python several times slower than back to back (cold caches), so the cost is per kind of work done per wake-up
more than per message: the agent at 0.8x the CPU with cycles at 25 Hz, for fixes taken in up to one output
period later (`toptag bench bus`, docs/real-time.md). A fix reaches the filter once it is about as old as the
recent fixes were when they arrived (a high quantile of their delays, at most --fix-hold-ms:
toptag.fusion.fix_hold), the fixes of a cycle in capture order. A fix's arrival, for the filter's health and
the latency log, is when the cycle took it in (up to one cycle after it reached the process), not when it was
released. The cycle's output holds the same inputs as when a callback thread fed each message to the filter on
arrival; it costs one wake-up per cycle instead of one per message (with a thread hop and a GIL hand-off each:
most of the agent's CPU at 100 Hz IMU and 40 fixes/s, `toptag bench bus`, docs/architecture.md). Its Zenoh runs
on one thread (protocol.transport.ONE_ZENOH_THREAD): no Python waits in Zenoh's threads here, and each message no longer
passes between Zenoh's rx, tx and net threads (context switches 0.4x, docs/real-time.md).
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import math
import threading
import time

import numpy as np

from protocol import keys
from protocol.convert import assessment_to_message, clock_to_message, fix_from_message, fused_pose_payload
from protocol.messages import (
    Approach,
    CoarsePosition,
    FusedPose,
    GnssFix,
    Imu,
    ImuBatch,
    Leave,
    PoseFix,
    RsuDiagnosis,
)
from protocol.transport import (
    ONE_ZENOH_THREAD,
    MessageCounters,
    MessagePublisher,
    declare_alive,
    publish,
    serve_session,
    subscribe_messages,
)
from protocol.transport.runner import ServiceSettings, add_service_arguments, run_service
from toptag.errors import InputError
from toptag.fusion import kernels as filter_kernels
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.fusion.fix_hold import FixHold
from toptag.fusion.presence import IntersectionPresence
from toptag.hostclock import HostClockProbe
from toptag.site import IntersectionSpec, MapFile
from toptag.units import ms_from_ns, ns_from_ms, ns_from_s, s_from_ns
from toptag.vehicle import Vehicle

log = logging.getLogger(__name__)

IMU_GAP_RESET_S = 1.0  # without IMU for this long the state cannot be propagated: start afresh
# The announcement is repeated while in session: one-shot messages can be lost when routes are new, and
# each repeat carries the bus's latest whereabouts, which the RSUs predict to each frame's time to skip
# searching while the bus cannot be in their view (the fresher, the tighter).
ANNOUNCE_PERIOD_S = 0.2
GNSS_MAX_AGE_S = 5.0  # an older GNSS fix says nothing useful of where the bus is
ANNOUNCED_MAX_SIGMA_M = 10.0  # a fused pose less certain than this is not announced (GNSS, if any, is)
# The announced sigma is never below this plus a share of the distance driven since the last fix: the
# filter's own is a few cm and, dead reckoning for seconds, it was off by up to 3.7 of its sigmas in
# `toptag bench rsu --scenario` (0.14 m at most); an RSU trusts the announcement to skip or crop.
ANNOUNCED_SIGMA_FLOOR_M = 0.05
ANNOUNCED_SIGMA_PER_M = 0.005
DIAGNOSIS_PERIOD_S = 1.0
DIAGNOSIS_KEEP_S = 30.0  # an RSU not heard from for this long is no longer assessed on the wire
# What the channels hold between two steps (the oldest dropped beyond, rather than stall Zenoh's thread):
# 10 s of IMU at 100 Hz (one or four samples to a message), and of fixes from 4 RSUs at 10 Hz and more; a step
# that late meets an IMU gap anyway.
# A step that finds one full counts it (counters "full", "dropped" by the IMU's seq) and logs it.
IMU_QUEUE = 1024
IMU_BATCH_QUEUE = 256  # batches of 4 and more
FIX_QUEUE = 512
GNSS_QUEUE = 16
STOP_POLL_S = 0.1  # the step loop sleeps at most this long at a time, so that stop() is seen
# The longest a fix waits in the agent before the filter takes it; the hold follows the delays seen, up to this
# (toptag.fusion.fix_hold: fewer re-applications of fixes for a little freshness). 0: no hold.
FIX_HOLD_MS = 150.0
# A filter cycle at every FILTER_EVERY-th output step; the steps between publish the cycle's predictions.
FILTER_EVERY = 2


class BusSettings(ServiceSettings):
    """`toptag bus --config FILE`: [zenoh] and [filter] (toptag.fusion.filter.FilterConfig)."""

    filter: FilterConfig = FilterConfig()


class BusAgent:
    def __init__(self, session, vehicle: Vehicle, map_file: MapFile, fused_hz: float = 50.0,
                 filter_config: FilterConfig | None = None, fix_hold_ms: float = FIX_HOLD_MS,
                 filter_every: int = FILTER_EVERY):
        self.session = session
        self.vehicle = vehicle
        self.bus_id = vehicle.id
        self.fused_period = 1.0 / fused_hz
        self._period_ns = ns_from_s(self.fused_period)
        self.filter_every = filter_every
        # The outputs a cycle predicted for the steps before the next one: (instant, FusedPose payload), oldest
        # first. A step publishes the first when it wakes within half a period of its instant.
        self._predicted: collections.deque[tuple[int, bytes]] = collections.deque()
        self.cycles = 0
        self.fix_hold = FixHold(ns_from_ms(fix_hold_ms))  # the fixes taken in, until the filter takes them
        self.filter_config = filter_config or FilterConfig()
        self.presence = IntersectionPresence(map_file)
        self.counters = MessageCounters()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        # The filter's compiled steps loaded from numba's cache now (tenths of a second of CPU), not at the
        # first fix (toptag/solvers/warmup.py fills the cache).
        filter_kernels.warm_up()
        self.filter = BusFilter(self.filter_config)
        self.filter_resets = 0
        self._past_paths: dict[str, int] = {}  # fix counts by path of the filters before this one
        self._last_imu_ns: int | None = None
        self._gnss: GnssFix | None = None
        self._wheel_speed: float | None = None
        self.fixes_received = 0
        # Session state (one intersection at a time).
        self._approach: Approach | None = None
        self._token = None
        self._queryable = None
        self._fix_sub = None
        self._last_announce = 0.0
        self._position: CoarsePosition | None = None
        self.clock = HostClockProbe().start()
        self._rsu_intersection: dict[str, str] = {}  # RSU -> the intersection its fixes came from
        self._diag_pubs: dict[str, MessagePublisher] = {}
        self._last_diagnosis = 0.0
        self._flagged: set[str] = set()
        self._fused_pub = MessagePublisher(session, keys.fused_pose(self.bus_id), FusedPose)
        # Its IMU samples one to a message (Imu) or several (ImuBatch, as the simulator sends them).
        self._imu_sub = subscribe_messages(session, keys.imu(self.bus_id), Imu, None, self.counters, log,
                                           capacity=IMU_QUEUE, drop_oldest=True)
        self._imu_batch_sub = subscribe_messages(session, keys.imu_batch(self.bus_id), ImuBatch, None, self.counters,
                                                 log, capacity=IMU_BATCH_QUEUE, drop_oldest=True)
        self._gnss_sub = subscribe_messages(session, keys.gnss(self.bus_id), GnssFix, None, self.counters, log,
                                            capacity=GNSS_QUEUE, drop_oldest=True)
        self._subs = [self._imu_sub, self._imu_batch_sub, self._gnss_sub]

    # ---- inputs (taken in by the step) -------------------------------------------------------------
    def take_inputs(self) -> None:
        """Everything received since the last call, fed to the filter: IMU, GNSS, then the fixes old enough
        (self.fix_hold); the others wait for a later call."""
        self._imu_sub.deliver(self._on_imu)
        self._imu_batch_sub.deliver(self._on_imu_batch)
        self._gnss_sub.deliver(self._on_gnss)
        now = time.time_ns()
        if self._fix_sub is not None:
            self._fix_sub.deliver(lambda m: self._on_fix(m, now))
        if self.fix_hold.held:
            self._release_fixes(now)

    def _on_imu(self, m: Imu) -> None:
        with self._lock:
            if self._last_imu_ns is not None and s_from_ns(m.t_ns - self._last_imu_ns) > IMU_GAP_RESET_S:
                # The vehicle was off (or the stream broke): nothing in the buffer describes it any more;
                # what it learnt of the RSUs (time offsets, drift flags) still holds.
                if self.filter.initialized:  # its fix counts go on in the next filter's health
                    old = self.filter.estimate().health.paths()
                    self._past_paths = {k: v + self._past_paths.get(k, 0) for k, v in old.items()}
                self.filter = BusFilter(self.filter_config, memory=self.filter.memory())
                self.filter_resets += 1
                log.info("IMU gap of %.1f s: filter restarted", s_from_ns(m.t_ns - self._last_imu_ns))
            self._last_imu_ns = m.t_ns
            self._wheel_speed = m.wheel_speed
            self.filter.add_imu(m.t_ns, m.gyro_z, m.accel_x, m.accel_y, m.wheel_speed)

    def _on_imu_batch(self, m: ImuBatch) -> None:
        for sample in m.samples:
            self._on_imu(sample)

    def _on_gnss(self, m: GnssFix) -> None:
        with self._lock:
            self._gnss = m

    def _on_fix(self, m: PoseFix, now: int) -> None:
        if m.bus_id != self.bus_id:
            return
        fix = fix_from_message(m, arrival_ns=now)
        with self._lock:
            self.fixes_received += 1
            self._rsu_intersection[m.rsu_id] = m.intersection_id
        self.fix_hold.add(fix, now)

    def _release_fixes(self, now: int) -> None:
        """The held fixes due at now to the filter (toptag.fusion.fix_hold), decided together when the filter is
        next asked (the step's estimate): an instant's fixes from several RSUs land in one step, which the filter
        would re-run for each (1218 applications for 1507 on `toptag bench bus`'s drive, the same estimates)."""
        due = self.fix_hold.due(now)
        if due:
            with self._lock:
                for f in due:
                    self.filter.add_fix(f, decide=False)

    # ---- position and sessions ------------------------------------------------------------------
    def position(self, now_ns: int) -> CoarsePosition | None:
        """Fused pose when the filter is healthy, else the latest GNSS fix (metres are enough here)."""
        with self._lock:
            est = self.filter.estimate(now_ns) if self.filter.initialized else None
            gnss = self._gnss
        return coarse_position(est, gnss, now_ns)

    def whereabouts(self, now_ns: int) -> CoarsePosition | None:
        """What the Approach tells the RSUs of where the bus is (announced_position)."""
        with self._lock:
            est = self.filter.estimate(now_ns) if self.filter.initialized else None
            gnss, speed = self._gnss, self._wheel_speed
        return announced_position(est, gnss, speed, now_ns)

    def _enter(self, inter: IntersectionSpec) -> None:
        self._approach = Approach(bus_id=self.bus_id, intersection_id=inter.id, vehicle=self.vehicle.spec,
                                  reference_time_ns=time.time_ns(), clock=clock_to_message(self.clock.current()),
                                  seq=0)
        self._fix_sub = subscribe_messages(self.session, keys.pose_fix(inter.id, self.bus_id, keys.ANY), PoseFix,
                                           None, self.counters, log, capacity=FIX_QUEUE, drop_oldest=True)
        # Queryable and token before the announcement: an RSU that hears the Approach late, or starts
        # later, finds both.
        self._queryable = serve_session(self.session, lambda: self._approach, logger=log)
        self._token = declare_alive(self.session, inter.id, self.bus_id)
        self._position = self.whereabouts(time.time_ns())
        self._announce()
        log.info("entered intersection %s: announced with tags %s", inter.id, self.vehicle.tag_ids)

    def _announce(self) -> None:
        a = self._approach
        self._approach = a.model_copy(update={"reference_time_ns": time.time_ns(), "seq": a.seq + 1,
                                              "position": self._position})
        publish(self.session, keys.approach(a.intersection_id, self.bus_id), self._approach)
        self._last_announce = time.monotonic()

    def _leave(self, reason: str) -> None:
        a = self._approach
        if a is None:
            return
        publish(self.session, keys.leave(a.intersection_id, self.bus_id),
                Leave(bus_id=self.bus_id, intersection_id=a.intersection_id, reference_time_ns=time.time_ns(),
                      reason=reason))
        for handle in (self._token, self._queryable, self._fix_sub):
            try:
                (handle.close if hasattr(handle, "close") else handle.undeclare)()
            except Exception:
                pass
        self._token = self._queryable = self._fix_sub = self._approach = None
        log.info("left intersection %s (%s)", a.intersection_id, reason)

    def step(self, now_ns: int) -> None:
        """The output of one period: the prediction a filter cycle made for now_ns if there is one (within half
        a period), else a filter cycle (self.cycle)."""
        predicted = self._predicted
        if predicted:
            t_ns, payload = predicted.popleft()
            if abs(now_ns - t_ns) * 2 <= self._period_ns:
                self._fused_pub.put_encoded(payload)
                return
            predicted.clear()  # late (a starved machine) or the clock stepped: the filter estimates now instead
        self.cycle(now_ns)

    def cycle(self, now_ns: int) -> None:
        """The inputs taken in, presence, repeated announcements and the fused output, and the predicted
        outputs of the filter_every - 1 steps after it. One filter estimate at now_ns serves the first three
        (position, whereabouts and the fused pose are of the same instant)."""
        self.cycles += 1
        self.take_inputs()
        with self._lock:
            est = self.filter.estimate(now_ns) if self.filter.initialized else None
            gnss, speed = self._gnss, self._wheel_speed
            past_paths = self._past_paths
        xy = presence_xy(est, gnss, now_ns)
        if xy is not None:
            for event, inter in self.presence.update(*xy):
                if event == "leave":
                    self._leave("left the approach radius")
                else:
                    self._enter(inter)
        if self._approach is not None and time.monotonic() - self._last_announce >= ANNOUNCE_PERIOD_S:
            self._position = announced_position(est, gnss, speed, now_ns)
            self._announce()
        if est is not None:
            self._fused_pub.put_encoded(self._fused_payload(est, past_paths))
            for k in range(1, self.filter_every):
                t_ns = now_ns + k * self._period_ns
                with self._lock:
                    ahead = self.filter.estimate(t_ns)
                self._predicted.append((t_ns, self._fused_payload(ahead, past_paths)))
        if time.monotonic() - self._last_diagnosis >= DIAGNOSIS_PERIOD_S:
            self._last_diagnosis = time.monotonic()
            self.publish_diagnoses(now_ns)

    def _fused_payload(self, est, past_paths: dict[str, int]) -> bytes:
        """The FusedPose of an estimate; its health counts every fix since the agent started, across filters."""
        if past_paths:
            est = dataclasses.replace(est, health=est.health.plus_paths(past_paths))
        return fused_pose_payload(est, self.bus_id)

    def publish_diagnoses(self, now_ns: int) -> list[RsuDiagnosis]:
        """The bus's RsuDiagnosis of every RSU heard from in the last DIAGNOSIS_KEEP_S, published."""
        with self._lock:
            assessed = self.filter.rsu_assessments()
            where = dict(self._rsu_intersection)
        out = []
        for rsu, a in assessed.items():
            if rsu not in where or s_from_ns(now_ns - a.last_fix_ns) > DIAGNOSIS_KEEP_S:
                continue
            msg = assessment_to_message(a, self.bus_id, where[rsu], now_ns)
            key = keys.key_of(msg)
            pub = self._diag_pubs.get(key)
            if pub is None:
                pub = self._diag_pubs[key] = MessagePublisher(self.session, key, RsuDiagnosis)
            pub.put(msg)
            out.append(msg)
            if a.flagged and rsu not in self._flagged:
                log.warning("RSU %s flagged for drift: %s", rsu, a.advice)
            elif not a.flagged and rsu in self._flagged:
                log.info("RSU %s no longer flagged for drift (disagreement %.1f cm)", rsu, 100 * a.disagreement_m)
            (self._flagged.add if a.flagged else self._flagged.discard)(rsu)
        return out

    def run(self, duration: float | None = None) -> None:
        t_end = None if duration is None else time.monotonic() + duration
        next_t = time.monotonic()
        while not self._stop.is_set() and (t_end is None or time.monotonic() < t_end):
            try:
                self.step(time.time_ns())
            except Exception as e:  # keep the agent alive; the next step retries
                log.exception("bus step failed: %s", e)
            next_t += self.fused_period
            # time.sleep, not self._stop.wait: a timed Event.wait runs Python's Condition code (a lock made,
            # taken, released) around each of the 50 wake-ups a second, cold every time; stop() is seen within
            # a period (or STOP_POLL_S).
            while (left := next_t - time.monotonic()) > 0 and not self._stop.is_set():
                time.sleep(min(left, STOP_POLL_S))

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._leave("agent stopped")
        log.info("bus %s: %d fixes received, capture-to-arrival latency %s, held %.0f ms at the end, filter %s",
                 self.bus_id, self.fixes_received, {k: round(v, 1) for k, v in self.latency_ms().items()},
                 ms_from_ns(self.fix_hold.hold_ns), self.filter.counters())
        for s in self._subs:
            s.close()
        self._fused_pub.close()
        for p in self._diag_pubs.values():
            p.close()
        self.clock.close()

    def latency_ms(self) -> dict:
        """Capture to arrival of the latest fixes (fix_hold's window: a running agent keeps no more)."""
        lat = ms_from_ns(np.asarray(self.fix_hold.delays_ns, dtype=float))
        if lat.size == 0:
            return {}
        return {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99))}


def coarse_position(est, gnss: GnssFix | None, now_ns: int) -> CoarsePosition | None:
    """Where presence takes the bus to be: its filter's estimate at now_ns when healthy, else the latest
    GNSS fix (metres are enough here)."""
    if _presence_takes_fused(est):
        sigma = float(np.sqrt(max(est.cov[0, 0], est.cov[1, 1], 1e-6)))
        return CoarsePosition(t_ns=now_ns, x=est.x, y=est.y, sigma_m=sigma, source="fused")
    return gnss_position(gnss, now_ns)


def presence_xy(est, gnss: GnssFix | None, now_ns: int) -> tuple[float, float] | None:
    """coarse_position's x, y, without the message: the step's presence needs no more, 50 times a second."""
    if _presence_takes_fused(est):
        return est.x, est.y
    return None if _gnss_too_old(gnss, now_ns) else (gnss.x, gnss.y)


def _presence_takes_fused(est) -> bool:
    """Presence takes the filter's pose only while it is healthy ("ok"), else the latest GNSS fix."""
    return est is not None and est.health.status == "ok"


def announced_position(est, gnss: GnssFix | None, wheel_speed: float | None, now_ns: int) -> CoarsePosition | None:
    """Where the bus tells the RSUs it is. Its filter's pose once a fix has started it (kept by IMU and
    odometry between fixes, its covariance growing honestly), with its velocity and that velocity's
    sigma; else its latest GNSS fix with its odometry's speed; else nothing. (Presence uses
    BusAgent.position: what "in session" means does not change.)"""
    if est is not None and est.health.status != "acquiring" and est.health.pos_sigma_m <= ANNOUNCED_MAX_SIGMA_M:
        c, s = math.cos(est.yaw), math.sin(est.yaw)
        P = est.state_cov  # STATE_NAMES: x, y, yaw, speed, ...
        v_sigma = math.sqrt(max(P[3, 3], 0.0) + est.speed ** 2 * max(P[2, 2], 0.0))
        since = est.health.since_last_fix_s
        floor = ANNOUNCED_SIGMA_FLOOR_M + ANNOUNCED_SIGMA_PER_M * abs(est.speed) * (since if math.isfinite(since) else 0.0)
        return CoarsePosition(t_ns=est.t_ns, x=est.x, y=est.y, sigma_m=math.hypot(est.health.pos_sigma_m, floor),
                              source="fused", vx=est.speed * c, vy=est.speed * s, velocity_sigma_mps=v_sigma,
                              yaw=est.yaw, yaw_sigma_rad=math.sqrt(max(P[2, 2], 0.0)))
    speed = None if wheel_speed is None or not math.isfinite(wheel_speed) else abs(wheel_speed)
    return gnss_position(gnss, now_ns, speed)


def gnss_position(gnss: GnssFix | None, now_ns: int, speed_mps: float | None = None) -> CoarsePosition | None:
    """The latest GNSS fix as a coarse position (None when there is none or it is too old to say
    where the bus is)."""
    if _gnss_too_old(gnss, now_ns):
        return None
    return CoarsePosition(t_ns=gnss.t_ns, x=gnss.x, y=gnss.y, sigma_m=gnss.sigma_m, source="gnss",
                          speed_mps=speed_mps)


def _gnss_too_old(gnss: GnssFix | None, now_ns: int) -> bool:
    """No GNSS fix, or one too old to say where the bus is."""
    return gnss is None or s_from_ns(now_ns - gnss.t_ns) >= GNSS_MAX_AGE_S


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag bus", description=__doc__.split("\n\n")[0])
    p.add_argument("--vehicle", required=True, help="this bus's vehicle file (its code bag)")
    p.add_argument("--map", required=True, help="map file of intersections")
    p.add_argument("--fused-hz", type=float, default=50.0)
    p.add_argument("--filter-every", type=int, default=FILTER_EVERY, metavar="N",
                   help=f"a filter cycle (inputs taken in, fixes decided) at every N-th output; the outputs between "
                        f"are the cycle's predictions for their instants (default {FILTER_EVERY}; 1: a cycle at "
                        f"every output)")
    p.add_argument("--fix-hold-ms", type=float, default=FIX_HOLD_MS,
                   help=f"the longest a PoseFix waits before the filter takes it; the wait follows the fixes' "
                        f"recent delays up to this: fewer re-applications for a little freshness (default "
                        f"{FIX_HOLD_MS:g}; 0: none)")
    add_service_arguments(p)
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)

    def load() -> tuple[Vehicle, MapFile]:
        if not (args.fix_hold_ms >= 0 and math.isfinite(args.fix_hold_ms)):
            raise InputError(f"--fix-hold-ms must be a finite number >= 0, got {args.fix_hold_ms}")
        if args.filter_every < 1:
            raise InputError(f"--filter-every must be a whole number >= 1, got {args.filter_every}")
        vehicle = Vehicle.load(args.vehicle)
        keys.imu(vehicle.id)  # the vehicle id must be usable as a bus id on the wire
        return vehicle, MapFile.load(args.map)

    return run_service("bus", args, load,
                       lambda session, inputs: BusAgent(session, *inputs, fused_hz=args.fused_hz,
                                                        filter_config=args.settings.filter,
                                                        fix_hold_ms=args.fix_hold_ms,
                                                        filter_every=args.filter_every),
                       lambda inputs: f"bus {inputs[0].id} ({len(inputs[1].intersections)} intersections known)",
                       settings=BusSettings, zenoh_runtime=ONE_ZENOH_THREAD)
