"""What became of each fix the bus filter was given: its `FixOutcome`, and the buffer's record of it.

Pure data: no I/O, no Zenoh."""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from toptag.fix import Fix


class FixOutcome(str, Enum):
    ACCEPTED = "accepted"  # passed the chi-square gate and was applied at its capture time
    REACQUIRED = "reacquired"  # failed the (capped) gate but agreed with a consensus of recent fixes
    INITIALIZED = "initialized"  # started the filter (first confident fix)
    REJECTED_GATE = "rejected_gate"  # chi-square gate on the innovation failed
    REFUSED_FLAGGED = "refused_flagged"  # its RSU is flagged for drift (toptag.fusion.trust) and the policy refuses
    UNCONFIRMED = "unconfirmed"  # start-up from a coarse prior: waiting for a consensus of fixes
    PENDING = "pending"  # stamped after the newest IMU sample; decided when the IMU catches up
    DUPLICATE = "duplicate"  # same source and (sequence or capture time) as a buffered fix
    TOO_OLD = "too_old"  # capture time older than the state buffer
    BEFORE_START = "before_start"  # capture time before the filter's start
    NOT_INITIALIZED = "not_initialized"  # arrived before any start-up and too coarse to start from
    FUTURE = "future"  # capture time implausibly far ahead of the newest IMU sample
    INVALID = "invalid"  # non-finite values or a covariance that is not symmetric positive definite

    @property
    def applied(self) -> bool:
        return self in (FixOutcome.ACCEPTED, FixOutcome.REACQUIRED, FixOutcome.INITIALIZED)


@dataclass
class FixRecord:
    """A fix kept in the filter's buffer, with its latest decision (re-taken on re-propagation)."""
    fix: Fix
    key: tuple  # (t_ns, source, seq): the canonical processing order
    outcome: FixOutcome = FixOutcome.PENDING
    d2: float = float("nan")  # Mahalanobis distance^2 of the innovation used by the gate
    arrival_ns: int | None = None
    flagged: bool = False  # its RSU was flagged for drift when it was processed (down-weighted or refused)
    bias_root: np.ndarray | None = None  # L (L L' = fix.calib_cov) when the filter models its RSU's bias


_APPLIED = tuple(o.value for o in FixOutcome if o.applied)


def applied_count(counts: dict[str, int]) -> int:
    """How many of the counted fixes (outcome value -> count) the filter applied."""
    return sum(counts.get(v, 0) for v in _APPLIED)


def count_outcomes(outcomes) -> dict[str, int]:
    out = {o.value: 0 for o in FixOutcome}
    for o in outcomes:
        out[o.value] += 1
    return out
