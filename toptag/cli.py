"""`toptag` command line: one entry point dispatching to each command's own module.

Modules are imported only for the command that runs, so `toptag locate` never loads Zenoh and a
service never loads the study code."""
from __future__ import annotations

import importlib
import os
import sys

from toptag.errors import ToptagError, report

# command words -> "module:function"; each function takes argv (list[str]) and returns an exit code.
COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("locate",): ("toptag.locate:main", "estimate a bus pose from RSU images, videos or streams"),
    ("calibrate",): ("toptag.calibration.cli:main", "calibrate a camera: intrinsics, extrinsics, check"),
    ("demo",): ("services.demo:main", "every service as its own process on a local Zenoh network"),
    ("router",): ("services.router:main", "Zenoh router for the toptag services"),
    ("certs",): ("services.security:main", "generate a CA and TLS certificates for toptag services"),
    ("rsu",): ("services.rsu.service:main", "RSU service for one camera"),
    ("bus",): ("services.bus.agent:main", "bus agent: announce, fuse fixes with IMU, publish FusedPose"),
    ("monitor",): ("services.monitor:main", "live localization quality of a running intersection"),
    ("view",): ("services.view.app:main", "the intersection live in a browser (Rerun web viewer)"),
    ("record",): ("services.recording:main", "record every message (MCAP) for replay and offline evaluation"),
    ("replay",): ("services.replay:main", "republish a recording with its original pacing"),
    ("site", "check"): ("sim.site_check:main", "validate a site folder and draw its top view"),
    ("sim", "examples"): ("sim.examples:main", "render example RSU images with ground truth"),
    ("sim", "run"): ("sim.live:main", "live simulator: RSU frames and bus sensors over Zenoh"),
    ("sim", "record"): ("sim.record:main", "one RSU's rendered frames as a video file with its truth"),
    ("bench", "latency"): ("services.bench_latency:main", "capture-to-arrival latency through router and RSU"),
    ("bench", "rsu"): ("services.rsu.bench:main", "tracked RSU pipeline vs full-frame detection"),
    ("bench", "filter"): ("sim.bench_filter:main", "cost of the bus filter's add_fix, add_imu, estimate"),
    ("bench", "bus"): ("services.bench_bus:main", "the bus agent process's CPU at 100 Hz IMU and 40 fixes/s"),
    ("eval", "fusion"): ("sim.studies.fusion:main", "fused pose error against latency, clock offsets, drift (study)"),
    ("bench", "solver"): ("services.bench_solver:main", "cost of one pose solve per solver (the RSU's two-tag case)"),
    ("bench", "demo"): ("services.bench_demo:main", "the whole demo: CPU per process, frames skipped, latency, fused ok"),
    ("eval", "replay"): ("services.replay_eval:main", "re-run a bus's fusion offline on a recording"),
    ("eval", "paper"): ("sim.studies.paper:main", "reproduce the paper's simulation study"),
    ("eval", "real"): ("sim.studies.real:main", "detection and every solver on real photographs with truth"),
    ("eval", "imagemodel"): ("sim.studies.imagemodel:main", "rendered vs real corner errors (simulator calibration)"),
    ("eval", "hamming"): ("sim.studies.hamming:main", "tags recovered vs false decodes per admitted bit error"),
    ("eval", "livefix"): ("sim.studies.livefix:main", "live RSU pipeline's fix bias per RSU (drift thresholds)"),
    ("eval", "calibration"): ("sim.studies.calibration:main", "calibration targets and their Cramér-Rao ratios"),
}


def _usage() -> str:
    lines = ["usage: toptag <command> [options]   (toptag <command> --help for its options)", "", "commands:"]
    for words, (_, text) in COMMANDS.items():
        lines.append(f"  {' '.join(words):<16} {text}")
    return "\n".join(lines)


def dispatch(argv: list[str]) -> int:
    for n in (2, 1):
        words = tuple(argv[:n])
        if words in COMMANDS:
            target = COMMANDS[words][0]
            module, func = target.split(":")
            try:
                return int(getattr(importlib.import_module(module), func)(argv[n:]) or 0)
            except ToptagError as e:  # one line and the kind's exit code (toptag.errors), never a traceback
                return report(" ".join(words), e)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    print(f"toptag: unknown command {' '.join(argv[:2])!r}\n{_usage()}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> None:
    try:
        code = dispatch(sys.argv[1:] if argv is None else argv)
    except KeyboardInterrupt:
        code = 130
    except BrokenPipeError:  # `toptag locate ... | head`: the reader has all it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 0
    except SystemExit as e:  # argparse's --help and usage errors
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        if isinstance(e.code, str):
            print(e.code, file=sys.stderr)
    # pupil-apriltags' Detector.__del__ may crash during interpreter teardown: everything has been
    # printed, so flush and leave without running finalisers.
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (BrokenPipeError, ValueError):
            pass
    os._exit(code)
