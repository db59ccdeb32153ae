"""Transport security for toptag: a private CA and mutual TLS certificates (`toptag certs`), the zenoh
config fragments that make a service connect with its certificate, and the secured router's config
(TLS listener with client certificates required, and zenoh access control by certificate common name).

    toptag certs --out DIR --router router [--router-host HOST ...] --rsu rsu-sw --rsu rsu-se
                 --bus bus-17 [--sim sim] [--monitor monitor] [--days 365]
    toptag router --secure DIR [--listen tls/0.0.0.0:7447]
    <service> --zenoh-config DIR/<role>.<id>.json5 --connect tls/<router host>:7447

Identities. Each certificate's subject common name (CN) is ``<role>:<id>``: ``rsu:rsu-sw``,
``bus:bus-17``, ``sim:sim``, ``monitor:monitor``, ``router:<name>``. The id is the one used in the key
expressions (protocol.keys), so the router's access control can bind an identity to its own keys: RSU
rsu-sw may publish toptag/v1/fix/*/*/rsu-sw and nothing else under fix/. Ids in certificates are limited
to letters, digits, '.', '_' and '-'.

Files written to DIR (key files and config fragments mode 0600):
- ca.pem, ca.key: the CA (EC P-256). Reused if DIR already holds one, so identities can be added later;
  ca.key need not leave the machine that issues certificates.
- <role>.<id>.pem / .key: each identity's certificate (signed by the CA, clientAuth; the router's also
  serverAuth with subjectAltNames localhost, 127.0.0.1, ::1, its name and every --router-host).
- <role>.<id>.json5: a zenoh config fragment for that identity (client mode, multicast scouting off,
  TLS with its certificate, key and the CA embedded as base64, so the one file works wherever it is
  mounted). The router's fragment is the complete secured router config (listener, TLS, ACL).
- toptag-certs.json: the manifest (identities and their files, relative to DIR) from which
  `toptag router --secure DIR` builds its access control.

Zenoh 1.10 facts this relies on (measured, tests/test_security.py; docs/security.md):
- A client learns through the router which subscribers match what it publishes and does not send puts
  nobody (that it knows of) reads: a publisher therefore needs ``declare_subscriber`` in the *egress*
  flow on the keys its readers subscribe to, besides ``put`` in the ingress flow.
- A rule's key expression must *include* the message's key expression: a subscription on toptag/v1/**
  is not allowed by rules on toptag/v1/fix/** etc. Subscribe to the allowed prefixes.
- With default_permission deny, a denied put is dropped at the router; the publisher gets no error.
"""
from __future__ import annotations

import argparse
import base64
import ipaddress
import json
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol import keys
from toptag.errors import InputError, report

ROLES = ("router", "rsu", "bus", "sim", "monitor")
MANIFEST = "toptag-certs.json"
CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_PORT = 7447
DEFAULT_SECURE_LISTEN = (f"tls/0.0.0.0:{DEFAULT_PORT}",)
DEFAULT_ROUTER_HOSTS = ("localhost", "127.0.0.1", "::1")
DEFAULT_DAYS = 365
CA_DAYS = 3650
ENV_OPENSSL = "TOPTAG_OPENSSL"
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


class SecurityError(InputError):
    """Certificates or a secured config cannot be made from what was given. str(e) is one line."""


# ---- identities -------------------------------------------------------------------------------

def common_name(role: str, ident: str) -> str:
    """The certificate CN, and the access-control subject, of an identity: 'rsu:rsu-sw'."""
    if role not in ROLES:
        raise SecurityError(f"unknown role {role!r} (one of {', '.join(ROLES)})")
    if not isinstance(ident, str) or not _ID_RE.match(ident):
        raise SecurityError(f"{role} id {ident!r}: use 1-64 letters, digits, '.', '_' or '-' "
                            f"(starting with a letter or digit)")
    return f"{role}:{ident}"


