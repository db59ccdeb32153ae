"""`toptag bench latency`: capture-to-arrival latency of PoseFixes through a real router and RSU process.

The benchmark is the camera and the bus: it announces a bus, publishes rendered 960x720 frames at 10 Hz
stamped with their capture time, and receives the fixes like the bus does. Each fix carries the RSU's own
detection-and-solve time, so the transport and queueing overhead (latency minus that time) is measured
per frame."""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from protocol import keys
from protocol.messages import Approach, Frame, PoseFix
from protocol.transport import (
    MessagePublisher,
    declare_alive,
    open_session,
    publish,
    serve_session,
    subscribe_messages,
)
from services.processes import TOPTAG, ProcessGroup, free_port
from toptag.progress import Progress
from toptag.units import ms_from_ns


def _frames(camera, count: int, seed: int = 0):
    from sim.render import PlacedVehicle, render_jpeg
    from sim.scene import bundled_vehicle

    bus = bundled_vehicle("bus_double")
    rng = np.random.default_rng(seed)
    return [render_jpeg(camera, [PlacedVehicle(bus, -6.0 + 0.2 * i, -1.85, 0.0, 3.0, speed=2.0)], rng=rng)
            for i in range(count)]


def run(frames: int = 150, fps: float = 10.0, progress=print) -> dict:
    from sim.scenario import bundled_scenario_path
    from toptag.camera import Camera
    from toptag.vehicle import Vehicle

    site = bundled_scenario_path().parent
    camera = Camera.load(site / "rsu-sw.json")
    vehicle = Vehicle.load(site / "bus-17.json")
    progress(f"rendering {min(frames, 50)} frames ...")
    jpegs = _frames(camera, min(frames, 50))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    group = ProcessGroup(Path(tempfile.mkdtemp(prefix="toptag-bench-")))
    router = group.start("router", TOPTAG + ["router", "--listen", endpoint])
    try:
        if not group.wait_for_log(router, "router listening", 15):
            raise RuntimeError(f"router did not start: {router.log_tail()}")
        rsu = group.start("rsu", TOPTAG + ["rsu", "--camera", str(site / "rsu-sw.json"), "--intersection", "x1",
                                           "--zenoh-mode", "client", "--connect", endpoint])
        if not group.wait_for_log(rsu, "ready", 30):
            raise RuntimeError(f"RSU did not start: {rsu.log_tail()}")
        session = open_session(mode="client", connect=[endpoint])
        received: list[tuple[int, PoseFix]] = []
        lock = threading.Lock()

        def on_fix(m: PoseFix):
            t = time.time_ns()
            with lock:
                received.append((t, m))

        sub = subscribe_messages(session, keys.pose_fix("x1", vehicle.id, keys.ANY), PoseFix, on_fix)
        approach = Approach(bus_id=vehicle.id, intersection_id="x1", vehicle=vehicle.spec,
                            reference_time_ns=time.time_ns())
        queryable = serve_session(session, approach)
        token = declare_alive(session, "x1", vehicle.id)
        publish(session, keys.approach("x1", vehicle.id), approach)
        pub = MessagePublisher(session, keys.frame(camera.id), Frame)
        time.sleep(1.0)
        next_t = time.monotonic()
        bar = Progress(frames, f"publishing frames at {fps:g} Hz")
        for seq in range(frames):
            bar.update()
            t = time.time_ns()
            pub.put(Frame(rsu_id=camera.id, capture_time_ns=t, seq=seq, encoding="jpeg", width=camera.width,
                          height=camera.height, image=jpegs[seq % len(jpegs)]))
            next_t += 1.0 / fps
            time.sleep(max(0.0, next_t - time.monotonic()))
        bar.close()
        time.sleep(1.0)
        for h in (sub, pub):
            h.close()
        token.undeclare()
        queryable.undeclare()
        session.close()
    finally:
        group.stop()
    with lock:
        rows = [(arr - m.capture_time_ns, m.processing_ns or 0) for arr, m in received]
    lat = ms_from_ns(np.array([r[0] for r in rows]))
    proc = ms_from_ns(np.array([r[1] for r in rows]))
    over = lat - proc
    pct = lambda a, q: round(float(np.percentile(a, q)), 2) if a.size else None  # noqa: E731
    return {"frames_sent": frames, "fixes_received": len(rows), "fps": fps,
            "latency_ms_p50": pct(lat, 50), "latency_ms_p99": pct(lat, 99),
            "rsu_processing_ms_p50": pct(proc, 50), "rsu_processing_ms_p99": pct(proc, 99),
            "overhead_ms_p50": pct(over, 50), "overhead_ms_p99": pct(over, 99)}


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag bench latency", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--fps", type=float, default=10.0)
    args = p.parse_args(argv)
    result = run(args.frames, args.fps, progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(json.dumps(result, indent=1))
    return 0
