"""The life of every toptag service process, in one place: logging, inputs, the Zenoh session,
SIGINT/SIGTERM, a clean close, and the exit code.

    run_service(prog, args, load, build, describe)

- the settings file (--config FILE, TOML or YAML) is read into the service's ``settings`` model (a
  ServiceSettings: a [zenoh] table and the service's own) as ``args.settings``; its [zenoh] table fills
  the Zenoh options the command line left unset;
- load() reads and checks the inputs (a bad file raises toptag.errors.InputError: one line, exit 2);
- the session opens from the Zenoh options (SetupError: one line, exit 1);
- build(session, inputs) makes the service; what start-up made is then left out of the garbage
  collector's full collections (`freeze_start_up`); SIGINT/SIGTERM call its stop(); run(duration) runs
  it; close() and the session's close follow, whatever happened; exit 0.
Exit codes come from toptag.errors.exit_code: the same mapping as the CLI's. Here, at the protocol
layer, so that the simulator (sim) and the services (services) share it."""
from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol, TypeVar

import zenoh
from pydantic import BaseModel, ConfigDict

from protocol.transport.config import (
    ZenohSettings,
    add_zenoh_arguments,
    apply_zenoh_settings,
    config_summary,
    open_session,
    zenoh_config_from_args,
)
from toptag.errors import EXIT_FAILURE, EXIT_OK, InputError, ToptagError, report
from toptag.settings import load_settings

log = logging.getLogger(__name__)

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class ServiceSettings(BaseModel):
    """A service's settings file: its [zenoh] table; services add their own tables."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    zenoh: ZenohSettings = ZenohSettings()


S = TypeVar("S", bound=ServiceSettings)


def load_service_settings(args: argparse.Namespace, model: type[S] = ServiceSettings) -> S:
    """``model`` from --config FILE (defaults without one); its [zenoh] table fills the unset options."""
    path = getattr(args, "config", None)
    if path is None:
        return model()
    settings = load_settings(path, model)
    apply_zenoh_settings(args, settings.zenoh, Path(path).parent)
    return settings


class Service(Protocol):
    """run() works until stop() or ``duration`` s and must not block for long without a timeout: the
    signal handlers run in the main thread, and a signal delivered to one of Zenoh's threads reaches them
    only when the main thread wakes up."""

    def run(self, duration: float | None) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


def add_service_arguments(p: argparse.ArgumentParser, *, default_mode: str = "peer", duration: bool = True) -> None:
    """--config, --duration, --log-level and the Zenoh options of add_zenoh_arguments."""
    p.add_argument("--config", default=None, metavar="FILE",
                   help="settings file (TOML, or YAML with the yaml extra): a [zenoh] table and the service's "
                        "own; options given here override it")
    if duration:
        p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_zenoh_arguments(p, default_mode=default_mode)


def setup_logging(level: str) -> None:
    if not logging.getLogger().handlers:
        logging.basicConfig(level=level, format=LOG_FORMAT, stream=sys.stderr)
    else:
        logging.getLogger().setLevel(level)


def run_service(prog: str, args: argparse.Namespace, load: Callable[[], Any],
                build: Callable[[zenoh.Session, Any], Service], describe: Callable[[Any], str], *,
                settings: type[ServiceSettings] = ServiceSettings,
                zenoh_config: Callable[[argparse.Namespace, Any], zenoh.Config] | None = None,
                zenoh_runtime: str | None = None) -> int:
    """Run one service process (see the module docstring). ``zenoh_config(args, inputs)`` builds the
    session's config when the default (the service's Zenoh options) is not enough (the router);
    ``zenoh_runtime``: Zenoh's runtime threads for the process (open_session's ``runtime``)."""
    setup_logging(args.log_level)
    service: Service | None = None

    def stop_service(name: str) -> None:
        log.info("received %s, stopping", name)
        if service is not None:
            service.stop()

    with stop_signals(stop_service) as signals:
        try:
            args.settings = load_service_settings(args, settings)
            inputs = load()
            if signals:
                return EXIT_OK
            conf = zenoh_config(args, inputs) if zenoh_config else zenoh_config_from_args(args)
            session = open_session(conf, runtime=zenoh_runtime)
            log.info("zenoh session open (%s)", config_summary(conf))
        except ToptagError as e:
            return report(prog, e)
        except ValueError as e:  # a loader's own check (e.g. pydantic): the input is unusable
            return report(prog, InputError(str(e)))
        try:
            service = build(session, inputs)
            freeze_start_up()
            if signals:
                service.stop()
            log.info("%s ready", describe(inputs))
            try:
                service.run(getattr(args, "duration", None))
            finally:
                service.close()
        except ToptagError as e:
            return report(prog, e)
        except Exception as e:  # a bug: logged with its traceback, the process still closes cleanly
            log.exception("%s failed: %s", prog, e)
            return EXIT_FAILURE
        finally:
            session.close()
            log.info("%s stopped", describe(inputs))
        return EXIT_OK


def freeze_start_up() -> None:
    """Leave what start-up made (modules, numba's kernels, pydantic's models, Zenoh's objects, a service's
    caches: 10^5 objects and more) out of the garbage collector's full collections from now on. Each full
    collection otherwise scans them all holding the GIL: in the demo's RSUs once or twice a minute, a
    frame's processing stopped 0.1-1.8 s (docs/architecture.md, "The RSU's processing tail"). What the
    service makes as it runs is still collected."""
    gc.collect()
    gc.freeze()


@contextlib.contextmanager
def stop_signals(on_stop: Callable[[str], None]) -> Iterator[list[str]]:
    """While the block runs, SIGINT and SIGTERM call on_stop(signal name) from a new thread (handlers
    are only installed from the main thread); yields the names of the signals received so far."""
    received: list[str] = []  # a plain list: the handler takes no lock

    def on_signal(signum, _frame):
        # The handler interrupts the main thread anywhere, possibly inside the lock of the very Event
        # that on_stop sets: called from another thread, which waits for that lock, it never deadlocks.
        received.append(signal.Signals(signum).name)
        threading.Thread(target=on_stop, args=(received[-1],), name="stop", daemon=True).start()

    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
