"""What every solver returns, and the statistics they share (noise estimate, covariances)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from toptag.geometry import wrap_angle
from toptag.solvers import kernels
from toptag.solvers.model import IX, IY, IYAW, Corners
from toptag.vehicle import HEIGHT_SIGMA_DEFAULT as SIGMA_H_DEFAULT  # the prior of a bag that declares none

# Corner noise per pixel coordinate, from real photographs (docs/real-data.md: toptag's detection path
# against saddle-point truth on a hand-held board (EuRoC) and a phone photo of a grid; 0.15-0.2 px).
# The prior is pooled into every estimate from a fit's residuals, worth PRIOR_DOF degrees of freedom;
# the floor keeps exact or few-dof data from claiming a noise no camera has.
SIGMA_PRIOR_PX = 0.17
SIGMA_FLOOR_PX = 0.05
PRIOR_DOF = 2.0


@dataclass
class PoseSolution:
    """A vehicle pose from one frame's tag corners.

    x, y: world position (m) of the vehicle origin (for S.Opt. and Bas.: of the vehicle-top frame origin,
    the roof point above the vehicle centre); yaw in (-pi, pi]; z: the roof (tag plane) height found (H.Opt.
    reports the vehicle height it assumed). covariance: 3x3 over (x, y, yaw). rms_px: RMS over the
    corners used of the reprojection error's length (pixels; about sqrt(2)·sigma_px for a good fit, as
    sigma_px is per image axis). When ok is False the pose fields are NaN and error says why in one
    line."""

    ok: bool
    method: str
    x: float = math.nan
    y: float = math.nan
    z: float = math.nan
    yaw: float = math.nan
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    rms_px: float = math.nan
    tags: list[int] = field(default_factory=list)
    dropped_tags: list[dict] = field(default_factory=list)  # {"tag", "camera", "reason"}
    cameras: list[str] = field(default_factory=list)
    error: str | None = None
    sigma_px: float = math.nan  # pixel noise the covariance assumes (given or estimated)
    n_corners: int = 0
    # One tag whose mirrored pose (IPPE's second solution) fits as well and is level enough: the
    # covariance then covers both poses (solvers/ambiguity.py).
    ambiguous: bool = False

    @property
    def position_sigma(self) -> float:
        """RMS position uncertainty (m): sqrt of the trace of the x, y covariance block."""
        return float(math.sqrt(max(self.covariance[0, 0] + self.covariance[1, 1], 0.0)))

    @property
    def yaw_sigma(self) -> float:
        return float(math.sqrt(max(self.covariance[2, 2], 0.0)))

    def pose(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw])

    def to_dict(self) -> dict:
        return {
            "ok": bool(self.ok),
            "method": self.method,
            "x": _json_float(self.x),
            "y": _json_float(self.y),
            "z": _json_float(self.z),
            "yaw": _json_float(self.yaw),
            "covariance": [[_json_float(v) for v in row] for row in np.asarray(self.covariance)],
            "rms_px": _json_float(self.rms_px),
            "sigma_px": _json_float(self.sigma_px),
            "n_corners": int(self.n_corners),
            "tags": [int(t) for t in self.tags],
            "dropped_tags": [{"tag": int(d["tag"]), "camera": str(d["camera"]), "reason": str(d["reason"])}
                             for d in self.dropped_tags],
            "cameras": [str(c) for c in self.cameras],
            "ambiguous": bool(self.ambiguous),
            "error": self.error,
        }


def _json_float(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass
class Fit:
    """A solver's raw result before the plausibility checks: the 6-vector pose and its statistics."""

    method: str
    theta: np.ndarray  # (x, y, yaw, z, pitch, roll)
    covariance: np.ndarray  # (3,3) over x, y, yaw
    rms_px: float
    sigma_px: float
    corners: Corners  # the observations actually used
    converged: bool = True
    dof: float = math.nan  # degrees of freedom left in the pixel residuals
    # The plausibility test's inputs. fit_rms_px: RMS of the residual of what the solver fits to the
    # pixels (Bas.: the homography, whose decomposition adds pose error that is no sign of bad data;
    # others: rms_px). height_rms_px: per-corner RMS of the pixel residual that a one-sigma roof-height
    # error leaves unexplained, so that a bouncing bus is not mistaken for bad corners.
    fit_rms_px: float = math.nan
    height_rms_px: float = 0.0
    # Per-corner RMS of the pixel residual that one-sigma errors of the cameras' extrinsics leave (when
    # their uncertainty is given): cameras that disagree by their calibration error are not bad corners.
    calib_rms_px: float = 0.0
    note: str | None = None  # why the fit is not usable, if the solver itself knows
    # The level model at theta, when the solver evaluated it there (H.Opt.): raw pixel residuals (2N,),
    # their Jacobian (2N, 4) over (x, y, yaw, z) and every corner in front (N,). The outlier test
    # linearises around it instead of fitting again.
    level_evaluation: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def solution(self) -> PoseSolution:
        t = self.theta
        return PoseSolution(ok=True, method=self.method, x=float(t[IX]), y=float(t[IY]), z=float(t[3]),
                            yaw=wrap_angle(t[IYAW]), covariance=self.covariance, rms_px=self.rms_px,
                            tags=self.corners.tag_ids, cameras=self.corners.camera_ids,
                            sigma_px=self.sigma_px, n_corners=self.corners.n)


def rms(r_px: np.ndarray) -> float:
    """RMS reprojection error per corner (pixels, over both image axes together)."""
    n = len(r_px) // 2
    return float(math.sqrt(r_px @ r_px / n)) if n else math.nan


def estimate_sigma(ss: float, dof: float, floor: float = SIGMA_FLOOR_PX,
                   prior: float = SIGMA_PRIOR_PX) -> float:
    """Per-coordinate pixel noise from a solve's own residual sum of squares with `dof` degrees of
    freedom, pooled with the real cameras' typical noise `prior` worth PRIOR_DOF degrees of freedom (a
    lone tag leaves Bas. 0 and H.Opt. 5: their own estimate alone is nearly random), never below floor."""
    dof = max(float(dof), 0.0)
    s2 = (max(ss, 0.0) + PRIOR_DOF * prior ** 2) / (dof + PRIOR_DOF)
    return float(max(math.sqrt(s2), floor))


def safe_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse of a normal matrix (or of each of a stack (..., n, n)), all-inf where the data do not
    determine the parameters: singular, not finite, or a condition number (1-norm: within a factor n
    of the 2-norm's) above kernels.MAX_CONDITION."""
    A = np.asarray(A, dtype=float)
    n = A.shape[-1]
    return kernels.safe_inverse(np.ascontiguousarray(A).reshape(-1, n, n)).reshape(A.shape)
