"""The router's access control: what each role may publish, subscribe to, query and declare, bound to
the identity's own ids. Every key expression comes from protocol.keys, so the ACL follows the key
layout. Zenoh 1.10 facts it relies on are in the package docstring (services.security)."""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from protocol import keys
from services.security.identities import Identity

A = keys.ANY
_ID = "{id}"  # the identity's own id, filled in per identity (Grant.keys_for)
_prefix = keys.every


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


# Patterns on the identity's own keys, built by protocol.keys like every key on the wire.
_OWN = {
    "fix_as": keys.pose_fix(A, A, _ID),
    "fix_for": keys.pose_fix(A, _ID, A),
    "status": keys.rsu_status(_ID),
    "detections": keys.detections(_ID),
    "frame": keys.frame(_ID),
    "approach": keys.approach(A, _ID),
    "leave": keys.leave(A, _ID),
    "alive": keys.alive(A, _ID),
    "session": keys.sessions(A, _ID),
    "fused": keys.fused_pose(_ID),
    "diag_by": keys.rsu_diagnosis(A, A, _ID),
    "diag_of": keys.rsu_diagnosis(A, _ID, A),
    "imu": keys.imu(_ID),
    "imu_batch": keys.imu_batch(_ID),
    "gnss": keys.gnss(_ID),
}
_ALL_KINDS = tuple(keys.LAYOUT)

ROLE_GRANTS: dict[str, tuple[Grant, ...]] = {
    "rsu": (
        _g("publish PoseFix as itself (any intersection, any bus)", "put", "ingress", _OWN["fix_as"]),
        _g("publish its RsuStatus and its TagDetections", "put", "ingress", _OWN["status"], _OWN["detections"]),
        _g("learn the subscribers of fixes, status and detections (or its puts are never sent)",
           "declare_subscriber", "egress", _prefix("pose_fix"), _prefix("rsu_status"), _prefix("tag_detections")),
        _g("read the other RSUs' fixes (where to search)", "declare_subscriber", "ingress", _prefix("pose_fix")),
        _g("", "put", "egress", _prefix("pose_fix")),
        _g("receive the buses' diagnoses of itself (time offset, drift flag)", "declare_subscriber", "ingress",
           _OWN["diag_of"]),
        _g("", "put", "egress", _OWN["diag_of"]),
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
        _g("publish its FusedPose and its diagnoses of RSUs", "put", "ingress", _OWN["fused"], _OWN["diag_by"]),
        _g("learn the subscribers of what it publishes", "declare_subscriber", "egress",
           _prefix("approach"), _prefix("leave"), _prefix("fused_pose"), _prefix("rsu_diagnosis")),
        _g("receive its own PoseFix, IMU and GNSS", "declare_subscriber", "ingress",
           _OWN["fix_for"], _OWN["imu"], _OWN["imu_batch"], _OWN["gnss"]),
        _g("", "put", "egress", _OWN["fix_for"], _OWN["imu"], _OWN["imu_batch"], _OWN["gnss"]),
    ),
    "sim": (
        _g("publish frames, IMU, ground truth, GNSS", "put", "ingress",
           _prefix("frame"), _prefix("imu"), _prefix("imu_batch"), _prefix("ground_truth"), _prefix("gnss")),
        _g("learn their subscribers", "declare_subscriber", "egress",
           _prefix("frame"), _prefix("imu"), _prefix("imu_batch"), _prefix("ground_truth"), _prefix("gnss")),
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
