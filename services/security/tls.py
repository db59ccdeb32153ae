"""Zenoh TLS configs: a client's fragment (mutual TLS with its certificate) and the secured router's
config (TLS listeners requiring client certificates, only the tls protocol, access control)."""
from __future__ import annotations

import base64
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from protocol.transport.config import FIX_QUEUE_BATCHES
from services.security.acl import access_control_config
from services.security.identities import SecurityError
from services.security.manifest import CertSet, load_certs

DEFAULT_PORT = 7447
DEFAULT_SECURE_LISTEN = (f"tls/0.0.0.0:{DEFAULT_PORT}",)


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
        "transport": {"link": {"protocols": ["tls"], "tls": tls,
                               "tx": {"queue": {"size": {"interactive_high": FIX_QUEUE_BATCHES}}}}},
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


def fragment_text(conf: dict[str, Any], header: Sequence[str]) -> str:
    return "".join(f"// {h}\n" for h in header) + json.dumps(conf, indent=2) + "\n"
