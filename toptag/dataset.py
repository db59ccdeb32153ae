"""A folder of real photographs of AprilTags with truth: its format, loading, and the truth made without
any tag detector (saddle points of a calibration grid, and the board pose from all of them).

DIR/dataset.json (docs/real-data.md describes it field by field):

    {"name": "euroc-aprilgrid", "source": "...", "licence": "...",
     "target": {"family": "tag36h11", "black_border": 2, "tag_size": 0.088,
                "grid": {"rows": 6, "cols": 6, "spacing": 0.3}},
     "cameras": {"cam0": {"width": 752, "height": 480, "model": "radtan",
                          "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [k1, k2, p1, p2]}},
     "images": [{"file": "euroc.png", "camera": "cam0",
                 "tags": [{"id": 0, "corners": [[u, v], [u, v], [u, v], [u, v]]}, ...],
                 "corner_truth": "saddle",
                 "pose": {"R": [[...], [...], [...]], "t": [x, y, z], "rms_px": 0.25}}]}

- Pixels are OpenCV's ((0, 0) the centre of the top-left pixel), as the camera delivered them (with
  its lens distortion); corners in the detector's order; an id may appear more than once (test photos
  of one tag). "camera" and "pose" may be absent (no intrinsics, no pose truth); "tags" lists every tag
  of the target that is wholly in view; "corner_truth" says what its corners are: "saddle" (independent:
  cv2.cornerSubPix on the grid's saddle points) or "reference" (another detector's output: they fix
  ids and the pixel convention, not the accuracy).
- The target: a Kalibr-style grid (tag id = row · cols + col, tag corners on the board plane z
  = 0 with x along the columns, y along the rows, both printed-up) or "tags": explicit board corners
  per id, or neither (no layout: no pose). tag_size is the edge of the black square (for a 2-cell
  border, the outer one).
- pose: the board in the camera, X_cam = R · X_board + t (metres).
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toptag.camera import Camera
from toptag.inputs import InputError, read_model
from toptag.vehicle import FAMILY_BITS

# Tag corners in the tag's own printed frame (x right, y up), detector order: bottom-left,
# bottom-right, top-right, top-left (SPEC.md).
UNIT_CORNERS = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
SADDLE_MAX_MOVE_PX = 2.0  # a saddle point further than this from where it was looked for is not one


class GridSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rows: int = Field(gt=0)
    cols: int = Field(gt=0)
    spacing: float = Field(ge=0, description="gap between tags over tag_size (Kalibr's tagSpacing)")


class TargetSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    family: str = "tag36h11"
    black_border: int = Field(default=1, ge=1, le=3)
    tag_size: float | None = Field(default=None, gt=0)
    grid: GridSpec | None = None
    tags: dict[str, list[list[float]]] | None = None  # id -> (4, 3) board corners, detector order
    height_sigma: float | None = Field(
        default=None, gt=0, description="how well the board's plane is known along its normal (board metres): "
                                        "a rigid board declares its tolerance; the eval's vehicles declare it, "
                                        "scaled, as their roof-height sigma (absent: a bus's default bounce)")

    @model_validator(mode="after")
    def _layout(self) -> "TargetSpec":
        if self.family not in FAMILY_BITS:
            raise ValueError(f"unknown tag family {self.family!r}")
        if self.grid is not None and self.tags is not None:
            raise ValueError("give grid or tags, not both")
        if self.grid is not None and self.tag_size is None:
            raise ValueError("a grid needs tag_size")
        return self


class Intrinsics(BaseModel):
    model_config = ConfigDict(extra="forbid")
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    model: Literal["radtan", "equidistant"] = "radtan"
    K: list[list[float]]
    dist: list[float] = Field(default_factory=lambda: [0.0] * 4)


class PoseTruth(BaseModel):
    model_config = ConfigDict(extra="forbid")
    R: list[list[float]]
    t: list[float]
    rms_px: float | None = None  # residual of the fit that made it
    # m (board units): the fit's standard error of the board plane along its normal, i.e. how well this
    # truth knows the board's height (what a rigid board may declare as its target.height_sigma)
    plane_sigma: float | None = None


class TagTruth(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: int = Field(ge=0)
    corners: list[list[float]] = Field(min_length=4, max_length=4)


class ImageEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    file: str
    camera: str | None = None
    tags: list[TagTruth] = Field(default_factory=list)
    corner_truth: Literal["saddle", "reference"] = "saddle"
    pose: PoseTruth | None = None


class DatasetFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    source: str = ""
    licence: str = ""
    target: TargetSpec
    cameras: dict[str, Intrinsics] = Field(default_factory=dict)
    images: list[ImageEntry] = Field(min_length=1)

    @model_validator(mode="after")
    def _cameras_known(self) -> "DatasetFile":
        for im in self.images:
            if im.camera is not None and im.camera not in self.cameras:
                raise ValueError(f"image {im.file}: unknown camera {im.camera!r}")
            if im.pose is not None and im.camera is None:
                raise ValueError(f"image {im.file}: pose truth needs a camera")
        return self


class Dataset:
    def __init__(self, root: Path, spec: DatasetFile):
        self.root, self.spec = root, spec

    @classmethod
    def load(cls, root: str | Path) -> "Dataset":
        root = Path(root)
        path = root / "dataset.json"
        if not path.is_file():
            raise InputError(f"{root}: no dataset.json (docs/real-data.md describes the format)")
        return cls(root, read_model(DatasetFile, path, "dataset file"))

    def image_path(self, entry: ImageEntry) -> Path:
        return (self.root / entry.file).resolve()

    def read_gray(self, entry: ImageEntry) -> np.ndarray:
        path = self.image_path(entry)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"image {path}: missing or not an image")
        return to_gray8(img)


def to_gray8(img: np.ndarray) -> np.ndarray:
    """8-bit luma of an 8- or 16-bit grey or colour image."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return np.ascontiguousarray(img.astype(np.uint8))


