"""toptag's errors: one base class, one exit code per kind, decided here and nowhere else.

str(e) of every ToptagError is one line naming what is wrong; the CLI and the service runner print it
as ``toptag <command>: <message>`` and exit with `exit_code(e)`."""
from __future__ import annotations

import sys

EXIT_OK = 0
EXIT_FAILURE = 1  # the command could not do its work (network, environment, a bug)
EXIT_USAGE = 2  # what the user gave is unusable: a file, an image, an argument, a message


class ToptagError(Exception):
    """Base of every error toptag raises on purpose."""

    exit_code = EXIT_FAILURE


class InputError(ToptagError, ValueError):
    """A user-supplied file, image, setting or argument is unusable."""

    exit_code = EXIT_USAGE


class SetupError(ToptagError, RuntimeError):
    """The environment cannot support the command: a Zenoh session cannot open, a port is taken."""

    exit_code = EXIT_FAILURE


class ProtocolError(ToptagError, ValueError):
    """A payload, id or key is not valid on the wire. ``reason`` is a short code for counters."""

    exit_code = EXIT_USAGE

    def __init__(self, message: str, reason: str = "invalid", msg_type: str = ""):
        super().__init__(message)
        self.reason = reason
        self.msg_type = msg_type


def exit_code(e: BaseException) -> int:
    """The process exit code for an error that ends a command."""
    if isinstance(e, ToptagError):
        return e.exit_code
    if isinstance(e, KeyboardInterrupt):
        return 130
    return EXIT_FAILURE


def report(prog: str, e: BaseException) -> int:
    """Print a command's one-line error as ``toptag <prog>: <message>`` on stderr; its exit code."""
    print(f"toptag {prog}: {e}", file=sys.stderr, flush=True)
    return exit_code(e)
