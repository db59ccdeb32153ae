"""Who may connect: roles, identities and their certificate common names (CN = ``<role>:<id>``)."""
from __future__ import annotations

import re
from dataclasses import dataclass

from toptag.errors import InputError

ROLES = ("router", "rsu", "bus", "sim", "monitor")
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


class SecurityError(InputError):
    """Certificates or a secured config cannot be made from what was given. str(e) is one line."""


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
