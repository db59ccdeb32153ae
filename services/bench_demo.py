"""`toptag bench demo`: the whole demo (`toptag demo`) for --duration s, measured the same way every time.

Prints and writes (--out, JSON) what says whether the demo keeps real time on this machine:
- CPU seconds of every process over the working window (from the simulator's first frame to the
  stop) and their total in cores;
- per RSU: frames that reached it and those it skipped because it was busy (count and fraction), those
  that never reached it (ticks the simulator skipped for running late: gaps in the frame numbers), and
  where its time went: frames and mean processing ms per kind of work (acquisition, tracking, nothing);
- fix latency (capture to arrival at the monitor) p50 / p99 over every bus's fixes, and by what the RSU
  did for that bus in that frame (tracked, hinted, acquired) with its parts: capture to the start of
  the RSU's processing (camera, transport, waiting), processing, transit;
- the fraction of fused samples with status "ok" while a bus is in session (its Approach to its Leave),
  and of those taken while two of its tags were decodable in some camera's image (its true pose; the scenario's
  cameras): where the cameras can see the bus at all, so what speed, not the site, decides.
The figures depend on the machine and its load: quote `nproc`, the CPU model and what else ran.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import tempfile
from pathlib import Path

from toptag.machine import cpu_model


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag bench demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=60.0, help="seconds of demo (default 60)")
    p.add_argument("--scenario", default=None, help="scenario file (default: the bundled two-bus demo)")
    p.add_argument("--out", default=None, help="write the figures as JSON here")
    p.add_argument("--logs", default=None, help="directory for each process's log (default: a temp dir)")
    return p


def figures(report: dict) -> dict:
    """The bench's figures from a `toptag demo --report` summary."""
    rsus = {}
    for rid, r in report.get("rsus", {}).items():
        # frames: taken by the RSU's loop; skipped: overwritten unseen while it was busy (their sum: the
        # frames that reached it); missing: never reached it (the simulator skipped the tick, running late).
        offered = r["frames"] + r["frames_skipped_busy"]
        missing = r.get("frames_missing", 0)
        rsus[rid] = {"frames": offered, "skipped_busy": r["frames_skipped_busy"],
                     "skipped_busy_fraction": round(r["frames_skipped_busy"] / offered, 4) if offered else None,
                     "missing": missing,
                     "missing_fraction": round(missing / (offered + missing), 4) if offered + missing else None,
                     "idle": r["frames_idle"], "processed": r["frames_processed"],
                     "detect_ms_mean": r["detect_ms_mean"],
                     "processing_ms_by_kind": r.get("processing_ms_by_kind", {})}
    totals = report.get("all_buses", {})
    buses = {b: {"fixes": v["fixes_received"], "latency_ms_p50": v["latency_ms_p50"],
                 "latency_ms_p99": v["latency_ms_p99"], "fused_in_session_samples": v["fused_in_session_samples"],
                 "fused_in_session_ok_fraction": v["fused_in_session_ok_fraction"]}
             for b, v in report.get("buses", {}).items()}
    cpu = report.get("cpu", {})
    return {"machine": {"nproc": os.cpu_count(), "cpu": cpu_model()},
            "cpu": {"window_s": cpu.get("window_s"), "cores": cpu.get("cores"), "total_s": cpu.get("total_s"),
                    "seconds": cpu.get("seconds", {})},
            "rsus": rsus,
            "fix_latency_ms": {"p50": totals.get("latency_ms_p50"), "p99": totals.get("latency_ms_p99"),
                               "fixes": totals.get("fixes_received")},
            "fix_latency_by_mode": totals.get("latency_by_mode", {}),
            "fused_ok_in_session": {"fraction": totals.get("fused_in_session_ok_fraction"),
                                    "samples": totals.get("fused_in_session_samples")},
            # ... at the moments two of the bus's tags were decodable in some camera's image (its true pose)
            "fused_ok_in_view": {"fraction": totals.get("fused_in_view_ok_fraction"),
                                 "samples": totals.get("fused_in_view_samples")},
            "buses": buses,
            "exit_codes": report.get("exit_codes", {})}


_SENT = re.compile(r"frames sent p50 ([\d.]+) / p99 ([\d.]+) ms after their tick")
_ARRIVED = re.compile(r"frames in session: arrived p50 ([\d.]+) / p99 ([\d.]+) ms after their capture stamp, "
                      r"waited p50 ([\d.]+) / p99 ([\d.]+) ms")


