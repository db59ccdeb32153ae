"""The deployment: docker/compose.yaml and docker/Dockerfile checked without a Docker engine, and the same
topology run on separate (namespaced) hosts.

The compose files are read (YAML) with docker/topology.py and every service's command is checked with the
real parser of its toptag command, against the files the image would hold. Then test_separate_hosts_*
runs exactly those commands and environments without Docker: every service in its own Linux network
namespace, joined to the others only through a bridge and the Zenoh router, and cuts one RSU's link
mid-run (root only; skipped otherwise). The image built and the compose files run on a real engine:
tests/test_compose.py.
"""
from __future__ import annotations

import bisect
import importlib
import importlib.util
import itertools
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_fused_claims_hold

pytestmark = pytest.mark.system

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
SERVICES = {"router", "sim", "rsu-sw", "rsu-se", "rsu-ne", "rsu-nw", "bus-17", "bus-42", "monitor"}


def _load_topology():
    spec = importlib.util.spec_from_file_location("toptag_docker_topology", DOCKER / "topology.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


topology = _load_topology()


def _toptag_command(argv: list[str]):
    """(module, the rest of argv) of a toptag command line, as toptag.cli dispatches it."""
    from toptag.cli import COMMANDS

    for n in (2, 1):
        words = tuple(argv[:n])
        if words in COMMANDS:
            module = importlib.import_module(COMMANDS[words][0].split(":")[0])
            return module, argv[n:]
    raise AssertionError(f"{argv[:2]} is not a toptag command")


@pytest.fixture(scope="module")
def compose():
    return {s.name: s for s in topology.services()}


@pytest.fixture(scope="module")
def layout():
    return topology.image_layout()


# ---- the compose file and the image, statically -------------------------------------------------

def test_compose_file_is_yaml_with_the_demo_services_on_one_image(compose):
    import yaml

    data = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    assert "name" not in data, "compose v1 (Debian's docker-compose 1.29) rejects a top-level name: use -p"
    assert set(compose) == SERVICES
    toptag = [s for s in compose.values() if s.is_toptag]
    assert {s.name for s in toptag} == SERVICES - {"router"}
    builders = [s for s in compose.values() if s.build is not None]
    # One image, built once from docker/Dockerfile with the repository as context, run by every service.
    assert len(builders) == 1 and builders[0].build == {"context": "..", "dockerfile": "docker/Dockerfile"}
    assert (DOCKER / builders[0].build["context"] / builders[0].build["dockerfile"]).resolve() == topology.DOCKERFILE
    assert {s.image for s in toptag} == {builders[0].image}


def test_every_service_is_a_zenoh_client_of_the_router_without_multicast(compose):
    from protocol.transport import zenoh_config_from_args

    for s in compose.values():
        if not s.is_toptag:
            continue
        assert s.env["TOPTAG_ZENOH_MODE"] == "client", s.name
        assert s.env["TOPTAG_ZENOH_CONNECT"] == "tcp/router:7447", s.name
        assert s.env["TOPTAG_ZENOH_MULTICAST"] == "0", s.name
        module, rest = _toptag_command(s.command)
        args = module.build_parser().parse_args(rest)
        conf = zenoh_config_from_args(args, environ=s.env)  # what the service does at start
        assert json.loads(conf.get_json("mode")) == "client", s.name
        assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/router:7447"], s.name
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False, s.name


def test_router_is_the_official_image_with_the_config_from_docker_dir(compose):
    import zenoh

    from protocol.transport import zenoh_config_from_args
    from services.router import build_parser

    r = compose["router"]
    m = re.fullmatch(r"eclipse/zenoh:(\d+)\.(\d+)\.(\d+)", r.image)
    assert m, f"pin an eclipse/zenoh release, not {r.image}"
    from importlib.metadata import version
    assert m.group(1, 2) == tuple(version("eclipse-zenoh").split(".")[:2]), "router and clients: same zenoh"
    assert r.command[0] in ("-c", "--config")
    conf_file = topology.host_path(r.command[1], r)
    assert conf_file == DOCKER / "zenoh-router.json5" and conf_file.is_file()
    conf = zenoh.Config.from_file(str(conf_file))  # zenoh's own JSON5 parser, as zenohd reads it
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    from protocol.transport.config import FIX_QUEUE_BATCHES, FIX_QUEUE_PATH
    assert json.loads(conf.get_json(FIX_QUEUE_PATH)) == FIX_QUEUE_BATCHES  # zenohd keeps fixes as toptag's processes do
    spec = topology.load_compose()["services"]["router"]
    # published on this host's loopback only unless TOPTAG_ROUTER_PUBLISH says otherwise
    assert spec["ports"] == ["${TOPTAG_ROUTER_PUBLISH:-127.0.0.1:7447}:7447"]
    # toptag router takes the same file (the bare-host router of the netns test)
    argv = topology.bare_argv(r)
    assert argv == ["router", "--zenoh-config", str(conf_file)]
    bare = zenoh_config_from_args(build_parser().parse_args(argv[1:]), mode="router", environ={})
    assert json.loads(bare.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    assert json.loads(bare.get_json("scouting/multicast/enabled")) is False


def test_every_command_parses_and_names_files_the_image_holds(compose, layout):
    """Each toptag service's command, parsed by its own command's parser; every path it names exists
    in the image (the repository file the Dockerfile copies there) and loads as what it is."""
    from sim.scenario import load_scenario
    from toptag.camera import Camera
    from toptag.site import MapFile
    from toptag.vehicle import Vehicle

    assert layout == {"/site/": REPO / "toptag" / "data" / "demo"}
    rsus, buses, sims = {}, {}, []
    for s in compose.values():
        if not s.is_toptag:
            continue
        paths = topology.container_paths(s.command)
        for p in paths:
            assert p.startswith("/site/"), f"{s.name}: {p} is not in the image's site directory"
            assert topology.host_path(p, s, layout).is_file(), f"{s.name}: {p} is not in the image"
        argv = topology.bare_argv(s, layout)
        module, rest = _toptag_command(argv)
        args = module.build_parser().parse_args(rest)  # SystemExit(2) on a bad command line
        if argv[0] == "rsu":
            cam = Camera.load(args.camera)
            assert cam.id == s.name, "the RSU id is its camera file's id and the service's name"
            rsus[cam.id] = args.intersection
        elif argv[0] == "bus":
            veh = Vehicle.load(args.vehicle)
            assert veh.id == s.name
            buses[veh.id] = MapFile.load(args.map)
        elif argv[:2] == ["sim", "run"]:
            sims.append(load_scenario(args.scenario))
        else:
            assert argv[0] == "monitor", s.name
    assert len(sims) == 1
    sc = sims[0]
    # One RSU service per camera of the scenario, one agent per bus, at the scenario's intersection.
    assert set(rsus) == {Camera.load(p).id for p in sc.camera_paths()}
    assert set(rsus.values()) == {sc.intersection_id}
    assert set(buses) == {Vehicle.load(p).id for p in sc.vehicle_paths()}
    for m in buses.values():
        assert m.get(sc.intersection_id)


def _dockerfile_instructions(text: str) -> list[str]:
    """The Dockerfile's instructions, one a line: continuation lines joined as Docker joins them, comments out."""
    lines, pending = [], ""
    for raw in text.splitlines():
        ln = raw.strip()
        if not pending and (not ln or ln.startswith("#")):
            continue
        if ln.endswith("\\"):
            pending += ln[:-1]
            continue
        lines.append(pending + ln)
        pending = ""
    return lines


def test_dockerfile_installs_the_project_with_toptag_as_entry_point(tmp_path):
    import tomllib

    lines = _dockerfile_instructions(topology.DOCKERFILE.read_text())
    assert lines[:2] == ["ARG PYTHON_IMAGE=python:3.11-slim", "FROM ${PYTHON_IMAGE}"]  # official by default
    assert lines[-2] == 'ENTRYPOINT ["toptag"]'
    installs = [ln for ln in lines if ln.startswith("RUN") and "pip install" in ln]
    assert installs and all(" -e" not in ln and "--editable" not in ln for ln in installs)
    # everything `pip install .` needs is copied: pyproject.toml and every package it finds
    copies = [ln.split()[1].rstrip("/") for ln in lines if ln.startswith("COPY ")]
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]}
    assert {"pyproject.toml"} | packages <= set(copies)
    # The dependencies are installed before any source is copied (a change of the sources rebuilds only the
    # layers after it), and they are pyproject.toml's own, read from it by the build: no second list to keep.
    deps = next(i for i, ln in enumerate(lines) if ln.startswith("RUN") and "pip install -r requirements.txt" in ln)
    first_source = next(i for i, ln in enumerate(lines) if ln.startswith("COPY ") and ln.split()[1].rstrip("/") in packages)
    assert deps < first_source and [ln for ln in lines[:deps] if ln.startswith("COPY ")] == ["COPY pyproject.toml ./"]
    code = re.search(r"python -c '([^']*)' > requirements\.txt", lines[deps]).group(1)
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=30)
    assert p.stdout.splitlines() == pyproject["build-system"]["requires"] + pyproject["project"]["dependencies"]
    # then the project itself, with nothing more from PyPI (its build backend is among the dependencies above)
    assert any(re.match(r"RUN pip install --no-deps --no-build-isolation \.(\s|$)", ln) for ln in installs[1:])
    assert pyproject["project"]["scripts"]["toptag"] == "toptag.cli:main"
    # The root .dockerignore (both builders read it) is an allow-list: everything out, then exactly what
    # the Dockerfile copies back in; a .venv, .git, outputs or certificates never enter the context.
    patterns = [ln.strip() for ln in (REPO / ".dockerignore").read_text().splitlines()
                if ln.strip() and not ln.startswith("#")]
    assert patterns[0] == "*"
    assert {p[1:] for p in patterns if p.startswith("!")} == {"pyproject.toml"} | packages
    assert not (DOCKER / "Dockerfile.dockerignore").exists(), "one ignore file, at the root"


