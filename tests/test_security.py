"""Transport security over real processes and real sessions: `toptag certs` issues the certificates, a
real `toptag router` process runs with mutual TLS and access control (services/security.py), and the
clients connect with the generated config fragments. A spoofed RSU's fixes never reach the bus.

One CA and one secured router serve the whole module (ports from the OS; every process is stopped by
its PID). Publishers that must be separate processes (the authorised RSU and the impostors) run the
small script PUBLISHER below, configured only through TOPTAG_ZENOH_CONFIG / TOPTAG_ZENOH_CONNECT."""
from __future__ import annotations

import json
import re
import stat
import subprocess
import sys
import threading
import time

import pytest
import zenoh
from conftest import REPO, Launched, _free_port, clean_env, make_samples

from protocol import Approach, Frame, PoseFix, keys
from protocol.transport import (
    MessagePublisher,
    ZenohSetupError,
    declare_alive,
    open_session,
    publish,
    query_sessions,
    serve_session,
    subscribe_messages,
    watch_buses,
    zenoh_config,
)
from services import security
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration

RSUS, BUSES = ("rsu-sw", "rsu-se"), ("bus-17", "bus-42")
X = "x1"


def _toptag(*args: str, timeout: float = 30) -> subprocess.CompletedProcess:
    """Run the real `toptag` command line (toptag.cli.main) in a subprocess."""
    return subprocess.run([sys.executable, "-c", "from toptag.cli import main; main()", *args], cwd=REPO,
                          env=clean_env(), capture_output=True, text=True, timeout=timeout, check=False)


class Inbox:
    def __init__(self):
        self.items, self.cond = [], threading.Condition()

    def __call__(self, item):
        with self.cond:
            self.items.append(item)
            self.cond.notify_all()

    def wait(self, pred, timeout: float = 60.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.items), timeout)


# ---- module fixtures: certificates, a secured router, client sessions ---------------------------

@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    base = tmp_path_factory.mktemp("pki")
    out, rogue = base / "certs", base / "rogue"
    args = ["certs", "--out", str(out), "--router", "router", "--router-host", "router.example",
            "--sim", "sim", "--monitor", "monitor", "--days", "2"]
    for r in RSUS:
        args += ["--rsu", r]
    for b in BUSES:
        args += ["--bus", b]
    r = _toptag(*args)
    assert r.returncode == 0, r.stderr
    # Another CA issuing the same names: what a spoofer can make on their own.
    r2 = _toptag("certs", "--out", str(rogue), "--rsu", "rsu-sw", "--bus", "bus-17", "--quiet")
    assert r2.returncode == 0 and r2.stdout == "", r2.stderr
    return {"dir": out, "rogue": rogue, "stdout": r.stdout}


@pytest.fixture(scope="module")
def secure_router(pki, tmp_path_factory):
    """`python -m services.router` configured by environment only (TOPTAG_ZENOH_SECURE and
    TOPTAG_ZENOH_LISTEN); zenoh's ACL decisions are logged (RUST_LOG) so the test can see where a put
    is dropped. Yields {"tls": endpoint, "port": port, "proc": Launched}."""
    port = _free_port()
    log_path = tmp_path_factory.mktemp("router") / "router.log"
    env = clean_env({"TOPTAG_ZENOH_SECURE": str(pki["dir"]), "TOPTAG_ZENOH_LISTEN": f"tls/127.0.0.1:{port}",
                     "RUST_LOG": "warn,zenoh::net::routing::interceptor::access_control=trace", "NO_COLOR": "1"})
    with open(log_path, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "services.router"], cwd=REPO, env=env, stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    router = Launched(proc, log_path)
    try:
        assert router.wait_for("router listening on", 20), router.output()[-2000:]
        yield {"tls": f"tls/localhost:{port}", "port": port, "proc": router}
    finally:
        assert router.stop() == 0, router.output()[-2000:]


