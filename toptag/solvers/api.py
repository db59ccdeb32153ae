"""`solve`: one vehicle's tag observations (any tags, any cameras) to a checked PoseSolution."""
from __future__ import annotations

import functools
import math

import numpy as np

from toptag.detection import TagObservation
from toptag.solvers.ambiguity import covering_covariance, mirror_candidate
from toptag.solvers.bas import fit_bas
from toptag.solvers.common import Fit, PoseSolution
from toptag.solvers.hopt import fit_hopt, initial_pose
from toptag.solvers.level import DETECTOR_BIAS, TURN_RATIO, DetectorBias, solve_level_corners
from toptag.solvers.model import Calibration, Corners, build_corners
from toptag.solvers.robust import (
    Limits,
    implausibility,
    screen_outliers,
    screening_fits,
    screening_needed,
)
from toptag.solvers.sopt import HEIGHT_MODELS, WEIGHTINGS, fit_sopt
from toptag.vehicle import Vehicle

METHODS = ("bas", "hopt", "sopt", "level")
_ALIASES = {"soptlevel": "level", "levelroof": "level"}


@functools.lru_cache(maxsize=64)
def canonical_method(method: str) -> str:
    """'Bas.', 'H.Opt.', 'h-opt', 'SOPT', 'level', 'sopt_level', 'S.Opt. level' ... to
    'bas' | 'hopt' | 'sopt' | 'level'."""
    m = "".join(ch for ch in str(method).lower() if ch.isalnum())
    m = _ALIASES.get(m, m)
    if m not in METHODS:
        raise ValueError(f"unknown solver {method!r} (known: Bas., H.Opt., S.Opt., level)")
    return m


