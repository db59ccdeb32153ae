"""`toptag router`: a Zenoh router for an intersection's RSUs and buses.

    python -m services.router [--listen tcp/0.0.0.0:7447] [--connect ENDPOINT] [--zenoh-config FILE]
                              [--secure CERT_DIR]

Listens on tcp/0.0.0.0:7447 unless --listen, TOPTAG_ZENOH_LISTEN or the config file say otherwise;
multicast scouting is off unless asked for. With --secure DIR (env TOPTAG_ZENOH_SECURE), a directory
written by `toptag certs`, it listens on tls/0.0.0.0:7447 only, requires client certificates from that
CA and enforces the access control of services/security.py (docs/security.md). RUST_LOG (e.g.
zenoh::net::routing::interceptor::access_control=trace) turns on zenoh's own logs. Logs "router listening on ..." once the session is open and
runs until SIGINT or SIGTERM, then closes the session and exits 0 (1 if the router cannot start).
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

import zenoh

from protocol.transport import (
    ZenohSetupError,
    add_zenoh_arguments,
    config_summary,
    open_session,
    zenoh_config_from_args,
)

DEFAULT_LISTEN = ("tcp/0.0.0.0:7447",)
DEFAULT_SECURE_LISTEN = ("tls/0.0.0.0:7447",)
ENV_SECURE = "TOPTAG_ZENOH_SECURE"
log = logging.getLogger("toptag.router")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag router", description=__doc__.split("\n\n")[0])
    add_zenoh_arguments(p, default_mode="router")
    p.add_argument("--secure", "--tls-dir", dest="secure", default=None, metavar="CERT_DIR",
                   help=f"mutual TLS and access control from a `toptag certs` directory (env {ENV_SECURE})")
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
    secure = args.secure or os.environ.get(ENV_SECURE) or None
    try:
        try:
            conf = zenoh_config_from_args(args, mode="router",
                                          default_listen=DEFAULT_SECURE_LISTEN if secure else DEFAULT_LISTEN)
            if secure:
                from services.security import SecurityError, secure_router_config
                try:
                    certs = secure_router_config(conf, secure)
                except SecurityError as e:
                    raise ZenohSetupError(f"--secure {secure}: {e}") from None
                log.info("mutual TLS with CA %s; access control for %d identities", certs.ca_cert,
                         len(certs.identities))
            zenoh.try_init_log_from_env()
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