@pytest.fixture
def client(pki, secure_router):
    """client(stem) -> zenoh.Session of the identity <stem> (e.g. "bus.bus-17") through its generated
    fragment; closed at teardown."""
    sessions = []

    def make(stem: str, directory=None):
        conf = zenoh_config(mode=None, connect=[secure_router["tls"]], multicast_scouting=None,
                            config_file=(directory or pki["dir"]) / f"{stem}.json5")
        s = open_session(conf)
        sessions.append(s)
        return s

    yield make
    for s in reversed(sessions):
        s.close()


def _wait_matching(pub: MessagePublisher, timeout: float = 60.0) -> bool:
    """Wait until the router has told this publisher about a matching subscriber."""
    return pub.wait_matching(timeout)


def _router_log(secure_router) -> str:
    return re.sub(r"\x1b\[[0-9;]*m", "", secure_router["proc"].output())


def _fix(rsu: str, bus: str, seq: int, x: float = 1.0) -> PoseFix:
    t = time.time_ns()
    return PoseFix(bus_id=bus, rsu_id=rsu, intersection_id=X, capture_time_ns=t, publish_time_ns=t, x=x, y=2.0,
                   z=3.0, yaw=0.1, covariance=[[0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.001]], method="s_opt",
                   tags_used=[3], reprojection_rms_px=0.3, frame_seq=seq)


# A publisher process: configured by the environment like any service, publishes ``count`` PoseFix
# with frame_seq base+i on keys.pose_fix(X, bus, as_rsu), then prints what it saw.
PUBLISHER = r"""
import argparse, json, sys, time
from protocol import PoseFix, keys
import zenoh
from protocol.transport import (MessagePublisher, Qos, ZenohSetupError, add_zenoh_arguments, open_session,
                             zenoh_config_from_args)
bus, as_rsu, base, count = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
matching_timeout = float(sys.argv[5])
p = argparse.ArgumentParser(); add_zenoh_arguments(p, default_mode="client")
try:
    session = open_session(zenoh_config_from_args(p.parse_args([])))
except ZenohSetupError as e:
    print(json.dumps({"error": str(e)}), flush=True); sys.exit(1)
# BLOCK, not PoseFix's DROP: this publisher tests who may publish, and on a busy machine DROP sheds fixes
qos = Qos(zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_HIGH)
pub = MessagePublisher(session, keys.pose_fix("x1", bus, as_rsu), PoseFix, qos=qos)
matching = pub.wait_matching(matching_timeout)
for i in range(count):
    t = time.time_ns()
    pub.put(PoseFix(bus_id=bus, rsu_id=as_rsu, intersection_id="x1", capture_time_ns=t, publish_time_ns=t,
                    x=float(base), y=0.0, z=3.0, yaw=0.0, covariance=[[0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.001]],
                    method="s_opt", tags_used=[3], reprojection_rms_px=0.3, frame_seq=base + i))
    time.sleep(0.02)
time.sleep(0.2)
print(json.dumps({"published": pub.published, "matching": bool(matching)}), flush=True)
session.close()
"""


def _start_publisher(pki, secure_router, stem: str, bus: str, as_rsu: str, base: int, count: int,
                     directory=None, matching_timeout: float = 3.0) -> subprocess.Popen:
    """matching_timeout: how long the publisher waits to learn of a subscriber before it publishes; long
    where it must learn (on a busy machine routing takes seconds), short where it must not."""
    env = clean_env({"TOPTAG_ZENOH_CONFIG": str((directory or pki["dir"]) / f"{stem}.json5"),
                     "TOPTAG_ZENOH_CONNECT": secure_router["tls"]})
    return subprocess.Popen([sys.executable, "-c", PUBLISHER, bus, as_rsu, str(base), str(count),
                             str(matching_timeout)], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 20) -> dict:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"publisher {proc.pid} did not finish: {out[-1000:]}")
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    assert lines, f"publisher {proc.pid} printed no result (exit {proc.returncode}): {out[-1000:]}"
    return json.loads(lines[-1]) | {"exit": proc.returncode}