@dataclass(frozen=True)
class Identity:
    role: str
    id: str

    @property
    def cn(self) -> str:
        return common_name(self.role, self.id)

    @property
    def stem(self) -> str:
        """File name stem in the certificate directory: 'rsu.rsu-sw'."""
        return f"{self.role}.{self.id}"


@dataclass
class CertSet:
    """What `toptag certs` wrote (paths absolute)."""
    dir: Path
    ca_cert: Path
    router: Identity
    router_hosts: list[str]
    identities: list[Identity] = field(default_factory=list)  # every identity, the router first

    def cert(self, who: Identity) -> Path:
        return self.dir / f"{who.stem}.pem"

    def key(self, who: Identity) -> Path:
        return self.dir / f"{who.stem}.key"

    def config(self, who: Identity) -> Path:
        return self.dir / f"{who.stem}.json5"

    def find(self, role: str, ident: str) -> Identity:
        for who in self.identities:
            if who.role == role and who.id == ident:
                return who
        raise SecurityError(f"no certificate for {role}:{ident} in {self.dir}")


# ---- openssl ----------------------------------------------------------------------------------

def _openssl_path(openssl: str | None = None) -> str:
    exe = openssl or os.environ.get(ENV_OPENSSL) or "openssl"
    found = shutil.which(exe)
    if not found:
        raise SecurityError(f"openssl command {exe!r} not found: install OpenSSL (the command line tool) "
                            f"or pass --openssl PATH")
    return found


def _run_openssl(exe: str, args: Sequence[str], what: str) -> None:
    try:
        r = subprocess.run([exe, *args], capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise SecurityError(f"openssl ({what}) could not run: {e}") from None
    if r.returncode != 0:
        lines = [ln.strip() for ln in (r.stderr or r.stdout or "").splitlines() if ln.strip()]
        detail = lines[0] if lines else f"exit status {r.returncode}"
        raise SecurityError(f"openssl ({what}) failed: {detail}")


def _private(path: Path) -> None:
    os.chmod(path, 0o600)


def _new_key(exe: str, path: Path) -> None:
    _run_openssl(exe, ["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
                       "-out", str(path)], f"key {path.name}")
    _private(path)


def _make_ca(exe: str, out: Path, days: int) -> None:
    key, cert = out / CA_KEY, out / CA_CERT
    _new_key(exe, key)
    _run_openssl(exe, ["req", "-x509", "-new", "-key", str(key), "-sha256", "-days", str(days),
                       "-subj", "/O=toptag/CN=toptag CA", "-set_serial", _serial(),
                       "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
                       "-addext", "keyUsage=critical,keyCertSign,cRLSign",
                       "-addext", "subjectKeyIdentifier=hash",
                       "-out", str(cert)], "CA certificate")


def _serial() -> str:
    return "0x" + secrets.token_hex(16)


def _san(hosts: Iterable[str]) -> str:
    names = []
    for h in hosts:
        try:
            names.append(f"IP:{ipaddress.ip_address(h)}")
        except ValueError:
            names.append(f"DNS:{h}")
    return ",".join(dict.fromkeys(names))


def _issue(exe: str, out: Path, who: Identity, days: int, hosts: Sequence[str] = ()) -> None:
    key, cert = out / f"{who.stem}.key", out / f"{who.stem}.pem"
    _new_key(exe, key)
    ext = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature",
           "subjectKeyIdentifier=hash", "authorityKeyIdentifier=keyid"]
    if who.role == "router":
        ext.append("extendedKeyUsage=serverAuth,clientAuth")
        ext.append(f"subjectAltName={_san(hosts)}")
    else:
        ext.append("extendedKeyUsage=clientAuth")
    with tempfile.TemporaryDirectory(prefix="toptag-certs-") as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text("\n".join(ext) + "\n")
        _run_openssl(exe, ["req", "-new", "-key", str(key), "-subj", f"/O=toptag/CN={who.cn}",
                           "-out", str(csr)], f"request for {who.cn}")
        _run_openssl(exe, ["x509", "-req", "-in", str(csr), "-CA", str(out / CA_CERT),
                           "-CAkey", str(out / CA_KEY), "-set_serial", _serial(), "-days", str(days),
                           "-sha256", "-extfile", str(extfile), "-out", str(cert)],
                     f"certificate for {who.cn}")


