"""The common life of a toptag service process: logging, inputs (exit 2 on a bad file), the Zenoh
session (exit 1 if it cannot open), SIGINT/SIGTERM to stop, a clean close, exit 0."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
from collections.abc import Callable
from typing import Any, Protocol

from protocol.transport import (
    ZenohSetupError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)
from toptag.inputs import InputError

log = logging.getLogger("toptag")


class Service(Protocol):
    def run(self, duration: float | None) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


def add_service_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_zenoh_arguments(p)


def run_service(prog: str, args: argparse.Namespace, load: Callable[[], Any],
                build: Callable[[Any, Any], Service], describe: Callable[[Any], str]) -> int:
    """load() reads and checks the inputs; build(session, inputs) makes the service; describe(inputs)
    names it in the 'ready' and 'stopped' log lines."""
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    try:
        inputs = load()
    except (InputError, ValueError) as e:
        print(f"toptag {prog}: {e}", file=sys.stderr)
        return 2
    try:
        session = open_session(zenoh_config_from_args(args))
    except ZenohSetupError as e:
        print(f"toptag {prog}: {e}", file=sys.stderr)
        return 1
    service = build(session, inputs)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: service.stop())
    log.info("%s ready", describe(inputs))
    try:
        service.run(args.duration)
    finally:
        service.close()
        session.close()
        log.info("%s stopped", describe(inputs))
    return 0