# ---- certificates -----------------------------------------------------------------------------

def _openssl(*args: str) -> str:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True).stdout


def test_certs_command_issues_ca_identities_and_fragments(pki):
    d = pki["dir"]
    manifest = json.loads((d / security.MANIFEST).read_text())
    cns = {i["cn"] for i in manifest["identities"]}
    assert cns == {"router:router", "rsu:rsu-sw", "rsu:rsu-se", "bus:bus-17", "bus:bus-42", "sim:sim", "monitor:monitor"}
    for ident in manifest["identities"]:
        cert, key, frag = d / ident["cert"], d / ident["key"], d / ident["config"]
        assert f"CN = {ident['cn']}" in _openssl("x509", "-in", str(cert), "-noout", "-subject")
        assert _openssl("verify", "-CAfile", str(d / "ca.pem"), str(cert)).strip().endswith("OK")
        for secret in (key, frag):
            assert stat.S_IMODE(secret.stat().st_mode) == 0o600, secret
        conf = zenoh.Config.from_file(str(frag))  # zenoh accepts the fragment as it is
        assert json.loads(conf.get_json("mode")) == ("router" if ident["role"] == "router" else "client")
        assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
        if ident["role"] == "router":  # zenohd keeps fixes as toptag's processes do (protocol.transport.config)
            from protocol.transport.config import FIX_QUEUE_BATCHES, FIX_QUEUE_PATH
            assert json.loads(conf.get_json(FIX_QUEUE_PATH)) == FIX_QUEUE_BATCHES
    assert stat.S_IMODE((d / "ca.key").stat().st_mode) == 0o600
    router_text = _openssl("x509", "-in", str(d / "router.router.pem"), "-noout", "-ext",
                           "subjectAltName,extendedKeyUsage")
    for name in ("DNS:localhost", "IP Address:127.0.0.1", "DNS:router", "DNS:router.example", "TLS Web Server Authentication"):
        assert name in router_text
    assert "TLS Web Server" not in _openssl("x509", "-in", str(d / "rsu.rsu-sw.pem"), "-noout", "-ext", "extendedKeyUsage")
    # the rogue CA is a different CA issuing the same names
    assert _openssl("x509", "-in", str(pki["rogue"] / "ca.pem"), "-noout", "-fingerprint") != \
        _openssl("x509", "-in", str(d / "ca.pem"), "-noout", "-fingerprint")
    assert "toptag router --secure" in pki["stdout"]


def test_certs_command_reuses_its_ca_and_fails_in_one_line(tmp_path):
    out = tmp_path / "c"
    assert _toptag("certs", "--out", str(out), "--rsu", "rsu-a", "--quiet").returncode == 0
    ca = (out / "ca.pem").read_bytes()
    r = _toptag("certs", "--out", str(out), "--bus", "bus-b")
    assert r.returncode == 0 and "using the existing CA" in r.stdout, r.stderr
    assert (out / "ca.pem").read_bytes() == ca
    assert {(i["role"], i["id"]) for i in json.loads((out / security.MANIFEST).read_text())["identities"]} == \
        {("router", "router"), ("rsu", "rsu-a"), ("bus", "bus-b")}
    for bad, text in ((["--bus", "a/b"], "bus id 'a/b'"), (["--rsu", "x", "--openssl", "/nonexistent/openssl"], "not found"),
                      (["--rsu", "x", "--days", "0"], "--days")):
        r = _toptag("certs", "--out", str(tmp_path / "bad"), *bad)
        assert r.returncode == 2 and text in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_acl_binds_each_identity_to_its_own_keys(pki):
    acl = security.access_control_config(security.load_certs(pki["dir"]).identities)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}

    def allowed(cn, message, flow):
        policy = next(p for p in acl["policies"] if p["subjects"] == [cn])
        return {k for rid in policy["rules"] for k in rules[rid]["key_exprs"]
                if message in rules[rid]["messages"] and flow in rules[rid]["flows"]}

    assert allowed("rsu:rsu-sw", "put", "ingress") == {"toptag/v1/fix/*/*/rsu-sw", "toptag/v1/status/rsu/rsu-sw",
                                                        "toptag/v1/detections/rsu-sw"}
    assert allowed("bus:bus-17", "put", "ingress") == {"toptag/v1/approach/*/bus-17", "toptag/v1/leave/*/bus-17",
                                                        "toptag/v1/fused/bus-17", "toptag/v1/diag/*/*/bus-17"}
    assert allowed("bus:bus-17", "liveliness_token", "ingress") == {"toptag/v1/alive/*/bus-17"}
    assert allowed("monitor:monitor", "put", "ingress") == set()
    assert allowed("sim:sim", "put", "ingress") == {"toptag/v1/frame/**", "toptag/v1/imu/**", "toptag/v1/imu_batch/**",
                                                    "toptag/v1/truth/**", "toptag/v1/gnss/**"}
    assert "router:router" not in {s["id"] for s in acl["subjects"]}  # the router's cert grants nothing
    with pytest.raises(security.SecurityError, match="tls/"):
        security.router_config(pki["dir"], listen=["tcp/0.0.0.0:7447"])


