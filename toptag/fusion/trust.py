"""Which RSUs the bus filter trusts: each RSU's record of disagreement, the drift detector that flags
a camera whose fixes disagree persistently with the other RSUs and the filter, and the assessment of
every RSU the filter reports (time offset, flag, disagreement, fix counts).

The detector. A consistent filter's innovations (fix minus prediction, nu, with covariance S) are
white. A turned camera or a moved pole adds a bias to every fix of its RSU, so that RSU's innovations
keep one sign. Per RSU the filter accumulates, with exponential forgetting over `window_s` (w =
exp(-dt / window_s) between two fixes of that RSU)::

    A = sum w S^-1,    A2 = sum w^2 S^-1,    b = sum w S^-1 nu
    bias m = A^-1 b (the weighted mean innovation: fix minus filter, in x, y, yaw)
    T = b' A2^-1 b    (chi-square, 3 dof, for white innovations: A2 is the covariance of b)

A single wild fix cannot do it: nu is clipped to the gate's Mahalanobis radius before it enters b.
An RSU is flagged when
  - T exceeds the chi-square quantile of `false_alarm` (a test of persistence) over at least
    `min_fixes` fixes (effective count (sum w)^2 / sum w^2: a few wild fixes are not persistence), and
  - its time offset is known to `max_offset_sigma_s` (until then the filter is still learning what
    part of its disagreement is a late clock: an offset looks like a bias along the track), and
  - the bias is larger than the calibration's accuracy (`min_pos_m` in position or `min_yaw_rad` in
    yaw: a bias that small is calibration error, not drift), and
  - at least `min_others` other, unflagged RSUs have sent fixes within the window (with one other
    the disagreement is symmetric: nobody can tell who is wrong), and its T is at least
    `isolation_ratio` times each of theirs: the filter follows every RSU a little, so the others see
    a share of one RSU's bias; the one that turned sees most of it.
Innovations enter only while the filter is healthy (tracking, a fix applied within the last second):
a starved or re-acquiring filter is no reference to judge an RSU by.
It is cleared when, over at least `min_fixes` fixes again, T falls below the `clear_probability`
quantile (old evidence fades with the window: a camera seen agreeing on the next pass is cleared
within a second or two).
While flagged, its fixes are down-weighted (covariance scaled and the bias added to it) or refused
(`FilterConfig.flagged_policy`); the statistic keeps running on the unweighted innovation so the
flag clears after a recalibration.

Pure: no I/O. Records are immutable (copy-on-write): the filter keeps one set per buffered step and
re-derives them on re-propagation, so an out-of-order replay ends with the same flags."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

CALIBRATE_CHECK = "toptag calibrate check --camera CAM.json --points POINTS.json IMAGE"


class RsuRecord(NamedTuple):
    """What the filter knows of one RSU at one step."""
    last_t: int  # capture time of its newest fix processed
    clock_known: bool  # its newest fix came with a clock bound
    A: np.ndarray | None = None
    A2: np.ndarray | None = None
    b: np.ndarray | None = None
    stat: float = 0.0
    n_eff: float = 0.0  # effective number of fixes in the statistic
    flagged_since: int | None = None
    # Its time offset (s) and variance (s²) when it had no slot in the state (given up, or carried
    # over from a previous filter), at time `offset_t`.
    offset: tuple[float, float] | None = None
    offset_t: int | None = None
    sums: tuple[float, float] = (0.0, 0.0)  # sum w, sum w^2 (for n_eff)
    calm_offset: tuple[float, float] | None = None  # its offset (s, s²) when it last agreed

    @property
    def _sw(self) -> float:
        return self.sums[0]

    @property
    def _sw2(self) -> float:
        return self.sums[1]

    @property
    def flagged(self) -> bool:
        return self.flagged_since is not None

    def bias(self) -> tuple[np.ndarray, np.ndarray]:
        """(m, C): the weighted mean innovation (x, y, yaw) and its covariance (zeros before any fix)."""
        if self.A is None:
            return np.zeros(3), np.zeros((3, 3))
        Ai = np.linalg.inv(self.A)
        return Ai @ self.b, Ai @ self.A2 @ Ai


@dataclass(frozen=True)
class DriftRule:
    """The detector's thresholds (from FilterConfig)."""
    window_s: float
    flag_stat: float  # chi-square quantile of 1 - false_alarm, 3 dof
    clear_stat: float
    min_pos_m: float
    min_yaw_rad: float
    isolation_ratio: float
    clip_d2: float  # innovations are clipped to this Mahalanobis radius²
    min_fixes: float
    max_offset_sigma_s: float
    min_others: int = 2

    def accumulate(self, rec: RsuRecord, t_ns: int, nu: np.ndarray, S: np.ndarray) -> RsuRecord:
        """The record with one more innovation nu (covariance S) at t_ns."""
        Si = np.linalg.inv(S)
        d2 = float(nu @ Si @ nu)
        if d2 > self.clip_d2:
            nu = nu * math.sqrt(self.clip_d2 / d2)
        if rec.A is None:
            A, A2, b, sw, sw2 = Si, Si, Si @ nu, 1.0, 1.0
        else:
            w = math.exp(-max(0, t_ns - rec.last_t) * 1e-9 / self.window_s)
            A, A2, b = w * rec.A + Si, (w * w) * rec.A2 + Si, w * rec.b + Si @ nu
            sw, sw2 = w * rec._sw + 1.0, w * w * rec._sw2 + 1.0
        stat = float(b @ np.linalg.solve(A2, b))
        return rec._replace(last_t=t_ns, A=A, A2=A2, b=b, stat=stat, n_eff=sw * sw / sw2, sums=(sw, sw2))

    def _large(self, m: np.ndarray) -> bool:
        return math.hypot(m[0], m[1]) > self.min_pos_m or abs(m[2]) > self.min_yaw_rad

    def decide(self, records: dict[str, RsuRecord], rsu: str, t_ns: int, offset_sigma_s: float = 0.0) -> int | None:
        """The flag of `rsu` (its flagged_since, or None) after its record was updated at t_ns;
        `offset_sigma_s`: the uncertainty of its time offset now."""
        rec = records[rsu]
        m, _ = rec.bias()
        if rec.flagged:
            if rec.stat < self.clear_stat and rec.n_eff >= self.min_fixes:
                return None
            return rec.flagged_since
        if rec.stat <= self.flag_stat or rec.n_eff < self.min_fixes or offset_sigma_s > self.max_offset_sigma_s \
                or not self._large(m):
            return None
        window_ns = self.window_s * 1e9
        others = [o for k, o in records.items()
                  if k != rsu and not o.flagged and o.A is not None and t_ns - o.last_t <= window_ns]
        if len(others) < self.min_others or any(rec.stat < self.isolation_ratio * o.stat for o in others):
            return None
        return t_ns


