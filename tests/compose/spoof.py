"""The impostor of the secured compose test (tests/test_compose.py), run in its own container of the
toptag image: an RSU that holds a valid certificate (its own identity, TOPTAG_ZENOH_CONFIG) publishes
PoseFix for a bus under another RSU's name, while a probe session holding the bus's own identity
(--probe-config) records every fix the router lets through to that bus. Writes --out (JSON) and exits 0.

    python spoof.py --as-rsu rsu-sw --bus bus-17 --seconds 20 --probe-config /certs/bus.bus-17.json5 --out F
"""
from __future__ import annotations

import argparse
import json
import os
import threading
import time
from collections import Counter
from pathlib import Path

from protocol import PoseFix, keys
from protocol.transport import (
    MessagePublisher,
    ZenohSetupError,
    add_zenoh_arguments,
    open_session,
    split_endpoints,
    subscribe_messages,
    zenoh_config,
    zenoh_config_from_args,
)

FORGED_SEQ = 900_000_000  # frame_seq of every forged fix: no real RSU counts that far in a test


def open_retrying(make_config, seconds: float = 60.0):
    """A client session, retried while the router container starts (client mode fails at once)."""
    t_end = time.monotonic() + seconds
    while True:
        try:
            return open_session(make_config())
        except ZenohSetupError:
            if time.monotonic() > t_end:
                raise
            time.sleep(1.0)


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--as-rsu", required=True)
    p.add_argument("--bus", required=True)
    p.add_argument("--intersection", default="x1")
    p.add_argument("--seconds", type=float, default=25.0, help="how long to forge fixes")
    p.add_argument("--wait", type=float, default=240.0, help="longest wait for the bus's first genuine fix")
    p.add_argument("--probe-config", required=True)
    p.add_argument("--out", required=True)
    add_zenoh_arguments(p, default_mode="client")
    args = p.parse_args()

    lock = threading.Lock()
    seen: Counter = Counter()  # (rsu_id, forged?) -> fixes that reached the bus's identity

    def on_fix(m: PoseFix) -> None:
        with lock:
            seen[(m.rsu_id, m.frame_seq >= FORGED_SEQ)] += 1

    connect = split_endpoints(os.environ.get("TOPTAG_ZENOH_CONNECT", ""))  # the services' router endpoint
    probe = open_retrying(lambda: zenoh_config(mode="client", connect=connect or None, multicast_scouting=None,
                                               config_file=args.probe_config))
    sub = subscribe_messages(probe, keys.pose_fix(args.intersection, args.bus, keys.ANY), PoseFix, on_fix)
    spoofer = open_retrying(lambda: zenoh_config_from_args(args))
    pub = MessagePublisher(spoofer, keys.pose_fix(args.intersection, args.bus, args.as_rsu), PoseFix)
    matching = pub.wait_matching(10.0)  # the router told it that the bus subscribes
    # Forge while the bus is being served: from the first genuine fix the probe sees (the simulator may
    # start long after this container on a loaded machine), for --seconds.
    t_wait = time.monotonic() + args.wait
    while time.monotonic() < t_wait:
        with lock:
            if any(not forged for (_, forged) in seen):
                break
        time.sleep(0.1)
    t_end, i = time.monotonic() + args.seconds, 0
    while time.monotonic() < t_end:
        t = time.time_ns()
        pub.put(PoseFix(bus_id=args.bus, rsu_id=args.as_rsu, intersection_id=args.intersection,
                        capture_time_ns=t, publish_time_ns=t, x=5.0, y=-3.0, z=3.0, yaw=0.0,
                        covariance=[[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-5]], method="forged", tags_used=[3],
                        reprojection_rms_px=0.2, frame_seq=FORGED_SEQ + i))
        i += 1
        time.sleep(0.1)
    time.sleep(1.0)  # anything still in flight
    sub.close()
    with lock:
        result = {"published": pub.published, "matching": bool(matching),
                  "forged_received": sum(n for (_, forged), n in seen.items() if forged),
                  "genuine_received_by_rsu": {rsu: n for (rsu, forged), n in sorted(seen.items()) if not forged}}
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps(result), flush=True)
    spoofer.close()
    probe.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