def test_topology_prints_bare_host_commands():
    p = subprocess.run([sys.executable, str(DOCKER / "topology.py"), "--router-host", "10.1.2.3"],
                       capture_output=True, text=True, timeout=30, check=False)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stdout.splitlines() if not ln.startswith("#")]
    assert len(lines) == len(SERVICES)
    assert all("TOPTAG_ZENOH_CONNECT=tcp/10.1.2.3:7447" in ln for ln in lines if "toptag router" not in ln)
    assert "toptag rsu --camera" in p.stdout and "toptag router --zenoh-config" in p.stdout


def test_secured_variant_names_the_files_toptag_certs_writes(tmp_path, compose):
    """docker/compose.secure.yaml (mutual TLS, access control): run its one-shot `certs` service's command,
    then every service's zenoh config (fragment + environment) builds and says who it is."""
    import zenoh

    from protocol.transport import zenoh_config_from_args

    if shutil.which("openssl") is None:
        pytest.skip("toptag certs needs the openssl command")
    secure = DOCKER / "compose.secure.yaml"
    merged = {s.name: s for s in topology.services(topology.COMPOSE, secure)}
    assert set(merged) == set(compose) | {"certs"}
    certs = merged.pop("certs")
    assert certs.is_toptag and certs.command[:3] == ["certs", "--out", "/certs"]
    assert certs.named_volumes == {"/certs": "certs"}  # the keys live in a volume, never on the host
    assert topology.load_compose(secure)["volumes"] == {"certs": {}}
    argv = list(certs.command)
    argv[argv.index("--out") + 1] = str(tmp_path / "certs")
    p = subprocess.run([sys.executable, "-m", "toptag", *argv], capture_output=True, text=True, timeout=60,
                       check=False)
    assert p.returncode == 0 and p.stdout == "", p.stderr  # --quiet
    roles = {"rsu": "rsu", "bus": "bus", "sim": "sim", "monitor": "monitor"}
    for s in merged.values():
        assert s.named_volumes == {"/certs": "certs"}, s.name
        assert topology.load_compose(secure)["services"][s.name]["volumes"] == ["certs:/certs:ro"], s.name
        s.volumes["/certs"] = tmp_path / "certs"  # where this test wrote them
        if not s.is_toptag:
            assert topology.load_compose(secure)["services"]["router"]["depends_on"] == \
                {"certs": {"condition": "service_completed_successfully"}}
            conf_file = topology.host_path(s.command[1], s)
            conf = zenoh.Config.from_file(str(conf_file))
            assert json.loads(conf.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]
            assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
            assert json.loads(conf.get_json("access_control/enabled")) is True
            continue
        assert s.command == compose[s.name].command  # only the zenoh settings change
        assert s.env["TOPTAG_ZENOH_CONNECT"] == "tls/router:7447"
        fragment = Path(s.env["TOPTAG_ZENOH_CONFIG"])
        assert fragment.name == f"{roles[s.command[0]]}.{s.name}.json5", "the identity is the service"
        env = topology.bare_env(s)
        assert Path(env["TOPTAG_ZENOH_CONFIG"]).is_file()
        module, rest = _toptag_command(s.command)
        conf = zenoh_config_from_args(module.build_parser().parse_args(rest), environ=env)
        assert json.loads(conf.get_json("mode")) == "client"
        assert json.loads(conf.get_json("connect/endpoints")) == ["tls/router:7447"]
        assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


