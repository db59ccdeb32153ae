"""Transport security for toptag (one module per concept: identities, pki, manifest, tls, acl, certs): a private CA and mutual TLS certificates (`toptag certs`), the zenoh
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
from services.security.acl import ROLE_GRANTS, Grant, access_control_config, acl_table
from services.security.certs import build_parser, generate_certs, main
from services.security.identities import ROLES, Identity, SecurityError, common_name
from services.security.manifest import CA_CERT, CA_KEY, MANIFEST, CertSet, load_certs
from services.security.pki import DEFAULT_DAYS, ENV_OPENSSL
from services.security.tls import (
    DEFAULT_PORT,
    DEFAULT_SECURE_LISTEN,
    check_tls_endpoints,
    client_config,
    client_tls_settings,
    router_config,
    router_config_paths,
    secure_router_config,
)

__all__ = [
    "CA_CERT", "CA_KEY", "DEFAULT_DAYS", "DEFAULT_PORT", "DEFAULT_SECURE_LISTEN", "ENV_OPENSSL", "MANIFEST", "ROLES",
    "ROLE_GRANTS", "CertSet", "Grant", "Identity", "SecurityError", "access_control_config", "acl_table",
    "build_parser", "check_tls_endpoints", "client_config", "client_tls_settings", "common_name", "generate_certs",
    "load_certs", "main", "router_config", "router_config_paths", "secure_router_config",
]
