"""System test: the compose demo built and run for real on a Docker engine, plain and secured.

The engine is Debian's docker.io (installed by `make docker-engine` where missing; started here with its
default flags only when none answers, and stopped by its PID at the end). Compose is v2 when the docker
CLI has it, else Debian's v1 (1.29.2). The official base images are used when they can be pulled;
otherwise the stand-ins of tests/dockerhost.py, through CI-only override files in tests/compose/ (the
shipped docker/ files are run unchanged). One image is built, once, and every service runs it.

Each variant: `up`, wait for the monitor's report (it runs for DURATION s and writes it into a mounted
folder), assert fixes and fused accuracy for every bus, `stop`, check that every container exited with 0
and never restarted, `down -v`. The secured variant adds the one-shot `certs` service, mutual TLS and
access control at the router, and an impostor container (tests/compose/spoof.py) whose forged fixes must
never reach the bus. Skipped, with the reason, where Docker cannot run (not root, no engine, no kernel
support). Timings of every phase are printed in the terminal summary (docs/deployment.md quotes them).
"""
from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
from conftest import SUMMARY, assert_fused_claims_hold
from dockerhost import (
    STANDIN_PYTHON,
    DockerUnavailable,
    Engine,
    compose_command,
    compose_version,
    containers,
    image_size_mb,
    pullable,
    run,
    standin_python,
)

from services.processes import free_port

pytestmark = pytest.mark.system

REPO = Path(__file__).resolve().parents[1]
DOCKER, CI = REPO / "docker", REPO / "tests" / "compose"
IMAGE = "toptag:0.1.0"
BUSES = ("bus-17", "bus-42")
DURATION_S = 25  # the monitor's span from the first bus message: the bundled scenario's first legs, bus-42 in
#                 session 5.3-10.5 s, bus-17 9.0-17.6 s (the next ones from 32.5 s)
TIMINGS: dict[str, str] = {}
ENGINE: dict[str, str] = {}


@pytest.fixture(autouse=True)
def _timings_in_summary(request):
    """The timings so far, as a line of the terminal summary (user properties reach the summary from an
    xdist worker too; the last test's line holds them all)."""
    yield
    if TIMINGS:
        request.node.user_properties.append((f"{SUMMARY}:compose",
            f"compose system test (engine {ENGINE.get('engine')}, compose {ENGINE.get('compose')}): " +
            "; ".join(f"{k} {v}" for k, v in TIMINGS.items())))


def _timed(name: str, t0: float) -> float:
    dt = time.monotonic() - t0
    TIMINGS[name] = f"{dt:.1f} s"
    return dt


def _official_images() -> tuple[str, str]:
    """(the Dockerfile's base image, the compose router's image), as the shipped files name them."""
    dockerfile = (DOCKER / "Dockerfile").read_text()
    base = re.search(r"^ARG PYTHON_IMAGE=(\S+)", dockerfile, re.MULTILINE).group(1)
    router = re.search(r"^\s+image: (eclipse/zenoh:\S+)", (DOCKER / "compose.yaml").read_text(), re.MULTILINE).group(1)
    return base, router


@pytest.fixture(scope="module")
def docker_host(tmp_path_factory):
    """A running engine, the compose command, the override files for stand-ins, the image built once."""
    work = tmp_path_factory.mktemp("docker")
    engine = Engine(work)
    t0 = time.monotonic()
    try:
        engine.start()
        cmd = compose_command()
    except DockerUnavailable as e:
        engine.stop()
        pytest.skip(f"Docker cannot run here: {e}")
    host: dict = {}
    try:
        _timed("engine ready" + (" (dockerd started)" if engine.started_here else ""), t0)
        overrides: list[Path] = []
        base, router = _official_images()
        t0 = time.monotonic()
        if not pullable(base):
            standin_python(work)
            overrides.append(CI / "ci.standin-python.yaml")
        _timed(f"base image ({'stand-in ' + STANDIN_PYTHON if overrides else base})", t0)
        if not pullable(router):
            overrides.append(CI / "ci.standin-router.yaml")
        host.update({"cmd": cmd, "overrides": overrides, "work": work, "engine": engine.server_version,
                     "compose": compose_version(cmd)})
        ENGINE.update(engine=host["engine"], compose=host["compose"])
        t0 = time.monotonic()
        run([*cmd, *_project(host, "toptag-ci-build", run_files=False), "build"], timeout=1200)
        _timed("image build (compose build)", t0)
        TIMINGS["image size"] = f"{image_size_mb(IMAGE):.0f} MB"
        yield host
    finally:
        left = _leftover_containers() if engine.server_version else []
        if left:
            run(["docker", "rm", "-f", *left], check=False)
        engine.stop()