# ---- separate hosts: network namespaces -----------------------------------------------------------

def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=False)
    if check and p.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {p.stderr.strip()}")
    return p


def _netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    probe = f"ttprobe{uuid.uuid4().hex[:6]}"
    p = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True, check=False)
    if p.returncode != 0:
        return f"cannot create a network namespace: {p.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True, check=False)
    return None


class NetnsLab:
    """Hosts as network namespaces on one bridge (itself in a namespace of its own, so nothing touches the
    machine's network). Each host: eth0 (a veth whose peer is a bridge port) with 10.<a>.<b>.<n>/24, lo,
    and /etc/netns/<ns>/hosts, which `ip netns exec` mounts over /etc/hosts (so `router` resolves as on
    the compose network). Names carry a per-run tag; close() removes all of it."""

    def __init__(self):
        self.tag = f"tt{uuid.uuid4().hex[:6]}"
        self.subnet = f"10.{200 + int(self.tag[2:4], 16) % 50}.{int(self.tag[4:6], 16)}"
        self.bridge_ns = f"{self.tag}-br"
        self.namespaces: list[str] = []
        self.hosts: dict[str, tuple[str, str, str]] = {}  # name -> (namespace, ip, bridge port)
        self.etc_dirs: list[Path] = []
        self._made_etc_netns = not Path("/etc/netns").exists()
        try:
            self._add_ns(self.bridge_ns)
            _ip("-n", self.bridge_ns, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.bridge_ns, "link", "set", "br0", "up")
        except Exception:
            self.close()
            raise

    def _add_ns(self, ns: str) -> None:
        _ip("netns", "add", ns)
        self.namespaces.append(ns)
        _ip("-n", ns, "link", "set", "lo", "up")

    def add_host(self, name: str) -> str:
        ns = f"{self.tag}-{name}"
        ip = f"{self.subnet}.{len(self.hosts) + 1}"
        port = f"p{len(self.hosts) + 1}"
        self._add_ns(ns)
        _ip("-n", self.bridge_ns, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", ns)
        _ip("-n", self.bridge_ns, "link", "set", port, "master", "br0")
        _ip("-n", self.bridge_ns, "link", "set", port, "up")
        _ip("-n", ns, "addr", "add", f"{ip}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")
        self.hosts[name] = (ns, ip, port)
        return ip

    def name_hosts(self, names: dict[str, str]) -> None:
        """/etc/hosts of every host: localhost plus ``names`` ({host name: ip})."""
        text = "127.0.0.1 localhost\n" + "".join(f"{ip} {n}\n" for n, ip in names.items())
        for ns, _, _ in self.hosts.values():
            d = Path("/etc/netns") / ns
            d.mkdir(parents=True, exist_ok=True)
            self.etc_dirs.append(d)
            (d / "hosts").write_text(text)

    def exec_argv(self, name: str, argv: list[str], env: dict[str, str]) -> list[str]:
        """`ip netns exec NS env K=V... ARGV`: ip and env exec, so the PID is the command's."""
        return ["ip", "netns", "exec", self.hosts[name][0], "env", *[f"{k}={v}" for k, v in env.items()], *argv]

    def link(self, name: str, up: bool) -> None:
        """Cut (or restore) a host's cable: its bridge port goes down, its eth0 loses carrier."""
        _ip("-n", self.bridge_ns, "link", "set", self.hosts[name][2], "up" if up else "down")

    def close(self) -> list[str]:
        problems = []
        for ns in reversed(self.namespaces):
            p = _ip("netns", "del", ns, check=False)
            if p.returncode != 0:
                problems.append(f"ip netns del {ns}: {p.stderr.strip()}")
        for d in self.etc_dirs:
            shutil.rmtree(d, ignore_errors=True)
        if self._made_etc_netns:
            try:
                Path("/etc/netns").rmdir()
            except OSError:
                pass
        return problems

    def leftovers(self) -> list[str]:
        listed = _ip("netns", "list", check=False).stdout.split()
        return [n for n in listed if n.startswith(self.tag)] + [str(d) for d in self.etc_dirs if d.exists()]


RECORDER = r"""
import argparse, json, signal, sys, threading, time
from protocol import keys
from protocol.messages import FusedPose, GroundTruth, PoseFix, RsuStatus
from protocol.transport import add_zenoh_arguments, open_session, subscribe_messages, zenoh_config_from_args
p = argparse.ArgumentParser()
p.add_argument("out")
add_zenoh_arguments(p)
args = p.parse_args()
out = open(args.out, "w", buffering=1)
lock = threading.Lock()
def rec(*fields):
    with lock:
        out.write(json.dumps([time.time_ns(), *fields]) + "\n")
session = open_session(zenoh_config_from_args(args))
subs = [
    subscribe_messages(session, keys.pose_fix(keys.ANY, keys.ANY, keys.ANY), PoseFix,
                       lambda m: rec("fix", m.bus_id, m.rsu_id, m.capture_time_ns)),
    subscribe_messages(session, keys.fused_pose(keys.ANY), FusedPose,
                       lambda m: rec("fused", m.bus_id, m.health.status, m.t_ns, m.x, m.y,
                                     max(m.covariance[0][0], m.covariance[1][1]) ** 0.5)),
    subscribe_messages(session, keys.ground_truth(keys.ANY), GroundTruth,
                       lambda m: rec("truth", m.bus_id, m.t_ns, m.x, m.y, m.yaw)),
    subscribe_messages(session, keys.rsu_status(keys.ANY), RsuStatus,
                       lambda m: rec("status", m.rsu_id, m.frames_received, m.fixes_published)),
]
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
rec("ready")
stop.wait()
for s in subs:
    s.close()
session.close()
"""

# The bundled scenario (it loops): bus-42 in view ~4-10 s, bus-17 ~8-18 s, bus-42 again from ~31 s, seen
# by rsu-se and rsu-sw. Which RSUs track bus-17 varies from run to run, so the test cuts whichever of
# rsu-se and rsu-sw is tracking it: the cut falls while that RSU contributes to bus-17. Every phase ends
# on what the probe has seen, not on the clock: a busy machine only makes the phases longer.
CUT_CANDIDATES, TRACKED_BUS = ("rsu-se", "rsu-sw"), "bus-17"
LOST_FRACTION = 0.02  # of a bus's fused samples in view during the cut, at most this many "lost"
TRACKING_FIXES = 3  # fixes of TRACKED_BUS in 2 s of its captures: the candidate is tracking it
CARRIED_FIXES, CARRIED_S = 10, 3.0  # during the cut: fixes from each of two other RSUs, seconds bus-17 in view
PHASE_TIMEOUT_S = 300


def _records(rec_path: Path) -> list:
    out = []
    for line in rec_path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # the line being written
            pass
    return out


def _tracking_rsu(records: list) -> str | None:
    """The candidate with at least TRACKING_FIXES fixes of TRACKED_BUS in the newest 2 s of its captures."""
    fixes = [(r[4], r[3]) for r in records if r[1] == "fix" and r[2] == TRACKED_BUS and r[3] in CUT_CANDIDATES]
    if not fixes:
        return None
    newest = max(t for t, _ in fixes)
    n = Counter(rsu for t, rsu in fixes if newest - 2_000_000_000 <= t)
    rsu, count = max(n.items(), key=lambda kv: kv[1])
    return rsu if count >= TRACKING_FIXES else None


def _analyse(records: list, cut_rsu: str, t0: float, t_cut: float, t_restore: float, t_end: float) -> dict:
    """Figures of the run from the probe's records (times in s since the epoch)."""
    from protocol.messages import GroundTruth
    from services.monitor import TruthTrack

    def window(t):
        return ("before" if t < t_cut else "during" if t < t_restore else "after" if t < t_end else None)

    fixes = {w: Counter() for w in ("before", "during", "after")}
    just_before = defaultdict(Counter)  # the last 2 s before the cut: which RSU saw which bus
    during_by_bus = defaultdict(Counter)
    span = {}  # bus -> (first, last) arrival of a fix during the cut
    during_arrivals = defaultdict(list)  # bus -> arrivals of the fixes captured during the cut
    truth = defaultdict(TruthTrack)
    fused = []
    status = []  # (t, frames_received) of the cut RSU
    stale_after = fresh_after = 0
    cut_rsu_through_cut = 0  # fixes of the cut RSU captured and delivered while its cable was cut
    first_fresh_fix = None
    for rec in records:
        t, kind, f = rec[0] * 1e-9, rec[1], rec[2:]
        if kind == "fix":
            bus, rsu, capture = f[0], f[1], f[2] * 1e-9
            w = window(capture)  # by capture time: a fix captured before the cut but held in a buffer
            if w:                # during it belongs to "before"
                fixes[w][rsu] += 1
            if t_cut - 2 <= capture < t_cut:
                just_before[bus][rsu] += 1
            if w == "during":
                during_by_bus[bus][rsu] += 1
                during_arrivals[bus].append(t)
                a, b = span.get(bus, (t, t))
                span[bus] = (min(a, t), max(b, t))
            if rsu == cut_rsu and t_cut <= capture and t < t_restore:
                cut_rsu_through_cut += 1
            if rsu == cut_rsu and t >= t_restore:
                if capture < t_restore:
                    stale_after += 1
                else:
                    fresh_after += 1
                    if first_fresh_fix is None:
                        first_fresh_fix = t - t_restore
        elif kind == "truth":
            truth[f[0]].add(GroundTruth(bus_id=f[0], t_ns=f[1], x=f[2], y=f[3], yaw=f[4]))
        elif kind == "fused":
            fused.append((t, f[0], f[1], f[2], f[3], f[4], f[5]))
        elif kind == "status" and f[0] == cut_rsu:
            status.append((t, f[1]))
    # while each bus was in view during the cut (first to last fix from the others): its fused pose
    # "In view": a fix of the bus from one of the other RSUs arrived in the last 2 s (a bus that leaves the
    # intersection and comes back during a long cut is not in view in between).
    in_view = {}
    for bus, (a, b) in span.items():
        arrivals = sorted(during_arrivals[bus])
        st, errs, ok_errs, covered = Counter(), [], [], []
        for t, fb, s, t_ns, x, y, sigma in fused:
            k = bisect.bisect_right(arrivals, t)
            if fb != bus or not a <= t <= b or k == 0 or t - arrivals[k - 1] > 2.0:
                continue
            st[s] += 1
            tr = truth[bus].at(t_ns)
            if tr is not None:
                errs.append(float(np.hypot(x - tr[0], y - tr[1])))
                covered.append(errs[-1] <= 3 * sigma + 0.01)  # the reported uncertainty holds the error
                if s == "ok":
                    ok_errs.append(errs[-1])
        rms = (lambda e: float(np.sqrt(np.mean(np.square(e)))) if e else None)  # noqa: E731
        in_view[bus] = {"seconds": round(b - a, 1), "fixes_by_rsu": dict(sorted(during_by_bus[bus].items())),
                        "fused": dict(st), "ok_fraction": round(st["ok"] / max(1, sum(st.values())), 3),
                        "fused_rms_m": rms(errs), "fused_ok_rms_m": rms(ok_errs),
                        "covered_fraction": round(float(np.mean(covered)), 3) if covered else None}
    # the cut RSU's status reaches the probe again (its link to the router carries data again), then its frame
    # count moves again (the router sends it frames: a new session, see docs/deployment.md)
    worked_before = any(b > a for (_, a), (t, b) in itertools.pairwise(status) if t < t_cut)
    after = [(t, n) for t, n in status if t >= t_restore]
    status_back = after[0][0] - t_restore if after else None
    frames_back = next((t - t_restore for (_, a), (t, b) in itertools.pairwise(after) if b > a), None)
    return {"cut_rsu": cut_rsu,
            "t_s": {k: round(v - t0, 2) if math.isfinite(v) else None
                    for k, v in (("cut", t_cut), ("restore", t_restore), ("end", t_end))},
            "fixes_by_capture": {w: dict(sorted(c.items())) for w, c in fixes.items()},
            "last_2s_before_cut": {b: dict(sorted(c.items())) for b, c in sorted(just_before.items())},
            "during_cut_in_view": in_view,
            "cut_rsu_received_frames_before": worked_before,
            "resume_s": {"status": status_back, "frames": frames_back, "fresh_fix": first_fresh_fix},
            "cut_rsu_fixes_through_cut": cut_rsu_through_cut,
            "cut_rsu_fixes_after": {"stale": stale_after, "fresh": fresh_after}}


def test_separate_hosts_run_the_compose_topology_and_survive_a_cut_rsu_link(tmp_path):
    """Every compose service on its own host (network namespace), connected only through the Zenoh router,
    with the compose commands and environment; the bundled scenario end to end. Mid-run one RSU's cable is
    cut for 8 s: the buses keep their estimate from the other RSUs; once restored, the RSU resumes."""
    from services.processes import ProcessGroup

    why_not = _netns_unavailable()
    if why_not:
        pytest.skip(why_not)
    t_test = time.monotonic()
    compose = {s.name: s for s in topology.services()}
    layout = topology.image_layout()
    lab = NetnsLab()
    group = ProcessGroup(tmp_path / "logs", env={k: v for k, v in os.environ.items()
                                                  if not k.startswith(("TOPTAG_", "ZENOH_"))})
    report_path, rec_path = tmp_path / "report.json", tmp_path / "record.jsonl"
    children = {}
    py = [sys.executable, "-m", "toptag"]

    def start(name, argv, env):
        children[name] = group.start(name, lab.exec_argv(name, argv, env))
        return children[name]

    def wait_for(what, condition):
        """Until condition() holds (every process still running), at most PHASE_TIMEOUT_S."""
        t_give_up = time.monotonic() + PHASE_TIMEOUT_S
        while not condition():
            dead = group.dead()
            assert not dead, "\n".join(f"{c.name} exited {c.popen.returncode}:\n{c.log_tail(20)}" for c in dead)
            assert time.monotonic() < t_give_up, f"{what}: not within {PHASE_TIMEOUT_S} s"
            time.sleep(0.2)

    try:
        ips = {name: lab.add_host(name) for name in [*compose, "probe"]}
        lab.name_hosts({"router": ips["router"]})  # the compose network's DNS name for the router, only
        router = start("router", py + topology.bare_argv(compose["router"], layout), {})
        assert group.wait_for_log(router, "router listening", 20), router.log_tail(20)
        start("probe", [sys.executable, "-c", RECORDER, str(rec_path)], compose["monitor"].env)
        start("monitor", py + topology.bare_argv(compose["monitor"], layout) + ["--report", str(report_path)],
              compose["monitor"].env)
        agents = [n for n in compose if n.startswith(("rsu-", "bus-"))]
        for name in agents:
            start(name, py + topology.bare_argv(compose[name], layout), compose[name].env)
        for name in agents:
            assert group.wait_for_log(children[name], "ready", 30), f"{name}:\n{children[name].log_tail(20)}"
        assert rec_path.exists() and "ready" in rec_path.read_text(), children["probe"].log_tail(20)
        sim = start("sim", py + topology.bare_argv(compose["sim"], layout), compose["sim"].env)
        assert group.wait_for_log(sim, "sim running", 30), sim.log_tail(20)
        t0 = int(re.search(r"t0_ns=(\d+)", sim.log_path.read_text()).group(1)) * 1e-9

        # cut the link of an RSU while it tracks bus-17 ...
        wait_for("a candidate RSU tracking bus-17", lambda: _tracking_rsu(_records(rec_path)) is not None)
        cut_rsu = _tracking_rsu(_records(rec_path))
        lab.link(cut_rsu, up=False)
        t_cut = time.time()  # after the link is down: a frame captured before may still get through

        # ... until two other RSUs have carried bus-17 on their own ...
        def carried():
            f = _analyse(_records(rec_path), cut_rsu, t0, t_cut, math.inf, math.inf)
            others = [n for r, n in f["fixes_by_capture"]["during"].items() if r != cut_rsu and n >= CARRIED_FIXES]
            tracked = f["during_cut_in_view"].get(TRACKED_BUS, {})
            return len(others) >= 2 and tracked.get("seconds", 0) >= CARRIED_S and len(tracked["fixes_by_rsu"]) >= 2
        wait_for("two other RSUs carrying bus-17", carried)
        t_restore = time.time()
        lab.link(cut_rsu, up=True)

        # ... and restore it until it is back: frames flow to it again and its fixes are fresh
        def back():
            f = _analyse(_records(rec_path), cut_rsu, t0, t_cut, t_restore, math.inf)
            return f["resume_s"]["frames"] is not None and f["cut_rsu_fixes_after"]["fresh"] > 0
        wait_for(f"{cut_rsu} back after the cut", back)
        t_end = time.time()
    finally:
        # buses first (they leave properly), then the simulator and RSUs, the observers; the router last
        order = [n for n in children if n.startswith("bus-")] + [n for n in children if n == "sim"]
        order += [n for n in children if n.startswith("rsu-")] + [n for n in ("monitor", "probe", "router")
                                                                 if n in children]
        codes = group.stop([children[n] for n in order])
        problems = lab.close()
        leftovers = lab.leftovers()
    assert not problems and not leftovers, (problems, leftovers)
    assert all(c == 0 for c in codes.values()), (codes, {n: c.log_tail(10) for n, c in children.items()})

    records = [json.loads(ln) for ln in rec_path.read_text().splitlines()]
    figures = _analyse(records, cut_rsu, t0, t_cut, t_restore, t_end)
    report = json.loads(report_path.read_text())
    figures["monitor"] = {b: {k: r[k] for k in ("fixes_received", "fixes_by_rsu", "fix_pos_rms_m", "fused_ok_samples",
                                                 "fused_pos_rms_m", "fused_ok_held_fraction",
                                                 "fused_confident_pos_rms_m")} for b, r in report["buses"].items()}
    figures["test_s"] = round(time.monotonic() - t_test, 1)
    print(json.dumps(figures, indent=1))
    (tmp_path / "figures.json").write_text(json.dumps(figures, indent=1))

    fixes = figures["fixes_by_capture"]
    # the cut RSU worked before the cut, and nothing it captured during the cut arrived while the cable was
    # cut. Frames the router had queued for it when the cable went down may still reach it once the cable is
    # back (TCP delivers them; a cut shorter than the Zenoh lease keeps the session): the fixes from those come
    # late, stamped with their capture time, and count as "stale" after the restore.
    assert figures["cut_rsu_received_frames_before"] and figures["cut_rsu_fixes_through_cut"] == 0, figures
    # the other RSUs carried on; bus-17, which the cut RSU was tracking, was "ok" at times, and every bus
    # in view kept an honest estimate: hardly ever "lost", within 8 cm RMS of the truth when "ok", and its
    # reported uncertainty (3 sigma) holding its error when not. How often it is "ok" depends on how fast
    # the machine lets the RSUs work (with two cores busy the cut lasted a minute and the RSUs sent
    # under one fix a second): reported, not asserted. "Lost" is the filter's word for 10 s without an
    # accepted fix: at load 32 the three connected RSUs sent 10 fixes in 86 s and bus-17 was "lost" in 2
    # of its 689 samples in view, which LOST_FRACTION allows; a filter that lost a bus the RSUs keep
    # fixing would be lost far more often.
    assert len([n for r, n in fixes["during"].items() if r != cut_rsu and n >= CARRIED_FIXES]) >= 2, figures
    tracked_before = [r for r in records if r[1] == "fix" and r[2] == TRACKED_BUS and r[3] == cut_rsu
                      and r[4] * 1e-9 < t_cut]
    assert len(tracked_before) >= TRACKING_FIXES, figures
    in_view = figures["during_cut_in_view"]
    assert in_view.get(TRACKED_BUS, {}).get("seconds", 0) >= CARRIED_S, figures
    assert len(in_view[TRACKED_BUS]["fixes_by_rsu"]) >= 2, figures
    for bus, v in in_view.items():
        if v["seconds"] >= 2:
            assert v["fused"].get("lost", 0) <= LOST_FRACTION * sum(v["fused"].values()), (bus, figures)
            assert v["fused_ok_rms_m"] is None or v["fused_ok_rms_m"] < 0.08, (bus, figures)
            assert v["covered_fraction"] >= 0.9, (bus, figures)
    assert in_view[TRACKED_BUS]["fused"].get("ok", 0) > 0, figures
    # the cut RSU came back: its status, then frames (a new session once the link lease expired), fresh fixes
    resume = figures["resume_s"]
    assert resume["frames"] is not None, figures
    assert figures["cut_rsu_fixes_after"]["fresh"] > 0, figures
    # end to end, as the single-machine demo, over a run that includes the cut
    assert set(report["rsus"]) == {"rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"}
    for bus in ("bus-17", "bus-42"):
        b = report["buses"][bus]
        assert b["fixes_received"] >= CARRIED_FIXES and len(b["fixes_by_rsu"]) >= 2, figures
        assert b["fix_pos_rms_m"] < 0.10, figures
        assert_fused_claims_hold(bus, b)
