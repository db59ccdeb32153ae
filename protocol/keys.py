"""Zenoh key expressions of toptag, all under one versioned root. Build keys only with these functions.

Every id argument is validated (protocol.messages.check_id). Pass ``ANY`` ("*", one chunk) in place of
an id to build a subscription / query pattern; publishing helpers refuse patterns (``is_pattern``).

| function                             | key expression                                     | payload        |
|--------------------------------------|----------------------------------------------------|----------------|
| approach(intersection, bus)          | toptag/v1/approach/<intersection>/<bus>            | Approach       |
| leave(intersection, bus)             | toptag/v1/leave/<intersection>/<bus>               | Leave          |
| pose_fix(intersection, bus, rsu)     | toptag/v1/fix/<intersection>/<bus>/<rsu>           | PoseFix        |
| frame(rsu)                           | toptag/v1/frame/<rsu>                              | Frame          |
| rsu_status(rsu)                      | toptag/v1/status/rsu/<rsu>                         | RsuStatus      |
| detections(rsu)                      | toptag/v1/detections/<rsu>                         | TagDetections  |
| rsu_diagnosis(intersection, rsu, bus)| toptag/v1/diag/<intersection>/<rsu>/<bus>          | RsuDiagnosis   |
| imu(bus)                             | toptag/v1/imu/<bus>                                | Imu            |
| imu_batch(bus)                       | toptag/v1/imu_batch/<bus>                          | ImuBatch       |
| ground_truth(bus)                    | toptag/v1/truth/<bus>                              | GroundTruth    |
| gnss(bus)                            | toptag/v1/gnss/<bus>                               | GnssFix        |
| fused_pose(bus)                      | toptag/v1/fused/<bus>                              | FusedPose      |
| alive(intersection, bus)             | toptag/v1/alive/<intersection>/<bus>               | liveliness     |
| sessions(intersection, bus=ANY)      | toptag/v1/session/<intersection>/<bus>             | ActiveSessions |
"""
from __future__ import annotations

from dataclasses import dataclass

from protocol.messages import PROTOCOL_VERSION, check_id
from toptag.errors import ProtocolError

ROOT = f"toptag/v{PROTOCOL_VERSION}"
ANY = "*"
EVERYTHING = f"{ROOT}/**"

# kind -> (path segment, names of the id chunks in order)
LAYOUT: dict[str, tuple[str, tuple[str, ...]]] = {
    "approach": ("approach", ("intersection", "bus")),
    "leave": ("leave", ("intersection", "bus")),
    "pose_fix": ("fix", ("intersection", "bus", "rsu")),
    "frame": ("frame", ("rsu",)),
    "rsu_status": ("status/rsu", ("rsu",)),
    "tag_detections": ("detections", ("rsu",)),
    "rsu_diagnosis": ("diag", ("intersection", "rsu", "bus")),
    "imu": ("imu", ("bus",)),
    "imu_batch": ("imu_batch", ("bus",)),
    "ground_truth": ("truth", ("bus",)),
    "gnss": ("gnss", ("bus",)),
    "fused_pose": ("fused", ("bus",)),
    "alive": ("alive", ("intersection", "bus")),
    "sessions": ("session", ("intersection", "bus")),
}


class KeyExprError(ProtocolError):
    """An id cannot be put in a key expression, or a key is not one of toptag's."""

    def __init__(self, message: str):
        super().__init__(message, reason="key")


def _chunk(name: str, value: str) -> str:
    if value == ANY:
        return value
    try:
        return check_id(value)
    except ValueError as e:
        raise KeyExprError(f"{name}: {e}") from None


def _build(kind: str, *ids: str) -> str:
    segment, names = LAYOUT[kind]
    return "/".join([ROOT, segment, *(_chunk(n, v) for n, v in zip(names, ids, strict=True))])


def approach(intersection: str, bus: str) -> str:
    return _build("approach", intersection, bus)


def leave(intersection: str, bus: str) -> str:
    return _build("leave", intersection, bus)


def pose_fix(intersection: str, bus: str, rsu: str) -> str:
    return _build("pose_fix", intersection, bus, rsu)


def frame(rsu: str) -> str:
    return _build("frame", rsu)


