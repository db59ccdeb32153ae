"""The paper study's models: the measured corner-noise model, the Cramér–Rao bound it implies, and the
study's own solver (level roof, roof height with its prior, optionally calibration-aware).

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

Solver `solve_level`: the level-roof model the bound describes, as a weighted least-squares problem:
corner residuals mapped to edge offsets and turns (turns over TURN_RATIO) over their sigma (estimated
from the fit), (z − h)/sigma_h, and, when the calibration is uncertain, the cameras' extrinsic
corrections over their prior sigmas (a per-RSU error shared by all of its corners: the estimator weighs
the RSUs accordingly instead of trusting each one's rays exactly). Garbled tags are weighed down by
their own misfit (see solve_level).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.geometry import rodrigues, wrap_angle
from toptag.solvers import Limits, PoseSolution, solve
from toptag.solvers.common import estimate_sigma
from toptag.solvers.lm import levenberg_marquardt
from toptag.solvers.model import IX, IY, IYAW, IZ, Corners, build_corners, evaluate, planar_theta, roof_world
from toptag.vehicle import Vehicle

TURN_RATIO = math.sqrt(3.0)  # sigma(turn) / sigma(offset) of a line fitted to evenly spread samples
OUTLIER_FACTOR = 5.0  # a tag whose corner RMS error exceeds this many times the case's median is garbled
MIN_TAGS = 12  # fewer good tags measured in a bin: the bins around it lend theirs
# The solvers' own floor (0.1 px, toptag.solvers.common) is above what this detector achieves on these
# images (edge offsets of 0.02-0.03 px): with it the height prior would be trusted too much.
SIGMA_FLOOR_PX = 0.005
NO_PRIOR_M = 100.0  # a roof-height "prior" that constrains nothing
# A tag fitted alone with a misfit up to this many times the best tag's is as good as it (two good tags'
# own misfits, 4 degrees of freedom each, differ by 3x one time in ten); beyond, its weight falls as the
# square of the excess: a garbled tag (measured: 15-2000x) counts for nothing.
MISFIT_FACTOR = 5.0


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
def _calib_jacobian(c: Corners, theta) -> np.ndarray:
    """d(pixels)/d(extrinsic correction) (2N, 6) of each row's own camera: rotation vector about the
    camera axes (R -> exp(w) R) and camera-centre shift (world), at the rows' cameras."""
    P_roof, _ = roof_world(theta, c.roof_points)
    P = P_roof[c.corner_of]
    Xc = np.einsum("nij,nj->ni", c.cam_R, P) + c.cam_t
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
    J_pos = -KD @ c.cam_R  # X_cam = R (X - c)
    return np.concatenate([J_rot, J_pos], axis=2).reshape(-1, 6)


def _weighted_rows(vehicle: Vehicle, cam: Camera, ids, noise, theta, params, calib: bool):
    """Whitened Jacobian rows (pose columns, calibration columns or None) of one camera's tags under
    `noise` (EdgeNoise: edge model; float: i.i.d. sigma per coordinate)."""
    obs = [TagObservation(int(t), np.zeros((4, 2)), cam) for t in ids]
    c = build_corners(vehicle, obs)
    ev = evaluate(c, theta)
    Jp = ev.J_px[:, params]
    Jc = _calib_jacobian(c, theta) if calib else None
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


# ---- the level-roof solver ----------------------------------------------------------------------------
@dataclass
class LevelSolution:
    ok: bool
    x: float = math.nan
    y: float = math.nan
    yaw: float = math.nan
    z: float = math.nan
    sigma_px: float = math.nan
    cameras: tuple[str, ...] = ()
    tags: tuple[int, ...] = ()
    error: str | None = None


def edge_whitener(pixels: np.ndarray, turn_ratio: float) -> np.ndarray:
    """(2N, 2N) block-diagonal map from corner residuals (tags of 4 corners, rows in order) to edge
    offsets and turns, the turns divided by turn_ratio: residuals of equal variance under the
    edge-line noise model. Edge normals from the observed quads."""
    n = len(pixels)
    T = np.zeros((2 * n, 2 * n))
    for k in range(0, n, 4):
        q = pixels[k:k + 4]
        for a in range(4):
            b = (a + 1) % 4
            u = q[b] - q[a]
            u = u / np.linalg.norm(u)
            nrm = np.array([-u[1], u[0]]) / 2
            ro, rw = 2 * (k + a), 2 * (k + a) + 1
            ia, ib = 2 * (k + a), 2 * (k + b)
            T[ro, ia:ia + 2] = nrm
            T[ro, ib:ib + 2] = nrm
            T[rw, ia:ia + 2] = -nrm / turn_ratio
            T[rw, ib:ib + 2] = nrm / turn_ratio
    return T


