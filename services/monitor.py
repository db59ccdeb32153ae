"""`toptag monitor`: watches a running intersection and tells how well it localizes its buses.

Listens to RSU heartbeats, every PoseFix, the simulator's ground truth and each bus's FusedPose, and
compares them: fix error at the fix's capture time, fused error at the fused pose's time, and the
capture-to-arrival latency of fixes. Reads the buses' RsuDiagnosis too: each RSU's time offset as
each bus estimates it, and drift flags. Prints a live table; `--report FILE` writes the summary as JSON.
"""
from __future__ import annotations

import argparse
import bisect
import json
import logging
import math
import threading
import time
from collections import defaultdict, deque
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from protocol import keys
from protocol.messages import (Approach, FusedPose, FusionHealth, GroundTruth, Leave, PoseFix, RsuDiagnosis,
                               RsuStatus, TagDetections)
from protocol.transport import MessageCounters, subscribe_messages
from protocol.transport.runner import add_service_arguments, run_service
from toptag.units import ms_from_ns, ns_from_s, s_from_ns

if TYPE_CHECKING:
    from sim.scenario import Scenario

log = logging.getLogger(__name__)
TRUTH_KEEP_S = 30.0


class TruthTrack:
    """Recent ground truth of one bus, interpolated at any time it covers."""

    def __init__(self):
        self.t: list[int] = []
        self.xyyaw: list[tuple[float, float, float]] = []
        self.z: float | None = None  # the roof's height, as last heard (it changes by a bounce only)

    def add(self, m: GroundTruth) -> None:
        if self.t and m.t_ns <= self.t[-1]:
            return
        self.t.append(m.t_ns)
        self.xyyaw.append((m.x, m.y, m.yaw))
        self.z = m.z
        if s_from_ns(self.t[-1] - self.t[0]) > 2 * TRUTH_KEEP_S:
            cut = bisect.bisect_left(self.t, self.t[-1] - ns_from_s(TRUTH_KEEP_S))
            del self.t[:cut], self.xyyaw[:cut]

    def at(self, t_ns: int) -> tuple[float, float, float] | None:
        i = bisect.bisect_left(self.t, t_ns)
        if i == 0 or i == len(self.t):
            return self.xyyaw[0] if self.t and self.t[0] == t_ns else None
        t0, t1 = self.t[i - 1], self.t[i]
        if s_from_ns(t1 - t0) > 0.5:  # the bus was away: no truth in between
            return None
        w = (t_ns - t0) / (t1 - t0)
        (x0, y0, a0), (x1, y1, a1) = self.xyyaw[i - 1], self.xyyaw[i]
        da = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        return x0 + w * (x1 - x0), y0 + w * (y1 - y0), a0 + w * da


class ErrorStats:
    """Running RMS / max of errors, and the recent values for percentiles (bounded memory)."""

    def __init__(self, keep: int = 20000):
        self.n, self.sumsq, self.max, self.last = 0, 0.0, None, None
        self.recent: deque = deque(maxlen=keep)

    def add(self, v: float) -> None:
        self.n += 1
        self.sumsq += v * v
        self.max = v if self.max is None else max(self.max, v)
        self.last = v
        self.recent.append(v)

    @property
    def rms(self) -> float | None:
        return float(np.sqrt(self.sumsq / self.n)) if self.n else None

    def pct(self, q: float) -> float | None:
        return float(np.percentile(self.recent, q)) if self.recent else None


def frame_kind(modes: dict[str, str]) -> str:
    """What an RSU did with a frame, from its buses' pipeline modes: "acquisition" when it searched for
    a bus it has not found, else "tracking" when it cropped around a bus, else "nothing to do"."""
    kinds = set(modes.values())
    if kinds & {"acquired", "searching"}:
        return "acquisition"
    if kinds & {"tracked", "hinted"}:
        return "tracking"
    return "nothing to do"


# What a fused "ok" pose claims: its error within 3 sigma (+ HOLD_SLACK_M for the truth's interpolation), and
# cm-level accuracy when its sigma is at most CONFIDENT_SIGMA_M. A pose is "ok" up to the filter's
# degraded_pos_sigma (0.5 m): on a machine too busy to send many fixes, "ok" poses may be 10+ cm off and
# honest about it, which the RMS of all "ok" poses alone would not tell from a wrong filter.
CONFIDENT_SIGMA_M = 0.05
HOLD_SLACK_M = 0.01


