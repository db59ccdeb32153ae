"""`toptag eval replay`: re-run one bus's fusion offline on a recording, deterministically.

    toptag eval replay RUN.mcap --bus BUS [--config BUS.toml] [--fix-latency-ms MS] [--out RESULTS.json]

Reads the bus's IMU samples and the RSUs' pose fixes from a recording (`toptag record`) and feeds them
to a fresh bus filter (toptag.fusion, the agent's filter with the agent's rules: a fix is added when
it was received, an IMU gap over IMU_GAP_RESET_S restarts the filter from what the last one learnt of
the RSUs, BusFilter.memory) in the order the recorder received them. `--fix-latency-ms MS` instead
re-times the fixes as arriving MS after their capture (IMU and truth at their own stamps, an IMU sample
first at an instant: however the recording batched them, ImuBatch or Imu, the same order): the same
live fixes as a quiet machine would deliver them, e.g. from a demo recorded on a busy one. Every RSU the
filter flagged for drift is listed (`drift_flags`: when, by which test, the advice). Wherever the recording holds the truth (the simulator's), the filter's estimate at the
truth's time, with what it knew when the truth was received, is scored as the monitor scores the live
bus (status ok only). Where it holds the bus's own FusedPose, the offline estimate is compared with
it: a filter change shows as a difference there. No clock, no threads, no network: two runs on one
recording give the same numbers to the last bit (``digest`` hashes every estimate).
"""
from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

from protocol import codec, keys
from protocol.codec import ProtocolError
from protocol.convert import fix_from_message
from protocol.messages import FusedPose, GroundTruth, Imu, ImuBatch, PoseFix
from services.bus.agent import IMU_GAP_RESET_S, BusSettings
from services.monitor import ErrorStats, TruthTrack
from services.recording import read_recording
from toptag.errors import InputError, ToptagError, report
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.settings import load_settings


def load_filter_config(path: str | Path | None) -> FilterConfig:
    """The [filter] table of a bus settings file (`toptag bus --config`, toptag.settings: TOML or YAML,
    unknown keys refused by name); defaults without a file."""
    return FilterConfig() if path is None else load_settings(path, BusSettings).filter


class OfflineFusion:
    """The bus filter fed from recorded messages, in reception order."""

    def __init__(self, config: FilterConfig):
        self.config = config
        self.filter = BusFilter(config)
        self.flags: list[dict] = []  # every RSU flagged for drift: when, by which test
        self._flagged: set[str] = set()
        self._t0: int | None = None
        self.resets = 0
        self._last_imu: int | None = None
        self.truth = TruthTrack()
        self.fused_err, self.fix_err, self.live_diff = ErrorStats(), ErrorStats(), ErrorStats()
        self.fixes = 0
        self.imu = 0
        self.status_counts: dict[str, int] = {}
        self._pending_fixes: list[tuple[int, float, float]] = []
        self._digest = hashlib.sha256()

    def imu_sample(self, m: Imu) -> None:
        if self._last_imu is not None and (m.t_ns - self._last_imu) * 1e-9 > IMU_GAP_RESET_S:
            self.filter = BusFilter(self.config, memory=self.filter.memory())  # as the agent does
            self.resets += 1
        self._last_imu = m.t_ns
        self._t0 = m.t_ns if self._t0 is None else self._t0
        self.filter.add_imu(m.t_ns, m.gyro_z, m.accel_x, m.accel_y, m.wheel_speed)
        self.imu += 1

    def fix(self, m: PoseFix, arrival_ns: int) -> None:
        self.filter.add_fix(fix_from_message(m, arrival_ns=arrival_ns))
        self.fixes += 1
        self._pending_fixes.append((m.capture_time_ns, m.x, m.y))

    def _estimate(self, t_ns: int):
        est = self.filter.estimate(t_ns) if self.filter.initialized else None
        if est is not None:
            self._digest.update(np.asarray([t_ns, est.x, est.y, est.yaw, *np.ravel(est.cov)], dtype=float).tobytes())
        return est

    def truth_sample(self, m: GroundTruth) -> None:
        self.truth.add(m)
        est = self._estimate(m.t_ns)
        if est is None:
            return
        self._note_flags(est.health.flagged_rsus, m.t_ns)
        status = est.health.status or "-"
        self.status_counts[status] = self.status_counts.get(status, 0) + 1
        if status == "ok":
            self.fused_err.add(float(np.hypot(est.x - m.x, est.y - m.y)))

    def _note_flags(self, flagged: tuple[str, ...], t_ns: int) -> None:
        new = set(flagged) - self._flagged
        if new:
            a = self.filter.rsu_assessments()
            for rsu in sorted(new):
                self.flags.append({"rsu": rsu, "t_s": (t_ns - (self._t0 or t_ns)) * 1e-9, "filter": self.resets,
                                   "flagged_by": a[rsu].flagged_by, "advice": a[rsu].advice})
        self._flagged = set(flagged)

    def live_fused(self, m: FusedPose) -> None:
        est = self._estimate(m.t_ns)
        if est is not None:
            self.live_diff.add(float(np.hypot(est.x - m.x, est.y - m.y)))

    def finish(self) -> None:
        for t, x, y in self._pending_fixes:
            truth = self.truth.at(t)
            if truth is not None:
                self.fix_err.add(float(np.hypot(x - truth[0], y - truth[1])))
        self._pending_fixes = []

    def report(self) -> dict:
        def stats(s: ErrorStats) -> dict:
            return {"n": s.n, "rms_m": s.rms, "max_m": s.max, "p95_m": s.pct(95)}
        return {"imu_samples": self.imu, "fixes": self.fixes, "filter_restarts": self.resets,
                "fused_vs_truth": stats(self.fused_err), "fixes_vs_truth": stats(self.fix_err),
                "offline_vs_live_fused": stats(self.live_diff), "status_at_truth": dict(sorted(self.status_counts.items())),
                "filter": self.filter.counters(), "drift_flags": self.flags, "digest": self._digest.hexdigest()}


