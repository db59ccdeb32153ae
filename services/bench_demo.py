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
  and of those taken while two of its tags were in some camera's image (its true pose; the scenario's
  cameras): where the cameras can see the bus at all, so what speed, not the site, decides.
The figures depend on the machine and its load: quote `nproc`, the CPU model and what else ran.
"""
from __future__ import annotations

import argparse
import json
import os
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
            # ... at the moments two of the bus's tags were in some camera's image (its true pose)
            "fused_ok_in_view": {"fraction": totals.get("fused_in_view_ok_fraction"),
                                 "samples": totals.get("fused_in_view_samples")},
            "buses": buses,
            "exit_codes": report.get("exit_codes", {})}


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
    ok = f["fused_ok_in_session"]
    lines.append(f"fused status ok while in session: {_fmt(None if ok['fraction'] is None else 100 * ok['fraction'])} %"
                 f" of {ok['samples']} samples")
    seen = f.get("fused_ok_in_view") or {}
    if seen.get("samples") is not None:
        lines.append(f"  of them while two of its tags were in some camera's image: "
                     f"{_fmt(None if seen['fraction'] is None else 100 * seen['fraction'])} % of {seen['samples']} samples")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    from services import demo

    with tempfile.TemporaryDirectory(prefix="toptag-bench-demo-") as tmp:
        report_path = Path(tmp) / "report.json"
        demo_args = ["--duration", str(args.duration), "--report", str(report_path), "--period", "10"]
        demo_args += ["--scenario", args.scenario] if args.scenario else []
        demo_args += ["--logs", args.logs] if args.logs else []
        code = demo.main(demo_args)
        if not report_path.exists():
            return code or 1
        f = figures(json.loads(report_path.read_text()))
    print("toptag bench demo:\n" + table(f))
    if args.out:
        Path(args.out).write_text(json.dumps(f, indent=1))
        print(f"toptag bench demo: figures written to {args.out}")
    return code
