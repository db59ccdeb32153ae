"""The measurement model shared by every solver: observed tag corners, the vehicle-top pose, and the
projection of one into the other with its analytic Jacobian.

Pose parameters are always the 6-vector theta = (x, y, yaw, z, pitch, roll): world position of the
vehicle-top frame origin (the roof point above the vehicle centre), and ZYX Euler angles, so that the
roof rotation is R = Rz(yaw) · Ry(pitch) · Rx(roll). (x, y, yaw) come first so that every covariance's
top-left 3x3 block is the one SPEC's pose reports; H.Opt. is the same model with z = h and no tilt.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.solvers import kernels
from toptag.vehicle import Vehicle

IX, IY, IYAW, IZ, IPITCH, IROLL = range(6)
MIN_DEPTH = kernels.MIN_DEPTH  # metres in front of the camera; anything closer is "behind"


@dataclass(frozen=True)
class Unit:
    """One tag seen by one camera: the unit the robustness test keeps or drops."""

    tag_id: int
    camera: Camera


@dataclass(frozen=True)
class Corners:
    """The corners of one vehicle's tag observations, stacked over tags and cameras.

    Per observed corner n: its vehicle-top coordinates, its ideal pixel, the observation unit, the
    physical corner it is (a tag seen by two cameras has its corners twice in the image data but only
    once on the roof), and its camera's projection parameters copied per row so that projection is one
    vectorised pass whatever the number of cameras."""

    units: tuple[Unit, ...]
    unit_of: np.ndarray  # (N,) index into units
    pixels: np.ndarray  # (N,2)
    corner_of: np.ndarray  # (N,) index into roof_points
    roof_points: np.ndarray  # (M,3) distinct physical corners, vehicle-top frame
    cam_R: np.ndarray  # (N,3,3)
    cam_t: np.ndarray  # (N,3)
    cam_K: np.ndarray  # (N,2,2) upper-left block of K (focal lengths and skew)
    cam_c: np.ndarray  # (N,2) principal point

    @property
    def n(self) -> int:
        return len(self.pixels)

    @functools.cached_property
    def points(self) -> np.ndarray:
        """(N,3) vehicle-top coordinates of each observed corner (computed once; never modified)."""
        return self.roof_points[self.corner_of]

    @functools.cached_property
    def level_projection(self) -> np.ndarray:
        """(3N, 6): each corner's homogeneous pixel (K·X_cam, rows of 3) as a linear map of
        (x, y, z, cos yaw, sin yaw, 1) of a level roof (pitch = roll = 0): the roof corner (px, py, pz) is at
        world (x + px·cos − py·sin, y + px·sin + py·cos, z + pz)."""
        return kernels.level_projection(self.cam_K, self.cam_c, self.cam_R, self.cam_t, self.points)

    def backprojected(self, h: float) -> np.ndarray:
        """Observed corners back-projected onto the world plane z = h (N,3), NaN where the ray misses
        (the last plane asked is kept: a solve asks for the roof's several times; never modify it)."""
        last = self.__dict__.get("_backprojected")
        if last is not None and last[0] == h:
            return last[1]
        W = kernels.backproject(self.cam_K, self.cam_c, self.cam_R, self.cam_t, self.pixels, float(h))
        self.__dict__["_backprojected"] = (h, W)
        return W

    @property
    def tag_ids(self) -> list[int]:
        return sorted({u.tag_id for u in self.units})

    @property
    def camera_ids(self) -> list[str]:
        return sorted({u.camera.id for u in self.units})

    def subset(self, keep_units) -> "Corners":
        """The same data restricted to the listed unit indices (units renumbered in the given order)."""
        keep_units = list(keep_units)
        units = tuple(self.units[i] for i in keep_units)
        remap = {old: new for new, old in enumerate(keep_units)}
        rows = np.flatnonzero(np.isin(self.unit_of, keep_units))
        used = np.unique(self.corner_of[rows])
        corner_map = np.full(len(self.roof_points), -1)
        corner_map[used] = np.arange(len(used))
        return Corners(units, np.array([remap[u] for u in self.unit_of[rows]], dtype=int),
                       self.pixels[rows], corner_map[self.corner_of[rows]], self.roof_points[used],
                       self.cam_R[rows], self.cam_t[rows], self.cam_K[rows], self.cam_c[rows])

    def camera_rows(self, camera_id: str) -> np.ndarray:
        return np.array([self.units[u].camera.id == camera_id for u in self.unit_of])


def build_corners(vehicle: Vehicle, observations: list[TagObservation]) -> Corners:
    """Stack observations that are already known valid (tag in the vehicle, finite (4,2) corners)."""
    units, unit_of, pixels, corner_of = [], [], [], []
    cams = []
    roof_keys: dict[tuple[int, int], int] = {}
    roof_points = []
    for obs in observations:
        u = len(units)
        units.append(Unit(int(obs.tag_id), obs.camera))
        pts = vehicle.tag_corners(obs.tag_id)
        for k in range(4):
            key = (int(obs.tag_id), k)
            if key not in roof_keys:
                roof_keys[key] = len(roof_points)
                roof_points.append(pts[k])
            corner_of.append(roof_keys[key])
        unit_of.extend([u] * 4)
        pixels.append(np.asarray(obs.corners, dtype=float).reshape(4, 2))
        cams.extend([obs.camera] * 4)
    return Corners(
        units=tuple(units),
        unit_of=np.asarray(unit_of, dtype=int),
        pixels=np.vstack(pixels) if pixels else np.zeros((0, 2)),
        corner_of=np.asarray(corner_of, dtype=int),
        roof_points=np.asarray(roof_points, dtype=float).reshape(-1, 3),
        cam_R=np.array([c.R for c in cams]).reshape(-1, 3, 3),
        cam_t=np.array([c.t for c in cams]).reshape(-1, 3),
        cam_K=np.array([c.K[:2, :2] for c in cams]).reshape(-1, 2, 2),
        cam_c=np.array([c.K[:2, 2] for c in cams]).reshape(-1, 2),
    )


# ---- pose ------------------------------------------------------------------------------------
def euler_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), written out."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _euler_with_derivatives(yaw, pitch, roll):
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    # R and its partial derivatives, written out (one array each).
    R = euler_rotation(yaw, pitch, roll)
    dyaw = np.array([[-sy * cp, -sy * sp * sr - cy * cr, -sy * sp * cr + cy * sr],
                     [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [0.0, 0.0, 0.0]])
    dpitch = np.array([[-cy * sp, cy * cp * sr, cy * cp * cr],
                       [-sy * sp, sy * cp * sr, sy * cp * cr],
                       [-cp, -sp * sr, -sp * cr]])
    droll = np.array([[0.0, cy * sp * cr + sy * sr, -cy * sp * sr + sy * cr],
                      [0.0, sy * sp * cr - cy * sr, -sy * sp * sr - cy * cr],
                      [0.0, cp * cr, -cp * sr]])
    return R, dyaw, dpitch, droll


def euler_angles(R) -> tuple[float, float, float]:
    """(yaw, pitch, roll) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = np.asarray(R, dtype=float)
    return (float(np.arctan2(R[1, 0], R[0, 0])), float(-np.arcsin(np.clip(R[2, 0], -1.0, 1.0))),
            float(np.arctan2(R[2, 1], R[2, 2])))


def theta_from_rt(R_wv, T_wv) -> np.ndarray:
    yaw, pitch, roll = euler_angles(R_wv)
    T = np.asarray(T_wv, dtype=float)
    return np.array([T[0], T[1], yaw, T[2], pitch, roll])


def planar_theta(x: float, y: float, yaw: float, z: float) -> np.ndarray:
    return np.array([x, y, yaw, z, 0.0, 0.0])


def roof_world(theta, points) -> tuple[np.ndarray, np.ndarray]:
    """World coordinates (M,3) of vehicle-top points and their derivative (M,3,6) w.r.t. theta."""
    R, dyaw, dpitch, droll = _euler_with_derivatives(theta[IYAW], theta[IPITCH], theta[IROLL])
    P = points @ R.T + np.array([theta[IX], theta[IY], theta[IZ]])
    dP = np.zeros((len(points), 3, 6))
    dP[:, 0, IX] = 1.0
    dP[:, 1, IY] = 1.0
    dP[:, 2, IZ] = 1.0
    # The three rotation derivatives in one product: (M,3) @ (3, 3·3) -> columns yaw, pitch, roll.
    rot = points @ np.hstack([dyaw.T, dpitch.T, droll.T])
    dP[:, :, IYAW] = rot[:, 0:3]
    dP[:, :, IPITCH] = rot[:, 3:6]
    dP[:, :, IROLL] = rot[:, 6:9]
    return P, dP


def depths_and_heights(c: Corners, theta) -> tuple[np.ndarray, np.ndarray]:
    """At pose theta: every observed corner's depth in its camera (N,) and every roof corner's world z
    (M,), without evaluate's pixels and Jacobians."""
    P = c.roof_points @ euler_rotation(theta[IYAW], theta[IPITCH], theta[IROLL]).T + \
        np.array([theta[IX], theta[IY], theta[IZ]])
    return np.einsum("nj,nj->n", c.cam_R[:, 2, :], P[c.corner_of]) + c.cam_t[:, 2], P[:, 2]


@dataclass
class Evaluation:
    """Model evaluated at theta: pixel residuals and roof-corner heights with their Jacobians."""

    r_px: np.ndarray  # (2N,) predicted minus observed pixels
    J_px: np.ndarray  # (2N,6)
    z: np.ndarray  # (M,) world z of each physical corner
    J_z: np.ndarray  # (M,6)
    depth: np.ndarray  # (N,) camera-frame depth of each observed corner

    @property
    def in_front(self) -> bool:
        return bool(np.all(self.depth > MIN_DEPTH))


def evaluate(c: Corners, theta) -> Evaluation:
    P_roof, dP_roof = roof_world(theta, c.roof_points)
    P, dP = P_roof[c.corner_of], dP_roof[c.corner_of]
    Xc = np.einsum("nij,nj->ni", c.cam_R, P) + c.cam_t
    Z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / Z
        xn = Xc[:, :2] * iz[:, None]
        uv = np.einsum("nij,nj->ni", c.cam_K, xn) + c.cam_c
        # d(normalised)/d(X_cam) = [I | -xn] / Z, chained through K, R_wc and the pose.
        A = np.einsum("nij,njk->nik", c.cam_R, dP)  # d(X_cam)/d(theta) (N,3,6)
        dxn = (A[:, :2, :] - xn[:, :, None] * A[:, 2:3, :]) * iz[:, None, None]
        J = np.einsum("nij,njk->nik", c.cam_K, dxn)
    return Evaluation((uv - c.pixels).ravel(), J.reshape(-1, 6), P_roof[:, 2], dP_roof[:, 2, :], Z)



def evaluate_level(c: Corners, x: float, y: float, yaw: float, z: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """`evaluate` for a level roof (pitch = roll = 0), in the few operations the solvers' inner loops
    need: (pixel residuals (2N,), their Jacobian (2N, 4) over (x, y, yaw, z), every corner in front)."""
    r, J, front = evaluate_level_batch(c, np.array([[x, y, yaw, z]]))
    return r[0], J[0], bool(front[0].all())


def evaluate_level_batch(c: Corners, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`evaluate_level` at B level poses P (B, 4) = (x, y, yaw, z) at once: pixel residuals (B, 2N), their
    Jacobians (B, 2N, 4) and whether each corner is in front of its camera (B, N).

    The homogeneous pixel of a level roof's corner is linear in (x, y, z, cos yaw, sin yaw, 1)
    (Corners.level_projection). A corner at depth 0 divides by zero: its residual is then not finite, and
    the caller refuses the pose through the in-front mask."""
    return kernels.evaluate_level(c.level_projection, c.pixels, np.ascontiguousarray(P, dtype=float))


# ---- camera calibration ------------------------------------------------------------------------
@dataclass(frozen=True)
class Calibration:
    """How well every camera's extrinsics are known: rotation error sigma (rad, about each camera
    axis: R -> exp(w) R) and camera-centre error sigma (m, per world axis), independent per camera,
    as sim.image_model.perturb_camera draws them. Zero: known exactly."""

    rot_sigma: float = 0.0
    trans_sigma: float = 0.0

    def __post_init__(self):
        if not (self.rot_sigma >= 0.0 and self.trans_sigma >= 0.0):
            raise ValueError("calibration sigmas must be >= 0")

    @property
    def known(self) -> bool:
        return not (self.rot_sigma > 0.0 or self.trans_sigma > 0.0)

    @property
    def columns(self) -> list[int]:
        """Which of a camera's 6 corrections (rotation 0..2, centre 3..5) are uncertain."""
        return ([0, 1, 2] if self.rot_sigma > 0 else []) + ([3, 4, 5] if self.trans_sigma > 0 else [])

    @property
    def sigmas(self) -> np.ndarray:
        """Prior sigmas of the uncertain corrections of one camera, in `columns` order."""
        return np.array([self.rot_sigma] * 3 * (self.rot_sigma > 0) + [self.trans_sigma] * 3 * (self.trans_sigma > 0))


KNOWN = Calibration()


def camera_index(c: Corners) -> np.ndarray:
    """(N,) index into c.camera_ids of each observed corner's camera."""
    ids = c.camera_ids
    return np.array([ids.index(c.units[u].camera.id) for u in c.unit_of], dtype=int)


def calib_jacobian(c: Corners, theta) -> np.ndarray:
    """d(pixels)/d(extrinsic correction) (2N, 6) of each row's own camera at pose theta: rotation vector
    about the camera axes (R -> exp(w) R) and camera-centre shift (world)."""
    P_roof, _ = roof_world(theta, c.roof_points)
    P = P_roof[c.corner_of]
    Xc = np.einsum("nij,nj->ni", c.cam_R, P) + c.cam_t
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / Xc[:, 2]
    xn = Xc[:, :2] * iz[:, None]
    D = np.zeros((len(Xc), 2, 3))
    D[:, 0, 0] = iz
    D[:, 1, 1] = iz
    D[:, :, 2] = -xn * iz[:, None]
    KD = c.cam_K @ D  # (N,2,3) d(pixel)/d(X_cam)
    skew = np.zeros((len(Xc), 3, 3))  # d(exp(w) X)/dw = -[X]x
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    skew[:, 0, 1], skew[:, 0, 2] = z, -y
    skew[:, 1, 0], skew[:, 1, 2] = -z, x
    skew[:, 2, 0], skew[:, 2, 1] = y, -x
    J_rot = KD @ skew
    J_pos = -KD @ c.cam_R  # X_cam = R (X - centre)
    return np.concatenate([J_rot, J_pos], axis=2).reshape(-1, 6)


def calib_columns(c: Corners, theta, calib: Calibration) -> np.ndarray:
    """d(pixels)/d(every camera's uncertain corrections) (2N, K·len(calib.columns)), camera by camera in
    c.camera_ids order: each row depends on its own camera's block only."""
    cols = calib.columns
    J6 = calib_jacobian(c, theta)[:, cols]
    cam = np.repeat(camera_index(c), 2)
    k = len(cols)
    out = np.zeros((2 * c.n, k * len(c.camera_ids)))
    for i in range(len(c.camera_ids)):
        rows = cam == i
        out[rows, i * k:(i + 1) * k] = J6[rows]
    return out


def calib_residual_rms(J_px: np.ndarray, estimator: np.ndarray, J_c: np.ndarray, calib: Calibration) -> float:
    """Per-corner RMS pixel residual that the cameras' calibration errors (one sigma) leave after a fit
    whose parameter change per pixel change is `estimator` (P, 2N): (I − J_px·estimator)·J_c·delta."""
    if calib.known or J_c.shape[1] == 0:
        return 0.0
    R = J_c - J_px @ (estimator @ J_c)
    s2 = np.tile(calib.sigmas ** 2, J_c.shape[1] // len(calib.columns))
    n = len(J_px) // 2
    return float(np.sqrt(np.sum(R * R * s2) / n)) if n else 0.0