# ---- the requirement: a spoofed RSU cannot feed a bus poses ----------------------------------

def test_only_the_authorised_rsu_process_feeds_the_bus(pki, secure_router, client):
    bus = client("bus.bus-17")
    inbox = Inbox()
    sub = subscribe_messages(bus, keys.pose_fix(X, "bus-17", keys.ANY), PoseFix, inbox)
    n = 20
    procs = {  # name -> (process, frame_seq base)
        "authorised rsu-sw": (_start_publisher(pki, secure_router, "rsu.rsu-sw", "bus-17", "rsu-sw", 1000, n,
                                               matching_timeout=30), 1000),
        "bus-42 certificate as rsu-sw": (_start_publisher(pki, secure_router, "bus.bus-42", "bus-17", "rsu-sw", 2000, n), 2000),
        "rsu-se certificate as rsu-sw": (_start_publisher(pki, secure_router, "rsu.rsu-se", "bus-17", "rsu-sw", 3000, n,
                                                          matching_timeout=30), 3000),
        "sim certificate as rsu-sw": (_start_publisher(pki, secure_router, "sim.sim", "bus-17", "rsu-sw", 4000, n), 4000),
        "rogue-CA rsu-sw": (_start_publisher(pki, secure_router, "rsu.rsu-sw", "bus-17", "rsu-sw", 5000, n,
                                             directory=pki["rogue"]), 5000),
        "rsu-se as itself": (_start_publisher(pki, secure_router, "rsu.rsu-se", "bus-17", "rsu-se", 6000, n,
                                              matching_timeout=30), 6000),
    }
    results = {name: _finish(p, timeout=60) for name, (p, _) in procs.items()}
    # the authorised fixes arrive (on a busy machine, seconds after their publishers exited) ...
    wait_until(lambda: len([m for m in inbox.items if m.frame_seq // 1000 in (1, 6)]) >= 2 * n, 30, 0.1)
    time.sleep(0.5)  # ... and an impostor's, had the router let any through, would have come with them
    sub.close()
    by_base = {}
    for m in inbox.items:
        by_base.setdefault(m.frame_seq // 1000 * 1000, []).append(m)

    # The authorised RSU (and rsu-se under its own name) get every fix through.
    assert results["authorised rsu-sw"] == {"published": n, "matching": True, "exit": 0}
    assert sorted(m.frame_seq for m in by_base.get(1000, [])) == list(range(1000, 1000 + n))
    assert len(by_base.get(6000, [])) == n and all(m.rsu_id == "rsu-se" for m in by_base[6000])
    # Impostors with valid certificates of the wrong identity: nothing reaches the bus.
    for name, base in (("bus-42 certificate as rsu-sw", 2000), ("rsu-se certificate as rsu-sw", 3000),
                       ("sim certificate as rsu-sw", 4000)):
        assert results[name]["exit"] == 0 and results[name]["published"] == n, (name, results[name])
        assert base not in by_base, f"{name}: {len(by_base[base])} fixes reached the bus"
    # rsu-se learnt that the bus subscribes (it may read fixes) and sent its puts: the router dropped
    # them, without any error at the publisher.
    assert results["rsu-se certificate as rsu-sw"]["matching"] is True
    log = _router_log(secure_router)
    assert re.search(r"CertCommonName\(rsu:rsu-se\).*unauthorized to Put \(ingress\) on "
                     r"toptag/v1/fix/x1/bus-17/rsu-sw", log), "no ingress denial logged for rsu-se"
    # Identities that may not publish fixes are not even told that the bus subscribes.
    assert results["bus-42 certificate as rsu-sw"]["matching"] is False
    assert results["sim certificate as rsu-sw"]["matching"] is False
    # A certificate from another CA does not get a session at all.
    assert results["rogue-CA rsu-sw"]["exit"] == 1 and "cannot open zenoh session" in results["rogue-CA rsu-sw"]["error"]
    assert 5000 not in by_base


def test_connections_without_a_valid_certificate_are_refused(pki, secure_router):
    tls, port, d, rogue = secure_router["tls"], secure_router["port"], pki["dir"], pki["rogue"]

    def tls_files(ca, cert=None, key=None):
        files = {"root_ca_certificate": str(ca), "enable_mtls": True}
        if cert is not None:
            files |= {"connect_certificate": str(cert), "connect_private_key": str(key)}
        return {"connect": [tls], "extra": {"transport/link/tls": files}}

    attempts = {
        "plain tcp": {"connect": [f"tcp/127.0.0.1:{port}"]},
        "tls without a client certificate": tls_files(d / "ca.pem"),
        "certificate of another CA (trusting the real CA)":
            tls_files(d / "ca.pem", rogue / "rsu.rsu-sw.pem", rogue / "rsu.rsu-sw.key"),
        "valid certificate, trusting another CA (the router's is refused)":
            tls_files(rogue / "ca.pem", d / "rsu.rsu-sw.pem", d / "rsu.rsu-sw.key"),
    }
    for name, kw in attempts.items():
        with pytest.raises(ZenohSetupError, match="cannot open zenoh session"):
            s = open_session(zenoh_config(mode="client", multicast_scouting=False, **kw))
            s.close()
    # the same client with its own certificate, by IP address (the router's certificate names 127.0.0.1)
    ok = open_session(zenoh_config(mode=None, connect=[f"tls/127.0.0.1:{port}"], multicast_scouting=None,
                                   config_file=d / "rsu.rsu-sw.json5"))
    ok.close()
    # the fragment only speaks tls: peer mode (which would listen on tcp) fails at once
    with pytest.raises(ZenohSetupError, match="tcp"):
        open_session(zenoh_config(mode="peer", connect=[tls], multicast_scouting=None,
                                  config_file=d / "rsu.rsu-sw.json5"))


def test_only_buses_announce_and_only_as_themselves(client):
    rsu = client("rsu.rsu-sw")
    inbox = Inbox()
    sub = subscribe_messages(rsu, keys.approach(X, keys.ANY), Approach, inbox)
    template = make_samples()["Approach"]
    senders = {"bus-17": client("bus.bus-17"), "bus-42 as bus-17": client("bus.bus-42"),
               "rsu-se as bus-17": client("rsu.rsu-se")}
    for seq in range(5):
        for name, s in senders.items():
            publish(s, keys.approach(X, "bus-17"), template.model_copy(update={"seq": seq + (0 if name == "bus-17" else 100)}))
        time.sleep(0.02)
    assert inbox.wait(lambda items: len(items) >= 5, 60)
    time.sleep(0.3)
    sub.close()
    assert sorted(m.seq for m in inbox.items) == list(range(5)), "an RSU or another bus announced bus-17"


def test_liveliness_and_session_queries_follow_identities(client):
    bus, bus42, rsu, rse, sim = (client(s) for s in ("bus.bus-17", "bus.bus-42", "rsu.rsu-sw", "rsu.rsu-se", "sim.sim"))
    approach = make_samples()["Approach"]  # bus-17 at x1
    queryable = serve_session(bus, approach)
    token = declare_alive(bus, X, "bus-17")
    fakes = [declare_alive(bus42, X, "bus-99"), declare_alive(rse, X, "bus-98")]  # not theirs to declare
    seen = Inbox()
    watcher = watch_buses(rsu, X, on_appear=seen)
    assert seen.wait(lambda items: "bus-17" in items, 60)
    assert set(query_sessions(rsu, X, timeout=1.0)) == {"bus-17"}
    assert query_sessions(sim, X, timeout=0.5) == {}  # the simulator may not ask
    time.sleep(0.2)
    assert seen.items == ["bus-17"]
    watcher.close()
    queryable.undeclare()
    del token, fakes


def test_frames_go_to_their_rsu_and_the_monitor_reads_per_kind_only(client):
    sim, rsu, rse, mon, bus = (client(s) for s in ("sim.sim", "rsu.rsu-sw", "rsu.rsu-se", "monitor.monitor", "bus.bus-17"))
    own, stolen = Inbox(), Inbox()
    s1 = subscribe_messages(rsu, keys.frame("rsu-sw"), Frame, own)
    s2 = subscribe_messages(rse, keys.frame("rsu-sw"), Frame, stolen)  # rsu-se may not read rsu-sw's camera
    pub = MessagePublisher(sim, keys.frame("rsu-sw"), Frame)
    assert _wait_matching(pub)
    for seq in range(3):
        pub.put(make_samples()["Frame"].model_copy(update={"seq": seq}))
    assert own.wait(lambda items: len(items) == 3, 60)

    # monitor: a wide subscription is refused (nothing matches it), per-kind prefixes work; it cannot publish
    wide, fixes, at_bus = Inbox(), Inbox(), Inbox()
    s3 = mon.declare_subscriber(keys.EVERYTHING, lambda s: wide(str(s.key_expr)))
    s4 = subscribe_messages(bus, keys.pose_fix(X, "bus-17", keys.ANY), PoseFix, at_bus)
    fix_pub = MessagePublisher(rsu, keys.pose_fix(X, "bus-17", "rsu-sw"), PoseFix)
    assert _wait_matching(fix_pub)
    fix_pub.put(_fix("rsu-sw", "bus-17", 1))
    assert at_bus.wait(lambda items: len(items) == 1, 60)
    time.sleep(0.2)
    assert wide.items == [], "a subscription on toptag/v1/** received something"
    s5 = subscribe_messages(mon, keys.pose_fix(keys.ANY, keys.ANY, keys.ANY), PoseFix, fixes)
    probe = MessagePublisher(rsu, keys.pose_fix(X, "bus-99", "rsu-sw"), PoseFix)  # no one but the monitor reads it
    assert _wait_matching(probe), "the router never routed the monitor's subscription"
    probe.close()
    fix_pub.put(_fix("rsu-sw", "bus-17", 2))
    assert fixes.wait(lambda items: len(items) == 1, 60) and fixes.items[0].frame_seq == 2
    publish(mon, keys.pose_fix(X, "bus-17", "rsu-sw"), _fix("rsu-sw", "bus-17", 666))
    time.sleep(0.3)
    assert [m.frame_seq for m in at_bus.items] == [1, 2], "the monitor published a fix"
    # the wide subscriber only shares what the per-kind one was sent (plus the monitor's own put,
    # delivered locally in its session)
    assert all(k.startswith("toptag/v1/fix/") for k in wide.items)
    assert stolen.items == []
    for s in (s1, s2, s4, s5):
        s.close()
    s3.undeclare()


# ---- the real services under the access control ---------------------------------------------

def test_the_real_services_work_under_the_access_control(pki, secure_router, client, tmp_path):
    """`toptag rsu` and `toptag bus` configured only by TOPTAG_ZENOH_CONFIG / TOPTAG_ZENOH_CONNECT, the
    test as the simulator (sim identity: frames, GNSS) and as a monitor (monitor identity): the bus
    announces itself, the RSU takes it into session and sends it fixes, the bus fuses them."""
    import numpy as np

    from protocol import FusedPose, GnssFix, RsuStatus
    from services.processes import ProcessGroup
    from sim.render import PlacedVehicle, render_jpeg
    from sim.scenario import bundled_scenario_path
    from sim.scene import bundled_vehicle
    from toptag.camera import Camera

    site = bundled_scenario_path().parent
    camera = Camera.load(site / "corners" / "rsu-sw.json")  # SPEC's corner pole, which sees this stretch of road
    vehicle, rng = bundled_vehicle("bus_double"), np.random.default_rng(4)
    frames = [render_jpeg(camera, [PlacedVehicle(vehicle, -6.0 + 0.5 * i, -1.85, 0.0, 3.0, speed=3.5)], rng=rng)
              for i in range(6)]

    sim, mon = client("sim.sim"), client("monitor.monitor")
    status, fixes, fused = Inbox(), Inbox(), Inbox()
    subs = [subscribe_messages(mon, keys.rsu_status(keys.ANY), RsuStatus, status),
            subscribe_messages(mon, keys.pose_fix(X, keys.ANY, keys.ANY), PoseFix, fixes),
            subscribe_messages(mon, keys.fused_pose(keys.ANY), FusedPose, fused)]
    group = ProcessGroup(tmp_path / "logs", env=clean_env())

    def start(name, stem, argv):
        group.env.update(TOPTAG_ZENOH_CONFIG=str(pki["dir"] / f"{stem}.json5"),
                         TOPTAG_ZENOH_CONNECT=secure_router["tls"])
        return group.start(name, [sys.executable, "-m", "toptag", *argv])

    stop = threading.Event()

    def simulate():
        frame_pub = MessagePublisher(sim, keys.frame("rsu-sw"), Frame)
        gnss_pub = MessagePublisher(sim, keys.gnss("bus-17"), GnssFix)
        seq = 0
        while not stop.is_set():
            t = time.time_ns()
            frame_pub.put(Frame(rsu_id="rsu-sw", capture_time_ns=t, seq=seq, encoding="jpeg", width=camera.width,
                                height=camera.height, image=frames[seq % len(frames)]))
            if seq % 2 == 0:
                gnss_pub.put(GnssFix(bus_id="bus-17", t_ns=t, x=-1.0, y=-1.85, sigma_m=2.0))  # where the frames show it
            seq += 1
            stop.wait(0.1)

    feeder = threading.Thread(target=simulate, daemon=True)
    try:
        rsu = start("rsu", "rsu.rsu-sw", ["rsu", "--camera", str(site / "corners" / "rsu-sw.json"), "--intersection", X])
        bus = start("bus", "bus.bus-17", ["bus", "--vehicle", str(site / "bus-17.json"), "--map", str(site / "map.json")])
        feeder.start()
        ok = fixes.wait(lambda items: len(items) >= 5, 40) and fused.wait(lambda items: len(items) >= 1, 60) and \
            status.wait(lambda items: bool(items) and "bus-17" in items[-1].active_buses, 60)
        assert ok, (f"status {status.items[-1:]} fixes {len(fixes.items)} fused {len(fused.items)}\n"
                    f"rsu: {rsu.log_tail(8)}\nbus: {bus.log_tail(8)}")
        assert {(m.rsu_id, m.bus_id) for m in fixes.items} == {("rsu-sw", "bus-17")}
        assert rsu.alive() and bus.alive()
    finally:
        stop.set()
        feeder.join(2)
        codes = group.stop()
        for s in subs:
            s.close()
    assert codes == {"rsu": 0, "bus": 0}, codes
