"""Pose fixes as the bus filter sees them, and what became of each one.

Pure data: no I/O, no Zenoh. A wire message (pydantic model, dict, ...) becomes a `PoseFix` with
`PoseFix.from_any`; the filter answers every fix with a `FixOutcome`."""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np


class FixOutcome(str, Enum):
    ACCEPTED = "accepted"  # passed the chi-square gate and was applied at its capture time
    REACQUIRED = "reacquired"  # failed the (capped) gate but agreed with a consensus of recent fixes
    INITIALIZED = "initialized"  # started the filter (first confident fix)
    REJECTED_GATE = "rejected_gate"  # chi-square gate on the innovation failed
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
class PoseFix:
    """A timestamped pose of the bus from one RSU: capture time t_ns (int ns), world x, y (m), yaw
    (rad), 3x3 covariance of (x, y, yaw), source (RSU id) and per-source sequence number (optional;
    duplicates are recognised by source and sequence, or by source and capture time).
    `arrival_ns` (optional) is when the bus received it; it only feeds the health report."""
    t_ns: int
    x: float
    y: float
    yaw: float
    cov: np.ndarray
    source: str = "rsu"
    seq: int | None = None
    arrival_ns: int | None = None
    z: float | None = None

    def __post_init__(self):
        self.t_ns = int(self.t_ns)
        self.x, self.y, self.yaw = float(self.x), float(self.y), float(self.yaw)
        self.cov = np.asarray(self.cov, dtype=float).reshape(3, 3) if np.size(self.cov) == 9 else \
            np.full((3, 3), np.nan)
        self.source = str(self.source)
        self.seq = None if self.seq is None else int(self.seq)

    @property
    def key(self) -> tuple:
        """Canonical processing order: capture time, source, sequence."""
        return (self.t_ns, self.source, -1 if self.seq is None else self.seq)

    @property
    def z_vec(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw])

    def problem(self) -> str | None:
        """Why this fix cannot be used, or None."""
        if not all(math.isfinite(v) for v in (self.x, self.y, self.yaw)):
            return "non-finite pose"
        c = self.cov
        if not np.all(np.isfinite(c)):
            return "non-finite covariance"
        if np.max(np.abs(c - c.T)) > 1e-9 * max(1.0, np.max(np.abs(c))):
            return "covariance not symmetric"
        try:
            np.linalg.cholesky(c)
        except np.linalg.LinAlgError:
            return "covariance not positive definite"
        return None

    def replace(self, **change) -> "PoseFix":
        d = dict(t_ns=self.t_ns, x=self.x, y=self.y, yaw=self.yaw, cov=self.cov.copy(), source=self.source,
                 seq=self.seq, arrival_ns=self.arrival_ns, z=self.z)
        d.update(change)
        return PoseFix(**d)

    @classmethod
    def from_any(cls, m, arrival_ns: int | None = None) -> "PoseFix":
        """From a dict or any object with attributes x, y, yaw and t_ns or capture_time_ns, cov or
        covariance, and optionally source / rsu_id, seq / frame_seq, arrival_ns, z (e.g. the
        protocol's PoseFix message)."""
        get = (lambda k: m.get(k)) if isinstance(m, dict) else (lambda k: getattr(m, k, None))

        def first(*keys):
            for k in keys:
                v = get(k)
                if v is not None:
                    return v
            return None
        t = first("t_ns", "capture_time_ns")
        if t is None:
            raise ValueError("a pose fix needs t_ns or capture_time_ns")
        return cls(t_ns=t, x=get("x"), y=get("y"), yaw=get("yaw"), cov=first("cov", "covariance"),
                   source=first("source", "rsu_id", "rsu") or "rsu", seq=first("seq", "frame_seq"),
                   arrival_ns=arrival_ns if arrival_ns is not None else get("arrival_ns"), z=get("z"))


@dataclass
class FixRecord:
    """A fix kept in the filter's buffer, with its latest decision (re-taken on re-propagation)."""
    fix: PoseFix
    key: tuple  # (t_ns, source, seq): the canonical processing order
    outcome: FixOutcome = FixOutcome.PENDING
    d2: float = float("nan")  # Mahalanobis distance^2 of the innovation used by the gate
    arrival_ns: int | None = None


def count_outcomes(outcomes) -> dict[str, int]:
    out = {o.value: 0 for o in FixOutcome}
    for o in outcomes:
        out[o.value] += 1
    return out