class BusScore:
    def __init__(self):
        self.fix_err, self.fused_err, self.latency_ms = ErrorStats(), ErrorStats(), ErrorStats()
        self.fused_confident_err = ErrorStats()  # "ok" poses whose sigma is at most CONFIDENT_SIGMA_M
        self.fused_held = 0  # "ok" poses within 3 sigma (+ HOLD_SLACK_M) of the truth
        # Where the latency goes: capture -> fix sent at the RSU (frame transport, decoding, waiting,
        # processing), of which processing, and fix sent -> arrival here.
        self.rsu_ms, self.processing_ms, self.fix_transit_ms = ErrorStats(), ErrorStats(), ErrorStats()
        self.fixes = 0
        self.fixes_by_rsu: dict[str, int] = defaultdict(int)
        self.fused = 0
        self.fused_status: str | None = None
        self.health: FusionHealth | None = None
        # Between the bus's Approach and its Leave (as heard here): fused samples, and how many said ok.
        self.in_session = False
        self.session_fused = 0
        self.session_fused_ok = 0
        # ... of which, with the truth at their time, two of the bus's tags decodable in some camera's image (only
        # with a ViewCoverage: the simulator's cameras), and how many of those said ok.
        self.session_in_view = 0
        self.session_in_view_ok = 0
        self.pending_fixes: list[tuple[int, float, float]] = []  # awaiting truth at their time
        self.pending_fused: list[tuple[int, float, float, str | None, float, bool]] = []


class ViewCoverage:
    """Whether a bus, at its true pose, has two of its tags decodable in some camera's image (sim.sampling.in_some_view,
    the scenario's cameras): the condition under which an RSU can fix it at all, and so where "fused ok"
    measures the system rather than where its cameras are."""

    def __init__(self, scenario: "Scenario"):
        from sim.world import World

        world = World(scenario)
        self.cameras = world.cameras
        self.vehicles = {b.id: b.vehicle for b in world.buses}
        # The first placement loads its modules and compiled kernels (~130 ms): here, at start-up, rather than
        # in the first summary, under the monitor's lock, while fixes wait for it (they arrived 60-90 ms late).
        for bus_id in self.vehicles:
            self(bus_id, [(0.0, 0.0, 0.0, np.nan)])

    def __call__(self, bus_id: str, poses) -> np.ndarray | None:
        """poses (N, 4): x, y, yaw, roof z (None or NaN: the vehicle's height); (N,) bools, or None for a bus
        the scenario does not have. All at once: a summary places seconds of fused poses (a pose at a time,
        ~0.3 ms of Python each, the monitor's callbacks waited 0.3-0.5 s for the lock it held meanwhile)."""
        from sim.sampling import in_some_view_many

        vehicle = self.vehicles.get(bus_id)
        if vehicle is None:
            return None
        poses = np.array(poses, dtype=float).reshape(-1, 4)
        poses[np.isnan(poses[:, 3]), 3] = vehicle.height
        return in_some_view_many(self.cameras, vehicle, poses)


