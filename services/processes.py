"""Child processes of a toptag run (demo, tests of the deployment): started in their own session with
their output in a log file, stopped by PID in a chosen order (SIGTERM, then SIGKILL after a grace)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

TOPTAG = [sys.executable, "-m", "toptag"]


def free_port() -> int:
    """A TCP port the OS just handed out on 127.0.0.1 (free at the time of the call)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_TICKS_PER_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds the running process `pid` has used so far (Linux /proc); None when
    it has exited or /proc is not there."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _TICKS_PER_S  # utime, stime (fields 14 and 15)


def parent_pids() -> dict[int, int]:
    """{pid: parent pid} of every process now running (Linux /proc)."""
    out = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat", "rb") as f:
                    out[int(d)] = int(f.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    return out


def tree_cpu_seconds(pid: int, parents: dict[int, int] | None = None) -> float | None:
    """cpu_seconds of `pid` and of its descendants running now (the simulator's render process is
    its child; parents: parent_pids(), when the caller has it already): None when `pid` has exited."""
    total = cpu_seconds(pid)
    if total is None:
        return None
    parents = parent_pids() if parents is None else parents
    tree, grew = {pid}, True
    while grew:
        new = {p for p, pp in parents.items() if pp in tree and p not in tree}
        tree |= new
        grew = bool(new)
    for p in tree - {pid}:
        total += cpu_seconds(p) or 0.0
    return total


def stop_process(popen: subprocess.Popen, sig: int = signal.SIGTERM, grace_s: float = 5.0) -> int | None:
    """Send `sig` to the process by its PID and wait; SIGKILL it if it outlives the grace. Its exit code."""
    if popen.poll() is None:
        try:
            os.kill(popen.pid, sig)
        except ProcessLookupError:
            pass
        try:
            popen.wait(grace_s)
        except subprocess.TimeoutExpired:
            os.kill(popen.pid, signal.SIGKILL)
            popen.wait(5.0)
    return popen.returncode


@dataclass
class Child:
    name: str
    argv: list[str]
    popen: subprocess.Popen
    log_path: Path

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, lines: int = 5) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class ProcessGroup:
    def __init__(self, log_dir: Path, env: dict | None = None):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.children: list[Child] = []

    def start(self, name: str, argv: list[str]) -> Child:
        log_path = self.log_dir / f"{name}.log"
        with open(log_path, "wb") as out:
            # Own session: a Ctrl-C at the terminal reaches only the parent, which stops children in order.
            p = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 env=self.env, start_new_session=True)
        child = Child(name, argv, p, log_path)
        self.children.append(child)
        return child

    def cpu_seconds(self) -> dict[str, float | None]:
        """CPU seconds used so far by each child and its own children (None for one that has exited)."""
        parents = parent_pids()  # one look at every process for all the children
        return {c.name: tree_cpu_seconds(c.pid, parents) for c in self.children}

    def dead(self) -> list[Child]:
        return [c for c in self.children if not c.alive()]

    def stop(self, children: list[Child] | None = None, grace_s: float = 5.0) -> dict[str, int | None]:
        """SIGTERM each (in the given order, waiting for each), SIGKILL what ignores it; exit codes."""
        codes: dict[str, int | None] = {}
        for c in list(children if children is not None else reversed(self.children)):
            codes[c.name] = stop_process(c.popen, grace_s=grace_s)
        return codes

    def wait_for_log(self, child: Child, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in child.log_path.read_text(errors="replace"):
                return True
            if not child.alive():
                return False
            time.sleep(0.05)
        return False