def _messages(recording: str | Path, bus: str, fix_latency_ms: float | None, bad: list[int]):
    """(arrival ns, message) of the bus's IMU samples (a batch's one by one), fixes, truth and fused poses in
    the order the recorder received them; with fix_latency_ms, IMU and truth at their stamps and each fix that
    long after its capture (fused poses left out: the live bus saw other arrivals)."""
    wanted = [keys.imu(bus), keys.imu_batch(bus), keys.pose_fix(keys.ANY, bus, keys.ANY), keys.ground_truth(bus),
              keys.fused_pose(bus)]
    out = []
    for k, rec in enumerate(read_recording(recording, wanted)):
        if rec.message_type not in (Imu, ImuBatch, PoseFix, GroundTruth, FusedPose):
            continue
        try:
            m = codec.decode(rec.payload, rec.message_type, key=rec.key)
        except ProtocolError:
            bad[0] += 1  # the live bus rejected it too
            continue
        for m in (m.samples if isinstance(m, ImuBatch) else (m,)):  # a batch's samples as the live bus took them
            if fix_latency_ms is None:
                yield rec.log_time_ns, m
            elif isinstance(m, PoseFix):
                out.append((m.capture_time_ns + int(round(fix_latency_ms * 1e6)), 1, k, m))
            elif not isinstance(m, FusedPose):  # at its stamp: an IMU sample before the rest of that instant
                out.append((m.t_ns, 0 if isinstance(m, Imu) else 1, k, m))
    for at, _, _, m in sorted(out, key=lambda e: e[:3]):
        yield at, m


def evaluate(recording: str | Path, bus: str, config: FilterConfig, fix_latency_ms: float | None = None) -> dict:
    """Run the offline fusion of ``bus`` over ``recording``; the report (see module doc)."""
    run = OfflineFusion(config)
    bad = [0]
    for at, m in _messages(recording, bus, fix_latency_ms, bad):
        if isinstance(m, Imu):
            run.imu_sample(m)
        elif isinstance(m, PoseFix):
            run.fix(m, at)
        elif isinstance(m, GroundTruth):
            run.truth_sample(m)
        else:
            run.live_fused(m)
    run.finish()
    out = {"recording": str(recording), "bus": bus, "fix_latency_ms": fix_latency_ms, **run.report(),
           "rejected_payloads": bad[0]}
    if run.imu == 0:
        raise InputError(f"recording {recording}: no IMU samples of bus {bus!r}")
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag eval replay", description=__doc__.split("\n\n")[0])
    p.add_argument("recording", metavar="RUN.mcap")
    p.add_argument("--bus", required=True, help="bus id whose fusion to re-run")
    p.add_argument("--config", default=None, metavar="BUS.toml",
                   help="a bus settings file (toptag bus --config): its [filter] table")
    p.add_argument("--fix-latency-ms", type=float, default=None, metavar="MS",
                   help="re-time every fix as arriving MS after its capture (default: as recorded)")
    p.add_argument("--out", default=None, metavar="RESULTS.json", help="also write the report here")
    return p


def _cm(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} cm"


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = load_filter_config(args.config)
        if args.fix_latency_ms is not None and args.fix_latency_ms < 0:
            raise InputError(f"--fix-latency-ms must be >= 0, got {args.fix_latency_ms}")
        result = evaluate(args.recording, args.bus, config, args.fix_latency_ms)
    except ToptagError as e:
        return report("eval replay", e)
    except ValueError as e:  # an unreadable recording
        return report("eval replay", InputError(str(e)))
    f, x, d = result["fused_vs_truth"], result["fixes_vs_truth"], result["offline_vs_live_fused"]
    print(f"bus {args.bus}: {result['imu_samples']} IMU samples, {result['fixes']} fixes, "
          f"{result['filter_restarts']} filter restarts")
    print(f"  fused vs truth (status ok): RMS {_cm(f['rms_m'])}, max {_cm(f['max_m'])} over {f['n']} truth samples")
    print(f"  fixes vs truth: RMS {_cm(x['rms_m'])} over {x['n']} fixes")
    print(f"  offline vs live fused pose: RMS {_cm(d['rms_m'])}, max {_cm(d['max_m'])} over {d['n']} poses")
    flags = result["drift_flags"]
    print(f"  drift flags: {len(flags)}" + "".join(f"\n    {f['rsu']} at {f['t_s']:.1f} s (filter {f['filter']}, "
                                                     f"by {f['flagged_by']})" for f in flags))
    print(f"  digest {result['digest']}")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    return 0
