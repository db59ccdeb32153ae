"""A fix is never more certain than the camera that saw it: the cameras' calibration covariance
(camera file, `calibration.extrinsics.covariance`) carried into a pose's covariance.

A camera whose pose is off by delta (rotation about its axes, centre shift) moves every ray it casts,
and the pose solved from those rays moves with it: d(pose) = −A⁻¹ Jᵀ W J_c · delta, where J is the
pixel Jacobian of the level-roof pose (x, y, yaw, z) at the solution, W the level solver's corner
weighting (edge offsets and turns), A = JᵀWJ plus the roof-height prior, and J_c the pixels' Jacobian
in each camera's pose delta (toptag.solvers.model.calib_jacobian). The roof height absorbs part of a
camera error (a tilt looks partly like a higher or lower roof), so a fix moves less than a single
pixel's roof point would.
The pose covariance gains G Σ_c Gᵀ, Σ_c block-diagonal over the cameras. Cameras with no calibration
covariance count as exact. This error is common to every fix of that camera: the filter sees it as a
slowly varying bias, not white noise.
"""
from __future__ import annotations

import math

import numpy as np

from toptag.detection import TagObservation
from toptag.solvers.common import SIGMA_H_DEFAULT, PoseSolution
from toptag.solvers.level import TURN_RATIO, edge_whitener, noise_scale
from toptag.solvers.model import build_corners, calib_jacobian, camera_index, evaluate, planar_theta
from toptag.vehicle import Vehicle

PRIOR_SIGMA_PX = 0.1  # the pixel noise that weighs the height prior when the solution gives none


def calibration_covariance(vehicle: Vehicle, observations: list[TagObservation], solution: PoseSolution,
                           sigma_h: float = SIGMA_H_DEFAULT, turn_ratio: float = TURN_RATIO) -> np.ndarray:
    """(3,3) covariance over (x, y, yaw) that the observing cameras' calibration uncertainty adds
    (turn_ratio: the corner-noise model the solution was weighted with, toptag.solvers.level)."""
    used = [o for o in observations if o.tag_id in solution.tags and o.camera.id in solution.cameras
            and o.tag_id in vehicle.tags]
    if not used or all(o.camera.extrinsic_covariance is None for o in used):
        return np.zeros((3, 3))
    c = build_corners(vehicle, used)
    z = solution.z if math.isfinite(solution.z) else vehicle.height
    theta = planar_theta(solution.x, solution.y, solution.yaw, z)
    # Weighted as the level solver weighs corners (edge offsets and turns, toptag.solvers.level), so that
    # the sensitivity is the estimator's own.
    T = edge_whitener(c.pixels, turn_ratio)
    J = T @ evaluate(c, theta).J_px[:, :4]
    s = solution.sigma_px if math.isfinite(solution.sigma_px) and solution.sigma_px > 0 else PRIOR_SIGMA_PX
    s_white = s / noise_scale(turn_ratio)
    A = J.T @ J
    A[3, 3] += (s_white / sigma_h) ** 2 if sigma_h > 0 else 1e12
    Jc6 = calib_jacobian(c, theta)
    cam_of_row = np.repeat(camera_index(c), 2)
    cams = {u.camera.id: u.camera for u in c.units}
    total = np.zeros((4, 4))
    for i, cid in enumerate(c.camera_ids):
        cov = cams[cid].extrinsic_covariance
        if cov is None:
            continue
        Jc = T @ np.where((cam_of_row == i)[:, None], Jc6, 0.0)
        G = -np.linalg.solve(A, J.T @ Jc)
        total += G @ cov @ G.T
    return total[:3, :3]


def with_calibration(vehicle: Vehicle, observations: list[TagObservation], solution: PoseSolution,
                     turn_ratio: float = TURN_RATIO) -> np.ndarray | None:
    """Adds the cameras' calibration covariance to the (ok) solution's covariance, in place, and returns
    that share (what every fix of these cameras has in common); None when they state none."""
    if not solution.ok:
        return None
    try:
        add = calibration_covariance(vehicle, observations, solution, turn_ratio=turn_ratio)
    except np.linalg.LinAlgError:
        return None
    solution.covariance = np.asarray(solution.covariance, float) + add
    return add if np.any(add) else None
