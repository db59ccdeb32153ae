"""The certificate directory: what `toptag certs` wrote (CertSet) and its manifest, toptag-certs.json,
from which `toptag router --secure DIR` builds its access control."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from services.security.identities import Identity, SecurityError, common_name

MANIFEST = "toptag-certs.json"
CA_CERT, CA_KEY = "ca.pem", "ca.key"


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


def write_manifest(cs: CertSet) -> None:
    data = {"version": 1, "ca": CA_CERT,
            "router": {"id": cs.router.id, "cn": cs.router.cn, "hosts": cs.router_hosts},
            "identities": [{"role": w.role, "id": w.id, "cn": w.cn, "cert": f"{w.stem}.pem", "key": f"{w.stem}.key",
                            "config": f"{w.stem}.json5"} for w in cs.identities]}
    (cs.dir / MANIFEST).write_text(json.dumps(data, indent=2) + "\n")