# ---- config fragments -------------------------------------------------------------------------

def _b64(path: Path) -> str:
    try:
        return base64.b64encode(Path(path).read_bytes()).decode("ascii")
    except OSError as e:
        raise SecurityError(f"cannot read {path}: {e.strerror}") from None


def client_tls_settings(ca_cert: str | os.PathLike, cert: str | os.PathLike, key: str | os.PathLike, *,
                        inline: bool = True) -> dict[str, Any]:
    """The transport/link/tls settings of a client: mutual TLS with this certificate and key, trusting
    only ``ca_cert``. ``inline`` embeds the PEM files (base64) instead of naming them."""
    if inline:
        return {"root_ca_certificate_base64": _b64(Path(ca_cert)),
                "connect_certificate_base64": _b64(Path(cert)),
                "connect_private_key_base64": _b64(Path(key)),
                "enable_mtls": True}
    return {"root_ca_certificate": str(Path(ca_cert).resolve()),
            "connect_certificate": str(Path(cert).resolve()),
            "connect_private_key": str(Path(key).resolve()),
            "enable_mtls": True}


def client_config(certs: CertSet | str | os.PathLike, role: str, ident: str, *,
                  connect: Sequence[str] | None = None, inline: bool = True) -> dict[str, Any]:
    """A client's zenoh config (nested dict, JSON-able) for identity role:ident from a certificate
    directory: client mode, multicast scouting off, only the tls protocol, mutual TLS."""
    cs = certs if isinstance(certs, CertSet) else load_certs(certs)
    who = cs.find(role, ident)
    conf: dict[str, Any] = {
        "mode": "client",
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"],
                               "tls": client_tls_settings(cs.ca_cert, cs.cert(who), cs.key(who), inline=inline)}},
    }
    if connect:
        conf["connect"] = {"endpoints": list(connect)}
    return conf


def router_config(certs: CertSet | str | os.PathLike, *, listen: Sequence[str] | None = None,
                  inline: bool = False) -> dict[str, Any]:
    """The secured router's zenoh config (nested dict): router mode, TLS listeners that require a client
    certificate from the CA, only the tls protocol, and access control (access_control_config)."""
    cs = certs if isinstance(certs, CertSet) else load_certs(certs)
    listen = list(listen or DEFAULT_SECURE_LISTEN)
    check_tls_endpoints(listen, "listen")
    key, cert = cs.key(cs.router), cs.cert(cs.router)
    if inline:
        tls = {"root_ca_certificate_base64": _b64(cs.ca_cert), "listen_certificate_base64": _b64(cert),
               "listen_private_key_base64": _b64(key), "connect_certificate_base64": _b64(cert),
               "connect_private_key_base64": _b64(key)}
    else:
        for p in (cs.ca_cert, cert, key):
            if not p.is_file():
                raise SecurityError(f"{p} is missing (run toptag certs --out {cs.dir} ...)")
        tls = {"root_ca_certificate": str(cs.ca_cert), "listen_certificate": str(cert),
               "listen_private_key": str(key), "connect_certificate": str(cert), "connect_private_key": str(key)}
    tls["enable_mtls"] = True
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"], "tls": tls}},
        "access_control": access_control_config(cs.identities),
    }


def router_config_paths(certs: CertSet | str | os.PathLike, *,
                        listen: Sequence[str] | None = None) -> dict[str, Any]:
    """router_config() as {config path: value} for zenoh.Config.insert_json5 (services.router)."""
    conf = router_config(certs, listen=listen)
    return {
        "mode": conf["mode"],
        "listen/endpoints": conf["listen"]["endpoints"],
        "scouting/multicast/enabled": False,
        "transport/link/protocols": conf["transport"]["link"]["protocols"],
        "transport/link/tls": conf["transport"]["link"]["tls"],
        "access_control": conf["access_control"],
    }


