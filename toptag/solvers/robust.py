"""Never a confident wrong answer: a per-tag outlier test, and plausibility checks on the final pose.

Outlier test (leave one observation out), whatever the solver asked for, with the level-roof model
(level.py: x, y, yaw and the roof height z with its prior N(h, sigma_h²); tag layout known): it has the
most redundancy (a lone tag leaves 4 of its 8 coordinates to check its shape), and it carries the
roof-height uncertainty as an unknown, so that a bouncing bus is not mistaken for bad corners. For each
tag-in-a-camera k, the roof is fitted without k and k's corners are predicted; the prediction error e_k
(whitened by the solver's corner-noise model: the edge-line model for "level", independent coordinates
otherwise) is judged against its covariance
    S_k = sigma²·I + J_k Cov(rest's fit) J_kᵀ + G_k Σ_cal G_kᵀ,
G_k the effect of the cameras' calibration errors (when their uncertainty is given) on k's prediction
error through the rest's fit, so d_k = e_kᵀ S_k⁻¹ e_k is chi-square with 8 degrees of freedom when k is
fine (F-distributed when sigma is estimated from the rest). The worst k above the (1 − alpha) quantile
is dropped, and the test repeats on what is left. A bad tag of a pair is told from the good one
because, fitted alone, its own corners disagree with its layout, which inflates the noise its
prediction of the good one is judged with.

With sigma unknown, the rest's residual is pooled with a prior of SCREEN_PRIOR_PX worth PRIOR_DOF
degrees of freedom: the real cameras' corner noise (0.17 px per coordinate, measured against saddle-point
truth on real photographs, docs/real-data.md). Every solver's tags are judged with the measured
corner-noise model (edge offsets, turns and each tag's common offset: level.edge_whitener), whatever the
solver. Nominal false-drop level: alpha = 0.1 %. Measured: no good tag dropped on EuRoC's real frame (84
tag-in-vehicle tests, every solver), at most 0.5 % of frames in 400 synthetic frames of two and three
tags at 6–20 m with real-level noise (tests/test_solvers.py). The price of not dropping good tags at real
noise: a pair's tag with one corner 3 px off is dropped about 90 % of the time at 12–16 m, one 1.5 px off
7 % (the level solver weighs down what is left). (Tuned before on the old renderer's 0.04–0.09 px corners,
the prior was 0.1 px and 7 of EuRoC's 32 good tags were dropped.)
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from toptag.solvers import kernels
from toptag.solvers.common import SIGMA_PRIOR_PX, Fit
from toptag.solvers.level import SubsetFit, SubsetFits, noise_scale
from toptag.solvers.model import (
    KNOWN,
    MIN_DEPTH,
    Calibration,
    Corners,
    calib_jacobian,
    depths_and_heights,
)

# Per corner coordinate: the real cameras' corner noise (common.SIGMA_PRIOR_PX), pooled with a lone
# tag's 4–5 degrees of freedom. More weight catches more garbled tags and falsely drops more good ones
# when the images are noisier.
SCREEN_PRIOR_PX = SIGMA_PRIOR_PX
PRIOR_DOF = 1.5


@dataclass(frozen=True)
class Limits:
    """When a pose is refused rather than returned.

    max_rms_px: limit on the RMS residual of the corners against the tag layout (H.Opt. model, and
    S.Opt.'s and the level solver's own); None means 1.5 px when sigma_px is unknown, else
    max(3·sigma_px, 0.5 px). Three times what a one-sigma roof-height error, and three times what
    one-sigma camera calibration errors (when given), leave in the residual are added in quadrature."""

    max_rms_px: float | None = None
    max_position_sigma_m: float = 1.0
    max_height_error_m: float = 0.5
    max_tilt_deg: float = 20.0  # S.Opt.'s roof tilt; any solver's roof must face up
    outlier_alpha: float = 1e-3

    def rms_limit(self, sigma_px: float | None, height_rms_px: float = 0.0, calib_rms_px: float = 0.0) -> float:
        base = self.max_rms_px
        if base is None:
            base = 1.5 if sigma_px is None else max(3.0 * sigma_px, 0.5)
        return math.hypot(base, 3.0 * height_rms_px, 3.0 * calib_rms_px)


def screening_fits(c: Corners, h: float, sigma_px: float | None, sigma_h: float,
                   turn_ratio: float | None) -> SubsetFits:
    """The level fits the outlier test (and the level solver's misfit weights) share."""
    scale = noise_scale(turn_ratio)
    sigma_w = (sigma_px if sigma_px is not None else SCREEN_PRIOR_PX) / scale
    return SubsetFits(c, h, sigma_h, turn_ratio, sigma_w)


# A frame is screened for real when any tag's linearised statistic reaches this fraction of its
# threshold: the linearisation is off by far less near a consistent frame's optimum, so every frame the
# test could drop a tag from is screened (and a garbled tag's statistic is many times its threshold).
SCREEN_MARGIN = 0.5


@dataclass
class Consistency:
    """screening_needed's verdict on a frame, and what the level solver reads from it when no tag could
    be dropped: the pose it was judged about and each unit's own fit, predicted (whitened residual sum
    of squares and degrees of freedom, NaN where a unit alone does not determine the pose)."""

    needed: bool
    about: SubsetFit | None = None
    own_ss: list[float] | None = None
    own_dof: list[float] | None = None


def screening_needed(c: Corners, fits: SubsetFits, sigma_px: float | None, sigma_h: float, alpha: float = 1e-3, *,
                     turn_ratio: float | None = None, about: SubsetFit | None = None) -> Consistency:
    """Whether screen_outliers could drop a tag of c, judged without its leave-one-out fits: those fits
    predicted from one fit of every tag (`about`: a level pose with every corner's residual and
    Jacobian; default the screening's own joint fit) by one Gauss–Newton step each
    (SubsetFits.linear_fits), and their statistics d_k (without the calibration term, which only lowers
    them) held against SCREEN_MARGIN times their thresholds. For a linear model the prediction is exact;
    a clean frame's tags score far below (chi-square 8 against its 0.1 % quantile), a garbled tag's far
    above."""
    n_u = len(c.units)
    if n_u < 2:
        return Consistency(False)
    if about is None:
        about = fits.get(range(n_u))
    if about is None or not about.converged or not about.all_in_front.all():
        return Consistency(True)
    rows = fits.rows(range(n_u)).reshape(n_u, -1)  # each unit's residual rows
    alone = np.zeros((n_u, 2 * c.n))
    alone[np.arange(n_u)[:, None], rows] = 1.0
    # Leave-one-out masks, then (three units or more) each unit alone; with two, each alone is the
    # other's leave-one-out.
    lin = fits.linear_fits(about, 1.0 - alone if n_u == 2 else np.vstack([1.0 - alone, alone]))
    if not np.isfinite(lin.dof[:n_u]).all():  # some rest does not determine the pose: judge it for real
        return Consistency(True)
    n_p = lin.p.shape[1]
    e = np.take_along_axis(lin.r_white[:n_u], rows, axis=1)
    Jk = about.all_J_white[rows][..., :n_p]
    S, H_inv, _, thr = _loo_covariance(Jk, lin.JtJ[:n_u], lin.ss[:n_u], lin.dof[:n_u], sigma_px, sigma_h,
                                    turn_ratio, alpha)
    d = _mahalanobis(e, S)
    finite = np.isfinite(H_inv).all(axis=(1, 2)).tolist()
    if not all(f and d_k <= SCREEN_MARGIN * t for f, d_k, t in zip(finite, d, thr)):  # False for a NaN
        return Consistency(True)
    own = slice(None, None, -1) if n_u == 2 else slice(n_u, None)
    return Consistency(False, about, lin.ss[own].tolist(), lin.dof[own].tolist())


def screen_outliers(c: Corners, h: float, sigma_px: float | None, sigma_h: float, alpha: float = 1e-3, *,
                    calib: Calibration = KNOWN, turn_ratio: float | None = None,
                    fits: SubsetFits | None = None) -> tuple[list[int], list[dict]]:
    """Unit indices to keep and the dropped ones ({"tag", "camera", "reason"}). turn_ratio: the corner
    noise model (level.edge_whitener; None: independent coordinates). fits: screening_fits(...) of c."""
    if fits is None:
        fits = screening_fits(c, h, sigma_px, sigma_h, turn_ratio)
    keep = list(range(len(c.units)))
    dropped: list[dict] = []
    while len(keep) >= 2:
        fits.prepare([[u for u in keep if u != k] for k in keep])  # every leave-one-out fit in one batch
        scores = _loo_statistics(c, fits, keep, sigma_px, sigma_h, calib, turn_ratio, alpha)
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


@functools.lru_cache(maxsize=4096)
def _threshold(alpha: float, m: int, dof10: int | None) -> float:
    """(1 − alpha) quantile of chi2(m), or of m·F(m, dof) with dof = dof10 / 10."""
    if dof10 is None:
        return float(stats.chi2.ppf(1.0 - alpha, m))
    return float(m * stats.f.ppf(1.0 - alpha, m, dof10 / 10.0))


def _cam_blocks(corners: Corners, theta, calib: Calibration, cam_ids: list[str]) -> np.ndarray:
    """d(pixels)/d(uncertain corrections of the cameras cam_ids) (2n, k·len(cam_ids))."""
    cols = calib.columns
    k = len(cols)
    J6 = calib_jacobian(corners, theta)[:, cols]
    out = np.zeros((2 * corners.n, k * len(cam_ids)))
    rows_cam = np.repeat([cam_ids.index(corners.units[u].camera.id) for u in corners.unit_of], 2)
    for i in range(len(cam_ids)):
        rows = rows_cam == i
        out[rows, i * k:(i + 1) * k] = J6[rows]
    return out


def _loo_statistics(c: Corners, fits: SubsetFits, keep: list[int], sigma_px: float | None, sigma_h: float,
                    calib: Calibration, turn_ratio: float | None, alpha: float) -> list[tuple[float, float]]:
    """(d_k, its threshold) for every unit k of keep, the matrix work of all of them at once."""
    out: list[tuple[float, float]] = [(math.nan, 1.0)] * len(keep)
    items = []  # (index in keep, k, the rest's fit, k's rows)
    for i, k in enumerate(keep):
        rest = fits.get([u for u in keep if u != k])
        if rest is None or not rest.converged:
            continue
        if not rest.all_in_front[c.unit_of == k].all():
            out[i] = (math.inf, 1.0)
            continue
        items.append((i, k, rest, fits.rows([k])))
    if not items:
        return out
    # k's corners as the rest's fit predicts them, whitened as k's own (the whitener is per unit).
    e = np.stack([rest.all_r_white[rows] for _, _, rest, rows in items])
    n_p = items[0][2].J_white.shape[1]
    Jk = np.stack([rest.all_J_white[rows][:, :n_p] for _, _, rest, rows in items])
    G = np.stack([rest.J_white for _, _, rest, _ in items])
    ss = np.array([float(rest.r_white @ rest.r_white) for _, _, rest, _ in items])
    dof = np.array([rest.dof for _, _, rest, _ in items])
    S, H_inv, s2, thr = _loo_covariance(Jk, np.swapaxes(G, 1, 2) @ G, ss, dof, sigma_px, sigma_h, turn_ratio,
                                        alpha)
    if not calib.known:
        for j, (_, k, rest, _) in enumerate(items):
            ck = c.subset([k])
            cam_ids = sorted({u.camera.id for u in rest.corners.units} | {ck.units[0].camera.id})
            Jc_rest = fits.whitener(rest.units) @ _cam_blocks(rest.corners, rest.theta, calib, cam_ids)
            Jc_k = fits.whitener([k]) @ _cam_blocks(ck, rest.theta, calib, cam_ids)
            Gc = Jc_k - Jk[j] @ (H_inv[j] @ (G[j].T @ Jc_rest) / s2[j])
            S[j] += (Gc * np.tile(calib.sigmas ** 2, len(cam_ids))) @ Gc.T
    finite = np.isfinite(H_inv).all(axis=(1, 2)).tolist()
    d = _mahalanobis(e, S)
    for j, (i, _, _, _) in enumerate(items):
        if finite[j] and not math.isnan(d[j]):
            out[i] = (d[j], thr[j])
    return out


def _loo_covariance(Jk: np.ndarray, GtG: np.ndarray, ss: np.ndarray, dof: np.ndarray, sigma_px: float | None,
                    sigma_h: float, turn_ratio: float | None,
                    alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """For K left-out units: the covariance S_k (K, m, m) of each one's prediction error from the rest's
    fit (whitened Jacobian Jk (K, m, n_p) of its rows, the rest's whitened normal matrix GtG (K, n_p,
    n_p), residual sum of squares ss and degrees of freedom dof (K,)), without the calibration term; the
    rest's parameter covariance H⁻¹ (K, n_p, n_p); the whitened noise variance it assumes (K,); and
    d_k's thresholds."""
    m = Jk.shape[1]
    scale = noise_scale(turn_ratio)
    if sigma_px is not None:
        s2 = np.full(len(Jk), (sigma_px / scale) ** 2)
        thr = [_threshold(alpha, m, None)] * len(Jk)
    else:
        dof = np.maximum(dof, 0.0)
        s2 = (ss + PRIOR_DOF * (SCREEN_PRIOR_PX / scale) ** 2) / (dof + PRIOR_DOF)
        thr = [_threshold(alpha, m, int(math.floor((d + PRIOR_DOF) * 10))) for d in dof.tolist()]
    z_prec = 1.0 / sigma_h ** 2 if Jk.shape[2] == 4 else 0.0
    S, H_inv = kernels.loo_covariance(np.ascontiguousarray(Jk), GtG, s2, z_prec)
    return S, H_inv, s2, thr


def _mahalanobis(e: np.ndarray, S: np.ndarray) -> list[float]:
    """e_kᵀ S_k⁻¹ e_k for each k (NaN where S_k is singular)."""
    return kernels.mahalanobis(np.ascontiguousarray(e), S).tolist()


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
    depth, z = depths_and_heights(fit.corners, fit.theta)
    if not (depth > MIN_DEPTH).all():
        return "pose puts the tags behind the camera"
    # The roof normal's angle from up: R[2, 2] = cos(pitch)·cos(roll).
    tilt = math.degrees(math.acos(min(max(math.cos(fit.theta[4]) * math.cos(fit.theta[5]), -1.0), 1.0)))
    if tilt >= 90.0:
        return f"pose has the roof facing down (tilt {tilt:.0f} deg): tags seen from below or mirrored"
    for f in (layout_fit, fit) if fit is not layout_fit else (layout_fit,):
        if f.method == "bas":
            continue
        limit = limits.rms_limit(sigma_px, f.height_rms_px, f.calib_rms_px)
        if not f.fit_rms_px <= limit:
            return (f"corners do not match the tag layout: RMS residual {f.fit_rms_px:.2f} px "
                    f"above the {limit:.2f} px limit")
    (a, b), (_, d) = fit.covariance[:2, :2].tolist()
    pos_sigma = math.sqrt(max((a + d) / 2.0 + math.hypot((a - d) / 2.0, b), 0.0))  # largest eigenvalue
    if pos_sigma > limits.max_position_sigma_m:
        return f"position uncertainty {pos_sigma:.2f} m above the {limits.max_position_sigma_m:.2f} m limit"
    if fit.method in ("sopt", "level"):
        if tilt > limits.max_tilt_deg:
            return f"roof tilted {tilt:.0f} deg (limit {limits.max_tilt_deg:.0f} deg)"
        dz = float(np.max(np.abs(z - h)))
        if dz > limits.max_height_error_m:
            return (f"tag corners {dz:.2f} m from the vehicle height {h:.2f} m "
                    f"(limit {limits.max_height_error_m:.2f} m)")
    return None
