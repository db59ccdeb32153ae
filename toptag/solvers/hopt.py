"""H.Opt.: (x, y, yaw) least squares of reprojection error with the tag plane fixed at the roof height."""
from __future__ import annotations

import functools
import math

import numpy as np

from toptag.solvers.common import (
    Fit,
    estimate_sigma,
    rms,
)
from toptag.solvers import kernels
from toptag.solvers.model import (
    KNOWN,
    Calibration,
    Corners,
    calib_columns,
    calib_residual_rms,
    planar_theta,
)

PLANAR = [0, 1, 2]  # x, y, yaw within theta


def initial_pose(c: Corners, h: float, yaw0: float | None) -> tuple[float, float, float] | None:
    """SPEC's start: x, y from the mean back-projected corner (less the rotated mean roof corner, so
    that the vehicle origin and not the tag centroid is estimated); yaw from Bas. when given, else
    from a planar fit of the back-projected corners."""
    start = initial_poses(c, h, np.ones((1, c.n), dtype=bool), yaw0)[0]
    return None if np.isnan(start[0]) else (float(start[0]), float(start[1]), float(start[2]))


def initial_poses(c: Corners, h: float, masks: np.ndarray, yaw0: float | None = None) -> np.ndarray:
    """`initial_pose` of each subset of c's corners (masks (B, N) bool) at once: (B, 3), NaN where fewer
    than two of its corners back-project onto the plane z = h."""
    m = np.ascontiguousarray(masks, dtype=bool)
    yaw = float(yaw0) if yaw0 is not None and math.isfinite(yaw0) else math.nan
    return kernels.initial_poses(c.backprojected(h), c.points, m, yaw)


@functools.lru_cache(maxsize=16)
def _identity(n: int) -> np.ndarray:
    return np.eye(n)  # H.Opt.'s whitener (never modified)


def fit_hopt(c: Corners, h: float, start: tuple[float, float, float], sigma_px: float | None = None,
             sigma_h: float = 0.0, calib: Calibration = KNOWN) -> Fit:
    """3-DOF fit from `start` = (x, y, yaw). The covariance adds the roof-height uncertainty sigma_h
    carried through dtheta/dh: the plane is fixed at h, so an error in h moves the answer; and likewise
    the cameras' calibration uncertainty when given."""
    n2 = 2 * c.n
    theta3, conv, r, J, front, _ = kernels.fit_level(c.level_projection, c.pixels, _identity(n2), np.ones((1, n2)),
                                                     np.ones((1, c.n), dtype=bool), 0.0, float(h),
                                                     np.array([start], dtype=float))
    p, converged, r_px, J4, front = theta3[0], bool(conv[0]), r[0], J[0], front[0]
    in_front = bool(front.all())
    theta = planar_theta(p[0], p[1], p[2], h)
    J = J4[:, PLANAR]
    sigma = sigma_px if sigma_px is not None else estimate_sigma(float(r_px @ r_px), 2 * c.n - 3)
    N_inv, cov, height_rms = kernels.planar_statistics(J4, float(sigma), float(sigma_h))
    calib_rms = 0.0
    if not calib.known:
        J_c = calib_columns(c, theta, calib)
        estimator = N_inv @ J.T
        G = estimator @ J_c
        cov = cov + (G * np.tile(calib.sigmas ** 2, J_c.shape[1] // len(calib.columns))) @ G.T
        calib_rms = calib_residual_rms(J, estimator, J_c, calib)
    note = None
    if not in_front:
        note = "pose puts the tag behind the camera"
    elif not converged:
        note = "H.Opt. did not converge"
    return Fit("hopt", theta, cov, rms(r_px), sigma, c, converged=converged and in_front,
               dof=2 * c.n - 3, fit_rms_px=rms(r_px), height_rms_px=height_rms, calib_rms_px=calib_rms,
               note=note, level_evaluation=(r_px, J4, front))