class Monitor:
    def __init__(self, session, in_view: Callable[[str, np.ndarray], np.ndarray | None] | None = None):
        """in_view: (bus, poses (N, 4) of x, y, yaw, roof z) -> can a camera see the bus at each (a
        ViewCoverage); with it the summary also tells how often the fused status was ok while in session and
        in view."""
        self.in_view = in_view
        self.started = time.monotonic()
        self.first_message: float | None = None  # monotonic time of the first message about a bus
        self.counters = MessageCounters()
        self._lock = threading.Lock()
        self.status: dict[str, RsuStatus] = {}
        self.detect_ms: dict[str, list] = {}  # rsu -> [sum of ms, frames, max ms] over the run
        self.truth: dict[str, TruthTrack] = defaultdict(TruthTrack)
        self.buses: dict[str, BusScore] = defaultdict(BusScore)
        self.diagnoses: dict[tuple[str, str], RsuDiagnosis] = {}  # (rsu, bus) -> latest
        self.flags: dict[tuple[str, str], int] = {}  # (rsu, bus) -> flagged since (ns), as first reported
        self.all_latency_ms = ErrorStats()  # every bus's fixes together
        # Where each fix's latency went, by what its RSU did for that bus in that frame (tracked, hinted,
        # acquired: TagDetections.modes): (rsu, frame seq, bus, ms from capture to arrival, to the start
        # of the RSU's processing, processing, transit), joined with the frames' modes in summary().
        self._fix_parts: deque = deque(maxlen=20000)
        self._modes: dict[tuple[str, int], dict[str, str]] = {}
        # rsu -> frame kind -> [frames, processing ms]: where an RSU's time goes (frame_kind)
        self.work: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(lambda: [0, 0.0]))
        self._subs = [
            subscribe_messages(session, keys.approach(keys.ANY, keys.ANY), Approach, self._on_approach,
                               self.counters, log),
            subscribe_messages(session, keys.leave(keys.ANY, keys.ANY), Leave, self._on_leave, self.counters, log),
            subscribe_messages(session, keys.detections(keys.ANY), TagDetections, self._on_detections, self.counters,
                               log),
            subscribe_messages(session, keys.rsu_status(keys.ANY), RsuStatus, self._on_status, self.counters, log),
            subscribe_messages(session, keys.pose_fix(keys.ANY, keys.ANY, keys.ANY), PoseFix, self._on_fix,
                               self.counters, log),
            subscribe_messages(session, keys.ground_truth(keys.ANY), GroundTruth, self._on_truth, self.counters, log),
            subscribe_messages(session, keys.fused_pose(keys.ANY), FusedPose, self._on_fused, self.counters, log),
            subscribe_messages(session, keys.rsu_diagnosis(keys.ANY, keys.ANY, keys.ANY), RsuDiagnosis,
                               self._on_diagnosis, self.counters, log),
        ]

    def _on_status(self, m: RsuStatus) -> None:
        with self._lock:
            prev = self.status.get(m.rsu_id)
            # Heartbeats carry the mean and max of the last interval: accumulate them over the run.
            n = m.frames_processed - (prev.frames_processed if prev and prev.started_ns == m.started_ns else 0)
            if m.detection_ns_mean is not None and n > 0:
                acc = self.detect_ms.setdefault(m.rsu_id, [0.0, 0, 0.0])
                acc[0] += ms_from_ns(m.detection_ns_mean) * n
                acc[1] += n
                acc[2] = max(acc[2], ms_from_ns(m.detection_ns_max or 0))
            self.status[m.rsu_id] = m

    def _on_diagnosis(self, m: RsuDiagnosis) -> None:
        with self._lock:
            self.diagnoses[(m.rsu_id, m.bus_id)] = m
            if m.drift_flagged and m.flagged_since_ns is not None:
                self.flags.setdefault((m.rsu_id, m.bus_id), m.flagged_since_ns)

    def _on_approach(self, m: Approach) -> None:
        with self._lock:
            self.buses[m.bus_id].in_session = True

    def _on_leave(self, m: Leave) -> None:
        with self._lock:
            self.buses[m.bus_id].in_session = False

    def _on_detections(self, m: TagDetections) -> None:
        if m.processing_ns is None:
            return
        with self._lock:
            acc = self.work[m.rsu_id][frame_kind(m.modes)]
            acc[0] += 1
            acc[1] += ms_from_ns(m.processing_ns)
            self._modes[(m.rsu_id, m.frame_seq)] = m.modes
            if len(self._modes) > 20000:
                del self._modes[next(iter(self._modes))]

    def _on_truth(self, m: GroundTruth) -> None:
        with self._lock:
            self._heard()
            self.truth[m.bus_id].add(m)

    def _on_fix(self, m: PoseFix) -> None:
        arrival = time.time_ns()
        with self._lock:
            self._heard()
            b = self.buses[m.bus_id]
            b.fixes += 1
            b.fixes_by_rsu[m.rsu_id] += 1
            latency_ms = ms_from_ns(arrival - m.capture_time_ns)
            b.latency_ms.add(latency_ms)
            self.all_latency_ms.add(latency_ms)
            b.rsu_ms.add(ms_from_ns(m.publish_time_ns - m.capture_time_ns))
            b.fix_transit_ms.add(ms_from_ns(arrival - m.publish_time_ns))
            if m.processing_ns is not None:
                b.processing_ms.add(ms_from_ns(m.processing_ns))
                self._fix_parts.append((m.rsu_id, m.frame_seq, m.bus_id, latency_ms,
                                        ms_from_ns(m.publish_time_ns - m.capture_time_ns - m.processing_ns),
                                        ms_from_ns(m.processing_ns), ms_from_ns(arrival - m.publish_time_ns)))
            b.pending_fixes.append((m.capture_time_ns, m.x, m.y))

    def _on_fused(self, m: FusedPose) -> None:
        with self._lock:
            self._heard()
            b = self.buses[m.bus_id]
            b.fused += 1
            b.fused_status = m.health.status
            b.health = m.health
            if b.in_session:
                b.session_fused += 1
                b.session_fused_ok += m.health.status == "ok"
            sigma = math.sqrt(max(m.covariance[0][0], m.covariance[1][1], 0.0))
            b.pending_fused.append((m.t_ns, m.x, m.y, m.health.status, sigma, b.in_session))

    def _heard(self) -> None:
        if self.first_message is None:
            self.first_message = time.monotonic()

    def _score(self) -> None:
        """Score the fixes and fused poses whose time the truth now covers; drop those it never will."""
        for bus, b in self.buses.items():
            track = self.truth.get(bus)
            if track is None or not track.t:
                continue
            newest = track.t[-1]
            keep_f = []
            for t, x, y in b.pending_fixes:
                truth = track.at(t)
                if truth is not None:
                    b.fix_err.add(float(np.hypot(x - truth[0], y - truth[1])))
                elif t > newest:
                    keep_f.append((t, x, y))
            b.pending_fixes = keep_f
            keep_u, viewed = [], []  # viewed: the poses in session, placed in the cameras' views together
            for t, x, y, status, sigma, in_session in b.pending_fused:
                truth = track.at(t)
                if truth is not None:
                    if in_session:
                        viewed.append(((*truth, np.nan if track.z is None else track.z), status))
                    if status == "ok":  # a degraded pose says so itself; score what claims to be good
                        err = float(np.hypot(x - truth[0], y - truth[1]))
                        b.fused_err.add(err)
                        b.fused_held += err <= 3 * sigma + HOLD_SLACK_M
                        if sigma <= CONFIDENT_SIGMA_M:
                            b.fused_confident_err.add(err)
                elif t > newest:
                    keep_u.append((t, x, y, status, sigma, in_session))
            b.pending_fused = keep_u
            seen = self.in_view(bus, [p for p, _ in viewed]) if viewed and self.in_view is not None else None
            if seen is not None:
                b.session_in_view += int(np.sum(seen))
                b.session_in_view_ok += sum(status == "ok" for (_, status), s in zip(viewed, seen) if s)

    # ---- outputs --------------------------------------------------------------------------------
    def summary(self) -> dict:
        with self._lock:
            self._score()
            rsus = {rid: {"frames": s.frames_received, "frames_processed": s.frames_processed,
                          "frames_idle": s.frames_idle, "frames_skipped_busy": s.frames_skipped,
                          "frames_missing": s.frames_missing,
                          "frames_detected": s.frames_with_fix, "fixes_published": s.fixes_published,
                          "seconds_active": round(s.active_s, 1), "active_buses": s.active_buses,
                          "detect_ms_mean": (self.detect_ms[rid][0] / self.detect_ms[rid][1]
                                             if self.detect_ms.get(rid, [0, 0])[1] else None),
                          "detect_ms_max": self.detect_ms[rid][2] if rid in self.detect_ms else None,
                          "detect_ms_last_s": None if s.detection_ns_mean is None else ms_from_ns(s.detection_ns_mean),
                          "messages_rejected": s.messages_rejected,
                          "clock": s.clock.model_dump(), "drift_flagged_in_status": s.drift_flagged,
                          "processing_ms_by_kind": {k: {"frames": n, "mean_ms": round(ms / n, 2)}
                                                    for k, (n, ms) in sorted(self.work.get(rid, {}).items())},
                          "source": s.source, "source_connected": s.source_connected, "source_fps": s.source_fps,
                          "source_reconnects": s.source_reconnects, "source_last_error": s.source_last_error}
                    for rid, s in sorted(self.status.items())}
            for rid in sorted({r for r, _ in self.diagnoses}):
                rsus.setdefault(rid, {}).update(self._trust(rid))
            buses = {}
            for bus in sorted(set(self.buses) | set(self.truth)):
                b = self.buses[bus]
                buses[bus] = {
                    "fixes_received": b.fixes,
                    "fixes_scored": b.fix_err.n,
                    "fix_pos_rms_m": b.fix_err.rms,
                    "fix_pos_max_m": b.fix_err.max,
                    "latency_ms_p50": b.latency_ms.pct(50),
                    "latency_ms_p99": b.latency_ms.pct(99),
                    "latency_parts_ms_p50": {"capture_to_fix_sent": b.rsu_ms.pct(50),
                                             "rsu_processing": b.processing_ms.pct(50),
                                             "fix_transit": b.fix_transit_ms.pct(50)},
                    "fixes_by_rsu": dict(sorted(b.fixes_by_rsu.items())),
                    "fused_samples": b.fused,
                    "fused_ok_samples": b.fused_err.n,
                    "fused_pos_rms_m": b.fused_err.rms,
                    "fused_pos_max_m": b.fused_err.max,
                    "fused_ok_held_fraction": round(b.fused_held / b.fused_err.n, 4) if b.fused_err.n else None,
                    "fused_confident_samples": b.fused_confident_err.n,
                    "fused_confident_pos_rms_m": b.fused_confident_err.rms,
                    "last_fix_err_m": b.fix_err.last,
                    "last_fused_err_m": b.fused_err.last,
                    "last_fused_status": b.fused_status,
                    "fix_paths": None if b.health is None else {
                        "accepted": b.health.accepted_fixes, "gated": b.health.rejected_fixes,
                        "too_old": b.health.too_old_fixes, "future": b.health.future_fixes,
                        "from_flagged_rsu": b.health.flagged_rsu_fixes, "unknown_clock": b.health.unknown_clock_fixes,
                        "other": b.health.other_fixes},
                    "flagged_rsus": [] if b.health is None else b.health.flagged_rsus,
                    "fused_in_session_samples": b.session_fused,
                    "fused_in_session_ok_fraction": (b.session_fused_ok / b.session_fused if b.session_fused
                                                     else None),
                    "fused_in_view_samples": b.session_in_view if self.in_view else None,
                    "fused_in_view_ok_fraction": (b.session_in_view_ok / b.session_in_view if b.session_in_view
                                                  else None),
                }
            n_session = sum(b.session_fused for b in self.buses.values())
            n_view = sum(b.session_in_view for b in self.buses.values())
            totals = {"latency_ms_p50": self.all_latency_ms.pct(50), "latency_ms_p99": self.all_latency_ms.pct(99),
                      "fixes_received": self.all_latency_ms.n,
                      "latency_by_mode": self._latency_by_mode(),
                      "fused_in_session_samples": n_session,
                      "fused_in_session_ok_fraction": (sum(b.session_fused_ok for b in self.buses.values())
                                                       / n_session if n_session else None),
                      "fused_in_view_samples": n_view if self.in_view else None,
                      "fused_in_view_ok_fraction": (sum(b.session_in_view_ok for b in self.buses.values())
                                                    / n_view if n_view else None)}
        return {"elapsed_s": round(time.monotonic() - self.started, 1), "rsus": rsus, "buses": buses,
                "all_buses": totals, "rejected_messages": self.counters.get("rejected")}

    def _latency_by_mode(self) -> dict:
        """Fix latency p50 / p99 (ms) by what the RSU did for the bus in that frame, each with the p50 / p99
        of its parts: capture to the start of the RSU's processing (the camera, the frame's transport, the
        wait for the RSU), the processing up to the fix, the fix's transit here."""
        by: dict[str, list] = defaultdict(list)
        for rsu, seq, bus, *ms in self._fix_parts:
            by[self._modes.get((rsu, seq), {}).get(bus, "unknown")].append(ms)
        out = {}
        for mode, rows in sorted(by.items()):
            a = np.asarray(rows)
            pct = {q: np.round(np.percentile(a, q, axis=0), 1) for q in (50, 99)}
            out[mode] = {"fixes": len(rows), "p50": float(pct[50][0]), "p99": float(pct[99][0]),
                         **{part: [float(pct[50][i]), float(pct[99][i])]
                            for i, part in enumerate(("before_processing", "processing", "transit"), 1)}}
        return out

    def _trust(self, rsu: str) -> dict:
        """What the buses think of one RSU: time offsets (per bus), drift flags, the advice."""
        diag = {bus: m for (r, bus), m in self.diagnoses.items() if r == rsu}
        flagged = sorted(bus for bus, m in diag.items() if m.drift_flagged)
        return {
            "time_offset_ms": {bus: {"estimate": None if m.time_offset_ns is None else ms_from_ns(m.time_offset_ns),
                                     "sigma": None if m.time_offset_sigma_ns is None else ms_from_ns(m.time_offset_sigma_ns),
                                     "clock_known": m.clock_known} for bus, m in sorted(diag.items())},
            "drift_flagged": bool(flagged), "flagged_by": flagged,
            "ever_flagged_by": {bus: t for (r, bus), t in sorted(self.flags.items()) if r == rsu},
            "disagreement_cm": {bus: round(100 * m.disagreement_m, 2) for bus, m in sorted(diag.items())},
            "advice": next((diag[b].advice for b in flagged), None),
        }

    def progress(self, summary: dict | None = None) -> str:
        s = summary or self.summary()
        lines = [f"t={s['elapsed_s']:6.1f}s"]
        for rid, r in s["rsus"].items():
            if "frames" not in r:  # heard of only through the buses' diagnoses
                lines.append(f"  {rid:8s} (no status){_trust_cells(r)}")
                continue
            det = "-" if r["detect_ms_last_s"] is None else f"{r['detect_ms_last_s']:.1f} ms"
            lines.append(f"  {rid:8s} buses {','.join(r['active_buses']) or '-':16s} frames {r['frames']:5d} "
                         f"processed {r['frames_processed']:5d} idle {r['frames_idle']:5d} "
                         f"behind {r['frames_skipped_busy']:3d} detect {det:>8s} fixes {r['fixes_published']}"
                         f"{_trust_cells(r)}")
            if r.get("source") is not None:
                lines.append("  " + source_line(r))
        for bus, b in s["buses"].items():
            fe = "-" if b["last_fix_err_m"] is None else f"{100 * b['last_fix_err_m']:.1f} cm"
            ue = "-" if b["last_fused_err_m"] is None else f"{100 * b['last_fused_err_m']:.1f} cm"
            lat = "-" if b["latency_ms_p50"] is None else f"{b['latency_ms_p50']:.0f} ms"
            flagged = f" flagged RSUs {','.join(b['flagged_rsus'])}" if b.get("flagged_rsus") else ""
            lines.append(f"  {bus:8s} fixes {b['fixes_received']:5d} last fix err {fe:>9s} fused err {ue:>9s} "
                         f"({b['last_fused_status'] or '-'}) latency p50 {lat}{flagged}")
        return "\n".join(lines)

    def close(self) -> None:
        for s in self._subs:
            s.close()


