"""The time offset of an RSU's fixes, as the bus filter models it.

An RSU stamps a frame with its own clock when it gets it: stamp = exposure + capture latency + clock
offset (RSU clock minus the bus's). Their sum is the RSU's *time offset* delta: the fix stamped t
shows the bus as it was at t - delta. The filter keeps one delta per RSU in its state (an augmented
EKF; toptag.fusion.filter) and predicts a fix stamped t from its state at t by driving the bus back
over delta with the motion model the filter itself propagates with (midpoint heading, the
accelerometer's forward acceleration a)::

    d   = v delta - a delta^2 / 2                       distance driven in (t - delta, t]
    phi = yaw - yaw_rate delta / 2                      mean heading over it
    h   = (x - d cos phi,  y - d sin phi,  yaw - yaw_rate delta)

Its Jacobian has the state part (x, y, yaw, speed, yaw_rate) and the offset part dh/d delta =
-(v cos phi, v sin phi, yaw_rate) to first order: the motion the offset implies. Through it the
offset's variance enters the innovation covariance of every fix of that RSU (velocity x sigma_delta
along the track, yaw rate x sigma_delta in yaw), and every fix updates the offset.

Pure: no I/O."""
from __future__ import annotations

import math

import numpy as np

from toptag.fusion import kernels
from toptag.fusion.state import ST_SPEED, ST_YAW, ST_YAW_RATE


def pose_before(x: np.ndarray, delta: float, accel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h, H_state, H_delta): the pose (x, y, yaw) `delta` seconds before the state x, the Jacobian of
    h with respect to the first five state entries (x, y, yaw, speed, yaw_rate; 3x5) and with respect
    to delta (3,). Compiled (toptag.fusion.kernels.pose_before), as the filter's fix update uses it."""
    return kernels.pose_before(np.ascontiguousarray(x, dtype=float), float(delta), float(accel))


def motion_rate(x: np.ndarray) -> np.ndarray:
    """d(x, y, yaw)/dt of the state: what one second of time offset moves a fix by."""
    v, th, w = x[ST_SPEED], x[ST_YAW], x[ST_YAW_RATE]
    return np.array([v * math.cos(th), v * math.sin(th), w])


__all__ = ["motion_rate", "pose_before"]
