"""The bus filter's state and what it reports: the one fused-state type of the core.

The state vector (world frame of SPEC.md)::

    x, y [m], yaw [rad, (-pi, pi]], speed [m/s, forward], yaw_rate [rad/s],
    gyro_bias [rad/s], wheel_scale [-] (the wheel reads (1 + wheel_scale) * speed)

`protocol.convert` turns a `FusedState` into the wire `protocol.messages.FusedPose`."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

STATE_NAMES = ("x", "y", "yaw", "speed", "yaw_rate", "gyro_bias", "wheel_scale")
STATE_DIM = len(STATE_NAMES)
# Indices into the filter's state vector (a solver's pose vector has its own, toptag.solvers.model).
ST_X, ST_Y, ST_YAW, ST_SPEED, ST_YAW_RATE, ST_GYRO_BIAS, ST_WHEEL_SCALE = range(STATE_DIM)


@dataclass(frozen=True)
class Health:
    """What a planner needs to know about the fused pose."""
    status: str  # acquiring | ok | degraded (no fix for degraded_after_s, or sigma) | lost
    since_last_fix_s: float  # estimate time - capture time of the last applied fix (inf if none)
    last_fix_delay_s: float  # arrival - capture of the last applied fix (nan if unknown)
    last_fix_source: str | None  # RSU of the last applied fix
    last_received_delay_s: float  # arrival - capture of the most recently received fix, any outcome
    rejected: int  # fixes rejected by the gate (total)
    consecutive_rejections: int  # rejected since the last applied fix
    accepted: int  # fixes applied (accepted, re-acquired, start-up)
    pos_sigma_m: float  # sqrt of the largest eigenvalue of the position covariance
    yaw_sigma_rad: float
    extrapolated_s: float  # how far beyond the newest IMU sample the estimate was predicted
    # Every fix's path (final decisions; fixes received, duplicates included): gated = rejected above.
    too_old: int = 0  # older than the buffer (or than the filter's start)
    future: int = 0  # stamped implausibly far ahead of the newest IMU sample
    from_flagged_rsu: int = 0  # from an RSU flagged for drift: down-weighted (counted accepted) or refused
    unknown_clock: int = 0  # from an RSU whose clock came without a bound (any outcome)
    other: int = 0  # duplicates, invalid, before start-up, waiting (acquiring, pending)
    flagged_rsus: tuple[str, ...] = ()  # RSUs flagged for drift now

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def paths(self) -> dict[str, int]:
        """Its fix counts by path (FIX_PATHS)."""
        return {k: getattr(self, k) for k in FIX_PATHS}

    def plus_paths(self, earlier: dict[str, int]) -> Health:
        """The same health with `earlier` fix counts (an earlier filter's paths()) added to its own."""
        return replace(self, **{k: getattr(self, k) + earlier.get(k, 0) for k in FIX_PATHS}) if earlier else self


# Health's counts of fixes by path (what became of every fix received).
FIX_PATHS = ("accepted", "rejected", "too_old", "future", "from_flagged_rsu", "unknown_clock", "other")


@dataclass(frozen=True)
class FusedState:
    """The filter's estimate at t_ns: the full state, its covariance, and health."""
    t_ns: int
    x: float
    y: float
    yaw: float
    speed: float
    yaw_rate: float
    gyro_bias: float
    wheel_scale: float
    cov: np.ndarray  # 3x3 covariance of (x, y, yaw)
    state_cov: np.ndarray  # 7x7 covariance of the full state (STATE_NAMES order)
    health: Health

    @property
    def state(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw, self.speed, self.yaw_rate, self.gyro_bias, self.wheel_scale])

    def to_dict(self) -> dict:
        return {"t_ns": self.t_ns, "x": self.x, "y": self.y, "yaw": self.yaw, "speed": self.speed,
                "yaw_rate": self.yaw_rate, "gyro_bias": self.gyro_bias, "wheel_scale": self.wheel_scale,
                "cov": self.cov.tolist(), "health": self.health.to_dict()}