def _trust_cells(r: dict) -> str:
    """' offset bus-17 +29.8±1.1 ms DRIFT (bus-17)' for the live table."""
    cells = []
    for bus, o in (r.get("time_offset_ms") or {}).items():
        if o["estimate"] is not None:
            cells.append(f"{bus} {o['estimate']:+.1f}±{o['sigma']:.1f} ms")
        elif bus in r.get("flagged_by", ()):  # its bias passes for an offset: none is estimated while flagged
            cells.append(f"{bus} excluded (flagged)")
    text = f" offset {', '.join(cells)}" if cells else ""
    if r.get("drift_flagged"):
        text += f" DRIFT ({','.join(r['flagged_by'])}: run toptag calibrate check)"
    return text


def source_line(r: dict) -> str:
    """An RSU's camera source as the monitor prints it: what it is, connected or lost, fps, reconnects,
    the last error (Zenoh-fed RSUs have no source line)."""
    state = {True: "connected", False: "LOST", None: "-"}[r["source_connected"]]
    fps = "-" if r["source_fps"] is None else f"{r['source_fps']:.1f} fps"
    err = f" last error: {r['source_last_error']}" if r["source_last_error"] else ""
    return f"  source {r['source']} {state} {fps} reconnects {r['source_reconnects']}{err}"


