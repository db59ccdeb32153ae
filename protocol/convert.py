"""Between the core's vocabulary and the wire: the only place where a `toptag.fix.Fix` becomes a
`PoseFix` message (and back), a `toptag.fusion.state.FusedState` becomes a `FusedPose` message, a
`toptag.fusion.trust.RsuAssessment` an `RsuDiagnosis`, a `toptag.hostclock.HostClock` a `ClockInfo`, and a
bus's `CoarsePosition` the RSU's `toptag.rsu.whereabouts.ReportedPosition`.

Field names differ on purpose: the wire names say what the receiver needs (``capture_time_ns``,
``rsu_id``, ``frame_seq``), the core names are the filter's (``t_ns``, ``source``, ``seq``)."""
from __future__ import annotations

import math

from pydantic_core import to_json

from protocol import codec
from protocol.messages import (
    PROTOCOL_VERSION,
    ClockInfo,
    CoarsePosition,
    FusedPose,
    FusionHealth,
    PoseFix,
    RsuDiagnosis,
    check_id,
)
from toptag.fix import Fix, clearly_covariance
from toptag.fusion.outcomes import FixOutcome, applied_count
from toptag.fusion.state import FusedState, Health
from toptag.fusion.trust import RsuAssessment
from toptag.geometry import wrap_angle
from toptag.hostclock import HostClock
from toptag.rsu.whereabouts import ReportedPosition
from toptag.units import ns_from_s


def clock_to_message(clock: HostClock) -> ClockInfo:
    """The wire ClockInfo of a host's clock (toptag.hostclock)."""
    return ClockInfo(source=clock.source, sync_uncertainty_ns=clock.bound_ns)


def fix_to_message(fix: Fix, bus_id: str, intersection_id: str, publish_time_ns: int,
                   processing_ns: int | None = None, clock: ClockInfo | None = None) -> PoseFix:
    """The wire PoseFix of an RSU's fix of ``bus_id``; ``clock``: the clock that stamped its capture time.
    The fix must say how it was made (method, tags, rms_px, z, seq), as an RSU's fix from
    `Fix.from_solution` does; raises ValueError otherwise."""
    missing = [name for name, v in (("method", fix.method), ("tags", fix.tags), ("rms_px", fix.rms_px),
                                    ("z", fix.z), ("seq", fix.seq)) if v is None or v == ()]
    if missing:
        raise ValueError(f"fix from {fix.source} at {fix.t_ns} lacks {', '.join(missing)} for the wire")
    return PoseFix(bus_id=bus_id, rsu_id=fix.source, intersection_id=intersection_id,
                   capture_time_ns=fix.t_ns, publish_time_ns=publish_time_ns, x=fix.x, y=fix.y, z=fix.z,
                   yaw=fix.yaw, covariance=fix.cov.tolist(), method=fix.method, tags_used=list(fix.tags),
                   reprojection_rms_px=fix.rms_px, frame_seq=fix.seq, processing_ns=processing_ns,
                   ambiguous=fix.ambiguous, clock=clock,
                   calibration_covariance=None if fix.calib_cov is None else fix.calib_cov.tolist(),
                   calibration_id=fix.calib_id)


def fix_from_message(m: PoseFix, arrival_ns: int | None = None) -> Fix:
    """The core fix of a received PoseFix; ``arrival_ns`` is when it arrived (for the filter's health).
    Its clock bound is the message's (None, an unknown clock, when the message says none)."""
    return Fix(t_ns=m.capture_time_ns, x=m.x, y=m.y, yaw=m.yaw, cov=m.covariance_matrix(), source=m.rsu_id,
               seq=m.frame_seq, arrival_ns=arrival_ns, z=m.z, method=m.method, tags=tuple(m.tags_used),
               rms_px=m.reprojection_rms_px, ambiguous=m.ambiguous,
               clock_bound_ns=None if m.clock is None else m.clock.sync_uncertainty_ns,
               calib_cov=m.calibration_covariance, calib_id=m.calibration_id)


def reported_position(p: CoarsePosition) -> ReportedPosition:
    """What an RSU makes of a bus's coarse position (its Approach's): a GNSS one gets the RSU's floor
    on its sigma (toptag.rsu.whereabouts.GNSS_SIGMA_FLOOR_M)."""
    return ReportedPosition(p.t_ns, p.x, p.y, p.sigma_m, None if p.vx is None else (p.vx, p.vy),
                            p.velocity_sigma_mps or 0.0, p.speed_mps, p.yaw, p.yaw_sigma_rad or 0.0,
                            gnss=p.source == "gnss")


def _ns_or_none(seconds: float) -> int | None:
    return ns_from_s(seconds) if math.isfinite(seconds) else None


