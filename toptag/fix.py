"""The pose fix: one RSU's estimate of one bus's pose at one frame's capture time.

The one fix type of the core. The RSU pipeline makes it from a solver's solution
(`Fix.from_solution`), the bus filter consumes it; `protocol.convert` turns it into the wire
`protocol.messages.PoseFix` and back. Pure data: no I/O, no Zenoh."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from toptag.solvers import PoseSolution


@dataclass
class Fix:
    """t_ns: capture time (int ns); x, y (m), yaw (rad) in the world frame; cov: 3x3 covariance of
    (x, y, yaw); source: the RSU id; seq: the per-source sequence number (the frame's; optional:
    duplicates are recognised by source and sequence, or by source and capture time); arrival_ns:
    when the bus received it (optional; feeds only the filter's health report). z (roof height, m),
    method (solver), tags (tag ids used) and rms_px (reprojection RMS) describe how it was made.
    clock_bound_ns: a bound on the offset of the clock that stamped t_ns (from the RSU's ClockInfo); None
    when that clock is not known to be disciplined (the filter then expects a larger time offset).
    calib_cov: the share of cov that the camera's calibration uncertainty adds (3x3; None: none stated).
    It is in cov (a fix is never more certain than the camera that saw it), and it is common to every
    fix of that camera: a constant bias, not noise (the bus's drift detector weighs it so).
    calib_id: which calibration of the camera made it (e.g. `Camera.calibration_id`; None: not said): when
    it changes the bus forgets what it learnt of the RSU's long-run disagreement with the others."""
    t_ns: int
    x: float
    y: float
    yaw: float
    cov: np.ndarray
    source: str = "rsu"
    seq: int | None = None
    arrival_ns: int | None = None
    z: float | None = None
    method: str | None = None
    tags: tuple[int, ...] = field(default=())
    rms_px: float | None = None
    ambiguous: bool = False  # a lone tag whose mirrored pose fits as well: cov covers both (issue 11)
    clock_bound_ns: int | None = None
    calib_cov: np.ndarray | None = None
    calib_id: str | None = None

    def __post_init__(self):
        self.t_ns = int(self.t_ns)
        self.x, self.y, self.yaw = float(self.x), float(self.y), float(self.yaw)
        self.cov = np.asarray(self.cov, dtype=float).reshape(3, 3) if np.size(self.cov) == 9 else \
            np.full((3, 3), np.nan)
        self.source = str(self.source)
        self.seq = None if self.seq is None else int(self.seq)
        self.tags = tuple(int(t) for t in self.tags)
        self.clock_bound_ns = None if self.clock_bound_ns is None else int(self.clock_bound_ns)
        if self.calib_cov is not None:
            self.calib_cov = np.asarray(self.calib_cov, dtype=float).reshape(3, 3)
        self.calib_id = None if self.calib_id is None else str(self.calib_id)

    @classmethod
    def from_solution(cls, solution: PoseSolution, t_ns: int, source: str, seq: int | None = None,
                      calib_cov: np.ndarray | None = None, calib_id: str | None = None) -> Fix:
        """The fix a solver's (ok) solution of the frame captured at t_ns gives; `calib_cov`: the share
        of its covariance that the cameras' calibration added; `calib_id`: which calibration of the camera."""
        if not solution.ok:
            raise ValueError(f"no fix from a failed solution: {solution.error}")
        return cls(t_ns=t_ns, x=solution.x, y=solution.y, yaw=solution.yaw, cov=solution.covariance,
                   source=source, seq=seq, z=solution.z, method=solution.method, tags=tuple(solution.tags),
                   rms_px=float(solution.rms_px), ambiguous=bool(solution.ambiguous), calib_cov=calib_cov,
                   calib_id=calib_id)

    @property
    def key(self) -> tuple:
        """Canonical processing order: capture time, source, sequence."""
        return (self.t_ns, self.source, -1 if self.seq is None else self.seq)

    @property
    def pose(self) -> np.ndarray:
        """(x, y, yaw), the measured part of the filter's state."""
        return np.array([self.x, self.y, self.yaw])

    def problem(self) -> str | None:
        """Why this fix cannot be used, or None."""
        if not all(math.isfinite(v) for v in (self.x, self.y, self.yaw)):
            return "non-finite pose"
        if clearly_covariance(self.cov.tolist()):  # numpy's tests would pass (they cost ~60 µs a fix)
            return None
        return covariance_problem(self.cov)

    def replace(self, **change) -> Fix:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["cov"] = self.cov.copy()
        d["calib_cov"] = None if self.calib_cov is None else self.calib_cov.copy()
        d.update(change)
        return Fix(**d)


def covariance_problem(c: np.ndarray) -> str | None:
    """Why a 3x3 array cannot be a fix's covariance (numpy's tests), or None."""
    if not np.all(np.isfinite(c)):
        return "non-finite covariance"
    if np.max(np.abs(c - c.T)) > 1e-9 * max(1.0, np.max(np.abs(c))):
        return "covariance not symmetric"
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return "covariance not positive definite"
    return None


def clearly_covariance(v: list[list[float]]) -> bool:
    """True when the 3x3 ``v`` passes the numpy tests of a covariance for sure (the wire's,
    protocol.messages._check_covariance, and Fix.problem's): finite, symmetric to the same tolerance (the
    same float operations), and the lower triangle (what eigvalsh and Cholesky read) positive definite with
    a margin far above rounding (its leading principal minors, Sylvester, scaled to entries in [-1, 1]: its
    smallest eigenvalue is then > 1e-13 of the scale). False says nothing: the numpy tests decide. Pure
    Python: numpy costs ~30 µs per 3x3, every PoseFix and FusedPose carries one or two, and the bus
    filter checks every fix."""
    (a, b, c), (d, e, f), (g, h, i) = v
    if not all(map(math.isfinite, (a, b, c, d, e, f, g, h, i))):
        return False
    m = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
    tol = 1e-9 * max(1.0, m)
    if abs(b - d) > tol or abs(c - g) > tol or abs(f - h) > tol or m == 0.0:
        return False
    a, d, g, e, h, i = a / m, d / m, g / m, e / m, h / m, i / m
    m2 = a * e - d * d
    m3 = a * (e * i - h * h) - d * (d * i - h * g) + g * (d * h - e * g)
    return a > 1e-12 and m2 > 1e-12 and m3 > 1e-12  # their rounding errors: ~1e-15
