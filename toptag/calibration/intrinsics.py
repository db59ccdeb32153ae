"""Intrinsic calibration from board views (OpenCV's calibrateCamera), with what a site needs to trust
it: per-view errors, the parameters' covariance, how much of the image the views covered, and the
Cramér–Rao bound of the same problem.

Lens model: OpenCV's (k1, k2, p1, p2, k3), fx, fy, cx, cy. The covariance is the inverse Fisher
information of the whole problem (intrinsics and every view's pose; the views marginalised by their
Schur complement) at the estimate, scaled by the residual variance. The same function at the true
parameters with a known corner noise is the Cramér–Rao bound (`intrinsics_information`).

The views must cover the image: there the fitted distortion is measured; beyond, it is extrapolated and
can be pixels off. `coverage` reports the covered share of a 3 × 3 grid of image zones and of the four
corner patches; `calibrate_intrinsics` refuses views that leave a zone of the 3 × 3 grid empty or cover
less than MIN_COVERAGE of the image, and warns when a corner patch is left uncovered.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from toptag.calibration.boards import BoardView
from toptag.camera import Camera
from toptag.errors import InputError

PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
MIN_VIEWS = 10
MIN_CORNERS = 8
MIN_COVERAGE = 0.35
# A corner whose residual after a first fit is this many robust sigmas (per coordinate, from the median
# residual) and at least OUTLIER_MIN_PX is left out and the fit repeated once. ChArUco corners at the
# board's edge or beside a marker smeared by the stream's codec are now and then 1-2 px off (about one
# in 300 on rendered H.264 views); a fifth of the squared error at 0.25 px corner noise.
OUTLIER_SIGMAS = 5.0
OUTLIER_MIN_PX = 0.75
CORNER_PATCH = 0.15  # a corner patch is this share of the width and of the height
ZONE_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
              ("bottom-left", "bottom", "bottom-right"))


class CalibrationError(InputError):
    """Calibration refused: too few views, views that do not cover the image, a degenerate point layout,
    a singular problem. str(e) is one line naming what is missing."""


@dataclass
class Coverage:
    fraction: float  # of the image inside some view's board outline
    zones: np.ndarray  # (3, 3) covered fraction per zone
    corners: dict[str, float]  # covered fraction per corner patch
    mask: np.ndarray = field(repr=False)  # (H/8, W/8) bool, the covered area at 1/8 scale

    @property
    def empty_zones(self) -> list[str]:
        return [ZONE_NAMES[r][c] for r in range(3) for c in range(3) if self.zones[r, c] < 0.05]

    @property
    def uncovered_corners(self) -> list[str]:
        return [k for k, v in self.corners.items() if v < 0.25]


def coverage(views: list[BoardView], size: tuple[int, int], scale: int = 8) -> Coverage:
    """The image area inside the convex outline of each view's corners (union over views)."""
    w, h = size
    mask = np.zeros(((h + scale - 1) // scale, (w + scale - 1) // scale), np.uint8)
    for v in views:
        if len(v.image_points) >= 3:
            hull = cv2.convexHull((v.image_points / scale).astype(np.float32)).astype(np.int32)
            cv2.fillConvexPoly(mask, hull, 1)
    m = mask.astype(bool)
    H, W = m.shape
    zones = np.array([[m[r * H // 3:(r + 1) * H // 3, c * W // 3:(c + 1) * W // 3].mean() for c in range(3)]
                      for r in range(3)])
    ph, pw = max(1, int(H * CORNER_PATCH)), max(1, int(W * CORNER_PATCH))
    corners = {"top-left": m[:ph, :pw].mean(), "top-right": m[:ph, -pw:].mean(),
               "bottom-left": m[-ph:, :pw].mean(), "bottom-right": m[-ph:, -pw:].mean()}
    return Coverage(float(m.mean()), zones, {k: float(v) for k, v in corners.items()}, m)


def covered_pixels(cov: Coverage, size: tuple[int, int], step: int = 16) -> np.ndarray:
    """(N, 2) pixels on a `step` grid inside the covered area."""
    w, h = size
    ys, xs = np.mgrid[step // 2:h:step, step // 2:w:step]
    scale_y, scale_x = cov.mask.shape[0] / h, cov.mask.shape[1] / w
    inside = cov.mask[(ys * scale_y).astype(int), (xs * scale_x).astype(int)]
    return np.column_stack([xs[inside], ys[inside]]).astype(float)


def intrinsics_information(K, dist, views: list[BoardView], rvecs, tvecs) -> np.ndarray:
    """Fisher information of the 9 intrinsic parameters (PARAMS order) for unit pixel noise, every
    view's pose marginalised (Schur complement)."""
    K = np.asarray(K, float)
    d = np.zeros(5)
    d[:min(5, len(np.ravel(dist)))] = np.ravel(dist)[:5]
    A = np.zeros((9, 9))
    for v, rv, tv in zip(views, rvecs, tvecs):
        _, J = cv2.projectPoints(v.object_points.astype(np.float64), np.asarray(rv, float).reshape(3, 1),
                                 np.asarray(tv, float).reshape(3, 1), K, d)
        Jp, Ji = J[:, :6], J[:, 6:15]  # pose (rvec, tvec); fx, fy, cx, cy, k1, k2, p1, p2, k3
        D = Jp.T @ Jp
        B = Ji.T @ Jp
        A += Ji.T @ Ji - B @ np.linalg.solve(D, B.T)
    return A


def undistort_points(K, dist, pixels) -> np.ndarray:
    """Pixels with the lens distortion removed, in the same camera matrix: Camera.undistort as a function
    of the intrinsics alone, which undistortion_sigma's numeric derivatives over them need (the camera's
    pose and image size play no part in it). The camera model's Newton inverts the lens to ~1e-13 px where
    cv2.undistortPoints stopped at ~1e-10 px, which a step of 1e-6 in a parameter turned into ~1e-4 of
    the derivative."""
    return Camera("intrinsics", 1, 1, K, dist, np.eye(3), np.zeros(3)).undistort(pixels)


def _params(K, dist) -> np.ndarray:
    d = np.zeros(5)
    d[:min(5, len(np.ravel(dist)))] = np.ravel(dist)[:5]
    return np.array([K[0][0], K[1][1], K[0][2], K[1][2], *d])


def _from_params(p) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
    return K, np.asarray(p[4:9], float)


def undistortion_sigma(K, dist, covariance: np.ndarray, pixels) -> np.ndarray:
    """(N,) standard deviation (px, both axes together) of the undistorted position of each pixel that
    the intrinsics' covariance implies (first order, numeric derivatives)."""
    p0 = _params(K, dist)
    u0 = undistort_points(K, dist, pixels)
    G = np.zeros((len(u0), 2, 9))
    for k in range(9):
        h = 1e-6 * max(1.0, abs(p0[k]))
        p = p0.copy()
        p[k] += h
        G[:, :, k] = (undistort_points(*_from_params(p), pixels) - u0) / h
    var = np.einsum("nik,kl,nil->n", G, covariance, G)
    return np.sqrt(np.maximum(var, 0.0))


@dataclass
class IntrinsicsResult:
    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    rms_px: float
    per_view_rms: list[tuple[str, float]]
    covariance: np.ndarray  # (9, 9), PARAMS order
    sigma_px: float  # corner noise per coordinate estimated from the residuals
    coverage: Coverage
    views: list[BoardView]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    warnings: list[str] = field(default_factory=list)
    outliers: int = 0  # corners left out as outliers (OUTLIER_SIGMAS)

    @property
    def std(self) -> dict[str, float]:
        return {k: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, k in enumerate(PARAMS)}

    def summary(self) -> dict:
        return {"rms_px": self.rms_px, "views": len(self.views), "sigma_px": self.sigma_px, "std": self.std,
                "coverage": round(self.coverage.fraction, 3),
                "uncovered_corners": self.coverage.uncovered_corners,
                "covariance": self.covariance.tolist(), "parameters": list(PARAMS)}


def calibrate_intrinsics(views: list[BoardView], size: tuple[int, int], min_views: int = MIN_VIEWS,
                         min_corners: int = MIN_CORNERS, names_without_board: list[str] | None = None
                         ) -> IntrinsicsResult:
    """Calibrate from board views (CalibrationError, one line, when the views cannot support it)."""
    usable = [v for v in views if len(v.ids) >= min_corners]
    few = [v.name or f"#{i}" for i, v in enumerate(views) if len(v.ids) < min_corners]
    if len(usable) < min_views:
        missing = []
        if names_without_board:
            missing.append(f"no board found in {_names(names_without_board)}")
        if few:
            missing.append(f"fewer than {min_corners} corners in {_names(few)}")
        raise CalibrationError(f"intrinsics need at least {min_views} views with {min_corners}+ board corners; "
                               f"got {len(usable)}" + (f" ({'; '.join(missing)})" if missing else ""))
    cov = coverage(usable, size)
    if cov.empty_zones or cov.fraction < MIN_COVERAGE:
        raise CalibrationError(f"the views do not cover the image (covered {100 * cov.fraction:.0f} %, at least "
                               f"{100 * MIN_COVERAGE:.0f} % needed)"
                               + (f": nothing in the {', '.join(cov.empty_zones)} of the image; add views "
                                  "with the board there" if cov.empty_zones else ""))
    rms, K, dist, rvecs, tvecs, per_view = _calibrate(usable, size)
    kept, dropped = _without_outliers(usable, K, dist, rvecs, tvecs, min_corners)
    if dropped and len(kept) >= min_views:
        usable = kept
        rms, K, dist, rvecs, tvecs, per_view = _calibrate(usable, size)
    else:
        dropped = 0
    dist = np.ravel(dist)[:5]
    n_obs = sum(2 * len(v.ids) for v in usable)
    n_par = 9 + 6 * len(usable)
    res = []
    for v, rv, tv in zip(usable, rvecs, tvecs):
        p, _ = cv2.projectPoints(v.object_points, rv, tv, K, dist)
        res.append((p.reshape(-1, 2) - v.image_points).ravel())
    ssr = float(np.sum(np.concatenate(res) ** 2))
    sigma = float(np.sqrt(ssr / max(1, n_obs - n_par)))
    info = intrinsics_information(K, dist, usable, rvecs, tvecs)
    try:
        covariance = np.linalg.inv(info) * sigma ** 2
    except np.linalg.LinAlgError:
        raise CalibrationError("intrinsics: the views leave the lens model undetermined (singular information "
                               "matrix): tilt the board more and vary its distance") from None
    result = IntrinsicsResult(K, dist, size, float(rms), [(v.name, float(e)) for v, e in zip(usable, np.ravel(per_view))],
                              covariance, sigma, cov, usable, [np.ravel(r) for r in rvecs], [np.ravel(t) for t in tvecs])
    if cov.uncovered_corners:
        result.warnings.append(f"the views leave the image corners uncovered ({', '.join(cov.uncovered_corners)}): "
                               "there the fitted distortion can be pixels off")
    if few:
        result.warnings.append(f"left out (fewer than {min_corners} corners): {_names(few)}")
    result.outliers = dropped
    return result


def _calibrate(views: list[BoardView], size: tuple[int, int]):
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(obj, img, size, None, None, criteria=crit)
    except cv2.error as e:
        raise CalibrationError(f"intrinsics: OpenCV could not calibrate ({str(e).strip().splitlines()[-1]})") from None
    return rms, K, np.ravel(dist)[:5], rvecs, tvecs, per_view


def _without_outliers(views: list[BoardView], K, dist, rvecs, tvecs, min_corners: int):
    """(views without the corners whose residual is an outlier, and without views left with too few
    corners; how many corners were left out)."""
    res = [np.linalg.norm(cv2.projectPoints(v.object_points, rv, tv, K, dist)[0].reshape(-1, 2) - v.image_points, axis=1)
           for v, rv, tv in zip(views, rvecs, tvecs)]
    # per coordinate: the median of a 2-D Gaussian residual's norm is 1.1774 sigma
    sigma = float(np.median(np.concatenate(res))) / 1.1774
    limit = max(OUTLIER_SIGMAS * sigma, OUTLIER_MIN_PX)
    kept, dropped = [], 0
    for v, r in zip(views, res):
        ok = r <= limit
        dropped += int((~ok).sum())
        if ok.sum() >= min_corners:
            kept.append(v if ok.all() else BoardView(v.ids[ok], v.image_points[ok], v.object_points[ok], v.name))
    return kept, dropped


def _names(names: list[str], most: int = 5) -> str:
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")
