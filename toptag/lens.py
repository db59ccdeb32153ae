"""OpenCV's lens distortion (k1 k2 p1 p2 k3, and the rational k4 k5 k6 when given) in normalized image
coordinates, with its analytic Jacobian, and its inverse by Newton's method: the camera model's
(toptag.camera.Camera) one home of the lens, compiled: its projection distorts with these kernels and its
undistortion inverts the same arithmetic. The RSU undistorts every detected tag's corners on every
frame (in numpy, twelve iterations of a dozen small array operations cost ~1 ms a tag, more than the
solve), and the renderer every pixel of a camera once (sim/raster.py)."""
from __future__ import annotations

import numpy as np

from toptag.jit import compiled

NEWTON_ITERATIONS = 12  # from the distorted point: ~1e-12 for real lenses over their image


def coefficients(dist: np.ndarray) -> np.ndarray:
    """The 8 coefficients the kernels take (k1 k2 p1 p2 k3 k4 k5 k6) from a camera's OpenCV vector (4, 5,
    8, 12 or 14 values; thin prism and tilt terms are not modelled)."""
    k = np.zeros(8)
    k[: min(5, dist.size)] = dist[:5]
    if dist.size >= 8:
        k[5:8] = dist[5:8]
    return k


@compiled
def distort_with_jacobian(x, y, k):
    """(xd, yd, dxd/dx, dxd/dy, dyd/dx, dyd/dy) of a normalized point (or of arrays of them)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7]
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = num / den
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    drad = (dnum * den - num * dden) / (den * den)  # d rad / d r2
    xy = x * y
    xd = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    a = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    b = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y
    d = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return xd, yd, a, b, b, d  # symmetric: dxd/dy = dyd/dx


@compiled
def undistort_normalized(xd, start, k, iterations):
    """The undistorted normalized points (N, 2) whose distortion is xd (N, 2), by `iterations` Newton steps
    from `start` (N, 2)."""
    out = np.empty_like(xd)
    for i in range(xd.shape[0]):
        x, y = start[i, 0], start[i, 1]
        for _ in range(iterations):
            fx, fy, a, b, c, d = distort_with_jacobian(x, y, k)
            ex, ey = fx - xd[i, 0], fy - xd[i, 1]
            det = a * d - b * c
            x = x - (d * ex - b * ey) / det
            y = y - (a * ey - c * ex) / det
        out[i, 0], out[i, 1] = x, y
    return out


@compiled
def distort_normalized(x, k):
    """The distorted normalized points (N, 2) of x (N, 2)."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i, 0], out[i, 1], _, _, _, _ = distort_with_jacobian(x[i, 0], x[i, 1], k)
    return out


def warm_up() -> None:
    """Compile the kernels (or load them from numba's cache) for the arrays the camera model passes."""
    k = coefficients(np.array([-0.1, 0.01, 0.001, 0.001, 0.0]))
    x = np.zeros((1, 2))
    undistort_normalized(x, x, k, NEWTON_ITERATIONS)
    distort_normalized(x, k)
