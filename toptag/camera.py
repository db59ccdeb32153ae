"""Calibrated pinhole camera with OpenCV lens distortion (SPEC.md: camera file).

X_cam = R_wc · X_world + T_wc; pixels in OpenCV convention ((0, 0) is the centre of the top-left pixel).

A camera file may carry an optional `calibration` block (written by `toptag calibrate`, docs/site.md):
how the intrinsics and the extrinsics were measured and how well. Its `extrinsics.covariance` (6x6 over
a rotation vector about the camera axes, R_wc -> exp(w)·R_wc, in rad, and the camera centre in the site
frame, in m) is carried into every fix's covariance: a fix is never more certain than the camera that
saw it. Files without the block stay valid (the extrinsics are then taken as exact). A block with
intrinsics but no extrinsics marks a camera not yet placed in the site: services refuse it.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from toptag.inputs import InputError, read_json, validate_model
from toptag.lens import NEWTON_ITERATIONS, coefficients, distort_normalized, undistort_normalized

ROTATION_TOLERANCE = 1e-6


def _check_matrix(v: list[list[float]], n: int) -> list[list[float]]:
    c = np.asarray(v, dtype=float)
    if c.shape != (n, n):
        raise ValueError(f"must be a {n}x{n} matrix")
    if not np.all(np.isfinite(c)):
        raise ValueError("must be finite")
    scale = max(1e-30, float(np.max(np.abs(c))))
    if np.max(np.abs(c - c.T)) > 1e-9 * scale:
        raise ValueError("must be symmetric")
    if np.min(np.linalg.eigvalsh((c + c.T) / 2)) < -1e-9 * scale:
        raise ValueError("must be positive semi-definite")
    return v


class IntrinsicsRecord(BaseModel):
    """How the intrinsics were calibrated (toptag calibrate intrinsics)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    rms_px: float = Field(ge=0, description="reprojection RMS per corner over all views (OpenCV's)")
    views: int = Field(ge=0)
    sigma_px: float = Field(ge=0, description="corner noise per coordinate estimated from the residuals")
    std: dict[str, float] = Field(default_factory=dict, description="standard deviation per parameter")
    coverage: float = Field(ge=0, le=1, description="share of the image the views covered")
    uncovered_corners: list[str] = Field(default_factory=list)
    parameters: list[str] = Field(default_factory=lambda: ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"])
    covariance: list[list[float]] | None = None
    board: str | None = None

    @field_validator("covariance")
    @classmethod
    def _cov(cls, v):
        return v if v is None else _check_matrix(v, 9)


class ExtrinsicsRecord(BaseModel):
    """How the extrinsics were calibrated (toptag calibrate extrinsics); covariance is what fixes carry."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    covariance: list[list[float]] = Field(description="6x6: rotation about camera x, y, z (rad), centre x, y, z (m)")
    rms_px: float | None = Field(default=None, ge=0)
    points: int | None = Field(default=None, ge=0)
    sigma_px: float | None = Field(default=None, ge=0)
    chi2_dof: float | None = Field(default=None, ge=0)
    parameters: str | None = None
    rotation_std_deg: list[float] | None = None
    centre_std_m: list[float] | None = None
    roof_mapping_sigma_m: dict | None = None

    @field_validator("covariance")
    @classmethod
    def _cov(cls, v):
        return _check_matrix(v, 6)


class CalibrationRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    intrinsics: IntrinsicsRecord | None = None
    extrinsics: ExtrinsicsRecord | None = None
    date: str | None = None


class CameraFile(BaseModel):
    """The camera JSON as it is stored and sent (the RSU calibration)."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(min_length=1)
    width: int
    height: int
    K: list[list[float]]
    dist: list[float] = Field(default_factory=lambda: [0.0] * 5)
    R_wc: list[list[float]]
    T_wc: list[float]
    calibration: CalibrationRecord | None = None

    @field_validator("width", "height")
    @classmethod
    def _positive(cls, v: int) -> int:
        if v <= 0:
            raise ValueError("must be positive")
        return v

    @field_validator("K", "R_wc")
    @classmethod
    def _three_by_three(cls, v: list[list[float]]) -> list[list[float]]:
        if len(v) != 3 or any(len(row) != 3 for row in v):
            raise ValueError("must be a 3x3 matrix")
        if not np.all(np.isfinite(np.asarray(v, dtype=float))):
            raise ValueError("must be finite")
        return v

    @field_validator("T_wc")
    @classmethod
    def _three_vector(cls, v: list[float]) -> list[float]:
        if len(v) != 3 or not np.all(np.isfinite(v)):
            raise ValueError("must be 3 finite numbers")
        return v

    @field_validator("dist")
    @classmethod
    def _distortion(cls, v: list[float]) -> list[float]:
        if len(v) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(v)):
            raise ValueError("must hold 4, 5, 8, 12 or 14 finite OpenCV distortion coefficients")
        return v

    @model_validator(mode="after")
    def _geometry(self) -> "CameraFile":
        K = np.asarray(self.K, dtype=float)
        if abs(np.linalg.det(K)) < 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("K: singular or non-positive focal length")
        if np.any(np.abs(K[2] - [0.0, 0.0, 1.0]) > 1e-9):
            raise ValueError("K: last row must be [0, 0, 1]")
        R = np.asarray(self.R_wc, dtype=float)
        if np.max(np.abs(R.T @ R - np.eye(3))) > ROTATION_TOLERANCE or abs(np.linalg.det(R) - 1.0) > ROTATION_TOLERANCE:
            raise ValueError("R_wc: not a rotation (R^T R != I or det != 1)")
        return self