def _leftover_containers() -> list[str]:
    """Containers of this test's compose projects still present (there must be none after `down`)."""
    listed = run(["docker", "ps", "-a", "--format", '{{.ID}} {{.Label "com.docker.compose.project"}}'],
                 check=False).stdout.split("\n")
    return [ln.split()[0] for ln in listed if len(ln.split()) == 2 and ln.split()[1].startswith("toptag-ci-")]


def _project(host: dict, name: str, secure: bool = False, run_files: bool = True) -> list[str]:
    files = [DOCKER / "compose.yaml"] + ([DOCKER / "compose.secure.yaml"] if secure else [])
    files += host["overrides"] + ([CI / "ci.run.yaml"] if run_files else [])
    files += [CI / "ci.secure.yaml"] if secure else []
    return ["-p", name, *[a for f in files for a in ("-f", str(f))]]


def _run_demo(host: dict, name: str, secure: bool, tmp_path: Path, monkeypatch) -> dict:
    """up, wait for the monitor's report, stop, read every container's end, logs, down -v."""
    reports = tmp_path / "reports"
    reports.mkdir()
    monkeypatch.setenv("TOPTAG_CI_REPORTS", str(reports))
    monkeypatch.setenv("TOPTAG_CI_DURATION", str(DURATION_S))
    monkeypatch.setenv("TOPTAG_ROUTER_PUBLISH", f"127.0.0.1:{free_port()}")
    cmd, project = host["cmd"], _project(host, name, secure)
    report = reports / "monitor.json"
    out: dict = {"reports": reports}
    t0 = time.monotonic()
    try:
        run([*cmd, *project, "up", "-d", "--no-build"], timeout=600)
        t_up = _timed(f"{name}: up -d", t0)
        deadline = time.monotonic() + DURATION_S + 240  # generous: the machine may be loaded
        expected = [report] + ([reports / "spoof.json"] if secure else [])
        while not all(f.exists() for f in expected) and time.monotonic() < deadline:
            time.sleep(1.0)
        _timed(f"{name}: up to the reports", t0)
        t1 = time.monotonic()
        # SIGTERM, then SIGKILL after 60 s (a generous grace: a killed container fails the test, exit 137).
        run([*cmd, *project, "stop", "-t", "60"], timeout=600)
        _timed(f"{name}: stop", t1)
        out["containers"] = containers(cmd, project)
        out["logs"] = run([*cmd, *project, "logs", "--no-color"], timeout=120, check=False).stdout
        (tmp_path / "compose.log").write_text(out["logs"])
        assert report.exists(), f"no monitor report after {DURATION_S + 240} s ({t_up:.0f} s to start):\n" + \
            out["logs"][-3000:]
        out["report"] = json.loads(report.read_text())
    finally:
        t1 = time.monotonic()
        run([*cmd, *project, "down", "-v", "--remove-orphans"], timeout=300, check=False)
        _timed(f"{name}: down -v", t1)
    _timed(f"{name}: whole run", t0)
    return out


def _assert_localized(report: dict) -> None:
    """Every bus got fixes from several RSUs and was localized as well as in `toptag demo`. The counts are
    low bars (an overloaded machine renders and detects only a few frames per second: seen here, 13 fixes
    of bus-17 from 3 RSUs when three other demos shared the 2 cores); the accuracy bars are not lowered."""
    for bus in BUSES:
        b = report["buses"].get(bus)
        assert b is not None, f"{bus}: not in the monitor's report {sorted(report['buses'])}"
        rsus = [r for r, n in b["fixes_by_rsu"].items() if n >= 2]
        assert b["fixes_received"] >= 5 and len(rsus) >= 2, (bus, b["fixes_by_rsu"])
        assert b["fix_pos_rms_m"] is not None and b["fix_pos_rms_m"] < 0.10, (bus, b["fix_pos_rms_m"])
        assert b["fused_ok_samples"] >= 10, (bus, b["fused_ok_samples"])
        assert_fused_claims_hold(bus, b)


def _assert_clean_exit(states: list[dict], expected: set[str]) -> None:
    assert {s["service"] for s in states} == expected
    for s in states:
        assert not s["running"] and s["exit_code"] == 0 and s["restarts"] == 0 and not s["oom"], s