def write_report(path: str | Path, summary: dict) -> None:
    Path(path).write_text(json.dumps(summary, indent=1))


class MonitorService:
    """`toptag monitor`: a progress table every ``period`` s; the summary written to ``report`` at the end."""

    def __init__(self, session, period: float, report: str | None):
        self.monitor = Monitor(session)
        self.period, self.report = period, report
        self._stop = threading.Event()

    def run(self, duration: float | None = None) -> None:
        """Until stop(), or ``duration`` s after the first message about a bus (see --duration)."""
        last_print = time.monotonic()
        while not self._stop.wait(min(self.period, 0.5)):
            first = self.monitor.first_message
            if duration is not None and first is not None and time.monotonic() >= first + duration:
                return
            if time.monotonic() - last_print >= self.period:
                print(self.monitor.progress(), flush=True)
                last_print = time.monotonic()

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        if self.report:
            write_report(self.report, self.monitor.summary())
        self.monitor.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag monitor", description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop S seconds after the first message about a bus (ground truth, fix or fused pose), "
                        "so a monitor started before the others watches the buses' traffic, not their "
                        "start-up; default: until stopped")
    p.add_argument("--period", type=float, default=2.0, help="seconds between progress tables")
    p.add_argument("--report", default=None, help="write the summary JSON here at the end")
    add_service_arguments(p, duration=False)
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return run_service("monitor", args, lambda: None,
                       lambda session, _: MonitorService(session, args.period, args.report), lambda _: "monitor")