def secure_router_config(conf, certs: CertSet | str | os.PathLike) -> CertSet:
    """Make a router's zenoh.Config (already holding mode and listen endpoints) secure, in place: every
    listen endpoint must be tls/; add the TLS certificates (client certificates required), restrict the
    link protocols to tls and add the access control of the identities in ``certs``."""
    cs = certs if isinstance(certs, CertSet) else load_certs(certs)
    try:
        listen = json.loads(conf.get_json("listen/endpoints"))
    except Exception:
        listen = None
    if isinstance(listen, dict):
        listen = listen.get("router", [])
    listen = check_tls_endpoints(listen or [], "listen")
    if not listen:
        raise SecurityError("a secured router needs at least one tls/<host>:<port> listen endpoint")
    try:
        connect = json.loads(conf.get_json("connect/endpoints")) or []
    except Exception:
        connect = []
    check_tls_endpoints(connect if isinstance(connect, list) else [], "connect")
    for path, value in router_config_paths(cs, listen=listen).items():
        if path in ("mode", "listen/endpoints", "scouting/multicast/enabled"):
            continue  # already decided by the caller's options
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as e:
            raise SecurityError(f"zenoh config {path}: {' '.join(str(e).split())[:200]}") from None
    return cs


def check_tls_endpoints(endpoints: Iterable[str], what: str) -> list[str]:
    out = [str(e).strip() for e in endpoints if str(e).strip()]
    bad = [e for e in out if not e.startswith("tls/")]
    if bad:
        raise SecurityError(f"secured {what} endpoints must be tls/<host>:<port>, not {', '.join(bad)}")
    return out


def _fragment_text(conf: dict[str, Any], header: Sequence[str]) -> str:
    return "".join(f"// {h}\n" for h in header) + json.dumps(conf, indent=2) + "\n"


# ---- access control ---------------------------------------------------------------------------

def _prefix(kind: str) -> str:
    return f"{keys.ROOT}/{keys.LAYOUT[kind][0]}/**"


A = keys.ANY


@dataclass(frozen=True)
class Grant:
    """One row of the ACL table: ``messages`` in ``flows`` on ``key_exprs`` (``{id}`` = the identity's
    id). Ingress = from that identity to the router; egress = from the router to that identity."""
    why: str
    messages: tuple[str, ...]
    flows: tuple[str, ...]
    key_exprs: tuple[str, ...]

    def keys_for(self, ident: str) -> list[str]:
        return [k.replace("{id}", ident) for k in self.key_exprs]


def _g(why: str, messages: str, flows: str, *key_exprs: str) -> Grant:
    return Grant(why, tuple(messages.split()), tuple(flows.split()), tuple(key_exprs))


_ID = "{id}"
# Patterns with the identity's own id; built from protocol.keys so the ACL follows the key layout.
_OWN = {
    "fix_as": f"{keys.ROOT}/fix/{A}/{A}/{_ID}",
    "fix_for": f"{keys.ROOT}/fix/{A}/{_ID}/{A}",
    "status": f"{keys.ROOT}/status/rsu/{_ID}",
    "frame": f"{keys.ROOT}/frame/{_ID}",
    "approach": f"{keys.ROOT}/approach/{A}/{_ID}",
    "leave": f"{keys.ROOT}/leave/{A}/{_ID}",
    "alive": f"{keys.ROOT}/alive/{A}/{_ID}",
    "session": f"{keys.ROOT}/session/{A}/{_ID}",
    "fused": f"{keys.ROOT}/fused/{_ID}",
    "imu": f"{keys.ROOT}/imu/{_ID}",
    "gnss": f"{keys.ROOT}/gnss/{_ID}",
}
_ALL_KINDS = tuple(keys.LAYOUT)