def health_to_message(h: Health) -> FusionHealth:
    return FusionHealth(status=h.status, accepted_fixes=h.accepted, rejected_fixes=h.rejected,
                        since_last_fix_ns=_ns_or_none(h.since_last_fix_s),
                        last_fix_delay_ns=_ns_or_none(h.last_fix_delay_s), last_fix_rsu=h.last_fix_source,
                        too_old_fixes=h.too_old, future_fixes=h.future, flagged_rsu_fixes=h.from_flagged_rsu,
                        unknown_clock_fixes=h.unknown_clock, other_fixes=h.other, flagged_rsus=list(h.flagged_rsus))


def fused_to_message(state: FusedState, bus_id: str) -> FusedPose:
    """The wire FusedPose of a bus's fused state (the wire carries the pose part and its health)."""
    return FusedPose(bus_id=bus_id, t_ns=state.t_ns, x=state.x, y=state.y, yaw=state.yaw, speed=state.speed,
                     yaw_rate=state.yaw_rate, covariance=state.cov.tolist(), health=health_to_message(state.health))


_STATUSES = frozenset(FusionHealth.model_fields["status"].annotation.__args__[0].__args__)


def fused_pose_payload(state: FusedState, bus_id: str) -> bytes:
    """``codec.encode(fused_to_message(state, bus_id))``, the same bytes (tests/test_protocol_fastpaths.py),
    from a dict in one pydantic-core call instead of validating a FusionHealth and a FusedPose and dumping
    them: the bus agent sends one 50 times a second, each cold after its 20 ms wait, where building and
    encoding them cost ~240 us of CPU and this ~60 us (docs/architecture.md). Every check of the models is
    made here, cheaply; a value that needs more (or fails) takes the models' path, which decides or raises."""
    h = state.health
    t_ns, yaw = state.t_ns, state.yaw
    x, y, speed, yaw_rate = float(state.x), float(state.y), float(state.speed), float(state.yaw_rate)
    cov = state.cov.tolist()
    since, delay = _ns_or_none(h.since_last_fix_s), _ns_or_none(h.last_fix_delay_s)
    counts = (h.accepted, h.rejected, h.too_old, h.future, h.from_flagged_rsu, h.unknown_clock, h.other)
    rsu = h.last_fix_source
    if (type(t_ns) is int and t_ns >= 0 and math.isfinite(x + y + yaw + speed + yaw_rate) and clearly_covariance(cov)
            and all(type(n) is int and n >= 0 for n in counts) and (since is None or since >= 0)
            and (delay is None or delay >= 0) and h.status in _STATUSES and not h.flagged_rsus
            and _is_id(bus_id) and (rsu is None or _is_id(rsu))):
        return to_json({
            "version": PROTOCOL_VERSION, "type": FusedPose.TYPE, "bus_id": bus_id, "t_ns": t_ns, "x": x, "y": y,
            "yaw": wrap_angle(yaw), "speed": speed, "yaw_rate": yaw_rate, "covariance": cov,
            "health": {"status": h.status, "accepted_fixes": counts[0], "rejected_fixes": counts[1],
                       "since_last_fix_ns": since, "last_fix_delay_ns": delay, "last_fix_rsu": rsu,
                       "too_old_fixes": counts[2], "future_fixes": counts[3], "flagged_rsu_fixes": counts[4],
                       "unknown_clock_fixes": counts[5], "other_fixes": counts[6], "flagged_rsus": []}})
    return codec.encode(fused_to_message(state, bus_id))


_IDS: set[str] = set()  # ids check_id passed: the bus's own and its RSUs', a handful
_IDS_MAX = 1024


def _is_id(value) -> bool:
    if type(value) is str and value in _IDS:
        return True
    try:
        check_id(value)
    except ValueError:
        return False
    if len(_IDS) < _IDS_MAX:
        _IDS.add(value)
    return True


def assessment_to_message(a: RsuAssessment, bus_id: str, intersection_id: str, reference_time_ns: int) -> RsuDiagnosis:
    """The wire RsuDiagnosis of a bus filter's assessment of one RSU."""
    fixes = a.fixes
    accepted = applied_count(fixes)
    gated = fixes.get(FixOutcome.REJECTED_GATE.value, 0)
    refused = fixes.get(FixOutcome.REFUSED_FLAGGED.value, 0)
    return RsuDiagnosis(
        bus_id=bus_id, rsu_id=a.rsu, intersection_id=intersection_id, reference_time_ns=reference_time_ns,
        time_offset_ns=None if a.offset_s is None else ns_from_s(a.offset_s),
        time_offset_sigma_ns=None if a.offset_sigma_s is None else ns_from_s(a.offset_sigma_s),
        clock_known=a.clock_known, drift_flagged=a.flagged, flagged_since_ns=a.flagged_since_ns,
        disagreement_m=a.disagreement_m, disagreement_yaw_rad=a.disagreement[2],
        disagreement_statistic=max(0.0, a.statistic), fixes_accepted=accepted, fixes_gated=gated,
        fixes_refused=refused, fixes_other=sum(fixes.values()) - accepted - gated - refused, policy=a.policy,
        advice=a.advice)