def board_corners(target: TargetSpec, tag_id: int) -> np.ndarray | None:
    if target.tags is not None:
        c = target.tags.get(str(tag_id))
        return None if c is None else np.asarray(c, dtype=float).reshape(4, 3)
    g = target.grid
    if g is None or not 0 <= tag_id < g.rows * g.cols:
        return None
    r, c = divmod(int(tag_id), g.cols)
    s = target.tag_size
    pitch = s * (1.0 + g.spacing)
    centre = np.array([c * pitch + s / 2, r * pitch + s / 2])
    return np.column_stack([centre + s * UNIT_CORNERS, np.zeros(4)])


# ---- lens models -------------------------------------------------------------------------------
def ideal_pixels(cam: Intrinsics, pixels) -> np.ndarray:
    """Observed pixels (N, 2) to those an ideal pinhole camera with the same K sees."""
    pts = np.asarray(pixels, dtype=float).reshape(-1, 2)
    K = np.asarray(cam.K, dtype=float)
    if cam.model == "equidistant":
        n = cv2.fisheye.undistortPoints(pts.reshape(-1, 1, 2), K, np.asarray(cam.dist, float)).reshape(-1, 2)
        return n @ K[:2, :2].T + K[:2, 2]
    return pinhole(cam).undistort(pts)


def project(cam: Intrinsics, R, t, points) -> np.ndarray:
    """Board points (N, 3) to observed pixels through the lens model."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    rvec = cv2.Rodrigues(np.asarray(R, dtype=float))[0]
    tvec = np.asarray(t, dtype=float).reshape(3, 1)
    K = np.asarray(cam.K, dtype=float)
    if cam.model == "equidistant":
        return cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), rvec, tvec, K, np.asarray(cam.dist, float))[0].reshape(-1, 2)
    return cv2.projectPoints(P, rvec, tvec, K, np.asarray(cam.dist, float))[0].reshape(-1, 2)


def pinhole(cam: Intrinsics, camera_id: str = "camera", R_wc=None, T_wc=None) -> Camera:
    """toptag's Camera with these intrinsics (radtan lenses keep their distortion; an equidistant lens is
    left out: give it ideal_pixels)."""
    dist = cam.dist if cam.model == "radtan" else [0.0] * 5
    dist = list(dist) + [0.0] * (5 - len(dist)) if len(dist) < 5 else list(dist)
    return Camera(camera_id, cam.width, cam.height, cam.K, dist, np.eye(3) if R_wc is None else R_wc,
                  np.zeros(3) if T_wc is None else T_wc)


# ---- truth without a tag detector ----------------------------------------------------------------
def refine_saddles(gray: np.ndarray, approx, window: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Saddle points (N, 2) near `approx` by cv2.cornerSubPix (gradient orthogonality, a few hundredths
    of a pixel on a sharp saddle), and which of them are trustworthy (moved less than
    SADDLE_MAX_MOVE_PX from where they were looked for, and not at the image border)."""
    a = np.asarray(approx, dtype=np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = cv2.cornerSubPix(gray, a.copy(), (window, window), (-1, -1), crit).reshape(-1, 2).astype(float)
    h, w = gray.shape
    inside = ((out[:, 0] > window) & (out[:, 0] < w - 1 - window) & (out[:, 1] > window)
              & (out[:, 1] < h - 1 - window))
    ok = inside & (np.linalg.norm(out - a.reshape(-1, 2), axis=1) < SADDLE_MAX_MOVE_PX)
    return out, ok


def fit_board_pose(cam: Intrinsics, board_points, pixels) -> PoseTruth:
    """The board pose from many corners (observed pixels): PnP on the ideal pixels, then refined by
    Levenberg–Marquardt through the lens model; rms_px is its reprojection residual."""
    obj = np.asarray(board_points, dtype=float).reshape(-1, 3)
    px = np.asarray(pixels, dtype=float).reshape(-1, 2)
    K = np.asarray(cam.K, dtype=float)
    ideal = ideal_pixels(cam, px)
    ok, rvec, tvec = cv2.solvePnP(obj, ideal, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("board pose: PnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, ideal, K, None, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    e = project(cam, R, tvec.ravel(), obj) - px
    return PoseTruth(R=R.tolist(), t=tvec.ravel().tolist(), rms_px=float(np.sqrt((e ** 2).sum(axis=1).mean())),
                     plane_sigma=_plane_sigma(cam, rvec.ravel(), tvec.ravel(), obj, e))


def _plane_sigma(cam: Intrinsics, rvec, tvec, obj, residuals, step: float = 1e-7) -> float:
    """Standard error of the fitted board plane's distance from the camera (n·t, n = R e_z): the pose's
    covariance from the residuals (sigma per coordinate, n - 6 dof) through numeric Jacobians."""
    p0 = np.r_[rvec, tvec]

    def pixels(p):
        return project(cam, cv2.Rodrigues(p[:3])[0], p[3:], obj).ravel()

    def offset(p):
        return float(cv2.Rodrigues(p[:3])[0][:, 2] @ p[3:])

    steps = np.eye(6) * step
    J = np.column_stack([(pixels(p0 + d) - pixels(p0 - d)) / (2 * step) for d in steps])
    g = np.array([(offset(p0 + d) - offset(p0 - d)) / (2 * step) for d in steps])
    r = np.asarray(residuals, float).ravel()
    cov = (r @ r) / max(len(r) - 6, 1) * np.linalg.inv(J.T @ J)
    return float(np.sqrt(g @ cov @ g))