ROLE_GRANTS: dict[str, tuple[Grant, ...]] = {
    "rsu": (
        _g("publish PoseFix as itself (any intersection, any bus)", "put", "ingress", _OWN["fix_as"]),
        _g("publish its RsuStatus", "put", "ingress", _OWN["status"]),
        _g("learn the subscribers of fixes and status (or its puts are never sent)",
           "declare_subscriber", "egress", _prefix("pose_fix"), _prefix("rsu_status")),
        _g("read the other RSUs' fixes (where to search)", "declare_subscriber", "ingress", _prefix("pose_fix")),
        _g("", "put", "egress", _prefix("pose_fix")),
        _g("receive its own camera frames", "declare_subscriber", "ingress", _OWN["frame"]),
        _g("", "put", "egress", _OWN["frame"]),
        _g("receive Approach and Leave", "declare_subscriber", "ingress", _prefix("approach"), _prefix("leave")),
        _g("", "put", "egress", _prefix("approach"), _prefix("leave")),
        _g("watch bus liveliness", "declare_liveliness_subscriber liveliness_query", "ingress", _prefix("alive")),
        _g("", "liveliness_token", "egress", _prefix("alive")),
        _g("query active sessions", "query", "ingress", _prefix("sessions")),
        _g("", "reply", "egress", _prefix("sessions")),
    ),
    "bus": (
        _g("announce itself: Approach and Leave", "put", "ingress", _OWN["approach"], _OWN["leave"]),
        _g("its liveliness token", "liveliness_token", "ingress", _OWN["alive"]),
        _g("serve its active sessions", "declare_queryable reply", "ingress", _OWN["session"]),
        _g("", "query", "egress", _prefix("sessions")),
        _g("publish its FusedPose", "put", "ingress", _OWN["fused"]),
        _g("learn the subscribers of what it publishes",
           "declare_subscriber", "egress", _prefix("approach"), _prefix("leave"), _prefix("fused_pose")),
        _g("receive its own PoseFix, IMU and GNSS", "declare_subscriber", "ingress",
           _OWN["fix_for"], _OWN["imu"], _OWN["gnss"]),
        _g("", "put", "egress", _OWN["fix_for"], _OWN["imu"], _OWN["gnss"]),
    ),
    "sim": (
        _g("publish frames, IMU, ground truth, GNSS", "put", "ingress",
           _prefix("frame"), _prefix("imu"), _prefix("ground_truth"), _prefix("gnss")),
        _g("learn their subscribers", "declare_subscriber", "egress",
           _prefix("frame"), _prefix("imu"), _prefix("ground_truth"), _prefix("gnss")),
    ),
    "monitor": (
        _g("read everything, per kind of message (read-only)", "declare_subscriber", "ingress",
           *(_prefix(k) for k in _ALL_KINDS if k not in ("alive", "sessions"))),
        _g("", "put", "egress", *(_prefix(k) for k in _ALL_KINDS if k not in ("alive", "sessions"))),
        _g("watch liveliness", "declare_liveliness_subscriber liveliness_query", "ingress", _prefix("alive")),
        _g("", "liveliness_token", "egress", _prefix("alive")),
        _g("query active sessions", "query", "ingress", _prefix("sessions")),
        _g("", "reply", "egress", _prefix("sessions")),
    ),
    "router": (),  # another router would need its own policy; none is granted
}