def frame_delays(logs: Path) -> dict:
    """Where a frame's age before its processing goes, from the processes' final log lines: the simulator
    sending it after its tick, each RSU receiving it after its capture stamp (sending included) and its
    frame loop taking it after its arrival; [p50, p99] ms each."""
    out: dict = {}
    sim = logs / "sim.log"
    if sim.exists() and (m := _SENT.search(sim.read_text(errors="replace"))):
        out["sim_sent_after_tick"] = [float(m[1]), float(m[2])]
    for log_file in sorted(logs.glob("rsu-*.log")):
        if m := _ARRIVED.search(log_file.read_text(errors="replace")):
            out[log_file.stem] = {"arrived_after_capture": [float(m[1]), float(m[2])],
                                  "waited_for_loop": [float(m[3]), float(m[4])]}
    return out


def _fmt(v, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def table(f: dict) -> str:
    lines = [f"machine: {f['machine']['nproc']} cores, {f['machine']['cpu']}",
             f"CPU over {_fmt(f['cpu']['window_s'])} s: {_fmt(f['cpu']['cores'], '.2f')} cores in all"]
    for name, s in f["cpu"]["seconds"].items():
        lines.append(f"  {name:14s} {_fmt(s, '.1f'):>7s} s")
    for rid, r in f["rsus"].items():
        frac = r["skipped_busy_fraction"]
        lines.append(f"  {rid:14s} frames {r['frames']:5d} skipped busy {r['skipped_busy']:4d} "
                     f"({_fmt(None if frac is None else 100 * frac)} %) missing {r['missing']:4d} "
                     f"({_fmt(None if r['missing_fraction'] is None else 100 * r['missing_fraction'])} %) "
                     f"idle {r['idle']:5d}; "
                     + ", ".join(f"{k} {v['frames']} x {v['mean_ms']:.1f} ms"
                                 for k, v in r["processing_ms_by_kind"].items()))
    lat = f["fix_latency_ms"]
    lines.append(f"fix latency p50 {_fmt(lat['p50'])} ms, p99 {_fmt(lat['p99'])} ms over {lat['fixes']} fixes")
    for mode, m in f.get("fix_latency_by_mode", {}).items():
        lines.append(f"  {mode:10s} {m['fixes']:5d} fixes p50 / p99 {m['p50']:.0f} / {m['p99']:.0f} ms: capture to "
                     f"processing {m['before_processing'][0]:.0f} / {m['before_processing'][1]:.0f}, processing "
                     f"{m['processing'][0]:.0f} / {m['processing'][1]:.0f}, transit {m['transit'][0]:.0f} / "
                     f"{m['transit'][1]:.0f}")
    delays = f.get("frame_delays_ms") or {}
    if delays:
        sent = delays.get("sim_sent_after_tick")
        lines.append("frames before processing, p50 / p99 ms: "
                     + (f"sim sent {sent[0]:.0f} / {sent[1]:.0f} after the tick; " if sent else "")
                     + "; ".join(f"{rid} arrived {d['arrived_after_capture'][0]:.0f} / "
                                 f"{d['arrived_after_capture'][1]:.0f}, waited {d['waited_for_loop'][0]:.0f} / "
                                 f"{d['waited_for_loop'][1]:.0f}"
                                 for rid, d in delays.items() if rid.startswith("rsu-")))
    ok = f["fused_ok_in_session"]
    lines.append(f"fused status ok while in session: {_fmt(None if ok['fraction'] is None else 100 * ok['fraction'])} %"
                 f" of {ok['samples']} samples")
    seen = f.get("fused_ok_in_view") or {}
    if seen.get("samples") is not None:
        lines.append(f"  of them while two of its tags were decodable in some camera's image: "
                     f"{_fmt(None if seen['fraction'] is None else 100 * seen['fraction'])} % of {seen['samples']} samples")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    from services import demo

    with tempfile.TemporaryDirectory(prefix="toptag-bench-demo-") as tmp:
        report_path = Path(tmp) / "report.json"
        logs = Path(args.logs) if args.logs else Path(tmp) / "logs"
        demo_args = ["--duration", str(args.duration), "--report", str(report_path), "--period", "10",
                     "--logs", str(logs)]
        demo_args += ["--scenario", args.scenario] if args.scenario else []
        code = demo.main(demo_args)
        if not report_path.exists():
            return code or 1
        f = figures(json.loads(report_path.read_text()))
        f["frame_delays_ms"] = frame_delays(logs)
    print("toptag bench demo:\n" + table(f))
    if args.out:
        Path(args.out).write_text(json.dumps(f, indent=1))
        print(f"toptag bench demo: figures written to {args.out}")
    return code