def solve(vehicle: Vehicle, observations: list[TagObservation], method: str = "sopt", *,
          weighting: str = "paper", sigma_px: float | None = None, sigma_h: float | None = None,
          mu: float = 1.0, robust: bool = True, height_model: str = "common",
          limits: Limits | None = None, calib_rot_sigma: float = 0.0, calib_trans_sigma: float = 0.0,
          turn_ratio: float | None = TURN_RATIO, detector_bias: DetectorBias = DETECTOR_BIAS) -> PoseSolution:
    """Estimate the vehicle pose with Bas., H.Opt., S.Opt. or the level-roof solver ("level").

    observations: TagObservations of this vehicle's tags from one or more cameras (ideal pixels).
    sigma_px: corner noise per pixel coordinate if known; else estimated from the residuals.
    sigma_h: standard deviation of the true roof height about vehicle.height (H.Opt.'s covariance,
    S.Opt.'s principled weighting and covariance, the level solver's height prior; the outlier and layout
    tests allow for it). None: what the vehicle's code bag declares (vehicle.height_sigma; a bag that
    declares nothing gets SIGMA_H_DEFAULT, a bouncing bus).
    mu: S.Opt.'s paper weighting of the height residuals (1/m). height_model: "common" (the roof is off
    by one offset, a bounce) or "independent" (each corner by its own), for S.Opt.
    calib_rot_sigma (rad, about each camera axis), calib_trans_sigma (m, camera centre per world axis):
    how well the cameras' extrinsics are known (0: exactly). The outlier and layout tests and the
    covariances allow for it, so that cameras disagreeing by their calibration error are not refused;
    the level solver estimates every camera's correction with that prior.
    turn_ratio: the level solver's corner-noise model (level.py: sigma of an edge line's turn over its
    offset's; None: independent corner coordinates). The other solvers assume independent coordinates.
    detector_bias: corner errors shared by a tag's or an image's corners, which the level solver's
    covariance carries (level.DetectorBias; default: measured on toptag's rendered frames; NO_BIAS for
    synthetic independent noise).
    robust: drop tags whose corners disagree with the rest (and, level, weigh down tags whose own
    corners misfit a tag's shape). limits: when to refuse a pose.
    A lone tag whose mirrored pose (IPPE's second solution) is also plausible comes back with
    ambiguous=True and a covariance that covers both poses.
    Never raises on bad data: an unusable or implausible result comes back with ok=False and `error`."""
    method = canonical_method(method)
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, not {weighting!r}")
    if height_model not in HEIGHT_MODELS:
        raise ValueError(f"height_model must be one of {HEIGHT_MODELS}, not {height_model!r}")
    if sigma_px is not None and not sigma_px > 0:
        raise ValueError("sigma_px must be positive (or None to estimate it)")
    sigma_h = float(vehicle.height_sigma if sigma_h is None else sigma_h)
    if not sigma_h >= 0 or (method == "sopt" and weighting == "principled" and not sigma_h > 0):
        raise ValueError("sigma_h must be >= 0, and > 0 for principled S.Opt.")
    if turn_ratio is not None and not turn_ratio > 0:
        raise ValueError("turn_ratio must be positive (or None for independent corner coordinates)")
    calib = Calibration(float(calib_rot_sigma), float(calib_trans_sigma))
    limits = limits or Limits()
    h = float(vehicle.height)

    usable, dropped = _usable(vehicle, observations)
    if not usable:
        why = "; ".join(sorted({d["reason"] for d in dropped})) or "none given"
        return PoseSolution(ok=False, method=method, dropped_tags=dropped,
                            error=f"no usable tag observations ({why})")
    corners = build_corners(vehicle, usable)
    # The corner-noise model (edge lines, each tag's common offset) judges every solver's outliers.
    noise_model = turn_ratio
    # Hopeless data (garbage corners) produce infinities on the way to an ok=False; not worth warnings.
    with np.errstate(all="ignore"):
        keep, screened, linear, first = list(range(len(corners.units))), None, None, None
        if robust and len(corners.units) >= 2:
            try:
                screened = screening_fits(corners, h, sigma_px, sigma_h, noise_model)
                # A consistent frame (nearly every one) is told from one fit of every tag: the level
                # solver's joint fit, the others' H.Opt. (layout) fit.
                about = None
                if method != "level":
                    first = _fit(method, corners, h, weighting=weighting, sigma_px=sigma_px, sigma_h=sigma_h,
                                 mu=mu, height_model=height_model, calib=calib, layout_only=True)
                    ev = first[1].level_evaluation if first is not None else None
                    if ev is not None:
                        about = screened.evaluated(first[1].theta[[0, 1, 2, 3]], *ev)
                linear = screening_needed(corners, screened, sigma_px, sigma_h, limits.outlier_alpha,
                                          turn_ratio=noise_model, about=about)
                if linear.needed:
                    keep, outliers = screen_outliers(corners, h, sigma_px, sigma_h, limits.outlier_alpha,
                                                     calib=calib, turn_ratio=noise_model, fits=screened)
                    dropped += outliers
            except (np.linalg.LinAlgError, FloatingPointError, ValueError) as e:
                return _failed(method, corners, dropped, f"solver failed: {e}")
        try:
            if method == "level":
                fit, misfits = solve_level_corners(corners, keep, h, sigma_h=sigma_h, sigma_px=sigma_px, calib=calib,
                                                   turn_ratio=turn_ratio, fits=screened if robust else None,
                                                   weigh_misfits=robust, calib_alpha=limits.outlier_alpha,
                                                   bias=detector_bias,
                                                   linear=None if linear is None or linear.needed else linear)
                dropped += misfits
                fits = None if fit is None else (fit, fit)
            else:
                if len(keep) < len(corners.units) or first is None:
                    yaw0 = screened.yaw_of(keep) if screened is not None else None
                    corners = corners.subset(keep) if len(keep) < len(corners.units) else corners
                    first = None
                fits = _fit(method, corners, h, weighting=weighting, sigma_px=sigma_px, sigma_h=sigma_h, mu=mu,
                            height_model=height_model, calib=calib, yaw0=yaw0 if first is None else None,
                            done=first)
        except (np.linalg.LinAlgError, FloatingPointError, ValueError) as e:
            return _failed(method, corners, dropped, f"solver failed: {e}")
        if fits is None:
            return _failed(method, corners, dropped, "no corner back-projects onto the roof plane")
        fit, layout_fit = fits
        corners = fit.corners
        error = implausibility(fit, layout_fit, h, limits, sigma_px)
    if error:
        return _failed(method, corners, dropped, error, fit)
    sol = fit.solution()
    sol.dropped_tags = dropped
    mirror = mirror_candidate(corners, sigma_px or fit.sigma_px, limits.max_tilt_deg)
    if mirror is not None:
        sol.ambiguous = True
        sol.covariance = covering_covariance(sol.covariance, sol.pose(), mirror)
    return sol


