"""A lone tag's pose can be mirrored: the homography of a small or distant square is matched almost as
well by a second pose whose plane is tilted the other way about the line of sight (the second solution
of IPPE, Collins & Bartoli 2014; found here by reflecting the best pose's normal about the line of
sight and refining, as OpenCV 5.0's SOLVEPNP_IPPE returned poses 0.26 px off on exact data). A level bus roof rules most mirrors out (the
second plane is tilted by far more than a roof tilts); where the second candidate is both level enough
and fits the corners within their noise, the pose is ambiguous: the solution says so and its
covariance covers both candidates, so that it is never reported as a confident pose.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import stats

from toptag.geometry import wrap_angle
from toptag.solvers.model import Corners, theta_from_rt

AMBIGUITY_ALPHA = 0.01  # the mirror is plausible when its extra residual is within this test level
_MIRROR_CHI2 = float(stats.chi2.ppf(1.0 - AMBIGUITY_ALPHA, 2))  # once: scipy's ppf costs ~0.1 ms a call


def mirror_candidate(c: Corners, sigma_px: float, max_tilt_deg: float) -> np.ndarray | None:
    """For one tag in one camera: the (x, y, yaw) of the mirrored pose (the best pose's plane normal
    reflected about the line of sight, then refined to its own least-squares minimum) when it is
    plausible: a roof tilt within max_tilt_deg, in front of the camera, and a residual within the
    noise of the best one's; else None."""
    if len(c.units) != 1 or c.n != 4:
        return None
    cam = c.units[0].camera
    obj = np.ascontiguousarray(c.points[:, :3], dtype=np.float64)
    centroid = obj.mean(axis=0)
    objc = obj - centroid
    img = np.ascontiguousarray(c.pixels, dtype=np.float64).reshape(-1, 1, 2)
    try:
        ok, rvec, tvec = cv2.solvePnP(objc, img, cam.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(objc, img, cam.K, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0]
        n, v = R[:, 2], tvec.ravel() / np.linalg.norm(tvec)
        n2 = 2.0 * (n @ v) * v - n
        axis = np.cross(n, n2)
        if np.linalg.norm(axis) < 1e-9:
            return None  # seen exactly along its normal: the mirror is the pose itself
        turn = axis / np.linalg.norm(axis) * math.atan2(np.linalg.norm(axis), float(n @ n2))
        R2 = cv2.Rodrigues(turn)[0] @ R
        rvec2, tvec2 = cv2.solvePnPRefineLM(objc, img, cam.K, None, cv2.Rodrigues(R2)[0], tvec.copy())
    except cv2.error:
        return None
    R2 = cv2.Rodrigues(rvec2)[0]
    if math.degrees(math.acos(float(np.clip(R2[:, 2] @ R[:, 2], -1.0, 1.0)))) < 0.5:
        return None  # refined back onto the best pose: no second minimum
    ss = [float(np.sum((cv2.projectPoints(objc, rv, tv, cam.K, None)[0].reshape(-1, 2) - c.pixels) ** 2))
          for rv, tv in ((rvec, tvec), (rvec2, tvec2))]
    depth = (objc @ R2.T + tvec2.ravel())[:, 2]
    if not np.all(depth > 0):
        return None
    R_wv = cam.R.T @ R2
    tilt = math.degrees(math.acos(float(np.clip(R_wv[2, 2], -1.0, 1.0))))
    if tilt > max_tilt_deg:
        return None
    # Two more parameters (the plane's tilt) than the level roof: the mirror is as plausible as the
    # best fit when the residual it adds is within chi-square(2) at AMBIGUITY_ALPHA.
    if (ss[1] - min(ss)) / sigma_px ** 2 > _MIRROR_CHI2:
        return None
    origin_cam = tvec2.ravel() - R2 @ centroid
    theta = theta_from_rt(R_wv, cam.R.T @ (origin_cam - cam.t))
    return theta[:3]


def covering_covariance(cov: np.ndarray, pose: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """cov widened to cover the mirror candidate as if it were one sigma away in every direction it
    differs."""
    d = np.asarray(mirror, float) - np.asarray(pose, float)
    d[2] = wrap_angle(d[2])
    return np.asarray(cov, float) + np.outer(d, d)
