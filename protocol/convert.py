"""Between the core's vocabulary and the wire: the only place where a `toptag.fix.Fix` becomes a
`PoseFix` message (and back) and a `toptag.fusion.state.FusedState` becomes a `FusedPose` message.

Field names differ on purpose: the wire names say what the receiver needs (``capture_time_ns``,
``rsu_id``, ``frame_seq``), the core names are the filter's (``t_ns``, ``source``, ``seq``)."""
from __future__ import annotations

import math

from protocol.messages import FusedPose, FusionHealth, PoseFix
from toptag.fix import Fix
from toptag.fusion.state import FusedState, Health
from toptag.units import ns_from_s


def fix_to_message(fix: Fix, bus_id: str, intersection_id: str, publish_time_ns: int,
                   processing_ns: int | None = None) -> PoseFix:
    """The wire PoseFix of an RSU's fix of ``bus_id``. The fix must say how it was made (method, tags,
    rms_px, z, seq), as an RSU's fix from `Fix.from_solution` does; raises ValueError otherwise."""
    missing = [name for name, v in (("method", fix.method), ("tags", fix.tags), ("rms_px", fix.rms_px),
                                    ("z", fix.z), ("seq", fix.seq)) if v is None or v == ()]
    if missing:
        raise ValueError(f"fix from {fix.source} at {fix.t_ns} lacks {', '.join(missing)} for the wire")
    return PoseFix(bus_id=bus_id, rsu_id=fix.source, intersection_id=intersection_id,
                   capture_time_ns=fix.t_ns, publish_time_ns=publish_time_ns, x=fix.x, y=fix.y, z=fix.z,
                   yaw=fix.yaw, covariance=fix.cov.tolist(), method=fix.method, tags_used=list(fix.tags),
                   reprojection_rms_px=fix.rms_px, frame_seq=fix.seq, processing_ns=processing_ns,
                   ambiguous=fix.ambiguous)


def fix_from_message(m: PoseFix, arrival_ns: int | None = None) -> Fix:
    """The core fix of a received PoseFix; ``arrival_ns`` is when it arrived (for the filter's health)."""
    return Fix(t_ns=m.capture_time_ns, x=m.x, y=m.y, yaw=m.yaw, cov=m.covariance_matrix(), source=m.rsu_id,
               seq=m.frame_seq, arrival_ns=arrival_ns, z=m.z, method=m.method, tags=tuple(m.tags_used),
               rms_px=m.reprojection_rms_px, ambiguous=m.ambiguous)


def _ns_or_none(seconds: float) -> int | None:
    return ns_from_s(seconds) if math.isfinite(seconds) else None


def health_to_message(h: Health) -> FusionHealth:
    return FusionHealth(status=h.status, accepted_fixes=h.accepted, rejected_fixes=h.rejected,
                        since_last_fix_ns=_ns_or_none(h.since_last_fix_s),
                        last_fix_delay_ns=_ns_or_none(h.last_fix_delay_s), last_fix_rsu=h.last_fix_source)


def fused_to_message(state: FusedState, bus_id: str) -> FusedPose:
    """The wire FusedPose of a bus's fused state (the wire carries the pose part and its health)."""
    return FusedPose(bus_id=bus_id, t_ns=state.t_ns, x=state.x, y=state.y, yaw=state.yaw, speed=state.speed,
                     yaw_rate=state.yaw_rate, covariance=state.cov.tolist(), health=health_to_message(state.health))
