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

from toptag.fusion.state import ST_SPEED, ST_X, ST_Y, ST_YAW, ST_YAW_RATE
from toptag.geometry import wrap_angle


def pose_before(x: np.ndarray, delta: float, accel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h, H_state, H_delta): the pose (x, y, yaw) `delta` seconds before the state x, the Jacobian of
    h with respect to the first five state entries (x, y, yaw, speed, yaw_rate; 3x5) and with respect
    to delta (3,)."""
    v, th, w = x[ST_SPEED], x[ST_YAW], x[ST_YAW_RATE]
    d = v * delta - 0.5 * accel * delta * delta
    dd = v - accel * delta  # d(d)/d(delta)
    phi = th - 0.5 * w * delta
    c, s = math.cos(phi), math.sin(phi)
    h = np.array([x[ST_X] - d * c, x[ST_Y] - d * s, wrap_angle(th - w * delta)])
    Hs = np.zeros((3, 5))
    Hs[0, ST_X] = Hs[1, ST_Y] = Hs[2, ST_YAW] = 1.0
    Hs[0, ST_YAW], Hs[1, ST_YAW] = d * s, -d * c
    Hs[0, ST_SPEED], Hs[1, ST_SPEED] = -delta * c, -delta * s
    Hs[0, ST_YAW_RATE], Hs[1, ST_YAW_RATE] = -0.5 * delta * d * s, 0.5 * delta * d * c
    Hs[2, ST_YAW_RATE] = -delta
    Hd = np.array([-dd * c - 0.5 * w * d * s, -dd * s + 0.5 * w * d * c, -w])
    return h, Hs, Hd


def motion_rate(x: np.ndarray) -> np.ndarray:
    """d(x, y, yaw)/dt of the state: what one second of time offset moves a fix by."""
    v, th, w = x[ST_SPEED], x[ST_YAW], x[ST_YAW_RATE]
    return np.array([v * math.cos(th), v * math.sin(th), w])


__all__ = ["motion_rate", "pose_before"]
