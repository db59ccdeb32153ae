"""The paper study's models: the measured corner-noise model and the Cramér–Rao bound it implies. (The
level-roof solver the study built is toptag.solvers' method "level", toptag/solvers/level.py.)

Corner noise. An AprilTag corner is the intersection of two fitted edge lines (AprilTag 3 refines each
quad edge by sampling the gradient along it, then intersects neighbouring lines), so corner errors are
not independent per coordinate: each edge contributes an offset error (the line moved along its normal,
measured at the edge's midpoint: o = n·(e_a + e_b)/2) and a turn (the endpoints moved oppositely along
the normal: w = n·(e_b − e_a)/2), independent between edges. A line fitted to evenly spread samples has
var(w) = 3·var(o); measured here, w/o ≈ 1.7–2.0. The tag centroid is therefore better determined than
the pooled per-coordinate sigma suggests (measured: H.Opt. in low_flat beats the i.i.d. bound by up to
2×, and sits at 0.7–1.1× the edge-model bound). Both are measured from detected against projected true
corners, per distance bin, after setting aside tags whose corners are wholly off (per-tag RMS above
OUTLIER_FACTOR × the case's median: a failed detection, counted and reported, not noise).

Bound. Unknowns: x, y, yaw of a level roof, and its height z with a Gaussian prior of the bounce's
standard deviation (a uniform bounce has no Fisher information; the Gaussian of equal variance stands in)
or z known (no bounce). With calibration error, every camera's extrinsics (rotation about the camera
axes, centre per world axis, as sim.image_model.perturb_camera draws them) join as unknowns with their
prior: the bound then says what no estimator can beat without better calibration.

The level solver (toptag.solvers.solve(..., "level")) is the estimator this bound describes: corner
residuals mapped to edge offsets and turns (turns over TURN_RATIO), (z − h)/sigma_h, and with calibration
error every camera's extrinsic correction with its prior.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.solvers.level import TURN_RATIO
from toptag.solvers.model import (
    IX,
    IY,
    IYAW,
    IZ,
    build_corners,
    calib_jacobian,
    evaluate,
    planar_theta,
)
from toptag.vehicle import Vehicle

__all__ = ["TURN_RATIO", "EdgeNoise", "edge_components", "outlier_flags", "measure_noise", "noise_at",
           "pose_bound"]

OUTLIER_FACTOR = 5.0  # a tag whose corner RMS error exceeds this many times the case's median is garbled
MIN_TAGS = 12  # fewer good tags measured in a bin: the bins around it lend theirs


@dataclass(frozen=True)
class EdgeNoise:
    """Measured corner noise of one distance bin (pixels)."""

    sigma_px: float  # pooled RMS per image axis (the i.i.d. model)
    offset_px: float  # RMS of an edge line's offset at its midpoint
    turn_px: float  # RMS of an edge line's endpoint displacement from its turn
    bias_px: tuple[float, float]
    n_tags: int  # good tags measured in this bin
    outlier_tags: int  # garbled tags set aside in this bin
    pooled_m: int = 0  # the estimate pools the bins within this many metres (too few tags in this one)

    def to_dict(self) -> dict:
        return {"sigma_px": round(self.sigma_px, 5), "edge_offset_px": round(self.offset_px, 5),
                "edge_turn_px": round(self.turn_px, 5), "bias_px": [round(b, 5) for b in self.bias_px],
                "n_tags": self.n_tags, "outlier_tags": self.outlier_tags, "pooled_m": self.pooled_m}


def edge_components(true_px: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(offset (4,), turn (4,)) of a tag's four edges (corner k to k+1) from its corner errors (4,2),
    the edge normals taken from the true corners (4,2). Works on any trailing shape of err (4,2,...)."""
    o, w = [], []
    for a in range(4):
        b = (a + 1) % 4
        u = true_px[b] - true_px[a]
        u = u / np.linalg.norm(u)
        n = np.array([-u[1], u[0]])
        o.append(np.tensordot(n, (err[a] + err[b]) / 2, axes=(0, 0)))
        w.append(np.tensordot(n, (err[b] - err[a]) / 2, axes=(0, 0)))
    return np.array(o), np.array(w)


def outlier_flags(tags: list[tuple[np.ndarray, np.ndarray]]) -> list[bool]:
    """Which tags [(true corners, corner errors), ...] of one case are failed detections: corner RMS
    error above OUTLIER_FACTOR times the median over the case (the noise itself varies 2-3x between 5 and
    20 m; garbled tags are 5-50x off)."""
    per_tag = np.array([math.sqrt(np.mean(np.asarray(e) ** 2)) for _, e in tags])
    cut = OUTLIER_FACTOR * float(np.median(per_tag)) if len(per_tag) else math.inf
    return [bool(r > cut) for r in per_tag]


