"""Extrinsic calibration: the camera pose in the site frame from surveyed control points, with its
covariance, and what that pose means downstream: where a pixel lands on the bus roof plane.

Estimator. Every control point has two errors: the survey's (sigma per axis, metres) and the image's
(corner noise sigma_px). Projected through the camera, a survey error is a pixel error of covariance
J_X Σ_X J_Xᵀ, so each point's residual has the covariance C_i = sigma_px² I + J_X Σ_X J_Xᵀ (the
errors-in-variables problem with the true points marginalised, exact to first order). The pose
minimises Σ r_iᵀ C_i⁻¹ r_i (scipy least squares on whitened residuals, C_i re-evaluated at each
estimate, started from OpenCV's solvePnP). Its covariance is (Σ J_iᵀ C_i⁻¹ J_i)⁻¹, inflated by the
residuals' chi-square per degree of freedom when that exceeds 1 (a model that under-states the errors
is not trusted further than its residuals); at the true pose with the true sigmas, the same matrix is
the Cramér–Rao bound (`pose_information`).

Pose parameters (the camera file's calibration covariance uses them): a rotation vector w about the
camera axes (R_wc -> exp(w)·R_wc, rad) and the camera centre in the site frame (m): the convention of
toptag.solvers.model.calib_jacobian.

Roof mapping. A fix is made where the tag corners' rays meet the roof plane (z = 3 m). A pose error
moves that meeting point: `mapping_error` (true vs estimated camera) and `mapping_sigma` (from a pose
covariance) measure it over the camera's footprint at 8-25 m horizontal distance.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from toptag.calibration.intrinsics import CalibrationError
from toptag.calibration.points import ControlPoint
from toptag.camera import Camera
from toptag.geometry import rodrigues

DEFAULT_SIGMA_PX = 0.3  # corner noise of a detected plate or a clicked point per coordinate (px)
ROOF_Z = 3.0
FOOTPRINT = (8.0, 25.0)  # horizontal distance from the camera, m
MIN_POINTS = 4
COLLINEAR_RATIO = 0.02  # second over first singular value of the centred points


def perturbed(camera: Camera, delta) -> Camera:
    """The camera with its pose moved by delta = (w (3), centre shift (3)) in the module's convention."""
    d = np.asarray(delta, float).reshape(6)
    R = rodrigues(d[:3]) @ camera.R
    c = camera.center + d[3:]
    return camera.with_extrinsics(R, -R @ c)


