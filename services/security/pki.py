"""The private CA and the certificates, made with the openssl command line tool (EC P-256 keys, mode
0600)."""
from __future__ import annotations

import ipaddress
import os
import secrets
import shutil
import subprocess
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

from services.security.identities import Identity, SecurityError
from services.security.manifest import CA_CERT, CA_KEY

DEFAULT_DAYS = 365
CA_DAYS = 3650
ENV_OPENSSL = "TOPTAG_OPENSSL"


def openssl_path(openssl: str | None = None) -> str:
    exe = openssl or os.environ.get(ENV_OPENSSL) or "openssl"
    found = shutil.which(exe)
    if not found:
        raise SecurityError(f"openssl command {exe!r} not found: install OpenSSL (the command line tool) "
                            f"or pass --openssl PATH")
    return found


def run_openssl(exe: str, args: Sequence[str], what: str) -> None:
    try:
        r = subprocess.run([exe, *args], capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise SecurityError(f"openssl ({what}) could not run: {e}") from None
    if r.returncode != 0:
        lines = [ln.strip() for ln in (r.stderr or r.stdout or "").splitlines() if ln.strip()]
        detail = lines[0] if lines else f"exit status {r.returncode}"
        raise SecurityError(f"openssl ({what}) failed: {detail}")


def private(path: Path) -> None:
    os.chmod(path, 0o600)


def new_key(exe: str, path: Path) -> None:
    run_openssl(exe, ["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
                       "-out", str(path)], f"key {path.name}")
    private(path)


def make_ca(exe: str, out: Path, days: int) -> None:
    key, cert = out / CA_KEY, out / CA_CERT
    new_key(exe, key)
    run_openssl(exe, ["req", "-x509", "-new", "-key", str(key), "-sha256", "-days", str(days),
                       "-subj", "/O=toptag/CN=toptag CA", "-set_serial", serial(),
                       "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
                       "-addext", "keyUsage=critical,keyCertSign,cRLSign",
                       "-addext", "subjectKeyIdentifier=hash",
                       "-out", str(cert)], "CA certificate")


def serial() -> str:
    return "0x" + secrets.token_hex(16)


def san(hosts: Iterable[str]) -> str:
    names = []
    for h in hosts:
        try:
            names.append(f"IP:{ipaddress.ip_address(h)}")
        except ValueError:
            names.append(f"DNS:{h}")
    return ",".join(dict.fromkeys(names))


def issue(exe: str, out: Path, who: Identity, days: int, hosts: Sequence[str] = ()) -> None:
    key, cert = out / f"{who.stem}.key", out / f"{who.stem}.pem"
    new_key(exe, key)
    ext = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature",
           "subjectKeyIdentifier=hash", "authorityKeyIdentifier=keyid"]
    if who.role == "router":
        ext.append("extendedKeyUsage=serverAuth,clientAuth")
        ext.append(f"subjectAltName={san(hosts)}")
    else:
        ext.append("extendedKeyUsage=clientAuth")
    with tempfile.TemporaryDirectory(prefix="toptag-certs-") as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text("\n".join(ext) + "\n")
        run_openssl(exe, ["req", "-new", "-key", str(key), "-subj", f"/O=toptag/CN={who.cn}",
                           "-out", str(csr)], f"request for {who.cn}")
        run_openssl(exe, ["x509", "-req", "-in", str(csr), "-CA", str(out / CA_CERT),
                           "-CAkey", str(out / CA_KEY), "-set_serial", serial(), "-days", str(days),
                           "-sha256", "-extfile", str(extfile), "-out", str(cert)],
                     f"certificate for {who.cn}")


def not_after(exe: str, cert: Path) -> str:
    try:
        r = subprocess.run([exe, "x509", "-in", str(cert), "-noout", "-enddate"], capture_output=True,
                           text=True, timeout=30, check=False)
        return r.stdout.strip().partition("=")[2] or "?"
    except (OSError, subprocess.TimeoutExpired):
        return "?"
