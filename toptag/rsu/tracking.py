"""Per-vehicle image tracking state: where a found bus will be in the next frame, and how sure we are.

Motion is bounded by the bus's physics (toptag.limits: speed, braking, yaw rate), so a short-term constant
velocity prediction with a margin that grows with the time since the last fix always contains it."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toptag.geometry import wrap_angle
from toptag.limits import BUS_MAX_DECEL_MPS2, BUS_MAX_SPEED_MPS, BUS_MAX_YAW_RATE
from toptag.units import s_from_ns

SPEED_MARGIN = 1.2  # on the bus's top speed: a region must hold a bus that speeds a little


@dataclass
class TrackSettings:
    base_radius_m: float = 0.08  # fix error and body flex; the crop adds its own pixel padding
    velocity_error_mps: float = 1.0  # what two noisy fixes 0.1 s apart may get wrong
    max_accel_mps2: float = BUS_MAX_DECEL_MPS2
    max_yaw_rate: float = BUS_MAX_YAW_RATE
    z_margin_m: float = 0.12  # roof bounce around the last measured roof height
    velocity_smoothing: float = 0.5  # weight of the newest velocity from consecutive fixes
    lost_after_misses: int = 3  # frames without any tag before falling back to acquisition


@dataclass
class PosePrediction:
    x: float
    y: float
    yaw: float
    z: float
    pos_radius: float
    yaw_margin: float
    z_margin: float


class VehicleTrack:
    """The last confident image fixes of one vehicle in one camera."""

    def __init__(self, settings: TrackSettings | None = None):
        self.settings = settings or TrackSettings()
        self.t_ns: int | None = None
        self.pose: np.ndarray | None = None  # x, y, yaw, z
        self.velocity: np.ndarray | None = None  # vx, vy, yaw_rate
        self.misses = 0

    @property
    def found(self) -> bool:
        return self.pose is not None

    def update(self, t_ns: int, x: float, y: float, yaw: float, z: float) -> None:
        pose = np.array([x, y, yaw, z])
        if self.pose is not None and t_ns > self.t_ns:
            dt = s_from_ns(t_ns - self.t_ns)
            v = np.array([(x - self.pose[0]) / dt, (y - self.pose[1]) / dt,
                          wrap_angle(yaw - self.pose[2]) / dt])
            speed = np.hypot(v[0], v[1])
            cap = BUS_MAX_SPEED_MPS * SPEED_MARGIN
            if speed > cap:  # a noisy pair of fixes must not throw the next region off
                v[:2] *= cap / speed
            v[2] = np.clip(v[2], -self.settings.max_yaw_rate, self.settings.max_yaw_rate)
            a = self.settings.velocity_smoothing
            self.velocity = v if self.velocity is None else a * v + (1 - a) * self.velocity
        self.pose, self.t_ns, self.misses = pose, t_ns, 0

    def miss(self) -> None:
        self.misses += 1
        if self.misses >= self.settings.lost_after_misses:
            self.reset()

    def reset(self) -> None:
        self.pose = self.velocity = self.t_ns = None
        self.misses = 0

    def predict(self, t_ns: int, extra_radius: float = 0.0) -> PosePrediction:
        """Where the vehicle is at t_ns (before or after the last fix), with a margin that surely holds it."""
        s = self.settings
        dt = s_from_ns(abs(t_ns - self.t_ns))
        x, y, yaw, z = self.pose
        if self.velocity is None:
            # One fix only: the bus may be moving at any legal speed in any direction.
            radius = s.base_radius_m + extra_radius + BUS_MAX_SPEED_MPS * SPEED_MARGIN * dt
            yaw_margin = s.max_yaw_rate * dt + 0.05
        else:
            vx, vy, w = self.velocity
            x, y, yaw = x + vx * dt, y + vy * dt, yaw + w * dt
            radius = s.base_radius_m + extra_radius + s.velocity_error_mps * dt + 0.5 * s.max_accel_mps2 * dt ** 2
            yaw_margin = 0.01 + 0.2 * dt
        return PosePrediction(x, y, float(wrap_angle(yaw)), z, radius, yaw_margin, s.z_margin_m)
