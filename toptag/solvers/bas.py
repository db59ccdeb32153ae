"""Bas.: the paper's baseline. One camera's homography by DLT, decomposed into the roof pose.

The whole chain (normalise, DLT, decompose, chain with the extrinsics) is written over a batch of pixel
sets so that its covariance can be propagated honestly through the algorithm itself (central
differences over every pixel coordinate in one vectorised pass) rather than through a reprojection
model Bas. does not minimise.
"""
from __future__ import annotations

import math

import numpy as np

from toptag.camera import Camera
from toptag.solvers.common import Fit, estimate_sigma, rms
from toptag.solvers.model import Corners, evaluate, theta_from_rt

FD_STEP_PX = 1e-4


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Hartley similarity (..., 3, 3): centroid to the origin, mean distance sqrt(2)."""
    m = pts.mean(axis=-2)
    d = np.linalg.norm(pts - m[..., None, :], axis=-1).mean(axis=-1)
    s = np.sqrt(2.0) / np.maximum(d, 1e-300)
    T = np.zeros(pts.shape[:-2] + (3, 3))
    T[..., 0, 0] = s
    T[..., 1, 1] = s
    T[..., 0, 2] = -s * m[..., 0]
    T[..., 1, 2] = -s * m[..., 1]
    T[..., 2, 2] = 1.0
    return T


def homographies(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """DLT homographies (B,3,3) mapping plane points src (N,2) to pixels dst (B,N,2): the eigenvector
    of the smallest eigenvalue of LᵀL (as a singular vector of L), in Hartley-normalised coordinates."""
    B, N = dst.shape[0], src.shape[0]
    Ts = _normaliser(src)
    Td = _normaliser(dst)
    X = src @ Ts[:2, :2].T + Ts[:2, 2]
    U = np.einsum("bij,bnj->bni", Td[:, :2, :2], dst) + Td[:, None, :2, 2]
    L = np.zeros((B, 2 * N, 9))
    one = np.ones(N)
    L[:, 0::2, 0:3] = np.column_stack([X, one])
    L[:, 1::2, 3:6] = np.column_stack([X, one])
    L[:, 0::2, 6:9] = -U[:, :, 0:1] * np.column_stack([X, one])
    L[:, 1::2, 6:9] = -U[:, :, 1:2] * np.column_stack([X, one])
    # The smallest right singular vector of L is that eigenvector of LᵀL, without squaring L's
    # condition number (eigh of LᵀL loses ~1e-9 of the pose on exact data).
    _, _, Vt = np.linalg.svd(L)
    Hn = Vt[:, -1, :].reshape(B, 3, 3)
    return np.linalg.inv(Td) @ Hn @ Ts


def decompose(H: np.ndarray, src: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Roof rotation (B,3,3) and origin (B,3) in world from plane-to-pixel homographies."""
    M = camera.K_inv @ H
    n1 = np.linalg.norm(M[:, :, 0], axis=1)
    n2 = np.linalg.norm(M[:, :, 1], axis=1)
    r1 = M[:, :, 0] / n1[:, None]
    r2 = M[:, :, 1] / n2[:, None]
    t = M[:, :, 2] * (2.0 / (n1 + n2))[:, None]
    # H has no sign: choose the one that puts the control points in front of the camera.
    depth = (src[:, 0].mean() * r1[:, 2] + src[:, 1].mean() * r2[:, 2] + t[:, 2])
    s = np.where(depth < 0, -1.0, 1.0)[:, None]
    r1, r2, t = r1 * s, r2 * s, t * s
    R = np.stack([r1, r2, np.cross(r1, r2)], axis=2)
    # Re-orthonormalise. cv2.Rodrigues (the paper's rotation-vector round trip) projects a matrix onto
    # the nearest rotation by SVD before reading its vector; this is that projection, batched. (A
    # further vector round trip would change nothing but precision: arccos loses ~1e-8 near pi.)
    U, _, Vt = np.linalg.svd(R)
    D = np.ones((len(R), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R_cv = (U * D[:, None, :]) @ Vt
    R_wv = camera.R.T @ R_cv
    T_wv = (t - camera.t) @ camera.R
    return R_wv, T_wv


def bas_poses(src: np.ndarray, pixels: np.ndarray, camera: Camera) -> np.ndarray:
    """(B,4) = (x, y, yaw, z) for a batch of pixel sets (B,N,2)."""
    R, T = decompose(homographies(src, pixels), src, camera)
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.column_stack([T[:, 0], T[:, 1], yaw, T[:, 2]])


def fit_bas(c: Corners, sigma_px: float | None = None, covariance: bool = True) -> Fit:
    """Bas. on the camera that sees the most corners (the homography is one camera's). covariance=False
    skips its propagation (NaN) when Bas. only seeds H.Opt.'s yaw."""
    cam_ids = [c.units[u].camera.id for u in c.unit_of]
    best = max(c.camera_ids, key=lambda cid: (cam_ids.count(cid), -c.camera_ids.index(cid)))
    c = c.subset(sorted({int(u) for u in c.unit_of[c.camera_rows(best)]}))
    camera = c.units[0].camera
    src = c.points[:, :2]
    H = homographies(src, c.pixels[None])
    R, T = decompose(H, src, camera)
    theta = theta_from_rt(R[0], T[0])
    ev = evaluate(c, theta)
    # The noise shows in what the DLT fits (8 parameters), not in the decomposed pose's reprojection.
    mapped = np.column_stack([src, np.ones(len(src))]) @ H[0].T
    r_h = (mapped[:, :2] / mapped[:, 2:3] - c.pixels).ravel()
    sigma = sigma_px if sigma_px is not None else estimate_sigma(float(r_h @ r_h), len(r_h) - 8)
    cov = _propagated_covariance(src, c.pixels, camera, sigma) if covariance else np.full((3, 3), np.nan)
    return Fit("bas", theta, cov, rms(ev.r_px), sigma, c,
               converged=ev.in_front, dof=len(r_h) - 8, fit_rms_px=rms(r_h),
               note=None if ev.in_front else "pose puts the tag behind the camera")


def _propagated_covariance(src, pixels, camera, sigma) -> np.ndarray:
    """sigma² · G Gᵀ with G = d(x, y, yaw)/d(pixels) of the Bas. algorithm itself."""
    flat = pixels.ravel()
    n = flat.size
    batch = np.repeat(flat[None], 2 * n, axis=0)
    idx = np.arange(n)
    batch[idx, idx] += FD_STEP_PX
    batch[n + idx, idx] -= FD_STEP_PX
    poses = bas_poses(src, batch.reshape(2 * n, -1, 2), camera)
    diff = poses[:n, :3] - poses[n:, :3]
    diff[:, 2] = (diff[:, 2] + math.pi) % (2 * math.pi) - math.pi
    G = (diff / (2 * FD_STEP_PX)).T
    return sigma ** 2 * (G @ G.T)