def _fit(method: str, c: Corners, h: float, *, weighting, sigma_px, sigma_h, mu,
         height_model, calib: Calibration, yaw0: float | None = None, layout_only: bool = False,
         done: tuple[Fit, Fit] | None = None) -> tuple[Fit, Fit] | None:
    """(the method's fit, the H.Opt. fit that judges the corners against the tag layout). yaw0: H.Opt.'s
    starting yaw when the outlier test's level fits already found one; else Bas.'s for Bas. (SPEC), and
    for the others the planar fit of the back-projected corners (initial_pose), which costs a fraction
    of Bas.'s; every start leads H.Opt. to the same minimum. layout_only: Bas. and H.Opt. only (S.Opt.'s
    fit left for `done`: what an earlier call returned on the same corners)."""
    if done is not None:
        bas, hopt = done
    else:
        if method == "bas":
            bas = fit_bas(c, sigma_px, covariance=True)
            yaw0 = float(bas.theta[2]) if bas.converged and np.all(np.isfinite(bas.theta)) else None
        start = initial_pose(c, h, yaw0)
        if start is None:
            return None
        hopt = fit_hopt(c, h, start, sigma_px, sigma_h, calib)
        if method != "bas":
            bas = hopt
    if method in ("bas", "hopt") or layout_only:
        return bas, hopt
    sopt = fit_sopt(c, h, hopt.theta, weighting=weighting, sigma_px=sigma_px, sigma_h=sigma_h, mu=mu,
                    height_model=height_model, calib=calib)
    return sopt, hopt


def _usable(vehicle: Vehicle, observations) -> tuple[list[TagObservation], list[dict]]:
    usable, dropped = [], []
    seen: dict[tuple[int, str], int] = {}
    for obs in observations:
        cam_id = getattr(getattr(obs, "camera", None), "id", None)
        reason = None
        if cam_id is None:
            reason = "no camera"
        elif obs.tag_id not in vehicle.tags:
            reason = "tag not on this vehicle"
        else:
            c = np.asarray(obs.corners, dtype=float)
            if c.shape != (4, 2) or not np.all(np.isfinite(c)):
                reason = "corners are not 4 finite pixels"
        if reason:
            dropped.append({"tag": int(obs.tag_id), "camera": str(cam_id), "reason": reason})
            continue
        key = (int(obs.tag_id), cam_id)
        if key in seen:
            dropped.append({"tag": key[0], "camera": cam_id, "reason": "tag seen twice by one camera"})
            seen[key] = -1
            continue
        seen[key] = len(usable)
        usable.append(obs)
    twice = {k for k, v in seen.items() if v == -1}
    kept = [o for o in usable if (int(o.tag_id), o.camera.id) not in twice]
    return kept, dropped


def _failed(method: str, c: Corners, dropped: list[dict], error: str, fit: Fit | None = None) -> PoseSolution:
    return PoseSolution(ok=False, method=method, tags=c.tag_ids, dropped_tags=dropped, cameras=c.camera_ids,
                        error=error, rms_px=fit.rms_px if fit is not None else math.nan,
                        sigma_px=fit.sigma_px if fit is not None else math.nan, n_corners=c.n)
