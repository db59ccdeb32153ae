"""Level roof: (x, y, yaw, z) of a roof held level, its height z with the prior z ~ N(h, sigma_h²), from
any tags in any cameras, the corner residuals weighed by the AprilTag edge-line noise model.

Why level. A bus roof bounces as a whole; it does not tilt by more than a fraction of a degree. The
paper's S.Opt. leaves pitch and roll free, and one camera can hardly tell a tilt from a shift along its
line of sight: measured (docs/paper-study.md), holding the roof level gains 2–5× at 10–20 m and reaches
the Cramér–Rao bound of the level roof.

Corner noise. An AprilTag corner is the intersection of two fitted edge lines, so corner errors are not
independent per coordinate: each edge line has an offset error (moved along its normal) and a turn
(its endpoints moved oppositely along the normal); and on real cameras a tag's four edges also move
in or out together (contrast, blur, gamma: the tag looks bigger or smaller). Measured on real
photographs against saddle-point truth (docs/real-data.md): per-edge offsets 0.10-0.13 px, turns 0.6-1.1
times that (TURN_RATIO = 1; a line fitted to evenly spread samples alone would give sqrt 3, and
toptag's old renderer gave 1.7-2.0), and a per-tag common offset 0.6-1.25 times the per-edge one
(TAG_RATIO = 1). The residuals are mapped to edge offsets and turns (`edge_whitener`), the turns divided
by the turn ratio and the offsets decorrelated from their tag's common part, which makes them of one
sigma, the per-edge offset sigma. The common part is what tells a tag's range from its size; weighing
it as the noise it is keeps a lone tag's size from overruling the roof-height prior. For a rectangle
a corner coordinate then has the variance (1 + tag_ratio² + turn_ratio²)·sigma_offset²: sigma_px (per
corner coordinate, as the other solvers use it) = noise_scale · sigma_offset. turn_ratio=None:
independent corner coordinates of sigma_px.

Garbled tags. The detector now and then returns one or two corners of a tag pixels off (about one tag
in a hundred in the study). Those the outlier test (robust.screen_outliers) does not drop are weighed
down by their own misfit: each tag-in-camera is fitted alone (its residual says how well its corners
fit a tag's shape), and its residuals are weighted by min(1, (MISFIT_FACTOR·r_min / r_k)^4): tags of
equal quality weigh alike (two good tags' misfits, 4–5 degrees of freedom each, differ by 5x about one
time in 150, by 9x one time in 2000), and a tag whose misfit is 9x the best one's or more (a garbled
tag: measured 8–2000x) is left out and reported in dropped_tags. A camera whose rotation is far off its
calibration shows the same way (its tags look tilted), and so loses its tags rather than bending the
pose; within its calibration uncertainty (when given) it does not: each tag's own fit then corrects its
camera's rotation within that prior.

Calibration. With the cameras' extrinsic uncertainty given (model.Calibration), every camera's
extrinsic correction (rotation about its axes, centre shift) is an unknown with that prior: a per-RSU
error is shared by all of its corners, and the estimator weighs the RSUs accordingly instead of trusting
each one's rays exactly. The covariance then carries the calibration uncertainty.

Covariance: the sandwich H⁻¹ B H⁻¹ of the weighted problem at the optimum (H⁻¹ when no tag is weighed
down), sigma given or estimated from the weighted residuals.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from toptag.geometry import rodrigues
from toptag.solvers.common import SIGMA_FLOOR_PX, SIGMA_PRIOR_PX, Fit, estimate_sigma, rms, safe_inverse
from toptag.solvers.hopt import initial_pose, initial_poses
from toptag.solvers import kernels
from toptag.solvers.lm import LmResult, levenberg_marquardt_batch
from toptag.solvers.model import (
    IX,
    IY,
    IYAW,
    IZ,
    KNOWN,
    Calibration,
    Corners,
    calib_columns,
    camera_index,
    evaluate,
    evaluate_level,
    evaluate_level_batch,
    planar_theta,
)

TURN_RATIO = 1.0  # sigma(turn) / sigma(offset) of an edge, real photographs (0.6-1.1)
TAG_RATIO = 1.0  # sigma of a tag's common edge offset / sigma(offset), real photographs (0.6-1.25)


@dataclass(frozen=True)
class DetectorBias:
    """Corner errors that every corner of a tag, or of an image, shares, so that no residual shows them;
    the covariance carries them (sigmas in px):
    - edge_common / edge_tag: the detector moves all four edges of a tag in or out together (blur,
      contrast, threshold): the tag looks bigger or smaller, i.e. nearer or farther, and the roof height
      absorbs it; a part common to the camera's tags and a part per tag;
    - image_shift: every corner of an image a fraction of a pixel off together, per axis: the fit reads
      it as a sideways shift of the bus."""

    edge_common: float = 0.0
    edge_tag: float = 0.0
    image_shift: float = 0.0


NO_BIAS = DetectorBias()
# What every tag of an image shares, which no residual shows: on real photographs the tags' mean edge
# offset after the detector's correction (DetectorSettings.edge_shift_px) is -0.03 to +0.02 px; a tag's
# own common offset is in the weighting (TAG_RATIO), not here.
DETECTOR_BIAS = DetectorBias(edge_common=0.03, edge_tag=0.0, image_shift=0.05)
MISFIT_FACTOR = 5.0  # a tag's misfit up to this many times the best tag's is as good as it (see below)
MISFIT_POWER = 4.0  # beyond, its residuals count (MISFIT_FACTOR·r_min / r_k)^MISFIT_POWER as much
MISFIT_MARGIN = 0.8  # linearised own misfits within this fraction of MISFIT_FACTOR: every weight is 1
MISFIT_DROP_WEIGHT = 0.1  # below (a misfit 9x the best tag's), the tag is left out and reported
MAX_ROUNDS = 3  # sigma estimated from the fit, the fit redone with it, until it changes by < 10 %
POSE = [IX, IY, IYAW, IZ]


@functools.lru_cache(maxsize=64)
def _chi2_quantile(alpha: float, k: int) -> float:
    return float(stats.chi2.ppf(1.0 - alpha, k))


def noise_scale(turn_ratio: float | None) -> float:
    """sigma_px (per corner coordinate) / sigma of the whitened residuals."""
    return math.sqrt(1.0 + TAG_RATIO ** 2 + turn_ratio ** 2) if turn_ratio else 1.0


def _edge_pattern():
    """Where edge_blocks' 32 entries go: (rows, columns, edge, which component of the edge direction u
    gives the normal's (the normal is (-u_y, u_x)), sign)."""
    rows, cols, edge, axis, sign = [], [], [], [], []
    for a in range(4):
        b = (a + 1) % 4
        for row, corner, s in ((2 * a, a, 1.0), (2 * a, b, 1.0), (2 * a + 1, a, -1.0), (2 * a + 1, b, 1.0)):
            for j, (component, flip) in enumerate(((1, -1.0), (0, 1.0))):
                rows.append(row), cols.append(2 * corner + j), edge.append(a), axis.append(component)
                sign.append(s * flip)
    return tuple(np.array(v) for v in (rows, cols, edge, axis, sign))


