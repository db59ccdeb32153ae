"""Small rigid-body helpers shared by the solvers, the simulator and the filter."""
from __future__ import annotations

import math

import numpy as np


def wrap_angle(a):
    """Wrap an angle (float) or an array of angles to (-pi, pi]."""
    if type(a) is float or np.ndim(a) == 0:  # the scalar path is hot (the filter wraps at every IMU step)
        w = math.remainder(float(a), 2.0 * math.pi)  # in [-pi, pi]
        return math.pi if w == -math.pi else w
    w = np.mod(np.asarray(a, dtype=float) + np.pi, 2 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def rot_z(yaw) -> np.ndarray:
    """Rotation about z by yaw (rad): (3, 3), or (M, 3, 3) for M yaws."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros(np.shape(c) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def rodrigues(rvec) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle)."""
    r = np.asarray(rvec, dtype=float).reshape(3)
    th = np.linalg.norm(r)
    if th < 1e-12:
        k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
        return np.eye(3) + k
    k = r / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * (kx @ kx)


def rotation_vector(R) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of `rodrigues`), robust near pi."""
    R = np.asarray(R, dtype=float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # atan2 keeps full precision near 0 and pi, where arccos of the trace loses half the digits.
    th = np.arctan2(np.linalg.norm(w) / 2, (np.trace(R) - 1) / 2)
    if th < 1e-8:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    if th > np.pi / 2:
        # sin(th) is small near pi: read the axis from the symmetric part, k kᵀ = (S - cos th I) / (1 - cos th).
        kk = ((R + R.T) / 2 - np.cos(th) * np.eye(3)) / (1 - np.cos(th))
        i = int(np.argmax(np.diag(kk)))
        axis = kk[i] / np.sqrt(kk[i, i])
        if axis @ w < 0:
            axis = -axis
        return th * axis / np.linalg.norm(axis)
    return th * w / (2 * np.sin(th))


def nearest_rotation(M) -> np.ndarray:
    """The rotation closest to M in the Frobenius sense (SVD projection)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def vehicle_to_world(points_top, x, y, yaw, z) -> np.ndarray:
    """Points in the vehicle-top frame (N,3) to world, for a vehicle at (x, y, yaw) with roof height z: (N,3).
    With M poses (x, y, yaw, z each an (M,) array): the points at each, (M, N, 3), to the bit what one pose
    at a time gives (one stacked product, the same BLAS arithmetic), so that a many-pose answer such as
    sim.sampling.in_some_view_many agrees with its one-pose reference at the edges."""
    P = np.asarray(points_top, dtype=float).reshape(-1, 3)
    return P @ rot_z(yaw).swapaxes(-1, -2) + np.array([x, y, z]).T[..., None, :]
