"""The physical limit: Cramér–Rao bound of the pose for given cameras, visible tags and corner noise.

Unknowns: the full 6-DOF roof pose (x, y, yaw, z, pitch, roll) when no height prior is given; with a
height prior sigma_h they are (x, y, yaw, z), the roof level, with z ~ N(h, sigma_h²). Pixel noise is
independent Gaussian sigma_px per coordinate. Every solver's error can then be stated as a ratio to it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.solvers.model import IZ, build_corners, evaluate, planar_theta
from toptag.vehicle import Vehicle


@dataclass
class Crlb:
    position_rms: float  # m: sqrt(trace of the x, y block of the inverse Fisher information)
    yaw_rms: float  # rad
    covariance: np.ndarray  # (3,3) bound over (x, y, yaw)
    n_corners: int


def position_crlb(vehicle: Vehicle, cameras_and_tag_ids, pose, sigma_px: float,
                  sigma_h: float | None = None) -> Crlb:
    """cameras_and_tag_ids: [(Camera, [tag ids it sees]), ...]; pose: (x, y, yaw) or (x, y, yaw, z)
    with z defaulting to vehicle.height (or any object with x, y, yaw attributes)."""
    if hasattr(pose, "yaw"):
        pose = (pose.x, pose.y, pose.yaw)
    x, y, yaw = (float(v) for v in pose[:3])
    z = float(pose[3]) if len(pose) > 3 else float(vehicle.height)
    theta = planar_theta(x, y, yaw, z)
    obs = []
    for cam, ids in cameras_and_tag_ids:
        if not isinstance(cam, Camera):
            raise TypeError("cameras_and_tag_ids must hold (Camera, tag ids) pairs")
        for tid in ids:
            obs.append(TagObservation(int(tid), np.zeros((4, 2)), cam))
    if not obs:
        return Crlb(math.inf, math.inf, np.full((3, 3), np.inf), 0)
    c = build_corners(vehicle, obs)
    ev = evaluate(c, theta)
    if not ev.in_front:
        raise ValueError("pose puts a tag behind a camera")
    if sigma_h is None:
        F = ev.J_px.T @ ev.J_px / sigma_px ** 2
    else:
        J = ev.J_px[:, : IZ + 1]
        F = J.T @ J / sigma_px ** 2
        F[IZ, IZ] += 1.0 / sigma_h ** 2
    try:
        if np.linalg.cond(F) > 1e15:
            raise np.linalg.LinAlgError
        cov = np.linalg.inv(F)[:3, :3]
    except np.linalg.LinAlgError:
        return Crlb(math.inf, math.inf, np.full((3, 3), np.inf), c.n)
    return Crlb(float(math.sqrt(cov[0, 0] + cov[1, 1])), float(math.sqrt(cov[2, 2])), cov, c.n)