_EDGE_ROWS, _EDGE_COLS, _EDGE_OF, _NORMAL_AXIS, _EDGE_SIGN = _edge_pattern()


def edge_blocks(pixels: np.ndarray, turn_ratio: float | None) -> np.ndarray:
    """(T, 8, 8) per tag (4 corners each, rows in order): its corner residuals (x0, y0, x1, ...) to its
    edges' offsets and turns (turns over turn_ratio), edge normals from the observed quad. Residuals of
    equal variance under the edge-line noise model; identity for turn_ratio None."""
    q = np.ascontiguousarray(pixels, dtype=float).reshape(-1, 2)
    if not turn_ratio:
        return np.broadcast_to(np.eye(8), (len(q) // 4, 8, 8)).copy()
    return kernels.edge_blocks(q, _edge_map(turn_ratio), _EDGE_OF, _NORMAL_AXIS)


@functools.lru_cache(maxsize=8)
def _edge_map(turn_ratio: float) -> np.ndarray:
    """(32, 64): edge_blocks' entries from the 32 edge-direction components it uses. Edge a's offset (row
    2a) is the mean of its two corners' moves along its normal (corners a and a+1, columns 2a.. and
    2(a+1)..); its turn (row 2a+1) their difference, over turn_ratio. Then the offsets o, of covariance
    s²(I + r² 11ᵀ) with r = TAG_RATIO, are whitened by I − (1 − 1/sqrt(1 + 4r²))·11ᵀ/4."""
    scale = _EDGE_SIGN / 2.0 * np.where(_EDGE_ROWS % 2, 1.0 / turn_ratio, 1.0)
    k = 1.0 - 1.0 / math.sqrt(1.0 + 4.0 * TAG_RATIO ** 2) if TAG_RATIO else 0.0
    rows = np.eye(8)
    rows[0::2, 0::2] -= k / 4.0
    out = np.zeros((32, 8, 8))
    out[np.arange(32), :, _EDGE_COLS] = rows[:, _EDGE_ROWS].T * scale[:, None]
    out.flags.writeable = False
    return out.reshape(32, 64)


def edge_whitener(pixels: np.ndarray, turn_ratio: float | None) -> np.ndarray:
    """(2N, 2N) block-diagonal map of edge_blocks."""
    return block_diagonal(edge_blocks(pixels, turn_ratio))


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """(T·8, T·8) with the (T, 8, 8) blocks on its diagonal (scipy's block_diag costs ~10x more here)."""
    n, m = blocks.shape[0], blocks.shape[1]
    out = np.zeros((n, m, n, m))
    idx = np.arange(n)
    out[idx, :, idx, :] = blocks
    return out.reshape(n * m, n * m)


# ---- the weighted least-squares problem -------------------------------------------------------------
class LevelProblem:
    """Unknowns p = (x, y, yaw[, z][, every camera's uncertain extrinsic corrections]); z is held at h
    when sigma_h is 0. Residuals: whitened corner residuals (times the unit weights) over sigma, then
    (z − h)/sigma_h, then the corrections over their prior sigmas."""

    def __init__(self, c: Corners, h: float, sigma_h: float, calib: Calibration = KNOWN,
                 turn_ratio: float | None = TURN_RATIO, unit_weights=None, whitener: np.ndarray | None = None,
                 bias: DetectorBias = NO_BIAS):
        self.c, self.h, self.sigma_h, self.calib, self.bias = c, float(h), float(sigma_h), calib, bias
        self.T = np.ascontiguousarray(edge_whitener(c.pixels, turn_ratio) if whitener is None else whitener)
        self.row_w = (np.ones(2 * c.n) if unit_weights is None
                      else np.repeat(np.asarray(unit_weights, dtype=float)[c.unit_of], 2))
        self.zfree = self.sigma_h > 0
        self.cols = POSE if self.zfree else POSE[:3]
        self.n_pose = len(self.cols)
        self.cams = c.camera_ids
        self.n_c = 0 if calib.known else len(calib.columns) * len(self.cams)
        self.n_p = self.n_pose + self.n_c
        prior = np.zeros(self.n_p)  # square roots of the prior precisions
        if self.zfree:
            prior[3] = 1.0 / self.sigma_h
        if self.n_c:
            prior[self.n_pose:] = np.tile(1.0 / calib.sigmas, len(self.cams))
        self.prior = prior
        self.prior2 = prior ** 2
        self._memo = None
        self._evaluated = None  # (p's bytes, pixels(p)) of the last minimise's result
        if self.n_c:
            cam = camera_index(c)
            self._cam_rows = [cam == k for k in range(len(self.cams))]
            self._R0 = [c.cam_R[rows][0] for rows in self._cam_rows]
            self._centre0 = [-R.T @ c.cam_t[rows][0] for R, rows in zip(self._R0, self._cam_rows)]

    def start(self, pose) -> np.ndarray:
        """p from (x, y, yaw) (the roof at h, cameras as calibrated) or (x, y, yaw, z)."""
        p = np.zeros(self.n_p)
        p[:3] = pose[:3]
        if self.zfree:
            p[3] = pose[3] if len(pose) > 3 else self.h
        return p

    def theta(self, p) -> np.ndarray:
        return planar_theta(p[0], p[1], p[2], p[3] if self.zfree else self.h)

    def corrected(self, p) -> Corners:
        """c with each camera's extrinsics corrected by p's share: R' = exp(w) R, centre' = centre + dc."""
        if not self.n_c:
            return self.c
        c, cols, k = self.c, self.calib.columns, len(self.calib.columns)
        R, t = c.cam_R.copy(), c.cam_t.copy()
        for i, rows in enumerate(self._cam_rows):
            corr = np.zeros(6)
            corr[cols] = p[self.n_pose + i * k:self.n_pose + (i + 1) * k]
            Rk = rodrigues(corr[:3]) @ self._R0[i]
            R[rows] = Rk
            t[rows] = -Rk @ (self._centre0[i] + corr[3:])
        return Corners(c.units, c.unit_of, c.pixels, c.corner_of, c.roof_points, R, t, c.cam_K, c.cam_c)

    def pixels(self, p):
        """(raw pixel residuals (2N,), their Jacobian (2N, n_p), every corner in front of its camera)."""
        p = np.asarray(p, dtype=float)
        if self._evaluated is not None and self._evaluated[0] == p.tobytes():
            return self._evaluated[1]
        return self._pixels(p)

    def _pixels(self, p):
        if not self.n_c:  # the RSU's case: a level roof, cameras as calibrated
            r_px, J, ok = evaluate_level(self.c, p[0], p[1], p[2], p[3] if self.zfree else self.h)
            return r_px, J[:, :self.n_pose], ok
        theta = self.theta(p)
        cc = self.corrected(p)
        ev = evaluate(cc, theta)
        J = ev.J_px[:, self.cols]
        if self.n_c:
            J = np.hstack([J, calib_columns(cc, theta, self.calib)])
        return ev.r_px, J, ev.in_front

    @functools.cached_property
    def _bias_patterns(self) -> tuple[np.ndarray, np.ndarray]:
        """Per tag-in-camera, in row order (build_corners keeps each one's 4 corners in consecutive rows):
        the raw pixel pattern of its four edges moved outward (T, 8), and which camera holds it (T, cams)."""
        c = self.c
        cam_ids = sorted({u.camera.id for u in c.units})
        cam = [cam_ids.index(c.units[u].camera.id) for u in c.unit_of[::4].tolist()]
        in_cam = (np.array(cam)[:, None] == np.arange(len(cam_ids))[None, :]).astype(float)
        return np.ascontiguousarray(_outward(c).reshape(-1, 8)), in_cam

    def minimise(self, p0, sigma: float) -> LmResult:
        """The least-squares p from p0, the pixels weighted with sigma."""
        if not self.n_c:  # the RSU's case: the compiled level fit
            p0 = np.asarray(p0, dtype=float)[None]
            theta, conv, r, J, front, _ = kernels.fit_level(
                self.c.level_projection, self.c.pixels, self.T, (self.row_w / sigma)[None],
                np.ones((1, self.c.n), dtype=bool), self.prior[3] ** 2 if self.zfree else 0.0, self.h, p0)
            res = LmResult(theta[0], bool(conv[0]), r[0], J[0][:, :self.n_pose])
            self._evaluated = (res.theta.tobytes(), (res.r, res.J, bool(front[0].all())))
            return res
        A = self.row_w[:, None] * self.T / sigma
        prior2 = self.prior ** 2
        offset = np.zeros(self.n_p)
        if self.zfree:
            offset[3] = self.h

        def normal(ps):
            p = ps[0]
            r_px, J_px, ok = self.pixels(p)
            r, J = A @ r_px, A @ J_px
            dp = prior2 * (p - offset)
            cost = float(r @ r + dp @ (p - offset)) if ok else math.inf
            return (np.array([cost]), (J.T @ J + np.diag(prior2))[None], (J.T @ r + dp)[None],
                    (r_px[None], J_px[None], np.array([ok])))

        res = levenberg_marquardt_batch(normal, np.asarray(p0, dtype=float)[None])
        r_px, J_px, ok = (e[0] for e in res.extra)
        theta = res.theta[0]
        self._evaluated = (theta.tobytes(), (r_px, J_px, bool(ok)))  # the statistics at theta reuse it
        return LmResult(theta, bool(res.converged[0]), r_px, J_px)

    def _normal(self, p, sigma: float):
        """At p weighted with sigma: (r_px, J_px, in front, Jw, d2, H_inv, dof, weighted whitened
        residuals), kept for the last (p, sigma) asked: the fit asks its residual's statistics, then the
        covariance at the same point."""
        key = (np.asarray(p, dtype=float).tobytes(), float(sigma))
        if self._memo is not None and self._memo[0] == key:
            return self._memo[1]
        r_px, J_px, ok = self.pixels(p)
        J_px = np.ascontiguousarray(J_px, dtype=float)
        Jw, H_inv, dof, rw, finite = kernels.level_normal(self.T, J_px, np.ascontiguousarray(r_px, dtype=float),
                                                          self.row_w, self.prior2, float(sigma))
        out = (r_px, J_px, ok, Jw, finite, H_inv, dof, rw)
        self._memo = (key, out)
        return out

    def residual_statistics(self, p, sigma: float) -> tuple[np.ndarray, float]:
        """(whitened weighted residuals (px of the whitened sigma), their degrees of freedom) at p."""
        _, _, _, _, _, _, dof, rw = self._normal(p, sigma)
        return rw, dof

    def statistics(self, p, sigma: float, sigma_noise: float | None = None) -> "LevelStats":
        """At p, weighted with sigma; the covariance under whitened pixel noise sigma_noise (default sigma)."""
        r_px, J_px, ok, Jw, finite, H_inv, dof, rw = self._normal(p, sigma)
        noise2 = 1.0 if sigma_noise is None else (sigma_noise / sigma) ** 2
        # The sandwich under that noise, plus the detector's shared corner errors (DetectorBias: the
        # weighted fit's response to each tag's outward edge shift, to every camera's common one and to
        # its image shift); per unknown, the residual a one-sigma prior error (roof height, calibration)
        # leaves: p moves by -H⁻¹P²·delta.
        b = self.bias
        outward, in_cam = self._bias_patterns if b != NO_BIAS else (_NO_PATTERN, _NO_PATTERN)
        cov, per = kernels.level_covariance(self.T, J_px, Jw, H_inv, finite, self.row_w, self.prior2, noise2,
                                            float(sigma), outward, in_cam,
                                            np.array([b.edge_tag, b.edge_common, b.image_shift]) ** 2)
        n = max(self.c.n, 1)
        height2 = float(per[3]) if self.zfree else 0.0
        return LevelStats(r_px, J_px, rw, cov, H_inv, dof, math.sqrt(height2 / n),
                          math.sqrt(float(per[self.n_pose:].sum()) / n), ok)


_NO_PATTERN = np.zeros((0, 8))  # level_covariance's outward and in_cam when there is no DetectorBias


def _outward(c: Corners) -> np.ndarray:
    """(2N,) per corner: the pixel shift of a one-pixel outward move of its tag's four edges (along the
    quad's diagonal, times sqrt 2). build_corners keeps each tag's four corners in consecutive rows."""
    q = c.pixels.reshape(-1, 4, 2)
    v = q - q.mean(axis=1, keepdims=True)
    return (v * (math.sqrt(2.0) / np.sqrt((v * v).sum(axis=2, keepdims=True)))).reshape(-1)


@dataclass
class LevelStats:
    r_px: np.ndarray  # raw pixel residuals
    J_px: np.ndarray
    r_white: np.ndarray  # whitened, weighted residuals (px of the whitened sigma)
    cov: np.ndarray  # (n_p, n_p)
    H_inv: np.ndarray
    dof: float
    height_rms_px: float
    calib_rms_px: float
    in_front: bool


# ---- fits --------------------------------------------------------------------------------------------
@dataclass
class SubsetFit:
    """A level fit of some of c's units (no unit weights; calibration unknowns only in SubsetFits.own)."""

    units: tuple[int, ...]
    source: Corners  # all the units' corners, of which this fit used `units`
    p: np.ndarray
    theta: np.ndarray
    r_white: np.ndarray  # whitened residuals (px) of the units fitted
    J_white: np.ndarray  # whitened Jacobian over (x, y, yaw[, z]) (px)
    dof: float  # NaN for the fit of every unit, as its information is None (nobody reads them)
    converged: bool
    # Every corner of `source` at this fit's pose (the outlier test predicts the units left out with
    # them): whitened residuals (2N,), Jacobian (2N, 4) over (x, y, yaw, z), and in front (N,).
    all_r_white: np.ndarray | None = None
    all_J_white: np.ndarray | None = None
    all_in_front: np.ndarray | None = None
    information: np.ndarray | None = None  # the fit's normal matrix (with the height prior), whitened sigma_w
    all_r_px: np.ndarray | None = None  # all_r_white and all_J_white before whitening (raw pixels)
    all_J_px: np.ndarray | None = None

    @functools.cached_property
    def corners(self) -> Corners:
        return self.source.subset(self.units)


@dataclass
class LinearFits:
    """SubsetFits.linear_fits: B subset fits predicted from one evaluation."""

    p: np.ndarray  # (B, n_p)
    r_white: np.ndarray  # (B, 2N) every corner's whitened residual at each fit's pose
    ss: np.ndarray  # (B,) each fit's whitened residual sum of squares over its own rows
    dof: np.ndarray  # (B,) NaN where the subset does not determine the pose
    JtJ: np.ndarray  # (B, n_p, n_p) its own rows' whitened normal matrix


class SubsetFits:
    """Level fits of subsets of c's units (by index in c), each computed once: the outlier test's
    leave-one-out fits and the misfit weights' one-tag fits are often the same ones, and those wanted
    together are solved together (`prepare`: one batch of small problems, each step of all of them a few
    numpy calls). sigma_w: the whitened sigma that weighs the pixels against the roof-height prior."""

    def __init__(self, c: Corners, h: float, sigma_h: float, turn_ratio: float | None, sigma_w: float):
        self.c, self.h, self.sigma_h, self.turn_ratio, self.sigma_w = c, h, sigma_h, turn_ratio, sigma_w
        self.blocks = edge_blocks(c.pixels, turn_ratio)  # per unit: build_corners keeps 4 rows per unit
        self.T = block_diagonal(self.blocks)
        self._fits: dict[tuple, SubsetFit | None] = {}
        self._whiteners: dict[tuple[int, ...], np.ndarray] = {}
        corners = np.argsort(c.unit_of, kind="stable").reshape(len(c.units), 4)  # each unit's 4 corners
        self._unit_rows = (2 * corners[..., None] + np.array([0, 1])).reshape(len(c.units), 8)
        self._whiteners[tuple(range(len(c.units)))] = self.T

    def whitener(self, units) -> np.ndarray:
        key = tuple(int(u) for u in units)
        if key not in self._whiteners:
            self._whiteners[key] = block_diagonal(self.blocks[list(key)])
        return self._whiteners[key]

    def rows(self, units) -> np.ndarray:
        """Indices of the units' residual rows (x and y of each of their corners) within c's 2N."""
        return self._unit_rows[list(units)].ravel()

    def get(self, units) -> SubsetFit | None:
        key = tuple(sorted(int(u) for u in units))
        if key not in self._fits:
            self.prepare([key])
        return self._fits[key]

    def prepare(self, subsets) -> None:
        """Fit every listed subset of units not fitted yet, all at once."""
        keys = list(dict.fromkeys(tuple(sorted(int(u) for u in s)) for s in subsets))
        keys = [k for k in keys if k not in self._fits]
        if keys:
            self._fits.update(zip(keys, self._fit_batch(keys)))

    def fitted(self, units) -> SubsetFit | None:
        """The fit of these units if it has been computed (never computes it)."""
        return self._fits.get(tuple(sorted(int(u) for u in units)))

    def yaw_of(self, units) -> float | None:
        """The yaw of the converged fit of the most of `units` (none of any other unit) fitted so far."""
        units = set(int(u) for u in units)
        fits = [f for key, f in self._fits.items() if f is not None and f.converged and isinstance(key[0], int)
                and units.issuperset(key)]
        return float(max(fits, key=lambda f: len(f.units)).theta[2]) if fits else None

    def own(self, k: int, calib: Calibration = KNOWN) -> SubsetFit | None:
        """Unit k fitted alone; with its camera's rotation correction as an unknown with its prior when
        the rotation is uncertain: a camera's rotation error makes a level tag look tilted, which at
        high resolution is a misfit well above the corner noise, not a sign of a garbled tag."""
        if not calib.rot_sigma > 0:
            return self.get((k,))
        key = ("own", int(k))
        if key not in self._fits:
            self._fits[key] = self._fit_calibrated(int(k), Calibration(calib.rot_sigma, 0.0))
        return self._fits[key]

    def _fit_batch(self, keys: list[tuple[int, ...]]) -> list[SubsetFit | None]:
        c, h, s_w = self.c, self.h, self.sigma_w
        in_key = np.zeros((len(keys), len(c.units)), dtype=bool)
        for b, key in enumerate(keys):
            in_key[b, list(key)] = True
        corner_mask = np.ascontiguousarray(in_key[:, c.unit_of])  # (B, N)
        row_w = np.repeat(corner_mask, 2, axis=1) / s_w  # (B, 2N): the subset's rows, over sigma
        starts = initial_poses(c, h, corner_mask)
        ok_start = np.isfinite(starts[:, 0])
        zfree = self.sigma_h > 0
        n_p = 4 if zfree else 3
        p0 = np.ascontiguousarray(np.column_stack([starts, np.full(len(keys), h)])[:, :n_p])
        p0[~ok_start] = 0.0
        T = self.T
        theta, conv, r_px, J_px, front, _ = kernels.fit_level(c.level_projection, c.pixels, T, row_w, corner_mask,
                                                              1.0 / self.sigma_h ** 2 if zfree else 0.0, h, p0)
        r_all, J_all = r_px @ T.T, T @ J_px  # whitened, every corner
        usable = (ok_start & np.isfinite(theta).all(axis=1)).tolist()
        if all(len(key) == len(c.units) for key in keys):
            # The fit of every unit is never a leave-one-out rest nor an own fit, the only readers of a
            # fit's dof and information: not computed (NaN, None).
            H, trace, determined = [None] * len(keys), [math.nan] * len(keys), [True] * len(keys)
        else:
            Jw = J_all[..., :n_p] * np.repeat(corner_mask, 2, axis=1)[..., None]
            JtJ = np.swapaxes(Jw, 1, 2) @ Jw
            H = JtJ / s_w ** 2
            if zfree:
                H[:, 3, 3] += 1.0 / self.sigma_h ** 2
            H_inv = safe_inverse(H)
            trace = np.einsum("bij,bji->b", H_inv, JtJ).tolist()
            determined = np.isfinite(H_inv).all(axis=(1, 2)).tolist()
        converged = (conv & (front | ~corner_mask).all(axis=1)).tolist()
        thetas = np.zeros((len(keys), 6))
        thetas[:, [IX, IY, IYAW, IZ]] = _level_poses(theta, h)
        out = []
        for b, key in enumerate(keys):
            if not usable[b]:
                out.append(None)
                continue
            rows = self.rows(key)
            dof = len(rows) - trace[b] / s_w ** 2 if determined[b] else 0.0
            out.append(SubsetFit(key, c, theta[b], thetas[b], r_all[b, rows], J_all[b, rows, :n_p], dof,
                                 converged[b], r_all[b], J_all[b], front[b], H[b], r_px[b], J_px[b]))
        return out

    def evaluated(self, pose, r_px: np.ndarray, J_px: np.ndarray, front: np.ndarray) -> SubsetFit:
        """Every unit at a level pose (x, y, yaw, z) some solver evaluated the model at (raw pixel
        residuals (2N,), Jacobian (2N, 4), in front (N,)), as a SubsetFit to linearise about."""
        n_p = 4 if self.sigma_h > 0 else 3
        r_all, J_all = self.T @ r_px, self.T @ J_px
        key = tuple(range(len(self.c.units)))
        return SubsetFit(key, self.c, np.asarray(pose[:n_p], dtype=float), planar_theta(*pose[:4]), r_all,
                         J_all[:, :n_p], math.nan, True, r_all, J_all, np.asarray(front, dtype=bool),
                         all_r_px=r_px, all_J_px=J_px)

    def linear_fits(self, about: SubsetFit, masks: np.ndarray, sigma_w: float | None = None) -> "LinearFits":
        """The fits of B subsets of the units (masks (B, 2N) of 0/1 over the residual rows) as one
        Gauss–Newton step each from `about` (a pose with every corner's whitened residuals and Jacobian)
        predicts them: no model evaluation, a few stacked matrix products for all of them. Exact for a
        linear model, and within a small fraction of sigma of the real fits near a consistent frame's
        optimum. sigma_w: the pixels weighed with this whitened sigma instead of the fits' own."""
        n_p, s2 = len(about.p), (self.sigma_w if sigma_w is None else sigma_w) ** 2
        z_prec, dz = (1.0 / self.sigma_h ** 2, about.p[3] - self.h) if n_p == 4 else (0.0, 0.0)
        J = np.ascontiguousarray(about.all_J_white[:, :n_p])
        step, r_new, ss, dof, JtJ = kernels.linear_fits(about.all_r_white, J, np.asarray(masks, dtype=float), s2,
                                                        z_prec, dz)
        return LinearFits(about.p + step, r_new, ss, dof, JtJ)

    def _fit_calibrated(self, k: int, calib: Calibration) -> SubsetFit | None:
        """Unit k alone with its camera's uncertain extrinsic corrections as unknowns."""
        sub = self.c.subset([k])
        start = initial_pose(sub, self.h, None)
        if start is None:
            return None
        T = self.whitener((k,))
        prob = LevelProblem(sub, self.h, self.sigma_h, calib, self.turn_ratio, whitener=T)
        res = prob.minimise(prob.start(start), self.sigma_w)
        if not np.all(np.isfinite(res.theta)):
            return None
        r_px, J_px, ok = prob.pixels(res.theta)
        Jw = T @ J_px
        H = Jw.T @ Jw / self.sigma_w ** 2 + np.diag(prob.prior ** 2)
        H_inv = safe_inverse(H)
        dof = (2 * sub.n - float(np.trace(H_inv @ (Jw.T @ Jw))) / self.sigma_w ** 2
               if np.all(np.isfinite(H_inv)) else 0.0)
        return SubsetFit((k,), self.c, res.theta, prob.theta(res.theta), T @ r_px, Jw, dof, res.converged and ok)


def _combined_start(fits: SubsetFits, units: list[int], weights) -> np.ndarray | None:
    """The joint fit's start from the units' own fits: their poses averaged by their information (each
    own fit's normal matrix, times its unit's weight squared): nearer the joint optimum than any one
    of them, which saves the joint fit an iteration or two. None unless every own fit converged."""
    own = [fits.fitted((k,)) for k in units]
    if not own or any(f is None or not f.converged or f.information is None for f in own):
        return None
    w2 = np.ones(len(own)) if weights is None else np.asarray(weights, dtype=float) ** 2
    P = np.array([f.p for f in own])
    P[:, 2] = P[0, 2] + (P[:, 2] - P[0, 2] + math.pi) % (2.0 * math.pi) - math.pi  # one branch of yaw
    H = np.array([f.information for f in own]) * w2[:, None, None]
    try:
        p0 = np.linalg.solve(H.sum(axis=0), np.einsum("kij,kj->i", H, P))
    except np.linalg.LinAlgError:
        return None
    return p0 if np.all(np.isfinite(p0)) else None


def _level_poses(p: np.ndarray, h: float) -> np.ndarray:
    """(B, 4) level poses (x, y, yaw, z) from (B, 3 or 4) parameters (z = h when not among them)."""
    return p if p.shape[1] == 4 else np.column_stack([p, np.full(len(p), h)])


def misfit_weights(fits: SubsetFits, units: list[int], floor_w: float,
                   calib: Calibration = KNOWN) -> tuple[np.ndarray, float | None, np.ndarray]:
    """Per unit (in `units` order): min(1, (MISFIT_FACTOR·r_min / r_k)^MISFIT_POWER) from each one's fit
    alone (r_k: RMS of its whitened residual); the pooled whitened sigma of those fits as the joint fit
    will weigh them (None if there is none); and r_k / r_min.
    A unit that cannot be fitted alone keeps weight 1. Two good tags' own misfits (4–5 degrees of
    freedom each) differ by 3× one time in ten; a garbled tag's is (measured) 15–2000× the best."""
    if not calib.rot_sigma > 0:
        fits.prepare([(k,) for k in units])
    own = [fits.own(k, calib) for k in units]
    return misfit_weights_of([float(f.r_white @ f.r_white) if f is not None and f.converged else math.nan
                              for f in own], [len(f.r_white) if f is not None else 1 for f in own],
                             [f.dof if f is not None else math.nan for f in own], floor_w)


def misfit_weights_of(ss_own: list[float], n_own: list[int], dof_own: list[float],
                      floor_w: float) -> tuple[np.ndarray, float | None, np.ndarray]:
    """misfit_weights from each unit's own fit's whitened residual sum of squares, its number of
    residuals and its degrees of freedom (NaN: the unit could not be fitted alone)."""
    own, ss, dof = [], [], []  # a few floats per unit: plain Python
    for ss_k, n_k, dof_k in zip(ss_own, n_own, dof_own):
        if math.isnan(ss_k) or math.isnan(dof_k):
            own.append(math.nan)
            continue
        own.append(math.sqrt(ss_k / n_k))
        ss.append(ss_k)
        dof.append(max(dof_k, 0.0))
    if not ss:
        return np.ones(len(units)), None, np.array(own)
    ref = max(min(r for r in own if not math.isnan(r)), floor_w)
    w = [1.0 if math.isnan(r) else 1.0 / max(r / (MISFIT_FACTOR * ref), 1.0) ** MISFIT_POWER for r in own]
    w2 = [wk * wk for wk, r in zip(w, own) if not math.isnan(r)]  # as the weighted fit counts them
    pooled = math.sqrt(sum(a * b for a, b in zip(w2, ss)) / max(sum(a * b for a, b in zip(w2, dof)), 1e-9))
    return np.array(w), max(pooled, floor_w), np.array(own) / ref


def fit_level(c: Corners, h: float, start, *, sigma_h: float, sigma_px: float | None = None,
              calib: Calibration = KNOWN, turn_ratio: float | None = TURN_RATIO, unit_weights=None,
              sigma0_w: float | None = None, calib_alpha: float = 1e-3, bias: DetectorBias = NO_BIAS,
              whitener: np.ndarray | None = None, at_minimum: tuple | None = None) -> Fit:
    """The weighted level-roof fit from start = (x, y, yaw) (or (x, y, yaw, z)). sigma_px: corner noise per
    coordinate if known.
    Else sigma0_w, when given, is the whitened noise the tags' own fits show (misfit_weights): the fit
    weighs with it (or with the smaller noise its own residual shows), and the covariance takes the noise
    its own residual shows; without sigma0_w (one tag) sigma is estimated from the fit's residual and the
    fit redone until it settles. Returns a Fit
    whose fit_rms_px is the RMS of the weighted pixel residuals (what the fit fits) and whose
    height_rms_px / calib_rms_px are the residuals a one-sigma roof-height / calibration error leaves.
    A camera whose estimated extrinsic correction is beyond its calibration prior (chi-square above its
    1 − calib_alpha quantile; the estimate shrinks toward the prior, so an honest error stays below it
    at least that often) makes the fit unusable: the cameras disagree by more than their calibration.
    whitener: edge_whitener(c.pixels, turn_ratio) when the caller has it already. at_minimum: the model at
    start (raw pixel residuals, their Jacobian over the pose, all in front) when start is the minimum of
    the fit's first weighting already (the caller solved it): no step is tried from there."""
    scale = noise_scale(turn_ratio)
    floor_w, prior_w = SIGMA_FLOOR_PX / scale, SIGMA_PRIOR_PX / scale
    prob = LevelProblem(c, h, sigma_h, calib, turn_ratio, unit_weights, whitener, bias=bias)
    known = sigma_px is not None
    p = prob.start(start)
    if at_minimum is not None:
        prob._evaluated = (p.tobytes(), at_minimum)

    def minimise(p, sigma):
        nonlocal at_minimum
        if at_minimum is None:
            return prob.minimise(p, sigma)
        at_minimum, (r_px, J_px, _) = None, at_minimum
        return LmResult(p, True, r_px, J_px)

    if known:
        sigma = sigma_cov = sigma_px / scale
        res = minimise(p, sigma)
        p = res.theta
    elif sigma0_w is not None:
        # Weighed with the tags' own-shape noise, or with the joint fit's own when that is smaller (the
        # cameras' corrections explain part of the own fits' misfit: a camera's rotation error looks
        # like a tilted tag), never with more: the tags' (or cameras') disagreement with each other must
        # not be explained away as pixel noise.
        sigma = sigma0_w
        for _ in range(MAX_ROUNDS):
            res = minimise(p, sigma)
            p = res.theta
            if not np.all(np.isfinite(p)):
                sigma_cov = sigma
                break
            rw, dof = prob.residual_statistics(p, sigma)
            sigma_cov = estimate_sigma(float(rw @ rw), dof, floor=floor_w, prior=prior_w)
            if sigma_cov >= 0.9 * sigma:
                break
            sigma = sigma_cov
    else:
        sigma = prior_w
        for _ in range(MAX_ROUNDS):  # sigma from the fit's own residuals, the fit redone with it
            res = minimise(p, sigma)
            p = res.theta
            if not np.all(np.isfinite(p)):
                break
            rw, dof = prob.residual_statistics(p, sigma)
            new = estimate_sigma(float(rw @ rw), dof, floor=floor_w, prior=prior_w)
            done = abs(new / sigma - 1.0) <= 0.1
            sigma = new
            if done:
                break
        sigma_cov = sigma
    # The covariance of the fit as weighted (the sandwich) under the noise found in its residual.
    st = prob.statistics(p, sigma, sigma_cov)
    theta = prob.theta(p)
    note = None
    if not st.in_front:
        note = "pose puts the tag behind the camera"
    elif not res.converged:
        note = "level-roof fit did not converge"
    elif prob.n_c:
        k = len(calib.columns)
        for i, cam_id in enumerate(prob.cams):
            z = p[prob.n_pose + i * k:prob.n_pose + (i + 1) * k] / calib.sigmas
            chi2, limit = float(z @ z), _chi2_quantile(calib_alpha, k)
            if not chi2 <= limit:
                note = (f"camera {cam_id}'s extrinsics disagree with the other observations beyond their "
                        f"calibration uncertainty (chi2 {chi2:.3g} > {limit:.3g})")
                break
    fit = Fit("level", theta, st.cov[:3, :3], rms(st.r_px), sigma_cov * scale, c,
              converged=res.converged and st.in_front, dof=st.dof, fit_rms_px=rms(prob.row_w * st.r_px),
              height_rms_px=st.height_rms_px, calib_rms_px=st.calib_rms_px, note=note)
    return fit


def solve_level_corners(c: Corners, keep: list[int], h: float, *, sigma_h: float, sigma_px: float | None,
                        calib: Calibration, turn_ratio: float | None, fits: SubsetFits | None,
                        weigh_misfits: bool = True, calib_alpha: float = 1e-3,
                        bias: DetectorBias = NO_BIAS, linear=None
                        ) -> tuple[Fit | None, list[dict]]:
    """The level solver on c's units `keep` (those that passed the outlier test, whose fits on c it
    reuses): misfit weights from each unit's own fit, then the joint fit. Returns the fit (None when no
    start is found) and the units left out because their weight fell below MISFIT_DROP_WEIGHT
    ({"tag", "camera", "reason"}).
    linear: robust.screening_needed's verdict when it found every unit consistent without fitting them
    one by one: the own fits' misfits are then its predictions, unless one unit's comes within
    MISFIT_MARGIN of weighing it down (then they are fitted), and the joint fit starts from the pose
    it linearised about."""
    scale = noise_scale(turn_ratio)
    weights, sigma0_w, dropped, start, at_minimum = None, None, [], None, None
    keep = list(keep)
    if len(keep) >= 2 and weigh_misfits:
        if fits is None or fits.turn_ratio != turn_ratio or fits.c is not c:
            sigma_w = sigma_px / scale if sigma_px is not None else SIGMA_PRIOR_PX / scale
            fits = SubsetFits(c, h, sigma_h, turn_ratio, sigma_w)
        if linear is not None and calib.known and keep == list(range(len(c.units))):
            _, sigma0_w, ratio = misfit_weights_of(linear.own_ss, [8] * len(keep), linear.own_dof,
                                                   SIGMA_FLOOR_PX / scale)
            if np.all(ratio <= MISFIT_MARGIN * MISFIT_FACTOR):  # every weight 1 (False for a NaN)
                # The joint fit the verdict is about, moved to the weighting with sigma0_w by one
                # Gauss-Newton step, the model there predicted along it (no evaluation).
                a = linear.about
                weigh = sigma_px / scale if sigma_px is not None else sigma0_w  # as fit_level weighs first
                start = fits.linear_fits(a, np.ones((1, 2 * c.n)), weigh).p[0]
                J = a.all_J_px[:, :len(start)]
                at_minimum = (a.all_r_px + J @ (start - a.p), J, bool(a.all_in_front.all()))
        if start is None:
            weights, sigma0_w, ratio = misfit_weights(fits, keep, SIGMA_FLOOR_PX / scale, calib)
            out = weights < MISFIT_DROP_WEIGHT
            if out.any():
                for k, r in zip(np.array(keep)[out], ratio[out]):
                    unit = c.units[int(k)]
                    dropped.append({"tag": unit.tag_id, "camera": unit.camera.id,
                                    "reason": f"corners misfit the tag's shape ({r:.0f}x the best tag's residual)"})
                keep = [k for k, o in zip(keep, out) if not o]
                weights = weights[~out]
    kept = c if keep == list(range(len(c.units))) else c.subset(keep)
    if start is None and fits is not None and calib.known:
        start = _combined_start(fits, keep, weights)
    if start is None:
        start = initial_pose(kept, h, None)
    if start is None:
        return None, dropped
    # The screening's whitener of these units, when it weighs as this fit does (keep is in c's order).
    whitener = fits.whitener(keep) if fits is not None and fits.c is c and fits.turn_ratio == turn_ratio else None
    return fit_level(kept, h, start, sigma_h=sigma_h, sigma_px=sigma_px, calib=calib, turn_ratio=turn_ratio,
                     unit_weights=weights, sigma0_w=sigma0_w, calib_alpha=calib_alpha, bias=bias,
                     whitener=whitener, at_minimum=at_minimum), dropped