def rsu_status(rsu: str) -> str:
    return _build("rsu_status", rsu)


def detections(rsu: str) -> str:
    return _build("tag_detections", rsu)


def rsu_diagnosis(intersection: str, rsu: str, bus: str) -> str:
    """A bus's assessment of an RSU (time offset, drift flag); the RSU subscribes to its own."""
    return _build("rsu_diagnosis", intersection, rsu, bus)


def imu(bus: str) -> str:
    return _build("imu", bus)


def imu_batch(bus: str) -> str:
    """A bus's IMU samples several to a message (ImuBatch); imu(bus) carries them one at a time."""
    return _build("imu_batch", bus)


def ground_truth(bus: str) -> str:
    return _build("ground_truth", bus)


def gnss(bus: str) -> str:
    return _build("gnss", bus)


def fused_pose(bus: str) -> str:
    return _build("fused_pose", bus)


def alive(intersection: str, bus: str) -> str:
    """Liveliness token of a bus that is in a session at an intersection."""
    return _build("alive", intersection, bus)


def sessions(intersection: str, bus: str = ANY) -> str:
    """Queryable of active sessions. A bus serves sessions(intersection, its_id); an RSU queries
    sessions(intersection) (every bus there)."""
    return _build("sessions", intersection, bus)


def every(kind: str) -> str:
    """Every key of one kind of message (``kind`` as in LAYOUT), and nothing else: a pattern for access
    control, e.g. every("pose_fix") == "toptag/v1/fix/**"."""
    if kind not in LAYOUT:
        raise KeyExprError(f"no kind of message {kind!r} (one of {', '.join(LAYOUT)})")
    return f"{ROOT}/{LAYOUT[kind][0]}/**"


def key_of(msg) -> str:
    """The key a message is published on, from its own ids (ActiveSessions: its responder's key)."""
    t = getattr(msg, "TYPE", None)
    if t in ("approach", "leave", "alive"):
        return _build(t, msg.intersection_id, msg.bus_id)
    if t == "pose_fix":
        return pose_fix(msg.intersection_id, msg.bus_id, msg.rsu_id)
    if t == "rsu_diagnosis":
        return rsu_diagnosis(msg.intersection_id, msg.rsu_id, msg.bus_id)
    if t in ("frame", "rsu_status", "tag_detections"):
        return _build(t, msg.rsu_id)
    if t in ("imu", "imu_batch", "ground_truth", "gnss", "fused_pose"):
        return _build(t, msg.bus_id)
    if t == "active_sessions":
        return sessions(msg.intersection_id, msg.responder_id)
    raise KeyExprError(f"no key for {type(msg).__name__}")


def is_pattern(key: str) -> bool:
    """True if the key expression holds a wildcard (cannot be published to)."""
    return "*" in key or "$" in key


@dataclass(frozen=True)
class ParsedKey:
    kind: str
    ids: dict[str, str]

    def __getitem__(self, name: str) -> str:
        return self.ids[name]


_BY_SEGMENT = sorted(((seg.split("/"), kind, names) for kind, (seg, names) in LAYOUT.items()),
                     key=lambda t: -len(t[0]))


def parse(key: str) -> ParsedKey:
    """Split a concrete toptag key into its kind and ids, e.g.
    parse("toptag/v1/fix/x1/bus-17/rsu-sw") -> ParsedKey("pose_fix", {"intersection": "x1", ...})."""
    key = str(key)
    root = ROOT.split("/")
    chunks = key.split("/")
    if chunks[: len(root)] != root:
        raise KeyExprError(f"key {key!r} is not under {ROOT}/")
    rest = chunks[len(root):]
    for seg, kind, names in _BY_SEGMENT:
        if rest[: len(seg)] == seg and len(rest) == len(seg) + len(names):
            values = rest[len(seg):]
            for n, v in zip(names, values):
                _chunk(n, v)
            return ParsedKey(kind, dict(zip(names, values)))
    raise KeyExprError(f"key {key!r} is not a toptag key")


# Which message field carries which key id, to check a message against the key it came on.
ID_FIELDS = {"intersection": "intersection_id", "bus": "bus_id", "rsu": "rsu_id"}
