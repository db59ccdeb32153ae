"""`toptag router`: a Zenoh router for an intersection's RSUs and buses.

    python -m services.router [--listen tcp/0.0.0.0:7447] [--connect ENDPOINT] [--zenoh-config FILE]

Listens on tcp/0.0.0.0:7447 unless --listen, TOPTAG_ZENOH_LISTEN or the config file say otherwise;
multicast scouting is off unless asked for. Logs "router listening on ..." once the session is open and
runs until SIGINT or SIGTERM, then closes the session and exits 0 (1 if the router cannot start).
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from services.common import (
    ZenohSetupError,
    add_zenoh_arguments,
    config_summary,
    open_session,
    zenoh_config_from_args,
)

DEFAULT_LISTEN = ("tcp/0.0.0.0:7447",)
log = logging.getLogger("toptag.router")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag router", description=__doc__.split("\n\n")[0])
    add_zenoh_arguments(p, default_mode="router")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not logging.getLogger().handlers:
        logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    else:
        logging.getLogger().setLevel(args.log_level)
    if args.zenoh_mode not in (None, "router"):
        log.error("the router runs in zenoh mode 'router', not %r", args.zenoh_mode)
        return 2

    stop = threading.Event()

    def on_signal(signum, _frame):
        log.info("received %s, stopping", signal.Signals(signum).name)
        stop.set()

    previous = {}
    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        try:
            conf = zenoh_config_from_args(args, mode="router", default_listen=DEFAULT_LISTEN)
            session = open_session(conf)
        except ZenohSetupError as e:
            log.error("%s", e)
            return 1
        try:
            log.info("router listening on %s (zid %s, %s)", ", ".join(_listen_endpoints(conf)) or "(nothing)",
                     session.zid(), config_summary(conf))
            while not stop.wait(0.5):
                pass
        finally:
            session.close()
            log.info("router stopped")
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _listen_endpoints(conf) -> list[str]:
    import json
    try:
        value = json.loads(conf.get_json("listen/endpoints"))
    except Exception:
        return []
    if isinstance(value, dict):
        value = value.get("router", [])
    return [str(v) for v in value or []]


if __name__ == "__main__":
    sys.exit(main())