@dataclass(frozen=True)
class RsuAssessment:
    """The bus filter's view of one RSU (toptag.fusion.filter.BusFilter.rsu_assessments)."""
    rsu: str
    offset_s: float | None  # estimated time offset (stamp minus exposure, in the bus's time), s
    offset_sigma_s: float | None
    clock_known: bool  # its fixes say how its clock is disciplined (a bound on the offset)
    flagged: bool
    flagged_since_ns: int | None
    disagreement: tuple[float, float, float]  # mean innovation (x m, y m, yaw rad): its fixes minus the filter
    disagreement_sigma: tuple[float, float, float]
    statistic: float  # chi-square (3 dof) of the disagreement's persistence
    last_fix_ns: int
    fixes: dict[str, int] = field(default_factory=dict)  # outcome -> count (final decisions)
    policy: str = "downweight"

    @property
    def disagreement_m(self) -> float:
        return math.hypot(self.disagreement[0], self.disagreement[1])

    @property
    def advice(self) -> str | None:
        """What the operator should do, for a flagged RSU."""
        if not self.flagged:
            return None
        what = "refused" if self.policy == "refuse" else "down-weighted"
        return (f"camera {self.rsu} disagrees with the other RSUs and the fused track by "
                f"{100 * self.disagreement_m:.1f} cm / {math.degrees(abs(self.disagreement[2])):.2f} deg: its fixes "
                f"are {what}; check its calibration: {CALIBRATE_CHECK}")


__all__ = ["CALIBRATE_CHECK", "DriftRule", "RsuAssessment", "RsuRecord"]