def measure_noise(tags_by_bin: dict[int, list[tuple[np.ndarray, np.ndarray]]]) -> dict[int, EdgeNoise]:
    """tags_by_bin: whole-metre distance -> [(true corners (4,2), corner errors (4,2)), ...] of one case.
    A bin with fewer than MIN_TAGS good tags borrows those of the bins around it (nearest first)."""
    flat = [(b, t) for b, tags in sorted(tags_by_bin.items()) for t in tags]
    bad = outlier_flags([t for _, t in flat])
    good: dict[int, list] = {}
    n_bad: dict[int, int] = {}
    for (b, t), is_bad in zip(flat, bad):
        if is_bad:
            n_bad[b] = n_bad.get(b, 0) + 1
        else:
            good.setdefault(b, []).append(t)
    out = {}
    for b in sorted(tags_by_bin):
        pool, r = list(good.get(b, [])), 0
        while len(pool) < MIN_TAGS and r < 30:
            r += 1
            pool += good.get(b - r, []) + good.get(b + r, [])
        if not pool:
            continue
        E = np.concatenate([np.asarray(e) for _, e in pool])
        ow = [edge_components(np.asarray(t), np.asarray(e)) for t, e in pool]
        O = np.concatenate([o for o, _ in ow])
        W = np.concatenate([w for _, w in ow])
        out[b] = EdgeNoise(float(np.sqrt(np.mean(E ** 2))), float(np.sqrt(np.mean(O ** 2))),
                           float(np.sqrt(np.mean(W ** 2))), tuple(float(v) for v in E.mean(axis=0)),
                           len(good.get(b, [])), n_bad.get(b, 0), r)
    return out


def noise_at(noise: dict[int, EdgeNoise], distance: float) -> EdgeNoise:
    """The noise of the whole-metre bin of `distance`, or of the nearest bin measured."""
    return noise[min(noise, key=lambda k: (abs(k - round(distance)), k))]


# ---- the bound ----------------------------------------------------------------------------------------
def _weighted_rows(vehicle: Vehicle, cam: Camera, ids, noise, theta, params, calib: bool):
    """Whitened Jacobian rows (pose columns, calibration columns or None) of one camera's tags under
    `noise` (EdgeNoise: edge model; float: i.i.d. sigma per coordinate)."""
    obs = [TagObservation(int(t), np.zeros((4, 2)), cam) for t in ids]
    c = build_corners(vehicle, obs)
    ev = evaluate(c, theta)
    Jp = ev.J_px[:, params]
    Jc = calib_jacobian(c, theta) if calib else None
    if not isinstance(noise, EdgeNoise):
        s = float(noise)
        return Jp / s, (Jc / s if Jc is not None else None)
    pred = (ev.r_px.reshape(-1, 2) + c.pixels)  # projected corners (pixels are zeros)
    rows_p, rows_c = [], []
    for k in range(len(ids)):
        sl = slice(8 * k, 8 * k + 8)
        true = pred[4 * k:4 * k + 4]
        for J, rows in ((Jp, rows_p), (Jc, rows_c)):
            if J is None:
                continue
            o, w = edge_components(true, J[sl].reshape(4, 2, -1))
            rows.append(np.vstack([o / noise.offset_px, w / noise.turn_px]))
    return np.vstack(rows_p), (np.vstack(rows_c) if calib else None)


def pose_bound(vehicle: Vehicle, views, pose, sigma_h: float, calib: tuple[float, float] | None = None):
    """Cramér–Rao bound (position RMS m, yaw RMS rad) of a level roof's (x, y, yaw[, z]).

    views: [(Camera, tag ids, noise), ...], noise an EdgeNoise (edge-line model) or a float (i.i.d.
    sigma per coordinate); pose = (x, y, yaw, z); sigma_h > 0: Gaussian prior of that sigma on z, 0: z
    known. calib = (rotation sigma rad, centre sigma m): every camera's extrinsics are unknowns too,
    with that prior. With one camera, i.i.d. noise and no calib this is position_crlb's bound."""
    x, y, yaw, z = (float(v) for v in pose)
    theta = planar_theta(x, y, yaw, z)
    params = [IX, IY, IYAW] + ([IZ] if sigma_h > 0 else [])
    blocks = [_weighted_rows(vehicle, cam, ids, noise, theta, params, calib is not None)
              for cam, ids, noise in views if len(ids)]
    if not blocks:
        return math.inf, math.inf
    n_p = len(params)
    n = n_p + (6 * len(blocks) if calib is not None else 0)
    F = np.zeros((n, n))
    for k, (Jp, Jc) in enumerate(blocks):
        F[:n_p, :n_p] += Jp.T @ Jp
        if Jc is not None:
            s = slice(n_p + 6 * k, n_p + 6 * k + 6)
            F[:n_p, s] += Jp.T @ Jc
            F[s, :n_p] += Jc.T @ Jp
            F[s, s] += Jc.T @ Jc + np.diag([calib[0] ** -2] * 3 + [calib[1] ** -2] * 3)
    if sigma_h > 0:
        F[3, 3] += 1.0 / sigma_h ** 2
    try:
        if np.linalg.cond(F) > 1e15:
            raise np.linalg.LinAlgError
        cov = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return math.inf, math.inf
    return float(math.sqrt(cov[0, 0] + cov[1, 1])), float(math.sqrt(cov[2, 2]))
