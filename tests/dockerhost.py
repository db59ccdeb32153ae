"""A Docker host for the compose system tests (tests/test_compose.py): the engine, compose, base images.

- Engine: whatever answers `docker info`; if nothing does, `dockerd` with its default flags, started here
  and stopped by its PID at the end. The engine and compose themselves are Debian's docker.io and
  docker-compose, installed by `make docker-engine` (tests/compose/install-docker.sh) where missing.
- Compose: v2 (`docker compose`) when the CLI has the plugin, else v1 (`docker-compose`, Debian's 1.29.2).
  Always with `-p NAME` (v1 rejects a top-level `name`).
- Base images: the official ones (docker/Dockerfile's `python:3.11-slim`, compose.yaml's router image)
  when they can be pulled; otherwise stand-ins, named in tests/compose/ci.standin.yaml (a CI-only
  override: the shipped files stay as they are). The Python stand-in is Debian bookworm (Python 3.11, as
  the official image) from `debootstrap --variant=minbase`, with a venv first on PATH, imported with
  `docker import`; pip in it trusts the host's certificate authorities (/etc/ssl/certs), as the host's
  pip does. The router stand-in is the toptag image itself (zenohd's `-c FILE` run as `toptag router
  --zenoh-config FILE`).

Every function raises DockerUnavailable (one line) when Docker cannot run here; the tests skip with it.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

STANDIN_PYTHON = "toptag-ci/python:3.11-bookworm"
STANDIN_PATH = "/opt/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
HOST_CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")


class DockerUnavailable(RuntimeError):
    """Docker cannot run on this machine; str(e) says why in one line."""


def run(argv: list[str], timeout: float = 600, check: bool = True, **kw) -> subprocess.CompletedProcess:
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, check=False, **kw)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{' '.join(argv[:4])} ...: no answer in {timeout:.0f} s") from None
    if check and p.returncode != 0:
        tail = "\n".join((p.stderr or p.stdout).strip().splitlines()[-15:])
        raise AssertionError(f"{' '.join(argv)}: exit {p.returncode}\n{tail}")
    return p


def _answers() -> bool:
    try:
        return subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True,
                              timeout=20, check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


class Engine:
    """The Docker engine for one test session: an answering one, or `dockerd` started (and stopped) here."""

    def __init__(self, log_dir: Path):
        self.log_path = Path(log_dir) / "dockerd.log"
        self.proc: subprocess.Popen | None = None
        self.server_version = ""

    def start(self, timeout: float = 90) -> Engine:
        if os.geteuid() != 0:
            raise DockerUnavailable("the Docker engine needs root here (no rootless setup)")
        if shutil.which("docker") is None:
            raise DockerUnavailable("no docker command: `make docker-engine` installs Debian's docker.io")
        if not _answers():
            if shutil.which("dockerd") is None:
                raise DockerUnavailable("no Docker engine answers and dockerd is not installed "
                                        "(`make docker-engine` installs Debian's docker.io)")
            with open(self.log_path, "wb") as log:
                self.proc = subprocess.Popen(["dockerd"], stdout=log, stderr=subprocess.STDOUT,
                                             stdin=subprocess.DEVNULL, start_new_session=True)
            t_end = time.monotonic() + timeout
            while not _answers():
                if self.proc.poll() is not None or time.monotonic() > t_end:
                    reason = self._failure()
                    self.stop()
                    raise DockerUnavailable(f"dockerd did not start: {reason}")
                time.sleep(0.5)
        self.server_version = run(["docker", "info", "--format", "{{.ServerVersion}}"]).stdout.strip()
        return self

    def _failure(self) -> str:
        lines = [ln for ln in self.log_path.read_text(errors="replace").splitlines()
                 if "level=fatal" in ln or "level=error" in ln]
        return (lines[-1][:300] if lines else "no answer") + f" (log {self.log_path})"

    @property
    def started_here(self) -> bool:
        return self.proc is not None

    def stop(self) -> int | None:
        """Stop the dockerd started here, by PID (SIGTERM; it stops its containers and containerd)."""
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        os.kill(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        return self.proc.returncode


def compose_command() -> list[str]:
    """`docker compose` (v2) if the CLI has it, else `docker-compose` (v1)."""
    if subprocess.run(["docker", "compose", "version"], capture_output=True, check=False).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise DockerUnavailable("neither `docker compose` nor `docker-compose` (`make docker-engine` installs "
                            "Debian's docker-compose)")


def compose_version(cmd: list[str]) -> str:
    return run([*cmd, "version", "--short"]).stdout.strip()


def image_exists(ref: str) -> bool:
    return run(["docker", "image", "inspect", ref], check=False).returncode == 0


def pullable(ref: str, timeout: float = 300) -> bool:
    """True when the image is here or `docker pull` gets it (no registry: False, quickly)."""
    return image_exists(ref) or run(["docker", "pull", "-q", ref], timeout=timeout, check=False).returncode == 0


def image_size_mb(ref: str) -> float:
    return int(run(["docker", "image", "inspect", "--format", "{{.Size}}", ref]).stdout) / 1e6


def standin_python(work: Path, log=print) -> str:
    """The Python stand-in base image (built once per Docker host; kept): Debian bookworm minbase with
    python3-venv, a venv at /opt/python first on PATH, the host's CA bundle and a pip.conf naming it."""
    if image_exists(STANDIN_PYTHON):
        return STANDIN_PYTHON
    if shutil.which("debootstrap") is None:
        raise DockerUnavailable("no base image can be pulled and debootstrap is not installed "
                                "(`make docker-engine` installs it)")
    root = Path(tempfile.mkdtemp(prefix="toptag-standin-", dir=work))
    try:
        t0 = time.monotonic()
        run(["debootstrap", "--variant=minbase", "--include=python3-venv,ca-certificates", "bookworm", str(root)],
            timeout=900)
        log(f"stand-in: debootstrap {time.monotonic() - t0:.0f} s")
        run(["chroot", str(root), "python3", "-m", "venv", "/opt/python"], timeout=300)
        if HOST_CA_BUNDLE.is_file():  # pip in the image trusts what the host's pip trusts
            shutil.copyfile(HOST_CA_BUNDLE, root / "etc/ssl/certs/ca-certificates.crt")
        (root / "etc/pip.conf").write_text("[global]\ncert = /etc/ssl/certs/ca-certificates.crt\ntimeout = 180\n")
        for d in ("var/cache/apt/archives", "var/lib/apt/lists"):
            for f in (root / d).glob("*"):
                if f.is_file():
                    f.unlink()
        tar = subprocess.Popen(["tar", "-C", str(root), "-c", "."], stdout=subprocess.PIPE)
        imp = subprocess.run(["docker", "import", "--change", f"ENV PATH={STANDIN_PATH}", "--change",
                              "ENV LANG=C.UTF-8", "--change", 'CMD ["python3"]', "-", STANDIN_PYTHON],
                             stdin=tar.stdout, capture_output=True, text=True, timeout=600, check=False)
        tar.stdout.close()
        tar.wait()
        if imp.returncode != 0:
            raise AssertionError(f"docker import: {imp.stderr.strip()}")
        log(f"stand-in: {STANDIN_PYTHON} in {time.monotonic() - t0:.0f} s, {image_size_mb(STANDIN_PYTHON):.0f} MB")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return STANDIN_PYTHON


def containers(cmd: list[str], project: list[str]) -> list[dict]:
    """State of every container of a compose project (running or exited): name, service, exit code,
    restarts, OOM."""
    ids = run([*cmd, *project, "ps", "-q"]).stdout.split()
    ids += run([*cmd, *project, "ps", "-q", "--all"] if cmd[0] == "docker" else [*cmd, *project, "ps", "-a", "-q"],
               check=False).stdout.split()
    out = []
    for cid in dict.fromkeys(ids):
        info = json.loads(run(["docker", "inspect", cid]).stdout)[0]
        out.append({"name": info["Name"].lstrip("/"),
                    "service": info["Config"]["Labels"].get("com.docker.compose.service"),
                    "running": info["State"]["Running"], "exit_code": info["State"]["ExitCode"],
                    "restarts": info["RestartCount"], "oom": info["State"]["OOMKilled"]})
    return out