def project_jacobians(camera: Camera, X: np.ndarray, h_pose: float = 1e-7, h_x: float = 1e-6):
    """Pixels (N,2), d(pixel)/d(pose delta) (N,2,6) and d(pixel)/d(world point) (N,2,3), numerically
    (central differences; the lens model makes analytic ones long)."""
    u0 = camera.project(X)
    Jp = np.zeros((len(X), 2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h_pose
        Jp[:, :, k] = (perturbed(camera, d).project(X) - perturbed(camera, -d).project(X)) / (2 * h_pose)
    Jx = np.zeros((len(X), 2, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h_x
        Jx[:, :, k] = (camera.project(X + e) - camera.project(X - e)) / (2 * h_x)
    return u0, Jp, Jx


def point_covariances(Jx: np.ndarray, survey_sigma: np.ndarray, sigma_px: float) -> np.ndarray:
    """(N,2,2) pixel covariance of each point: image noise plus its survey error projected."""
    S = np.einsum("nik,nk,njk->nij", Jx, survey_sigma ** 2, Jx)
    return S + sigma_px ** 2 * np.eye(2)


def pose_information(camera: Camera, world: np.ndarray, survey_sigma: np.ndarray, sigma_px: float) -> np.ndarray:
    """Fisher information (6,6) of the pose delta from points `world` (N,3) with survey sigmas (N,3) and
    corner noise sigma_px, at `camera`'s pose. Its inverse at the true pose is the Cramér–Rao bound."""
    _, Jp, Jx = project_jacobians(camera, world)
    Ci = np.linalg.inv(point_covariances(Jx, survey_sigma, sigma_px))
    return np.einsum("nik,nij,njl->kl", Jp, Ci, Jp)


def check_layout(points: list[ControlPoint]) -> None:
    """CalibrationError naming why a layout cannot fix a camera pose (too few, collinear)."""
    if len(points) < MIN_POINTS:
        raise CalibrationError(f"extrinsics need at least {MIN_POINTS} control points with pixels; got "
                               f"{len(points)}" + (f" ({', '.join(p.id for p in points)})" if points else ""))
    W = np.array([p.world for p in points])
    distinct = np.unique(np.round(W, 3), axis=0)
    if len(distinct) < MIN_POINTS:
        raise CalibrationError(f"extrinsics need at least {MIN_POINTS} distinct control points; got {len(distinct)}")
    s = np.linalg.svd(W - W.mean(axis=0), compute_uv=False) / np.sqrt(len(W))
    if s[1] < COLLINEAR_RATIO * s[0] or s[1] < 0.05:
        raise CalibrationError(f"the {len(W)} control points are (nearly) collinear: they spread {2 * s[0]:.2f} m "
                               f"along a line but only {2 * s[1]:.2f} m across it; add points off that line")
    P = np.array([p.pixel for p in points])
    sp = np.linalg.svd(P - P.mean(axis=0), compute_uv=False) / np.sqrt(len(P))
    if sp[1] < COLLINEAR_RATIO * sp[0] or sp[1] < 1.0:
        raise CalibrationError(f"the {len(P)} control points lie (nearly) on one line in the image "
                               f"({2 * sp[1]:.1f} px across it); add points off that line")


@dataclass
class ExtrinsicsResult:
    camera: Camera  # with the estimated pose
    covariance: np.ndarray  # (6,6) pose delta covariance (rotation about camera axes rad, centre m)
    points: list[ControlPoint]
    residuals_px: np.ndarray  # (N,2) observed minus projected
    normalized: np.ndarray  # (N,) Mahalanobis length of each residual under its covariance
    chi2_dof: float
    sigma_px: float
    missing: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals_px ** 2, axis=1))))

    def roof_mapping_sigma(self, z: float = ROOF_Z, footprint=FOOTPRINT) -> float:
        """RMS over the footprint of the horizontal roof-plane mapping sigma that the covariance implies."""
        pts = footprint_points(self.camera, z, footprint)
        return float(np.sqrt(np.mean(mapping_sigma(self.camera, self.covariance, pts) ** 2))) if len(pts) else float("nan")

    def summary(self) -> dict:
        std = np.sqrt(np.diag(self.covariance))
        return {"rms_px": self.rms_px, "points": len(self.points), "sigma_px": self.sigma_px,
                "chi2_dof": self.chi2_dof, "covariance": self.covariance.tolist(),
                "parameters": "rotation vector about the camera x, y, z axes (rad: R_wc -> exp(w) R_wc); "
                              "camera centre x, y, z in the site frame (m)",
                "rotation_std_deg": np.degrees(std[:3]).tolist(), "centre_std_m": std[3:].tolist(),
                "roof_mapping_sigma_m": {"z": ROOF_Z, "range_m": list(FOOTPRINT), "rms": self.roof_mapping_sigma()}}


