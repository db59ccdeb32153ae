"""The Rerun viewer's server: the `rerun` binary bundled in rerun-sdk (package rerun_cli), started with
--serve-web bound to one address (the SDK's serve functions bind every interface), a gRPC port the
view logs to and an HTTP port the browser opens; stopped by its own PID."""
from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import time
import urllib.parse
from pathlib import Path

from services.processes import free_port, stop_process
from toptag.errors import SetupError


class ViewerError(SetupError):
    """The viewer cannot be started. str(e) is one line."""


def rerun_binary() -> Path:
    try:
        import rerun  # noqa: F401  (the SDK the view logs with)
        import rerun_cli
    except ImportError:
        raise ViewerError("the live view needs rerun-sdk: pip install 'toptag[view]'") from None
    exe = Path(rerun_cli.__file__).parent / "rerun"
    if not exe.is_file():
        raise ViewerError(f"rerun-sdk is installed but its viewer binary {exe} is missing")
    return exe


def parse_bind(text: str) -> tuple[str, int]:
    """'127.0.0.1:9090' -> ('127.0.0.1', 9090); port 0 or none: a free port."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, "0"
    try:
        p = int(port)
        socket.inet_aton(host)
    except (ValueError, OSError):
        raise ViewerError(f"--bind {text!r} is not IPv4-ADDRESS:PORT, e.g. 127.0.0.1:9090") from None
    if not 0 <= p < 65536:
        raise ViewerError(f"--bind {text!r}: port out of range")
    return host, p


try:  # resolved here, in the parent: the child between fork and exec must not import (other threads' locks)
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):
    _PRCTL = None
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the view dies, even by SIGKILL (Linux)."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGTERM)


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


class RerunServer:
    """`rerun --serve-web`: a gRPC proxy (the view logs to it) and the web viewer (browsers open it)."""

    def __init__(self, host: str = "127.0.0.1", web_port: int = 0, grpc_port: int = 0, *,
                 memory_limit: str = "512MiB", log_path: str | os.PathLike | None = None):
        self.host = host
        self.web_port = web_port or free_port()
        self.grpc_port = grpc_port or free_port()
        self.memory_limit = memory_limit
        self.log_path = Path(log_path) if log_path else None
        self.proc: subprocess.Popen | None = None

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://{self.host}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """What a browser opens: the web viewer, told where the data comes from."""
        return f"http://{self.host}:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"

    def start(self, timeout: float = 20.0) -> None:
        argv = [str(rerun_binary()), "--serve-web", "--bind", self.host, "--port", str(self.grpc_port),
                "--web-viewer-port", str(self.web_port), "--server-memory-limit", self.memory_limit]
        env = {**os.environ, "RERUN_ANALYTICS": "0"}  # nothing leaves this machine
        out = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL
        try:
            self.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env=env, start_new_session=True, preexec_fn=_die_with_parent)
        finally:
            if out is not subprocess.DEVNULL:
                out.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise ViewerError(f"the rerun viewer exited with {self.proc.returncode} at start "
                                  f"(ports {self.grpc_port}, {self.web_port} taken?)")
            if _listening(self.host, self.grpc_port) and _listening(self.host, self.web_port):
                return
            time.sleep(0.05)
        self.stop()
        raise ViewerError(f"the rerun viewer did not listen on {self.host}:{self.grpc_port} and :{self.web_port} "
                          f"within {timeout:.0f} s")

    def stop(self) -> None:
        if self.proc is not None:
            stop_process(self.proc, grace_s=3.0)
