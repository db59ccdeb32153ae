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
import sys
import threading
import time

import zenoh

from protocol.transport import config_summary, zenoh_config_from_args
from protocol.transport.runner import add_service_arguments, run_service
from toptag.errors import InputError, SetupError

DEFAULT_LISTEN = ("tcp/0.0.0.0:7447",)
DEFAULT_SECURE_LISTEN = ("tls/0.0.0.0:7447",)
ENV_SECURE = "TOPTAG_ZENOH_SECURE"
log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag router", description=__doc__.split("\n\n")[0])
    add_service_arguments(p, default_mode="router", duration=False)
    p.add_argument("--secure", "--tls-dir", dest="secure", default=None, metavar="CERT_DIR",
                   help=f"mutual TLS and access control from a `toptag certs` directory (env {ENV_SECURE})")
    return p


class Router:
    """The router's work is its session: it serves until stopped."""

    def __init__(self, session: zenoh.Session, conf: zenoh.Config):
        self._stop = threading.Event()
        log.info("router listening on %s (zid %s, %s)", ", ".join(_listen_endpoints(conf)) or "(nothing)",
                 session.zid(), config_summary(conf))

    def run(self, duration: float | None = None) -> None:
        t_end = None if duration is None else time.monotonic() + duration
        # Wake up twice a second: a signal that Zenoh's threads receive reaches the Python handler only
        # when the main thread runs, never while it blocks without a timeout.
        while not self._stop.wait(0.5) and (t_end is None or time.monotonic() < t_end):
            pass

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        pass


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    secure = args.secure or os.environ.get(ENV_SECURE) or None

    def load() -> zenoh.Config:
        if args.zenoh_mode not in (None, "router"):
            raise InputError(f"the router runs in zenoh mode 'router', not {args.zenoh_mode!r}")
        conf = zenoh_config_from_args(args, mode="router",
                                      default_listen=DEFAULT_SECURE_LISTEN if secure else DEFAULT_LISTEN)
        if secure:
            from services.security import SecurityError, secure_router_config
            try:
                certs = secure_router_config(conf, secure)
            except SecurityError as e:
                raise SetupError(f"--secure {secure}: {e}") from None
            log.info("mutual TLS with CA %s; access control for %d identities", certs.ca_cert,
                     len(certs.identities))
        zenoh.try_init_log_from_env()
        return conf

    return run_service("router", args, load, Router, lambda _conf: "router" + (" (secure)" if secure else ""),
                       zenoh_config=lambda _args, conf: conf)


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