def _fit_level(c: Corners, h: float, sigma_h: float, calib, turn_ratio, start_xyyaw, sigma0: float,
               unit_weights=None, rounds: int = 3):
    """The weighted level-roof least squares on corners c from (x, y, yaw) with z = h and no
    calibration correction; unit_weights (per tag-in-camera, <= 1) scale each one's whitened residuals.
    Returns (LmResult, sigma (offset px), whitened weighted pixel residuals (px))."""
    cam_ids = c.camera_ids
    row_cam = np.array([cam_ids.index(c.units[u].camera.id) for u in c.unit_of])
    n_c = 6 * len(cam_ids) if calib is not None else 0
    prior = (np.array(([1 / calib[0]] * 3 + [1 / calib[1]] * 3) * len(cam_ids)) if calib is not None
             else np.zeros(0))
    cols = [IX, IY, IYAW, IZ]
    W = edge_whitener(c.pixels, turn_ratio) if turn_ratio else np.eye(2 * c.n)
    if unit_weights is not None:
        W = np.repeat(np.asarray(unit_weights, dtype=float)[c.unit_of], 2)[:, None] * W
    cam_rows = [row_cam == k for k in range(len(cam_ids))]
    px_rows = [np.flatnonzero(np.repeat(rows, 2)) for rows in cam_rows]

    def corrected(p) -> Corners:
        """Each camera's extrinsics corrected by p's share: R' = exp(w) R, centre' = centre + dc."""
        if not n_c:
            return c
        R, t = c.cam_R.copy(), c.cam_t.copy()
        for k, rows in enumerate(cam_rows):
            w, dc = p[4 + 6 * k:7 + 6 * k], p[7 + 6 * k:10 + 6 * k]
            R0, t0 = c.cam_R[rows][0], c.cam_t[rows][0]
            Rk = rodrigues(w) @ R0
            R[rows] = Rk
            t[rows] = -Rk @ (-R0.T @ t0 + dc)
        return Corners(c.units, c.unit_of, c.pixels, c.corner_of, c.roof_points, R, t, c.cam_K, c.cam_c)

    def make(sigma):
        def fun(p):
            theta = planar_theta(p[0], p[1], p[2], p[3])
            cc = corrected(p)
            ev = evaluate(cc, theta)
            m = len(ev.r_px)
            J = np.zeros((m + 1 + n_c, 4 + n_c))
            J[:m, :4] = W @ ev.J_px[:, cols] / sigma
            J[m, 3] = 1.0 / sigma_h
            r = [W @ ev.r_px / sigma, [(p[3] - h) / sigma_h]]
            if n_c:
                Jc = np.zeros((m, n_c))
                Jcam = _calib_jacobian(cc, theta)
                for k, rows in enumerate(px_rows):
                    Jc[rows, 6 * k:6 * k + 6] = Jcam[rows]
                J[:m, 4:] = W @ Jc / sigma
                J[m + 1:, 4:] = np.diag(prior)
                r.append(p[4:] * prior)
            r = np.concatenate(r)
            if not ev.in_front:
                r = np.full_like(r, np.inf)
            return r, J
        return fun

    p = np.concatenate([start_xyyaw, [h], np.zeros(n_c)])
    sigma = sigma0
    res = None
    for _ in range(rounds):  # sigma from the fit's own residuals, then solved again with it
        res = levenberg_marquardt(make(sigma), p if res is None else res.theta)
        r_px = res.r[:2 * c.n] * sigma
        new = estimate_sigma(float(r_px @ r_px), 2 * c.n - 4, floor=SIGMA_FLOOR_PX)
        if abs(new / sigma - 1.0) <= 0.1:
            break
        sigma = new
    return res, sigma, res.r[:2 * c.n] * sigma


def solve_level(vehicle: Vehicle, observations: list[TagObservation], sigma_h: float,
                calib: tuple[float, float] | None = None, limits: Limits | None = None,
                turn_ratio: float | None = TURN_RATIO, start: PoseSolution | None = None) -> LevelSolution:
    """(x, y, yaw, z) of a level roof from any tags in any cameras: pixel residuals over their sigma,
    (z − h)/sigma_h, and with calib = (rotation sigma rad, centre sigma m) every camera's extrinsic
    correction as an unknown with that prior. turn_ratio: weigh the corner residuals by the edge-line
    noise model (each edge's offset and turn, the turn's sigma turn_ratio times the offset's, sigma
    estimated from the fit); None: independent corner coordinates of equal sigma.

    Tags the paper's H.Opt. outlier test drops are dropped. The detector now and then returns one or
    two corners of a tag pixels off (about one tag in a hundred here), which that pooled-sigma test
    lets through; so each tag-in-camera is first fitted alone, its roof height free (its own RMS
    residual r_k says how well its corners fit a tag's shape), and its residuals are weighted by
    min(1, (MISFIT_FACTOR·r_min / r_k)²): tags of equal quality weigh alike, a garbled one counts for
    nothing. H.Opt. gives the start
    (pass `start`, H.Opt.'s solution of the same observations, if it is at hand)."""
    if start is None:
        start = solve(vehicle, observations, "hopt", sigma_h=sigma_h, limits=limits)
    if not start.ok:
        return LevelSolution(False, error=start.error)
    dropped = {(d["tag"], d["camera"]) for d in start.dropped_tags}
    obs = [o for o in observations if (int(o.tag_id), o.camera.id) not in dropped]
    h = float(vehicle.height)
    xyyaw = np.array([start.x, start.y, start.yaw])
    sigma0 = start.sigma_px if math.isfinite(start.sigma_px) else 0.5
    c = build_corners(vehicle, obs)
    weights = None
    if len(c.units) >= 2:
        # Each alone, its roof height free (no prior): the residual is the misfit of its shape only.
        own = np.array([math.sqrt(float(np.mean(_fit_level(c.subset([k]), h, NO_PRIOR_M, None, turn_ratio, xyyaw,
                                                            sigma0, rounds=1)[2] ** 2))) for k in range(len(c.units))])
        ref = max(float(own.min()), SIGMA_FLOOR_PX)
        excess = np.maximum(own / (MISFIT_FACTOR * ref), 1.0)
        weights = 1.0 / excess ** 2
        sigma0 = ref
    res, sigma, _ = _fit_level(c, h, sigma_h, calib, turn_ratio, xyyaw, sigma0, weights)
    if res is None or not res.converged or not np.all(np.isfinite(res.theta)):
        return LevelSolution(False, error="level-roof fit did not converge")
    p = res.theta
    return LevelSolution(True, float(p[0]), float(p[1]), wrap_angle(p[2]), float(p[3]), sigma,
                         tuple(c.camera_ids), tags=tuple(sorted({u.tag_id for u in c.units})))