class Camera:
    """One calibrated camera. All methods take and return numpy arrays; no I/O but `load`."""

    def __init__(self, id: str, width: int, height: int, K, dist, R_wc, T_wc,
                 calibration: CalibrationRecord | None = None):
        self.id = id
        self.width = int(width)
        self.height = int(height)
        self.K = np.asarray(K, dtype=float).reshape(3, 3)
        d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
        self.dist = d
        self.R = np.asarray(R_wc, dtype=float).reshape(3, 3)
        self.t = np.asarray(T_wc, dtype=float).reshape(3)
        self.K_inv = np.linalg.inv(self.K)
        self._focal_inv_T = np.linalg.inv(self.K[:2, :2]).T
        self.has_distortion = bool(np.any(d != 0.0))
        self.lens = coefficients(d)  # the compiled lens kernels' form of dist
        self.calibration = calibration
        ext = calibration.extrinsics if calibration is not None else None
        self.extrinsic_covariance: np.ndarray | None = None if ext is None else np.asarray(ext.covariance, float)

    @property
    def calibration_id(self) -> str:
        """Which calibration this is: 12 hex digits of a digest of the intrinsics, distortion and pose (and the
        calibration's date, when the file says it). A fix states it (`Fix.calib_id`, PoseFix.calibration_id)
        so that a bus forgets what it learnt of a camera's long-run disagreement once it is recalibrated."""
        h = hashlib.sha256((np.concatenate([self.K.ravel(), self.dist, self.R.ravel(), self.t]).round(12) + 0.0).tobytes())
        date = None if self.calibration is None else self.calibration.date
        if date:
            h.update(date.encode())
        return h.hexdigest()[:12]

    def require_extrinsics(self, source: str = "camera") -> "Camera":
        """InputError if the file says its extrinsics were never calibrated (intrinsics only)."""
        c = self.calibration
        if c is not None and c.intrinsics is not None and c.extrinsics is None:
            raise InputError(f"{source} {self.id}: extrinsics not calibrated yet (run toptag calibrate extrinsics)")
        return self

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_model(cls, m: CameraFile) -> "Camera":
        return cls(m.id, m.width, m.height, m.K, m.dist, m.R_wc, m.T_wc, m.calibration)

    @classmethod
    def from_dict(cls, data: dict, source: str = "camera") -> "Camera":
        return cls.from_model(validate_model(CameraFile, data, source))

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        return cls.from_dict(read_json(path, "camera file"), source=f"camera file {path}")

    @classmethod
    def looking_at(cls, id: str, position, target_yaw: float, pitch_down: float, hfov: float,
                   width: int, height: int, dist=None) -> "Camera":
        """A camera at world `position`, heading `target_yaw` (rad from +x, CCW), tilted `pitch_down`
        below the horizon, with horizontal field of view `hfov` (rad) and square pixels."""
        f = (width / 2.0) / np.tan(hfov / 2.0)
        K = [[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
        fwd = np.array([np.cos(target_yaw) * np.cos(pitch_down), np.sin(target_yaw) * np.cos(pitch_down),
                        -np.sin(pitch_down)])
        right = np.array([np.sin(target_yaw), -np.cos(target_yaw), 0.0])
        down = np.cross(fwd, right)
        R = np.vstack([right, down, fwd])
        t = -R @ np.asarray(position, dtype=float)
        return cls(id, width, height, K, dist, R, t)

    def to_model(self) -> CameraFile:
        return CameraFile(id=self.id, width=self.width, height=self.height, K=self.K.tolist(),
                          dist=self.dist.tolist(), R_wc=self.R.tolist(), T_wc=self.t.tolist(),
                          calibration=self.calibration)

    def to_json(self) -> str:
        """The camera file's text (no calibration block when there is none: old readers stay happy)."""
        return self.to_model().model_dump_json(indent=1, exclude_none=True)

    def with_extrinsics(self, R_wc, T_wc) -> "Camera":
        return Camera(self.id, self.width, self.height, self.K, self.dist, R_wc, T_wc, self.calibration)

    def with_calibration(self, calibration: CalibrationRecord | None) -> "Camera":
        return Camera(self.id, self.width, self.height, self.K, self.dist, self.R, self.t, calibration)

    # ---- geometry -----------------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    def to_camera(self, points_world) -> np.ndarray:
        P = np.asarray(points_world, dtype=float).reshape(-1, 3)
        return P @ self.R.T + self.t

    def project(self, points_world, distort: bool = True) -> np.ndarray:
        """World points (N,3) to pixels (N,2); with distortion unless `distort=False` (ideal pinhole)."""
        Pc = self.to_camera(points_world)
        xn = Pc[:, :2] / Pc[:, 2:3]
        if distort and self.has_distortion:
            xn = self.distort_normalized(xn)
        return xn @ self.K[:2, :2].T + self.K[:2, 2]

    def distort_normalized(self, xn: np.ndarray) -> np.ndarray:
        """Ideal normalized points (N,2) to distorted ones: the lens kernel that the undistortion inverts,
        so that projecting and undistorting share one model of the lens to the bit."""
        return distort_normalized(np.ascontiguousarray(xn, dtype=float).reshape(-1, 2), self.lens)

    def normalized(self, pixels, distorted: bool = True) -> np.ndarray:
        """Pixels (N,2) to ideal normalized image coordinates (N,2), removing lens distortion."""
        uv = np.asarray(pixels, dtype=float).reshape(-1, 2)
        xd = (uv - self.K[:2, 2]) @ self._focal_inv_T
        if not (distorted and self.has_distortion):
            return xd
        return undistort_normalized(xd, xd, self.lens, NEWTON_ITERATIONS)

    def undistort(self, pixels) -> np.ndarray:
        """Observed pixels to the pixels an ideal (distortion-free) camera with the same K would see."""
        return self.normalized(pixels) @ self.K[:2, :2].T + self.K[:2, 2]

    def rays(self, pixels, distorted: bool = True) -> np.ndarray:
        """World-frame unit ray directions through pixels (N,3)."""
        xn = self.normalized(pixels, distorted)
        d_cam = np.column_stack([xn, np.ones(len(xn))])
        d = d_cam @ self.R  # R^T applied row-wise
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def backproject_to_plane(self, pixels, z: float, distorted: bool = True) -> np.ndarray:
        """Intersect the rays through pixels with the world plane Z = z (N,3); NaN where parallel/behind."""
        d = self.rays(pixels, distorted)
        c = self.center
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (z - c[2]) / d[:, 2]
        s = np.where(s > 0, s, np.nan)
        return c + s[:, None] * d

    def in_image(self, pixels, margin: float = 0.0) -> np.ndarray:
        uv = np.asarray(pixels, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin))

