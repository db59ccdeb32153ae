"""S.Opt.: 6-DOF least squares of reprojection error plus a height residual for every roof corner.

Weighting "paper": pixels as they are and mu·(z_i − h) with mu = 1 (metres against pixels, as the
paper does). Weighting "principled": every residual divided by its sigma: pixel residuals by sigma_px,
height residuals by sigma_h·sqrt(M) for the M roof corners when their error is one common offset
(height_model="common", the default), by sigma_h when each corner's is independent ("independent").

Either way the covariance is the sandwich H⁻¹ B H⁻¹ of the estimator actually run, under the noise
that is really there: independent pixel noise sigma_px, and a roof height off by one common offset of
standard deviation sigma_h (the bus bounces as a whole, so its corners' height errors are one error,
not independent ones; height_model="independent" assumes the opposite).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from toptag.solvers.common import SIGMA_FLOOR_PX, Fit, estimate_sigma, rms, safe_inverse
from toptag.solvers.lm import levenberg_marquardt
from toptag.solvers.model import (
    KNOWN,
    Calibration,
    Corners,
    Evaluation,
    calib_columns,
    calib_residual_rms,
    evaluate,
)

WEIGHTINGS = ("paper", "principled")
SIGMA_ROUNDS = 3  # principled, sigma unknown: solve, re-estimate sigma, solve again until it settles
HEIGHT_MODELS = ("common", "independent")


@dataclass
class _Weights:
    px: float  # weight of a squared pixel residual
    h: float  # weight of a squared height residual (1/m²)


def _weights(weighting: str, sigma_w: float, sigma_h: float, mu: float, height_model: str,
             n_roof: int) -> _Weights:
    if weighting == "paper":
        return _Weights(1.0, mu * mu)
    if height_model == "common":
        # M residuals that share one error carry the information of one: each gets sigma_h·sqrt(M), so
        # together they are one sigma_h prior on the roof height (weighting each by sigma_h alone
        # trusts h sqrt(M) times too much and, measured, loses ~50 % of accuracy at 16 m).
        return _Weights(1.0 / sigma_w ** 2, 1.0 / (n_roof * sigma_h ** 2))
    return _Weights(1.0 / sigma_w ** 2, 1.0 / sigma_h ** 2)


def _minimise(c: Corners, h: float, theta0, w: _Weights):
    sp, sh = math.sqrt(w.px), math.sqrt(w.h)

    def fun(theta):
        ev = evaluate(c, theta)
        r = np.concatenate([sp * ev.r_px, sh * (ev.z - h)])
        J = np.vstack([sp * ev.J_px, sh * ev.J_z])
        if not ev.in_front:
            r = np.full_like(r, np.inf)
        return r, J

    return levenberg_marquardt(fun, theta0)


def _statistics(ev: Evaluation, w: _Weights, sigma_px: float | None, sigma_h: float, height_model: str,
                J_c: np.ndarray | None = None, calib: Calibration = KNOWN):
    """(covariance 6x6, sigma_px used, effective pixel degrees of freedom, per-corner pixel RMS that a
    one-sigma common roof offset leaves in the residual, and that one-sigma calibration errors leave).
    J_c: d(pixels)/d(the cameras' uncertain extrinsic corrections) when calib is given."""
    JpJp = ev.J_px.T @ ev.J_px
    Hn = w.px * JpJp + w.h * (ev.J_z.T @ ev.J_z)
    H_inv = safe_inverse(Hn)
    # Degrees of freedom left in the pixel residuals: 2N minus the pixel block of the hat matrix's trace.
    dof = len(ev.r_px) - w.px * float(np.trace(H_inv @ JpJp)) if np.all(np.isfinite(H_inv)) else 0.0
    sigma = sigma_px if sigma_px is not None else estimate_sigma(float(ev.r_px @ ev.r_px), dof)
    if height_model == "common":
        s = ev.J_z.sum(axis=0)
        height_term = np.outer(s, s)
    else:
        height_term = ev.J_z.T @ ev.J_z
    B = (w.px ** 2) * sigma ** 2 * JpJp + (w.h ** 2) * sigma_h ** 2 * height_term
    # Residual left by a roof offset delta: the height prior pulls the pose by -H⁻¹ J_zᵀ w_h·delta·1.
    height_rms = sigma_h * rms(ev.J_px @ (H_inv @ (w.h * ev.J_z.sum(axis=0))))
    cov = H_inv @ B @ H_inv
    calib_rms = 0.0
    if J_c is not None and not calib.known:
        estimator = w.px * (H_inv @ ev.J_px.T)
        G = estimator @ J_c
        cov = cov + (G * np.tile(calib.sigmas ** 2, J_c.shape[1] // len(calib.columns))) @ G.T
        calib_rms = calib_residual_rms(ev.J_px, estimator, J_c, calib)
    return cov, sigma, dof, height_rms, calib_rms


def fit_sopt(c: Corners, h: float, theta0, *, weighting: str = "paper", sigma_px: float | None = None,
             sigma_h: float, mu: float = 1.0, sigma_weight: float | None = None,
             height_model: str = "common", calib: Calibration = KNOWN) -> Fit:
    """6-DOF fit from theta0. sigma_weight is the pixel sigma the principled problem is first weighted
    with when sigma_px is unknown (default SIGMA_FLOOR_PX; then re-estimated from the fit's own residuals
    and solved again, up to SIGMA_ROUNDS times, until it changes by less than 10 %)."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, not {weighting!r}")
    if height_model not in HEIGHT_MODELS:
        raise ValueError(f"height_model must be one of {HEIGHT_MODELS}, not {height_model!r}")
    if weighting == "principled" and not sigma_h > 0:
        raise ValueError("principled weighting needs sigma_h > 0")
    # Unknown sigma: start from the detector noise floor, not from H.Opt.'s residual (which, with the roof
    # held at h, shows the roof bounce: 8 px at 5 m and 3200x2400 would weigh the height prior 1000x too
    # much), and re-estimate until it settles.
    sigma_w = sigma_px if sigma_px is not None else (sigma_weight or SIGMA_FLOOR_PX)
    theta = np.asarray(theta0, dtype=float)
    for _ in range(SIGMA_ROUNDS):
        w = _weights(weighting, sigma_w, sigma_h, mu, height_model, len(c.roof_points))
        res = _minimise(c, h, theta, w)
        theta = res.theta
        ev = evaluate(c, theta)
        J_c = None if calib.known else calib_columns(c, theta, calib)
        cov6, sigma, dof, height_rms, calib_rms = _statistics(ev, w, sigma_px, sigma_h, height_model, J_c, calib)
        if weighting != "principled" or sigma_px is not None or abs(sigma / sigma_w - 1.0) <= 0.1:
            break
        sigma_w = sigma
    note = None
    if not ev.in_front:
        note = "pose puts the tag behind the camera"
    elif not res.converged:
        note = "S.Opt. did not converge"
    return Fit("sopt", res.theta, cov6[:3, :3], rms(ev.r_px), sigma, c,
               converged=res.converged and ev.in_front, dof=dof, fit_rms_px=rms(ev.r_px),
               height_rms_px=height_rms, calib_rms_px=calib_rms, note=note)