def solve_extrinsics(camera: Camera, points: list[ControlPoint], sigma_px: float = DEFAULT_SIGMA_PX,
                     start: Camera | None = None) -> ExtrinsicsResult:
    """The camera pose from control points (camera gives the intrinsics and, unless `start`, nothing
    else: the start comes from solvePnP)."""
    check_layout(points)
    W = np.array([p.world for p in points], float)
    P = np.array([p.pixel for p in points], float)
    Ssig = np.array([p.sigma for p in points], float)
    if start is None:
        ok, rvec, tvec = cv2.solvePnP(W, P, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError("extrinsics: OpenCV found no pose for these points")
        ok, rvec, tvec = cv2.solvePnP(W, P, camera.K, camera.dist, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
        start = camera.with_extrinsics(cv2.Rodrigues(rvec)[0], tvec.ravel())
    if np.any(start.to_camera(W)[:, 2] <= 0):
        raise CalibrationError("extrinsics: the best pose puts control points behind the camera "
                               "(check the points' pixels and world coordinates)")
    cam = start
    for _ in range(4):  # the point covariances depend on the pose: re-evaluate them at each estimate
        _, _, Jx = project_jacobians(cam, W)
        L = np.linalg.cholesky(np.linalg.inv(point_covariances(Jx, Ssig, sigma_px)))  # C^-1 = L Lᵀ

        def whitened(delta, base=cam, L=L):
            r = perturbed(base, delta).project(W) - P
            return np.einsum("nji,nj->ni", L, r).ravel()

        sol = least_squares(whitened, np.zeros(6), method="lm", x_scale=np.array([1e-3] * 3 + [1e-2] * 3))
        step = sol.x
        cam = perturbed(cam, step)
        if np.max(np.abs(step[:3])) < 1e-9 and np.max(np.abs(step[3:])) < 1e-7:
            break
    u, Jp, Jx = project_jacobians(cam, W)
    C = point_covariances(Jx, Ssig, sigma_px)
    Ci = np.linalg.inv(C)
    r = P - u
    m2 = np.einsum("ni,nij,nj->n", r, Ci, r)
    dof = max(1, 2 * len(W) - 6)
    chi2_dof = float(m2.sum() / dof)
    info = np.einsum("nik,nij,njl->kl", Jp, Ci, Jp)
    if np.linalg.cond(info) > 1e14:
        raise CalibrationError("extrinsics: the control points leave the camera pose undetermined (singular "
                               "information); spread them over the view")
    cov = np.linalg.inv(info) * max(1.0, chi2_dof)
    result = ExtrinsicsResult(cam, cov, points, r, np.sqrt(m2), chi2_dof, sigma_px)
    bad = [p.id for p, m in zip(points, np.sqrt(m2)) if m > 4.0]
    if bad:
        result.warnings.append(f"points beyond 4 sigma of the fit (a wrong pixel or coordinate?): {', '.join(bad)}")
    if chi2_dof > 4.0:
        result.warnings.append(f"residuals are {np.sqrt(chi2_dof):.1f}x what the survey and pixel sigmas explain; "
                               "the covariance is scaled up accordingly")
    return result


# ---- the roof plane -------------------------------------------------------------------------------
def footprint_points(camera: Camera, z: float = ROOF_Z, footprint=FOOTPRINT, step: float = 0.5) -> np.ndarray:
    """(N,3) points of the plane at height z, `footprint` metres (horizontal) from the camera, that the
    camera sees (projected inside the image)."""
    c = camera.center
    r = footprint[1]
    xs = np.arange(c[0] - r, c[0] + r + step / 2, step)
    ys = np.arange(c[1] - r, c[1] + r + step / 2, step)
    X, Y = np.meshgrid(xs, ys)
    d = np.hypot(X - c[0], Y - c[1])
    keep = (d >= footprint[0]) & (d <= footprint[1])
    pts = np.column_stack([X[keep], Y[keep], np.full(int(keep.sum()), float(z))])
    front = camera.to_camera(pts)[:, 2] > 0.5
    pts = pts[front]
    return pts[camera.in_image(camera.project(pts))]


def mapping_error(true_camera: Camera, estimated: Camera, points: np.ndarray) -> np.ndarray:
    """(N,) horizontal distance between roof points and where the estimated camera puts the pixels the
    true camera sees them at (on the same plane)."""
    px = true_camera.project(points)
    back = estimated.backproject_to_plane(px, float(points[0, 2]))
    return np.hypot(*(back[:, :2] - points[:, :2]).T)


def mapping_jacobian(camera: Camera, points: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """(N,2,6): how the roof point a fixed pixel maps to moves (x, y) with the camera's pose delta."""
    px = camera.project(points)
    z = float(points[0, 2])
    G = np.zeros((len(points), 2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        a = perturbed(camera, d).backproject_to_plane(px, z)[:, :2]
        b = perturbed(camera, -d).backproject_to_plane(px, z)[:, :2]
        G[:, :, k] = (a - b) / (2 * h)
    return G


def mapping_sigma(camera: Camera, covariance: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) horizontal roof-plane mapping sigma (sqrt of the 2x2 covariance's trace) of each point."""
    G = mapping_jacobian(camera, points)
    return np.sqrt(np.maximum(np.einsum("nik,kl,nil->n", G, covariance, G), 0.0))
