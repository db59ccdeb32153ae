"""`toptag bench bus`: the bus agent process's CPU at 100 Hz IMU and 40 fixes/s, as % of one core.

    toptag bench bus [--duration 30] [--rsus 4] [--fix-hz 10] [--latency-ms 100] [--jitter-ms 30]
                     [--imu-per-message 4] [--json]

Starts the real agent (`toptag bus`, its own process, the demo's bus-42 and the corner site's map, whose 45 m
approach radius holds the drive from its start) connected in peer mode
to this process's Zenoh peer (tcp/127.0.0.1:<free port>, multicast scouting off). This process plays one
drive of that bus through the demo's intersection in real time (the fusion study's left turn from the
west, slowed so that it lasts --duration s): IMU/odometry at 100 Hz (sim.motion.ImuModel; --imu-per-message
samples to an ImuBatch, sent at its newest sample's time, as the simulator sends them; 1: each an Imu), GNSS at 1 Hz
from the truth, and once the agent has announced itself, PoseFixes from --rsus corner RSUs at --fix-hz
each (sim.studies.fusion's fix model, every RSU seeing the bus the whole way), each published
latency ± jitter ms after its capture as an RSU would. It subscribes to everything the agent publishes
(FusedPose, RsuDiagnosis, Approach), as the demo's monitor and RSUs do, and counts it.

The figure: the agent process's CPU seconds (user + system, /proc) over the drive, divided by the
drive's wall time. The agent's start-up and session entry are not in it. Quote it with the machine's
load average: the process's CPU also grows with contention (caches, context switches).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from protocol import keys
from protocol.convert import fix_to_message
from protocol.messages import (
    IMU_BATCH_MAX,
    Approach,
    ClockInfo,
    FusedPose,
    GnssFix,
    Imu,
    ImuBatch,
    PoseFix,
    RsuDiagnosis,
)
from protocol.transport import MessagePublisher, imu_publisher, open_session, subscribe_messages
from services.processes import TOPTAG, ProcessGroup, cpu_seconds, free_port
from sim.motion import DEFAULT_T0_NS, ImuModel, bus_trajectory
from sim.studies.fusion import BUS_ROOF_Z, FixErrorModel, simulate_fixes
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.machine import cpu_model, usable_cores
from toptag.units import NS_PER_S, ns_from_ms, ns_from_s
from toptag.vehicle import Vehicle

DEMO = Path(__file__).resolve().parents[1] / "toptag" / "data" / "demo"
VEHICLE = DEMO / "bus-42.json"
MAP = DEMO / "corners" / "map.json"  # the demo site's 18 m radius leaves the drive's start out of session
INTERSECTION = "x1"
GNSS_HZ = 1.0
GNSS_SIGMA_M = 2.0
ROUTE = ("left", "w")


@dataclasses.dataclass
class Drive:
    """One drive's messages, each with its send time in ns after the drive's start (stamps likewise;
    shifted to the wall clock when played)."""
    events: list[tuple[int, str, object]]  # (send offset ns, kind, Imu | GnssFix | Fix)
    duration_s: float
    speed_mps: float
    imu: int
    fixes: int
    gnss: int


def make_drive(duration_s: float, n_rsu: int = 4, fix_hz: float = 10.0, latency_ms: float = 100.0,
               jitter_ms: float = 30.0, seed: int = 0) -> Drive:
    """The bench's drive: the fusion study's left turn from the west at the speed that makes it last
    duration_s (at most the bus's top speed), its IMU, GNSS and fixes (every RSU sees the bus throughout)."""
    rng = np.random.default_rng(seed)
    probe = bus_trajectory(*ROUTE, speed=BUS_MAX_SPEED_MPS, seed=seed)
    speed = min(BUS_MAX_SPEED_MPS, probe.path.length / duration_s)
    traj = bus_trajectory(*ROUTE, speed=speed, seed=seed)
    imu = ImuModel().synthesize(traj, 0.0, traj.duration, rng)
    fixes = simulate_fixes(traj, FixErrorModel(rate_hz=fix_hz, range_m=1e3), n_rsu, rng)
    delays = np.maximum(0.0, latency_ms + jitter_ms * rng.standard_normal(len(fixes)))
    t0 = DEFAULT_T0_NS
    events: list[tuple[int, str, object]] = []
    for t_ns, g, ax, ay, w in imu.rows():
        events.append((t_ns - t0, "imu", (t_ns - t0, g, ax, ay, w)))
    for f, d in zip(fixes, delays):
        events.append((f.t_ns - t0 + ns_from_ms(float(d)), "fix", dataclasses.replace(f, t_ns=f.t_ns - t0)))
    t_g = np.arange(0.0, traj.duration, 1.0 / GNSS_HZ)
    st = traj.state_at(t_g)
    noise = GNSS_SIGMA_M * rng.standard_normal((len(t_g), 2))
    for i, t in enumerate(t_g.tolist()):
        events.append((ns_from_s(t), "gnss", (ns_from_s(t), float(st.x[i] + noise[i, 0]), float(st.y[i] + noise[i, 1]))))
    events.sort(key=lambda e: e[0])
    return Drive(events, traj.duration, speed, len(imu), len(fixes), len(t_g))


class _Received:
    """What the agent published, counted on this process's Zenoh callback threads."""

    def __init__(self):
        self.lock = threading.Lock()
        self.fused = 0
        self.fused_ok = 0
        self.last_fused: FusedPose | None = None
        self.diagnoses = 0
        self.approaches = 0
        self.entered = 0  # agents that announced themselves (their first Approach, seq 1)
        self.changed = threading.Condition(self.lock)
        self.counting = False

    def on_fused(self, m: FusedPose) -> None:
        with self.lock:
            if self.counting:
                self.fused += 1
                self.fused_ok += m.health.status == "ok"
            self.last_fused = m

    def on_diagnosis(self, m: RsuDiagnosis) -> None:
        with self.lock:
            self.diagnoses += self.counting

    def on_approach(self, m: Approach) -> None:
        with self.lock:
            self.approaches += self.counting
            self.entered += m.seq == 1
            self.changed.notify_all()


def _fixes_in(h) -> int:
    """Every fix the agent's filter saw, by the health it published."""
    return (h.accepted_fixes + h.rejected_fixes + h.too_old_fixes + h.future_fixes + h.flagged_rsu_fixes
            + h.other_fixes)


def run(duration_s: float = 30.0, n_rsu: int = 4, fix_hz: float = 10.0, latency_ms: float = 100.0,
        jitter_ms: float = 30.0, seed: int = 0, logs: str | None = None, agent_source: str | None = None,
        also: list[str] | None = None, imu_per_message: int = 4) -> dict:
    """Play the drive to a freshly started agent and measure it (see the module doc). agent_source: run
    the agent from that checkout of toptag instead of this one (PYTHONPATH), to compare two versions
    with the same bench. also: checkouts whose agents run beside it on the same drive at the same time
    (the same load for both: a paired comparison); their CPU is in "also", and then what the bench
    received (fused poses, approaches) is of all agents together."""
    drive = make_drive(duration_s, n_rsu, fix_hz, latency_ms, jitter_ms, seed)
    vehicle = Vehicle.load(VEHICLE)
    bus = vehicle.id
    tags = tuple(vehicle.tag_ids[:2])
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    session = open_session(mode="peer", listen=[endpoint], multicast_scouting=False)
    got = _Received()
    subs = [subscribe_messages(session, keys.fused_pose(bus), FusedPose, got.on_fused),
            subscribe_messages(session, keys.rsu_diagnosis(INTERSECTION, keys.ANY, bus), RsuDiagnosis, got.on_diagnosis),
            subscribe_messages(session, keys.approach(INTERSECTION, bus), Approach, got.on_approach)]
    imu_pub = imu_publisher(session, bus, imu_per_message)
    imu_batch: list[Imu] = []
    gnss_pub = MessagePublisher(session, keys.gnss(bus), GnssFix)
    fix_pubs: dict[str, MessagePublisher] = {}
    tmp = None if logs else tempfile.TemporaryDirectory(prefix="toptag-bench-bus-")
    group = ProcessGroup(Path(logs or tmp.name))
    agents = []
    for i, source in enumerate([agent_source, *(also or [])]):
        env, python = dict(os.environ), TOPTAG
        if source:  # -P: not the working directory's toptag either
            python = [TOPTAG[0], "-P", *TOPTAG[1:]]
            env["PYTHONPATH"] = os.pathsep.join([str(Path(source).resolve())]
                                                + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        group.env = env
        agents.append(group.start("bus" if i == 0 else f"bus-also-{i}",
                                  python + ["bus", "--vehicle", str(VEHICLE), "--map", str(MAP), "--zenoh-mode",
                                            "peer", "--connect", endpoint, "--no-multicast-scouting"]))
    agent = agents[0]
    try:
        # Session entry: GNSS at the drive's start until the agent announces itself (and subscribes to fixes).
        first_gnss = next(e[2] for e in drive.events if e[1] == "gnss")
        deadline = time.monotonic() + 60.0
        while got.entered < len(agents):  # (each agent's first Approach)
            dead = [a for a in agents if not a.alive()]
            if time.monotonic() > deadline or dead:
                raise RuntimeError(f"the bus agent did not announce itself: {(dead or agents)[0].log_tail()}")
            gnss_pub.put(GnssFix(bus_id=bus, t_ns=time.time_ns(), x=first_gnss[1], y=first_gnss[2],
                                 sigma_m=GNSS_SIGMA_M))
            with got.lock:
                got.changed.wait(0.2)
        time.sleep(0.5)  # its fix subscription's route reaches this peer
        start_ns = time.time_ns() + ns_from_ms(20)
        late = []
        cpu0 = wall0 = None
        published = {"imu": 0, "fix": 0, "gnss": 0}
        for off, kind, item in drive.events:
            due = start_ns + off
            wait = (due - time.time_ns()) / NS_PER_S
            if wait > 0:
                time.sleep(wait)
            else:
                late.append(-wait)
            if cpu0 is None:
                cpu0, wall0 = [cpu_seconds(a.pid) for a in agents], time.monotonic()
                got.counting = True
            if kind == "imu":
                t, g, ax, ay, w = item
                sample = Imu(bus_id=bus, t_ns=start_ns + t, gyro_z=g, accel_x=ax, accel_y=ay, wheel_speed=w,
                             seq=published["imu"])
                if imu_per_message == 1:
                    imu_pub.put(sample)
                else:
                    imu_batch.append(sample)
                    if len(imu_batch) == imu_per_message:
                        imu_pub.put(ImuBatch(bus_id=bus, samples=imu_batch, seq=published["imu"] // imu_per_message))
                        imu_batch = []
            elif kind == "gnss":
                t, x, y = item
                gnss_pub.put(GnssFix(bus_id=bus, t_ns=start_ns + t, x=x, y=y, sigma_m=GNSS_SIGMA_M))
            else:
                f = dataclasses.replace(item, t_ns=start_ns + item.t_ns, z=BUS_ROOF_Z, method="h_opt", tags=tags,
                                        rms_px=0.4)
                pub = fix_pubs.get(f.source)
                if pub is None:
                    pub = fix_pubs[f.source] = MessagePublisher(session, keys.pose_fix(INTERSECTION, bus, f.source),
                                                                PoseFix)
                clock = None if f.clock_bound_ns is None else ClockInfo(source="sim", sync_uncertainty_ns=f.clock_bound_ns)
                pub.put(fix_to_message(f, bus, INTERSECTION, time.time_ns(), clock=clock))
            published[kind] += 1
        cpu1, wall1 = [cpu_seconds(a.pid) for a in agents], time.monotonic()
        got.counting = False
        time.sleep(0.3)
        if cpu0 is None or None in cpu0 + cpu1:
            raise RuntimeError(f"the bus agent exited during the drive: {agent.log_tail()}")
    finally:
        code = group.stop()
        for s in subs:
            s.close()
        for p in [imu_pub, gnss_pub, *fix_pubs.values()]:
            p.close()
        session.close()
        if tmp is not None:
            tmp.cleanup()
    window = wall1 - wall0
    cpus = [b - a for a, b in zip(cpu0, cpu1)]
    cpu = cpus[0]
    last = got.last_fused
    return {
        "agent_cpu_s": round(cpu, 3), "window_s": round(window, 3),
        "agent_cpu_fraction": round(cpu / window, 4) if window > 0 else None,
        "imu_hz": round(published["imu"] / window, 1), "imu_per_message": imu_per_message,
        "fixes_per_s": round(published["fix"] / window, 1),
        "published": published, "rsus": n_rsu, "fix_hz_per_rsu": fix_hz, "latency_ms": latency_ms,
        "jitter_ms": jitter_ms, "speed_mps": round(drive.speed_mps, 2),
        "late_sends_over_5ms": sum(x > 0.005 for x in late),
        "received": {"fused": got.fused, "fused_hz": round(got.fused / window, 1),
                     "fused_ok_fraction": round(got.fused_ok / got.fused, 4) if got.fused else None,
                     "diagnoses": got.diagnoses, "approaches": got.approaches,
                     "fixes_seen_by_agent": None if last is None else _fixes_in(last.health),
                     "fixes_accepted_by_agent": None if last is None else last.health.accepted_fixes},
        "agent_exit_code": code.get("bus"), "agent_source": str(Path(agent_source).resolve()) if agent_source else None,
        "also": [{"agent_source": str(Path(src).resolve()), "agent_cpu_s": round(c, 3),
                  "agent_cpu_fraction": round(c / window, 4) if window > 0 else None,
                  "agent_exit_code": code.get(f"bus-also-{i + 1}")} for i, (src, c) in enumerate(zip(also or [], cpus[1:]))],
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "machine": f"{cpu_model(unknown='unknown CPU')}, nproc {usable_cores()}",
    }


def table(r: dict) -> str:
    rec = r["received"]
    ok = rec["fused_ok_fraction"]
    return "\n".join([
        f"machine: {r['machine']}; load average {' '.join(map(str, r['load_average']))}",
        f"drive {r['window_s']:.1f} s at {r['speed_mps']} m/s: IMU {r['imu_hz']} Hz ({r['imu_per_message']} to a "
        f"message), fixes {r['fixes_per_s']}/s "
        f"({r['rsus']} RSUs x {r['fix_hz_per_rsu']:g} Hz, {r['latency_ms']:g} ± {r['jitter_ms']:g} ms after capture), "
        f"GNSS {r['published']['gnss']}; sends late by > 5 ms: {r['late_sends_over_5ms']}",
        f"agent: fused {rec['fused']} ({rec['fused_hz']} Hz, ok {'-' if ok is None else f'{100 * ok:.1f}'} %), "
        f"diagnoses {rec['diagnoses']}, approaches {rec['approaches']}; fixes its filter saw "
        f"{rec['fixes_seen_by_agent']} (accepted {rec['fixes_accepted_by_agent']})",
        f"bus agent process CPU: {r['agent_cpu_s']:.2f} s over {r['window_s']:.1f} s = "
        f"{100 * r['agent_cpu_fraction']:.2f} % of a core" + (f" ({r['agent_source']})" if r["agent_source"] else ""),
    ] + [f"beside it, on the same drive: {a['agent_cpu_s']:.2f} s = {100 * a['agent_cpu_fraction']:.2f} % of a core "
         f"({a['agent_source']})" for a in r["also"]])


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag bench bus", description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=30.0, help="seconds of drive (default 30)")
    p.add_argument("--rsus", type=int, default=4, choices=(1, 2, 3, 4), help="corner RSUs sending fixes (default 4)")
    p.add_argument("--fix-hz", type=float, default=10.0, help="fixes per second per RSU (default 10)")
    p.add_argument("--latency-ms", type=float, default=100.0, help="mean delay from capture to publish (default 100)")
    p.add_argument("--jitter-ms", type=float, default=30.0, help="its standard deviation (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--imu-per-message", type=int, default=4, metavar="N",
                   help=f"IMU samples to a message (ImuBatch), as the simulator's default scenario sends them "
                        f"(default 4; 1: each sample an Imu on its own key, as an agent before ImuBatch takes them; "
                        f"at most {IMU_BATCH_MAX})")
    p.add_argument("--agent-source", default=None, metavar="DIR",
                   help="run the agent from this checkout of toptag (e.g. an older worktree) to compare versions; an "
                        "agent older than ImuBatch (main 65ec073) reads only Imu: add --imu-per-message 1")
    p.add_argument("--also", action="append", default=None, metavar="DIR",
                   help="also run the agent of this checkout beside it on the same drive (repeatable): CPU of "
                        "each under the same load")
    p.add_argument("--logs", default=None, help="directory for the agent's log (default: a temp dir)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if not (a.duration > 0 and math.isfinite(a.duration)):
        print("toptag bench bus: --duration must be a positive number of seconds")
        return 2
    if not 1 <= a.imu_per_message <= IMU_BATCH_MAX:
        print(f"toptag bench bus: --imu-per-message must be 1 to {IMU_BATCH_MAX}, got {a.imu_per_message}")
        return 2
    r = run(a.duration, a.rsus, a.fix_hz, a.latency_ms, a.jitter_ms, a.seed, a.logs, a.agent_source, a.also,
            a.imu_per_message)
    print(json.dumps(r, indent=1) if a.json else "toptag bench bus:\n" + table(r))
    return 0 if r["agent_exit_code"] == 0 and all(a["agent_exit_code"] == 0 for a in r["also"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