SERVICES = {"router", "sim", "rsu-sw", "rsu-se", "rsu-ne", "rsu-nw", "bus-17", "bus-42", "monitor"}


def test_compose_files_are_valid_for_the_compose_here(docker_host, monkeypatch):
    """`config` of every combination a user or CI runs (v1 validates against the compose schema and
    rejects v2-only keys such as a top-level `name`); one build for all, every toptag service on it."""
    monkeypatch.setenv("TOPTAG_CI_REPORTS", "/tmp")
    monkeypatch.setenv("TOPTAG_CI_DURATION", "1")
    for secure in (False, True):
        files = ["-f", str(DOCKER / "compose.yaml")] + (["-f", str(DOCKER / "compose.secure.yaml")] if secure else [])
        p = run([*docker_host["cmd"], "-p", "toptag", *files, "config"], timeout=60)
        assert "toptag:0.1.0" in p.stdout
        assert p.stdout.count("dockerfile: docker/Dockerfile") == 1, "one service builds the image"
        run([*docker_host["cmd"], *_project(docker_host, "toptag", secure), "config", "-q"], timeout=60)


def test_runtime_image_leaves_out_the_studies(docker_host):
    """The image runs every service, not the studies: matplotlib is not in it, and `toptag eval` says
    what to install instead of failing after minutes of work."""
    p = run(["docker", "run", "--rm", IMAGE, "eval", "fusion", "--out", "/tmp/fusion"], timeout=120, check=False)
    assert p.returncode == 1 and "pip install 'toptag[studies]'" in p.stderr, (p.returncode, p.stderr)
    p = run(["docker", "run", "--rm", "--entrypoint", "python", IMAGE, "-c", "import matplotlib"],
            timeout=120, check=False)
    assert p.returncode != 0 and "No module named 'matplotlib'" in p.stderr
    p = run(["docker", "run", "--rm", IMAGE, "rsu", "--help"], timeout=120)
    assert "--camera" in p.stdout


def test_image_carries_the_solvers_compiled_kernels(docker_host):
    """The image build compiled the solvers' numba kernels into their cache (docker/Dockerfile): a container
    loads every one of them and compiles none, so no RSU container spends seconds of CPU on it at its
    start."""
    p = run(["docker", "run", "--rm", "--entrypoint", "python", IMAGE, "-m", "toptag.solvers.warmup"], timeout=300)
    assert "(0 compiled, the rest from the cache)" in p.stdout, p.stdout


def test_plain_demo_runs_in_compose_and_stops_cleanly(docker_host, tmp_path, monkeypatch):
    res = _run_demo(docker_host, "toptag-ci-plain", False, tmp_path, monkeypatch)
    _assert_clean_exit(res["containers"], SERVICES)
    _assert_localized(res["report"])
    assert set(res["report"]["rsus"]) == {"rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"}
    assert res["report"]["rejected_messages"] == 0


def test_secured_demo_runs_in_compose_and_keeps_an_impostor_out(docker_host, tmp_path, monkeypatch):
    res = _run_demo(docker_host, "toptag-ci-secure", True, tmp_path, monkeypatch)
    _assert_clean_exit(res["containers"], SERVICES | {"certs", "spoofer"})
    _assert_localized(res["report"])  # every service on mutual TLS with its own identity, under the ACL
    logs = re.sub(r"\x1b\[[0-9;]*m", "", res["logs"])
    assert re.search(r"router.*access control is enabled", logs, re.IGNORECASE), "the router did not enable access control"
    spoof = json.loads((res["reports"] / "spoof.json").read_text())
    # The impostor holds rsu-se's valid certificate, was told the bus subscribes, and sent its forgeries...
    assert spoof["matching"] is True and spoof["published"] >= 50, spoof
    # ...which the router dropped: not one reached the bus's identity, while the real RSUs' fixes did.
    assert spoof["forged_received"] == 0, spoof
    assert sum(spoof["genuine_received_by_rsu"].values()) >= 5, spoof
    assert re.search(r"CertCommonName\(rsu:rsu-se\).*unauthorized to Put \(ingress\) on "
                     r"toptag/v1/fix/x1/bus-17/rsu-sw", logs), "no ingress denial logged for the impostor"
    # No forged fix reached the monitor either (it would count as a 1-10 m fix error of bus-17).
    assert res["report"]["buses"]["bus-17"]["fix_pos_max_m"] < 1.0


def test_nothing_is_left_behind(docker_host):
    """Runs last in this module: every container of the runs above is gone."""
    assert _leftover_containers() == []