def access_control_config(identities: Iterable[Identity]) -> dict[str, Any]:
    """zenoh ``access_control``: default deny; one subject per identity (its certificate CN), one rule
    per ROLE_GRANTS row with the identity's id filled in, one policy per identity."""
    rules, subjects, policies = [], [], []
    for who in identities:
        grants = ROLE_GRANTS.get(who.role, ())
        if not grants:
            continue
        subjects.append({"id": who.cn, "cert_common_names": [who.cn]})
        ids = []
        for n, g in enumerate(grants):
            rid = f"{who.cn}#{n}"
            rules.append({"id": rid, "permission": "allow", "flows": list(g.flows), "messages": list(g.messages),
                          "key_exprs": g.keys_for(who.id)})
            ids.append(rid)
        policies.append({"id": who.cn, "rules": ids, "subjects": [who.cn]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def acl_table() -> str:
    """The ACL as a Markdown table (docs/security.md)."""
    lines = ["| role | messages | flow | key expressions | why |", "| --- | --- | --- | --- | --- |"]
    for role, grants in ROLE_GRANTS.items():
        for g in grants:
            lines.append(f"| {role} | {', '.join(g.messages)} | {', '.join(g.flows)} | "
                         f"{'<br>'.join('`' + k + '`' for k in g.key_exprs)} | {g.why or '(goes with the row above)'} |")
    return "\n".join(lines)


# ---- manifest ---------------------------------------------------------------------------------

def load_certs(directory: str | os.PathLike) -> CertSet:
    d = Path(directory).resolve()
    path = d / MANIFEST
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise SecurityError(f"{path} not found: generate certificates with `toptag certs --out {directory} ...`") from None
    except (OSError, ValueError) as e:
        raise SecurityError(f"{path}: cannot read: {e}") from None
    try:
        router = Identity("router", data["router"]["id"])
        ids = [Identity(i["role"], i["id"]) for i in data["identities"]]
        for who in ids:
            common_name(who.role, who.id)
        return CertSet(dir=d, ca_cert=d / data.get("ca", CA_CERT), router=router,
                       router_hosts=list(data["router"].get("hosts", [])), identities=ids)
    except (KeyError, TypeError, SecurityError) as e:
        raise SecurityError(f"{path}: not a toptag certificate manifest ({e})") from None


def _write_manifest(cs: CertSet) -> None:
    data = {"version": 1, "ca": CA_CERT,
            "router": {"id": cs.router.id, "cn": cs.router.cn, "hosts": cs.router_hosts},
            "identities": [{"role": w.role, "id": w.id, "cn": w.cn, "cert": f"{w.stem}.pem", "key": f"{w.stem}.key",
                            "config": f"{w.stem}.json5"} for w in cs.identities]}
    (cs.dir / MANIFEST).write_text(json.dumps(data, indent=2) + "\n")


def _not_after(exe: str, cert: Path) -> str:
    try:
        r = subprocess.run([exe, "x509", "-in", str(cert), "-noout", "-enddate"], capture_output=True,
                           text=True, timeout=30, check=False)
        return r.stdout.strip().partition("=")[2] or "?"
    except (OSError, subprocess.TimeoutExpired):
        return "?"


def generate_certs(out: str | os.PathLike, router: str = "router", *, router_hosts: Sequence[str] = (),
                   rsus: Sequence[str] = (), buses: Sequence[str] = (), sims: Sequence[str] = (),
                   monitors: Sequence[str] = (), days: int = DEFAULT_DAYS, openssl: str | None = None,
                   log=None) -> CertSet:
    """Create (or reuse) the CA in ``out`` and issue a certificate, key and zenoh config fragment per
    identity; write the manifest. Identities already in an existing manifest are kept (and re-issued
    if named again). Raises SecurityError (one line)."""
    exe = _openssl_path(openssl)
    if days < 1:
        raise SecurityError("--days must be at least 1")
    say = log or (lambda _msg: None)
    out = Path(out).resolve()
    wanted = [Identity("router", router)] + [Identity(r, i) for r, ids in
                                             (("rsu", rsus), ("bus", buses), ("sim", sims), ("monitor", monitors))
                                             for i in ids]
    for who in wanted:
        common_name(who.role, who.id)  # validate before touching anything
    if len({w.stem for w in wanted}) != len(wanted):
        raise SecurityError("an identity is named twice")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SecurityError(f"cannot create {out}: {e.strerror}") from None
    hosts = list(dict.fromkeys([*DEFAULT_ROUTER_HOSTS, router, *router_hosts]))

    previous: list[Identity] = []
    if (out / CA_KEY).exists() and (out / CA_CERT).exists():
        say(f"using the existing CA {out / CA_CERT}")
        if (out / MANIFEST).exists():
            old = load_certs(out)
            previous = [w for w in old.identities if w.role != "router"]
    elif (out / CA_KEY).exists() or (out / CA_CERT).exists():
        raise SecurityError(f"{out} holds only one of {CA_CERT} and {CA_KEY}: remove it or give both")
    else:
        _make_ca(exe, out, max(CA_DAYS, days))
        say(f"created CA {out / CA_CERT}")

    for who in wanted:
        _issue(exe, out, who, days, hosts if who.role == "router" else ())
    identities = wanted + [w for w in previous if w not in wanted]
    cs = CertSet(dir=out, ca_cert=out / CA_CERT, router=wanted[0], router_hosts=hosts, identities=identities)
    _write_manifest(cs)

    for who in wanted:
        expires = _not_after(exe, cs.cert(who))
        if who.role == "router":
            conf = router_config(cs, inline=True)
            header = [f"zenoh config of the secured toptag router {who.cn} (generated by `toptag certs`;",
                      f"certificate valid until {expires}). Embeds its private key: keep it private.",
                      "Equivalent to `toptag router --secure DIR`; the access control is fixed at start."]
        else:
            conf = client_config(cs, who.role, who.id)
            header = [f"zenoh config fragment of {who.cn} (generated by `toptag certs`; certificate valid",
                      f"until {expires}). Embeds its private key: keep it private. Use with",
                      "--zenoh-config THIS --connect tls/<router host>:7447 (or TOPTAG_ZENOH_CONFIG /",
                      "TOPTAG_ZENOH_CONNECT)."]
        path = cs.config(who)
        path.write_text(_fragment_text(conf, header))
        _private(path)
        say(f"{who.cn:<24} {cs.cert(who).name}  {path.name}  (until {expires})")
    return cs


# ---- command line -----------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="toptag certs",
        description="Generate a CA and mutual-TLS certificates for toptag services (CN = <role>:<id>), "
                    "one zenoh config fragment per identity and the manifest `toptag router --secure` reads.")
    p.add_argument("--out", required=True, metavar="DIR", help="directory to write to (an existing CA there is reused)")
    p.add_argument("--router", default="router", metavar="NAME", help="router name (CN router:NAME; also a DNS SAN)")
    p.add_argument("--router-host", action="append", default=[], metavar="HOST",
                   help="extra DNS name or IP address of the router for its certificate (repeatable; "
                        "localhost, 127.0.0.1, ::1 and NAME are always included)")
    p.add_argument("--rsu", action="append", default=[], metavar="ID", help="RSU identity (repeatable)")
    p.add_argument("--bus", action="append", default=[], metavar="ID", help="bus identity (repeatable)")
    p.add_argument("--sim", action="append", default=[], metavar="ID", help="simulator identity (repeatable)")
    p.add_argument("--monitor", action="append", default=[], metavar="ID", help="read-only monitor identity (repeatable)")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity of the issued certificates (default {DEFAULT_DAYS})")
    p.add_argument("--openssl", default=None, metavar="PATH", help=f"openssl executable (env {ENV_OPENSSL}; default: openssl on PATH)")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    say = (lambda _m: None) if args.quiet else (lambda m: print(m, flush=True))
    try:
        cs = generate_certs(args.out, args.router, router_hosts=args.router_host, rsus=args.rsu, buses=args.bus,
                            sims=args.sim, monitors=args.monitor, days=args.days, openssl=args.openssl, log=say)
    except SecurityError as e:
        return report("certs", e)
    say(f"wrote {cs.dir / MANIFEST}; start the router with: toptag router --secure {cs.dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
