"""`toptag demo`: the whole system on one machine, every service its own process.

A `toptag router` on loopback; the simulator, one RSU per camera and one agent per bus of the scenario
connect to it as Zenoh clients (the topology of the compose demo). The demo itself joins as a monitor,
prints live progress, and at --duration or Ctrl-C stops every process (buses first, so they leave
properly; the router last) and writes --report.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from protocol.transport.runner import freeze_start_up, stop_signals
from services.processes import TOPTAG, ProcessGroup, cpu_seconds, free_port
from toptag.progress import Progress

SERVICE_READY_S = 120.0  # how long a service may take to start on a busy machine


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, help="scenario file (default: the bundled two-bus demo)")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds to run from the simulator's first frame (default 60; with --replay: seconds of the "
                        "recording, default all of it)")
    p.add_argument("--bus-config", default=None, metavar="BUS.toml",
                   help="settings file for every bus (toptag bus --config; default: the scenario's bus_config)")
    p.add_argument("--report", default=None, help="write the JSON report here")
    p.add_argument("--logs", default=None, help="directory for each process's log (default: a temp dir)")
    p.add_argument("--period", type=float, default=2.0, help="seconds between progress tables")
    p.add_argument("--view", action="store_true", help="start the live view (toptag view) and print its URL")
    p.add_argument("--bind", default="127.0.0.1:0", metavar="ADDR:PORT", help="where the live view listens")
    p.add_argument("--record", default=None, metavar="RUN.mcap", help="record every message (toptag record)")
    p.add_argument("--record-frames", action="store_true", help="with --record: the camera frames too")
    p.add_argument("--replay", default=None, metavar="RUN.mcap",
                   help="instead of the simulator, replay a recorded drive (its frames, IMU, GNSS and truth, "
                        "shifted to now) through fresh RSUs and buses; --duration seconds of it (default: all)")
    return p


STARTUP_S = 120.0  # the longest the simulator's start-up may take before --duration counts anyway


class CpuWindow:
    """Each process's CPU seconds over the demo's working window: from the moment the simulator (or
    replay) is running (its start-up, imports and caches, excluded) to the moment the demo stops it."""

    def __init__(self, group: ProcessGroup, source):
        self.group, self.source = group, source
        self.start: tuple[float, dict, float] | None = None
        self.end: tuple[float, dict, float] | None = None

    def _now(self) -> tuple[float, dict, float]:
        return time.monotonic(), self.group.cpu_seconds(), cpu_seconds(os.getpid()) or 0.0

    def sample(self, final: bool = False) -> None:
        if self.start is None and (final or self._source_running()):
            self.start = self._now()
        if final:
            self.end = self._now()

    def _source_running(self) -> bool:
        text = self.source.log_path.read_text(errors="replace")
        return "sim running" in text or "replaying " in text

    def report(self) -> dict:
        if self.start is None or self.end is None:
            return {"window_s": 0.0, "seconds": {}, "total_s": 0.0, "cores": None}
        (t0, c0, d0), (t1, c1, d1) = self.start, self.end
        seconds = {name: (round(c1[name] - c0[name], 2) if c1.get(name) is not None and c0.get(name) is not None
                          else None) for name in c1}
        seconds["demo+monitor"] = round(d1 - d0, 2)
        total = sum(v for v in seconds.values() if v is not None)
        window = t1 - t0
        return {"window_s": round(window, 1), "seconds": seconds, "total_s": round(total, 2),
                "cores": round(total / window, 3) if window > 0 else None}


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    from sim.scenario import bundled_scenario_path, load_scenario
    from toptag.errors import InputError, report

    scenario_path = Path(args.scenario) if args.scenario else bundled_scenario_path()
    try:
        scenario = load_scenario(scenario_path)
    except InputError as e:
        return report("demo", e)
    stop = threading.Event()
    with stop_signals(lambda _name: stop.set()):
        return _run(args, scenario_path, scenario, stop)


def _run(args: argparse.Namespace, scenario_path: Path, scenario, stop: threading.Event) -> int:
    log_dir = Path(args.logs) if args.logs else Path(tempfile.mkdtemp(prefix="toptag-demo-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = ["--zenoh-mode", "client", "--connect", endpoint]
    group = ProcessGroup(log_dir)
    print(f"toptag demo: router on {endpoint}; logs in {log_dir}", flush=True)

    router = group.start("router", TOPTAG + ["router", "--listen", endpoint])
    if not group.wait_for_log(router, "router listening", 15):
        print(f"toptag demo: the router did not start:\n{router.log_tail()}", file=sys.stderr)
        group.stop()
        return 1
    from protocol.transport import open_session
    from services.monitor import Monitor, ViewCoverage, write_report

    session = open_session(mode="client", connect=[endpoint])
    monitor = Monitor(session, in_view=ViewCoverage(scenario))
    rsu_settings = ["--config", str(scenario.rsu_config)] if scenario.rsu_config else []
    rsus = [group.start(cam.stem, TOPTAG + ["rsu", "--camera", str(cam), "--intersection", scenario.intersection_id]
                        + rsu_settings + client) for cam in scenario.camera_paths()]
    bus_config = args.bus_config or scenario.bus_config
    bus_settings = ["--config", str(bus_config)] if bus_config else []
    buses = [group.start(f"bus-{veh.stem}", TOPTAG + ["bus", "--vehicle", str(veh), "--map", str(scenario.map_path())]
                         + bus_settings + client) for veh in scenario.vehicle_paths()]
    tools = []  # recorder and view: stopped after the services, before the router
    if args.record:
        tools.append(group.start("record", TOPTAG + ["record", "--out", args.record] + client
                                 + (["--frames"] if args.record_frames else [])))
    if args.view:
        view = group.start("view", TOPTAG + ["view", "--bind", args.bind, "--scenario", str(scenario_path)] + client)
        tools.append(view)
        if not group.wait_for_log(view, "open http", 30):
            print(f"toptag demo: the live view did not start:\n{view.log_tail()}", file=sys.stderr)
        else:
            url = next(line for line in view.log_path.read_text().splitlines() if "open http" in line)
            print(f"toptag demo: live view: {url.split('open ', 1)[1]}", flush=True)
    # Subscribed before the first message: the recorder and the view always; with --replay every service
    # too, for a recorded drive is played once and, on a busy machine where a process takes many seconds
    # to start, would otherwise pass unseen (the simulator loops its scenario and starts at once).
    for c in (rsus + buses if args.replay else []) + tools:
        if not group.wait_for_log(c, "ready", SERVICE_READY_S):
            print(f"toptag demo: {c.name} not ready after {SERVICE_READY_S:.0f} s; starting the drive anyway",
                  file=sys.stderr, flush=True)
    if args.replay:
        sim = group.start("replay", TOPTAG + ["replay", args.replay, "--sensors", "--shift-to-now",
                                              "--wait-subscribers", "10"] + client
                          + ([] if args.duration is None else ["--duration", str(args.duration)]))
    else:
        sim = group.start("sim", TOPTAG + ["sim", "run", "--scenario", str(scenario_path)] + client)

    freeze_start_up()  # the monitor in this process is a service like the others
    t_start = time.monotonic()
    cpu = CpuWindow(group, sim)
    # With --replay the demo ends with the replay (its own --duration); else --duration s after the
    # simulator's first frame (its start-up, at most STARTUP_S, is not counted).
    seconds = 60.0 if args.duration is None else args.duration
    bar = Progress(seconds, "toptag demo", unit=" s")
    exit_code = 0
    last_print = t_start
    try:
        while not stop.wait(0.25):
            now = time.monotonic()
            cpu.sample()
            began = cpu.start[0] if cpu.start is not None else None
            if not args.replay and now >= (began if began is not None else t_start + STARTUP_S) + seconds:
                break
            if now - last_print >= args.period:
                last_print = now
                bar.set(round(now - (began if began is not None else now)),
                        note="Ctrl-C stops it and writes the report")
                print(monitor.progress(), flush=True)
            dead = group.dead()
            if args.replay and dead == [sim] and sim.popen.returncode == 0:
                break  # the recorded drive is over
            if dead:
                for c in dead:
                    print(f"toptag demo: {c.name} exited with {c.popen.returncode}:\n{c.log_tail()}", file=sys.stderr)
                exit_code = 1
                break
    finally:
        bar.close()
        cpu.sample(final=True)
        # Buses first (they send Leave), then the sim, the RSUs, and the router last.
        codes = group.stop(buses + [sim] + rsus)
        time.sleep(0.2)
        codes.update(group.stop(tools))
        summary = monitor.summary()
        monitor.close()
        session.close()
        codes.update(group.stop([router]))
    summary["cpu"] = cpu.report()
    summary["exit_codes"] = codes
    summary["logs"] = str(log_dir)
    print(monitor.progress(summary))
    print(json.dumps({b: {k: v for k, v in r.items() if k in ("fixes_received", "fix_pos_rms_m", "fused_pos_rms_m",
                                                                  "latency_ms_p50", "latency_ms_p99")}
                      for b, r in summary["buses"].items()}, indent=1))
    c = summary["cpu"]
    print(f"toptag demo: CPU over {c['window_s']} s: {c['cores']} cores "
          f"({', '.join(f'{k} {v:.1f} s' for k, v in c['seconds'].items() if v is not None)})")
    if args.report:
        write_report(args.report, summary)
        print(f"toptag demo: report written to {args.report}")
    if args.record:
        print(f"toptag demo: recording written to {args.record}")
    if any(c not in (0, None) for c in codes.values()):
        print(f"toptag demo: processes exited with {codes}", file=sys.stderr)
        exit_code = exit_code or 1
    return exit_code
