"""Never a confident wrong answer: a per-tag outlier test, and plausibility checks on the final pose.

Both judge the corners with the H.Opt. model (tag layout known, roof at the vehicle height give or take
sigma_h), whatever the solver asked for: it has the most redundancy (a lone tag leaves 5 of its 8
coordinates to check the layout; Bas. on one tag leaves none), and the roof-height uncertainty is
carried explicitly so that a bouncing bus is not mistaken for bad corners.

Outlier test (leave one observation out). For each tag-in-a-camera k, the pose is fitted without k and
k's corners are predicted; the prediction error e_k is judged against its covariance
    S_k = sigma²·(I + J_k N⁻¹ J_kᵀ) + sigma_h²·v vᵀ,   v = dpixels_k/dh through the rest's fit,
so d_k = e_kᵀ S_k⁻¹ e_k is chi-square with 8 degrees of freedom when k is fine (F-distributed when sigma
is estimated from the rest). The worst k above the (1 − alpha) quantile is dropped, and the test repeats
on what is left. A bad tag of a pair is told from the good one because, fitted alone, its own corners
disagree with its layout, which inflates the noise its prediction of the good one is judged with.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from toptag.solvers.common import SIGMA_PRIOR_PX, Fit, safe_inverse
from toptag.solvers.hopt import PLANAR, fit_hopt, initial_pose
from toptag.solvers.model import IZ, Corners, euler_rotation, evaluate

# With sigma unknown, a lone tag's residual leaves ~5 degrees of freedom: too few to judge by alone
# (F(8, 5) at 99.9 % would let a 10 px corner pass). Detector noise is known to be of the order of
# SIGMA_PRIOR_PX, so it joins as a conjugate prior worth this many degrees of freedom.
PRIOR_DOF = 4.0


@dataclass(frozen=True)
class Limits:
    """When a pose is refused rather than returned.

    max_rms_px: limit on the RMS residual of the corners against the tag layout (H.Opt. model, and
    S.Opt.'s own); None means 1.5 px when sigma_px is unknown, else max(3·sigma_px, 0.5 px). Three
    times what a one-sigma roof-height error leaves in the residual is added in quadrature."""

    max_rms_px: float | None = None
    max_position_sigma_m: float = 1.0
    max_height_error_m: float = 0.5
    max_tilt_deg: float = 20.0  # S.Opt.'s roof tilt; any solver's roof must face up
    outlier_alpha: float = 1e-3

    def rms_limit(self, sigma_px: float | None, height_rms_px: float = 0.0) -> float:
        base = self.max_rms_px
        if base is None:
            base = 1.5 if sigma_px is None else max(3.0 * sigma_px, 0.5)
        return math.hypot(base, 3.0 * height_rms_px)


def screen_outliers(c: Corners, h: float, sigma_px: float | None, sigma_h: float,
                    alpha: float = 1e-3) -> tuple[list[int], list[dict]]:
    """Unit indices to keep and the dropped ones ({"tag", "camera", "reason"})."""
    keep = list(range(len(c.units)))
    dropped: list[dict] = []
    while len(keep) >= 2:
        scores = [_loo_statistic(c, keep, k, h, sigma_px, sigma_h, alpha) for k in keep]
        ratios = [-math.inf if math.isnan(d) else d / thr for d, thr in scores]
        worst = int(np.argmax(ratios))
        if not ratios[worst] > 1.0:
            break
        d, thr = scores[worst]
        unit = c.units[keep[worst]]
        dropped.append({"tag": unit.tag_id, "camera": unit.camera.id,
                        "reason": f"corners disagree with the other tags (chi2 {d:.3g} > {thr:.3g})"})
        del keep[worst]
    return keep, dropped


def _loo_statistic(c: Corners, keep: list[int], k: int, h: float, sigma_px: float | None,
                   sigma_h: float, alpha: float) -> tuple[float, float]:
    rest = c.subset([u for u in keep if u != k])
    start = initial_pose(rest, h, None)
    if start is None:
        return math.nan, 1.0
    fit = fit_hopt(rest, h, start, sigma_px, sigma_h)
    if not fit.converged:
        return math.nan, 1.0
    ev_rest = evaluate(rest, fit.theta)
    ev_k = evaluate(c.subset([k]), fit.theta)
    if not ev_k.in_front:
        return math.inf, 1.0
    J_rest, J_k = ev_rest.J_px[:, PLANAR], ev_k.J_px[:, PLANAR]
    N_inv = safe_inverse(J_rest.T @ J_rest)
    if not np.all(np.isfinite(N_inv)):
        return math.nan, 1.0
    v = ev_k.J_px[:, IZ] - J_k @ (N_inv @ (J_rest.T @ ev_rest.J_px[:, IZ]))
    m = len(ev_k.r_px)
    if sigma_px is not None:
        sigma2, thr = sigma_px ** 2, float(stats.chi2.ppf(1.0 - alpha, m))
    else:
        ss = float(ev_rest.r_px @ ev_rest.r_px)
        sigma2 = (ss + PRIOR_DOF * SIGMA_PRIOR_PX ** 2) / (fit.dof + PRIOR_DOF)
        thr = float(m * stats.f.ppf(1.0 - alpha, m, fit.dof + PRIOR_DOF))
    S = sigma2 * (np.eye(m) + J_k @ N_inv @ J_k.T) + sigma_h ** 2 * np.outer(v, v)
    return float(ev_k.r_px @ np.linalg.solve(S, ev_k.r_px)), thr


def implausibility(fit: Fit, layout_fit: Fit, h: float, limits: Limits, sigma_px: float | None) -> str | None:
    """Why this fit must not be reported as a pose (one line), or None if it is plausible.
    layout_fit: the H.Opt. fit of the same corners, which judges whether they match the tag layout."""
    for f in (layout_fit, fit):
        if f.note:
            return f.note
    if not np.all(np.isfinite(fit.theta)):
        return "pose is not finite"
    if not np.all(np.isfinite(fit.covariance)):
        return "pose is not determined by the corners (covariance not finite)"
    if not evaluate(fit.corners, fit.theta).in_front:
        return "pose puts the tags behind the camera"
    tilt = math.degrees(math.acos(np.clip(euler_rotation(*fit.theta[2:3], *fit.theta[4:6])[2, 2], -1.0, 1.0)))
    if tilt >= 90.0:
        return f"pose has the roof facing down (tilt {tilt:.0f} deg): tags seen from below or mirrored"
    for f in (layout_fit, fit) if fit.method == "sopt" else (layout_fit,):
        limit = limits.rms_limit(sigma_px, f.height_rms_px)
        if not f.fit_rms_px <= limit:
            return (f"corners do not match the tag layout: RMS residual {f.fit_rms_px:.2f} px "
                    f"above the {limit:.2f} px limit")
    pos_sigma = math.sqrt(max(np.linalg.eigvalsh(fit.covariance[:2, :2]).max(), 0.0))
    if pos_sigma > limits.max_position_sigma_m:
        return f"position uncertainty {pos_sigma:.2f} m above the {limits.max_position_sigma_m:.2f} m limit"
    if fit.method == "sopt":
        if tilt > limits.max_tilt_deg:
            return f"roof tilted {tilt:.0f} deg (limit {limits.max_tilt_deg:.0f} deg)"
        dz = float(np.max(np.abs(evaluate(fit.corners, fit.theta).z - h)))
        if dz > limits.max_height_error_m:
            return (f"tag corners {dz:.2f} m from the vehicle height {h:.2f} m "
                    f"(limit {limits.max_height_error_m:.2f} m)")
    return None
