"""Compiled kernels (numba) of the level-roof model: its projection, its evaluation and its
Levenberg–Marquardt fit, which every solve runs (H.Opt., the level solver, the outlier test's fits).

Why compiled. These are fixed-size problems (a few dozen residuals, 3 or 4 unknowns): in numpy each
step is a few dozen calls of 1-3 µs on arrays of 16 numbers, most of a solve's cost; as one compiled
loop a whole fit costs a few µs. The arithmetic is the numpy code's, so results agree to rounding.

Cached: numba compiles each kernel on its first call (seconds of CPU for all of them: warmup.py does it
ahead) and keeps the machine code beside this file (`__pycache__`; see toptag.jit.compiled for where else),
where later processes load it in milliseconds. NUMBA_CACHE_DIR, when set, is where it goes instead.
"""
from __future__ import annotations

import math

import numpy as np

from toptag.jit import compiled, solve_small

MIN_DEPTH = 1e-6  # model.MIN_DEPTH (model imports this module)
COST_RTOL = 1e-10  # relative cost change that is rounding or negligible (~1e-5 sigma), not progress
PROMISED_RTOL = 1e-7  # a step promising less than this fraction of the cost is not worth trying
LAMBDA0 = 1e-4  # the damping it starts with; the promised-decrease stop applies while it is no larger


@compiled
def level_projection(cam_K, cam_c, cam_R, cam_t, points):
    """(3N, 6): each corner's homogeneous pixel (K·X_cam) as a linear map of (x, y, z, cos yaw, sin yaw, 1)
    of a level roof (see model.Corners.level_projection)."""
    n = points.shape[0]
    M = np.empty((3 * n, 6))
    Kh = np.zeros((3, 3))
    Kh[2, 2] = 1.0
    for i in range(n):
        Kh[0, 0], Kh[0, 1], Kh[1, 0], Kh[1, 1] = cam_K[i, 0, 0], cam_K[i, 0, 1], cam_K[i, 1, 0], cam_K[i, 1, 1]
        Kh[0, 2], Kh[1, 2] = cam_c[i, 0], cam_c[i, 1]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for a in range(3):
            g0 = Kh[a, 0] * cam_R[i, 0, 0] + Kh[a, 1] * cam_R[i, 1, 0] + Kh[a, 2] * cam_R[i, 2, 0]
            g1 = Kh[a, 0] * cam_R[i, 0, 1] + Kh[a, 1] * cam_R[i, 1, 1] + Kh[a, 2] * cam_R[i, 2, 1]
            g2 = Kh[a, 0] * cam_R[i, 0, 2] + Kh[a, 1] * cam_R[i, 1, 2] + Kh[a, 2] * cam_R[i, 2, 2]
            t = Kh[a, 0] * cam_t[i, 0] + Kh[a, 1] * cam_t[i, 1] + Kh[a, 2] * cam_t[i, 2]
            row = 3 * i + a
            M[row, 0], M[row, 1], M[row, 2] = g0, g1, g2
            M[row, 3] = g0 * px + g1 * py
            M[row, 4] = g1 * px - g0 * py
            M[row, 5] = t + g2 * pz
    return M


@compiled
def backproject(cam_K, cam_c, cam_R, cam_t, pixels, h):
    """Every corner's ray met with the world plane z = h (N, 3), NaN where the ray misses it."""
    n = pixels.shape[0]
    W = np.empty((n, 3))
    for i in range(n):
        # Normalised camera ray K⁻¹ (u − c), then its world direction R^T d.
        k00, k01, k10, k11 = cam_K[i, 0, 0], cam_K[i, 0, 1], cam_K[i, 1, 0], cam_K[i, 1, 1]
        u, v = pixels[i, 0] - cam_c[i, 0], pixels[i, 1] - cam_c[i, 1]
        det = k00 * k11 - k01 * k10
        xn, yn = (k11 * u - k01 * v) / det, (k00 * v - k10 * u) / det
        d = np.empty(3)
        centre = np.empty(3)
        for a in range(3):
            d[a] = cam_R[i, 0, a] * xn + cam_R[i, 1, a] * yn + cam_R[i, 2, a]
            centre[a] = -(cam_R[i, 0, a] * cam_t[i, 0] + cam_R[i, 1, a] * cam_t[i, 1] + cam_R[i, 2, a] * cam_t[i, 2])
        s = (h - centre[2]) / d[2] if d[2] != 0.0 else math.nan
        if not s > 0.0:
            s = math.nan
        for a in range(3):
            W[i, a] = centre[a] + s * d[a]
    return W


@compiled
def _evaluate_into(M, pixels, x, y, yaw, z, r, J, front):
    """The level model at (x, y, yaw, z): pixel residuals r (2N,), their Jacobian J (2N, 4) over
    (x, y, yaw, z) and each corner in front of its camera (N,), written into the given arrays."""
    c, s = math.cos(yaw), math.sin(yaw)
    for i in range(pixels.shape[0]):
        q = np.empty(3)
        qy = np.empty(3)
        for a in range(3):
            m = M[3 * i + a]
            q[a] = m[0] * x + m[1] * y + m[2] * z + m[3] * c + m[4] * s + m[5]
            qy[a] = -m[3] * s + m[4] * c  # its yaw derivative
        front[i] = q[2] > MIN_DEPTH
        iz = 1.0 / q[2]
        for a in range(2):
            uv = q[a] * iz
            r[2 * i + a] = uv - pixels[i, a]
            ma, m2 = M[3 * i + a], M[3 * i + 2]
            J[2 * i + a, 0] = (ma[0] - uv * m2[0]) * iz
            J[2 * i + a, 1] = (ma[1] - uv * m2[1]) * iz
            J[2 * i + a, 2] = (qy[a] - uv * qy[2]) * iz
            J[2 * i + a, 3] = (ma[2] - uv * m2[2]) * iz


@compiled
def evaluate_level(M, pixels, P):
    """The level model at B poses P (B, 4) = (x, y, yaw, z): residuals (B, 2N), Jacobians (B, 2N, 4),
    in front (B, N)."""
    n_b, n = P.shape[0], pixels.shape[0]
    r = np.empty((n_b, 2 * n))
    J = np.empty((n_b, 2 * n, 4))
    front = np.empty((n_b, n), dtype=np.bool_)
    for b in range(n_b):
        _evaluate_into(M, pixels, P[b, 0], P[b, 1], P[b, 2], P[b, 3], r[b], J[b], front[b])
    return r, J, front


@compiled
def _normal(M, pixels, W, row_w, need_front, z_prec, h, p, r_px, J_px, front, A, g):
    """The weighted level problem at p (x, y, yaw[, z]; z = h when p has 3): evaluates the model into
    r_px, J_px, front, its normal equations into A, g, and returns the cost |w·W r|² + z_prec (z − h)²
    (inf when a corner that counts is behind its camera)."""
    n_p = len(p)
    z = p[3] if n_p == 4 else h
    _evaluate_into(M, pixels, p[0], p[1], p[2], z, r_px, J_px, front)
    m = len(r_px)
    A[:, :] = 0.0
    g[:] = 0.0
    cost = 0.0
    jw = np.empty(n_p)
    for i in range(m):
        w = row_w[i]
        if w == 0.0:
            continue
        rw = 0.0
        for k in range(n_p):
            jw[k] = 0.0
        for j in range(m):
            t = W[i, j]
            if t != 0.0:
                rw += t * r_px[j]
                for k in range(n_p):
                    jw[k] += t * J_px[j, k]
        rw *= w
        cost += rw * rw
        for k in range(n_p):
            jk = jw[k] * w
            g[k] += jk * rw
            for l in range(k + 1):
                A[k, l] += jk * jw[l] * w
    for k in range(n_p):
        for l in range(k):
            A[l, k] = A[k, l]
    if n_p == 4:
        dz = p[3] - h
        cost += z_prec * dz * dz
        A[3, 3] += z_prec
        g[3] += z_prec * dz
    for i in range(len(front)):
        if need_front[i] and not front[i]:
            return math.inf
    return cost


@compiled
def fit_level(M, pixels, W, row_w, need_front, z_prec, h, P0, max_iter=60, step_tol=1e-11):
    """Levenberg–Marquardt fits of B level problems from P0 (B, n_p), n_p 3 (x, y, yaw; z = h) or 4
    (x, y, yaw, z with the prior precision z_prec about h). Problem b's residuals are row_w[b] · (W r_px)
    (W: the whitener, (2N, 2N)); need_front[b]: the corners whose being behind their camera makes a pose
    invalid. The same algorithm as lm.levenberg_marquardt_batch, step for step.
    Returns (theta (B, n_p), converged (B,), and at theta: r_px (B, 2N), J_px (B, 2N, 4), front (B, N),
    evaluations (B,))."""
    n_b, n_p = P0.shape
    n, m = pixels.shape[0], 2 * pixels.shape[0]
    theta = P0.copy()
    converged = np.zeros(n_b, dtype=np.bool_)
    r_out = np.empty((n_b, m))
    J_out = np.empty((n_b, m, 4))
    front_out = np.empty((n_b, n), dtype=np.bool_)
    n_eval = np.zeros(n_b, dtype=np.int64)
    A, g = np.empty((n_p, n_p)), np.empty(n_p)
    A_new, g_new = np.empty((n_p, n_p)), np.empty(n_p)
    r_new, J_new, front_new = np.empty(m), np.empty((m, 4)), np.empty(n, dtype=np.bool_)
    D = np.empty((n_p, n_p))
    for b in range(n_b):
        p = theta[b]
        r, J, front = r_out[b], J_out[b], front_out[b]
        cost = _normal(M, pixels, W, row_w[b], need_front[b], z_prec, h, p, r, J, front, A, g)
        n_eval[b] = 1
        active = math.isfinite(cost)
        lam = LAMBDA0
        for _ in range(max_iter):
            if not active:
                break
            dsum = 0.0
            for k in range(n_p):
                dsum += A[k, k]
            for k in range(n_p):
                for l in range(n_p):
                    D[k, l] = A[k, l]
                D[k, k] += lam * (A[k, k] + 1e-12 * (dsum + 1.0))
            step, solved = solve_small(D, -g)
            if not solved:
                lam *= 10.0
                continue
            promised = 0.0
            for k in range(n_p):
                promised -= 0.5 * g[k] * step[k]
            if lam <= LAMBDA0 and promised <= PROMISED_RTOL * cost:
                converged[b] = True  # at the minimum, as far as any noise could tell
                break
            big_step, big_p = 0.0, 0.0
            for k in range(n_p):
                big_step = max(big_step, abs(step[k]))
                big_p = max(big_p, abs(p[k]))
            small = big_step < step_tol * (1.0 + big_p)
            trial = p + step
            cost_new = _normal(M, pixels, W, row_w[b], need_front[b], z_prec, h, trial, r_new, J_new, front_new,
                               A_new, g_new)
            n_eval[b] += 1
            if cost_new <= cost:
                p[:] = trial
                r[:], J[:, :], front[:] = r_new, J_new, front_new
                A[:, :], g[:] = A_new, g_new
                c_old, cost = cost, cost_new
                lam = max(lam * 0.1, 1e-12)
                if small or c_old - cost_new <= COST_RTOL * c_old or cost_new == 0.0:
                    converged[b] = True
                    break
            elif math.isfinite(cost_new) and (cost_new - cost <= COST_RTOL * cost or small):
                converged[b] = True  # rounding noise at the minimum: no step can decrease the cost any more
                break
            else:
                lam *= 10.0
                if lam > 1e12:
                    break
    return theta, converged, r_out, J_out, front_out, n_eval


# ---- covariances and the outlier test's gate ------------------------------------------------------
MAX_CONDITION = 1e15  # a normal matrix more ill-conditioned than this does not determine its parameters


@compiled
def _inverse_into(A, out):
    """out = A⁻¹ by Gauss–Jordan elimination with partial pivoting; False when A is singular or not
    finite (out then undefined)."""
    n = A.shape[0]
    a = A.copy()
    for i in range(n):
        for j in range(n):
            out[i, j] = 1.0 if i == j else 0.0
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        piv = a[p, k]
        if not (piv != 0.0 and math.isfinite(piv)):
            return False
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
                out[k, j], out[p, j] = out[p, j], out[k, j]
        for j in range(n):
            a[k, j] /= piv
            out[k, j] /= piv
        for i in range(n):
            if i != k:
                f = a[i, k]
                if f != 0.0:
                    for j in range(n):
                        a[i, j] -= f * a[k, j]
                        out[i, j] -= f * out[k, j]
    return True


@compiled
def _norm1(A):
    best = 0.0
    for j in range(A.shape[1]):
        s = 0.0
        for i in range(A.shape[0]):
            s += abs(A[i, j])
        if not s <= best:  # a NaN column sum wins
            best = s
    return best


@compiled
def _safe_inverse_into(A, out):
    """common.safe_inverse of one matrix into out; whether it is finite (determined)."""
    if _inverse_into(A, out) and _norm1(A) * _norm1(out) <= MAX_CONDITION:
        return True
    out[:, :] = math.inf
    return False


@compiled
def safe_inverse(A):
    """Inverses of a stack (K, n, n) of normal matrices, all-inf where one does not determine its
    parameters (singular, not finite, or 1-norm condition number above MAX_CONDITION)."""
    out = np.empty_like(A)
    for k in range(A.shape[0]):
        _safe_inverse_into(A[k], out[k])
    return out


@compiled
def linear_fits(r, J, masks, s2, z_prec, dz):
    """One Gauss–Newton step from a pose (whitened residuals r (2N,), Jacobian J (2N, n_p)) for each of
    B subsets of the rows (masks (B, 2N) of 0/1), the pixels weighed with variance s2 and, when n_p is
    4, z with the prior precision z_prec (dz: the pose's z − h). Returns each subset's step (B, n_p),
    every row's residual after it (B, 2N), its own rows' sum of squares (B,), degrees of freedom (B,;
    NaN where the subset does not determine the pose) and normal matrix JᵀJ (B, n_p, n_p)."""
    n_b, m, n_p = masks.shape[0], J.shape[0], J.shape[1]
    step = np.zeros((n_b, n_p))
    r_new = np.empty((n_b, m))
    ss = np.zeros(n_b)
    dof = np.empty(n_b)
    JtJ = np.zeros((n_b, n_p, n_p))
    H, H_inv, g = np.empty((n_p, n_p)), np.empty((n_p, n_p)), np.empty(n_p)
    for b in range(n_b):
        g[:] = 0.0
        n_rows = 0.0
        for i in range(m):
            w = masks[b, i]
            n_rows += w
            if w == 0.0:
                continue
            for k in range(n_p):
                jk = J[i, k] * w
                g[k] += jk * r[i]
                for l in range(n_p):
                    JtJ[b, k, l] += jk * J[i, l]
        for k in range(n_p):
            g[k] /= s2
            for l in range(n_p):
                H[k, l] = JtJ[b, k, l] / s2
        if n_p == 4:
            H[3, 3] += z_prec
            g[3] += dz * z_prec
        if _safe_inverse_into(H, H_inv):
            trace = 0.0
            for k in range(n_p):
                acc = 0.0
                for l in range(n_p):
                    acc -= H_inv[k, l] * g[l]
                    trace += H_inv[k, l] * JtJ[b, l, k]
                step[b, k] = acc
            dof[b] = n_rows - trace / s2
        else:
            dof[b] = math.nan
        for i in range(m):
            acc = r[i]
            for k in range(n_p):
                acc += J[i, k] * step[b, k]
            r_new[b, i] = acc
            ss[b] += acc * acc * masks[b, i]
    return step, r_new, ss, dof, JtJ


@compiled
def loo_covariance(Jk, GtG, s2, z_prec):
    """For K left-out units (robust._loo_covariance): the covariance S_k = s2_k·I + J_k H_k⁻¹ J_kᵀ (K, m, m)
    of each one's prediction error, H_k = GtG_k / s2_k (+ z_prec on z when n_p is 4), and H_k⁻¹."""
    n_k, m, n_p = Jk.shape
    S = np.empty((n_k, m, m))
    H_inv = np.empty((n_k, n_p, n_p))
    H = np.empty((n_p, n_p))
    JH = np.empty((m, n_p))
    for b in range(n_k):
        for k in range(n_p):
            for l in range(n_p):
                H[k, l] = GtG[b, k, l] / s2[b]
        if n_p == 4:
            H[3, 3] += z_prec
        _safe_inverse_into(H, H_inv[b])
        for i in range(m):
            for l in range(n_p):
                acc = 0.0
                for k in range(n_p):
                    acc += Jk[b, i, k] * H_inv[b, k, l]
                JH[i, l] = acc
        for i in range(m):
            for j in range(m):
                acc = s2[b] if i == j else 0.0
                for l in range(n_p):
                    acc += JH[i, l] * Jk[b, j, l]
                S[b, i, j] = acc
    return S, H_inv


@compiled
def mahalanobis(e, S):
    """e_kᵀ S_k⁻¹ e_k for each k (NaN where S_k is singular)."""
    n_k = e.shape[0]
    d = np.empty(n_k)
    for b in range(n_k):
        x, ok = solve_small(S[b], e[b])
        if ok:
            acc = 0.0
            for i in range(len(x)):
                acc += e[b, i] * x[i]
            d[b] = acc
        else:
            d[b] = math.nan
    return d


# ---- starts and whiteners ----------------------------------------------------------------------
@compiled
def initial_poses(W, points, masks, yaw0):
    """hopt.initial_poses: (B, 3) starts (x, y, yaw) of B subsets of the corners (masks (B, N)) from their
    back-projections W (N, 3) (NaN rows: missed the plane) and roof points (N, 3); yaw0 NaN: each
    subset's planar Kabsch rotation, else that yaw. NaN rows where fewer than two corners back-project."""
    n_b, n = masks.shape
    out = np.empty((n_b, 3))
    for b in range(n_b):
        count = 0
        for i in range(n):
            if masks[b, i] and math.isfinite(W[i, 0]):
                count += 1
        w = 1.0 / max(count, 1)
        mw, mp = 0j, 0j
        cross = 0j
        for i in range(n):
            if masks[b, i] and math.isfinite(W[i, 0]):
                wi = complex(W[i, 0], W[i, 1])
                pi = complex(points[i, 0], points[i, 1])
                mw += w * wi
                mp += w * pi
                cross += w * (pi.conjugate() * wi)
        if math.isnan(yaw0):
            z = cross - mp.conjugate() * mw
            yaw = math.atan2(z.imag, z.real)
        else:
            yaw = math.atan2(math.sin(yaw0), math.cos(yaw0))
        origin = mw - complex(math.cos(yaw), math.sin(yaw)) * mp
        if count < 2:
            out[b, 0] = out[b, 1] = out[b, 2] = math.nan
        else:
            out[b, 0], out[b, 1], out[b, 2] = origin.real, origin.imag, yaw
    return out


@compiled
def edge_blocks(pixels, edge_map, edge_of, normal_axis):
    """level.edge_blocks for a turn ratio: (T, 8, 8) per tag of 4 consecutive corners, its edges' unit
    directions (edge a: corner a -> a + 1) read at (edge_of, normal_axis) and mapped by edge_map (32, 64)."""
    n_t = pixels.shape[0] // 4
    out = np.zeros((n_t, 8, 8))
    u = np.empty((4, 2))
    v = np.empty(32)
    for t in range(n_t):
        for a in range(4):
            i, j = 4 * t + a, 4 * t + (a + 1) % 4
            dx, dy = pixels[j, 0] - pixels[i, 0], pixels[j, 1] - pixels[i, 1]
            norm = math.sqrt(dx * dx + dy * dy)
            u[a, 0], u[a, 1] = dx / norm, dy / norm
        for k in range(32):
            v[k] = u[edge_of[k], normal_axis[k]]
        for e in range(64):
            acc = 0.0
            for k in range(32):
                acc += v[k] * edge_map[k, e]
            out[t, e // 8, e % 8] = acc
    return out


@compiled
def planar_statistics(J4, sigma, sigma_h):
    """H.Opt.'s covariance at its minimum (Jacobian J4 (2N, 4) over x, y, yaw, z; z is not fitted):
    (N⁻¹ of the fitted columns (3, 3), sigma² N⁻¹ + sigma_h² (dθ/dh)(dθ/dh)ᵀ (3, 3), and the RMS per
    corner of the pixel residual a one-sigma height error leaves, sigma_h · rms(J_h + J dθ/dh))."""
    m = J4.shape[0]
    N = np.zeros((3, 3))
    Jh = np.zeros(3)
    for i in range(m):
        for k in range(3):
            Jh[k] += J4[i, k] * J4[i, 3]
            for l in range(3):
                N[k, l] += J4[i, k] * J4[i, l]
    N_inv = np.empty((3, 3))
    _safe_inverse_into(N, N_inv)
    dth = np.zeros(3)
    for k in range(3):
        for l in range(3):
            dth[k] -= N_inv[k, l] * Jh[l]
    cov = np.empty((3, 3))
    for k in range(3):
        for l in range(3):
            cov[k, l] = sigma * sigma * N_inv[k, l] + sigma_h * sigma_h * dth[k] * dth[l]
    ss = 0.0
    for i in range(m):
        acc = J4[i, 3]
        for k in range(3):
            acc += J4[i, k] * dth[k]
        ss += acc * acc
    n = m // 2
    height_rms = sigma_h * math.sqrt(ss / n) if n else math.nan
    return N_inv, cov, height_rms


@compiled
def level_normal(T, J_px, r_px, row_w, prior2, sigma):
    """The level fit's normal equations at a point (level.LevelProblem._normal): the whitened Jacobian
    Jw = T·J_px / sigma (m, n_p), the inverse of H = Jwᵀ D² Jw + diag(prior2) (D: the row weights; all-inf
    where H does not determine p), the fit's degrees of freedom Σ D² − tr(H⁻¹ Jwᵀ D² Jw) (0 where not
    determined) and the weighted whitened residuals D·T·r_px (m,)."""
    m, n_p = J_px.shape
    Jw = np.zeros((m, n_p))
    rw = np.zeros(m)
    for i in range(m):
        acc = 0.0
        for k in range(m):
            t = T[i, k]
            acc += t * r_px[k]
            for j in range(n_p):
                Jw[i, j] += t * J_px[k, j]
        rw[i] = row_w[i] * acc
        for j in range(n_p):
            Jw[i, j] /= sigma
    JtD2J = np.zeros((n_p, n_p))
    d2_sum = 0.0
    for i in range(m):
        d2 = row_w[i] * row_w[i]
        d2_sum += d2
        for a in range(n_p):
            wa = Jw[i, a] * d2
            for b in range(n_p):
                JtD2J[a, b] += wa * Jw[i, b]
    H = JtD2J.copy()
    for a in range(n_p):
        H[a, a] += prior2[a]
    H_inv = np.empty((n_p, n_p))
    _safe_inverse_into(H, H_inv)
    finite = True
    trace = 0.0
    for a in range(n_p):
        for b in range(n_p):
            finite = finite and math.isfinite(H_inv[a, b])
            trace += H_inv[a, b] * JtD2J[b, a]
    dof = d2_sum - trace if finite else 0.0
    return Jw, H_inv, dof, rw, finite


@compiled
def level_covariance(T, J_px, Jw, H_inv, finite, row_w, prior2, noise2, sigma, outward, in_cam, bias2):
    """The level fit's sandwich covariance (level.LevelProblem.statistics) from level_normal's Jw, H_inv:
    H⁻¹ (noise2·Jwᵀ D⁴ Jw + diag(prior2)) H⁻¹, plus the detector's shared corner errors (bias2: the squared
    sigmas of a tag's outward edge shift, the camera's common one and the image shift; outward (tags, 8):
    each tag's raw pixel pattern of its edges moved outward; in_cam (tags, cams): which camera holds it),
    carried through the fit's response H⁻¹ Jwᵀ D² T / sigma to raw pixels. Also each unknown's
    J_px H⁻¹ column sum of squares times its prior precision (the residual a one-sigma prior error leaves)."""
    m, n_p = J_px.shape
    B = np.zeros((n_p, n_p))
    for i in range(m):
        d4 = noise2 * (row_w[i] * row_w[i]) ** 2
        for a in range(n_p):
            wa = Jw[i, a] * d4
            for b in range(n_p):
                B[a, b] += wa * Jw[i, b]
    for a in range(n_p):
        B[a, a] += prior2[a]
    HB = H_inv @ B
    cov = HB @ H_inv
    if bias2[0] != 0.0 or bias2[1] != 0.0 or bias2[2] != 0.0:
        A = np.empty((n_p, m))
        for a in range(n_p):
            for i in range(m):
                A[a, i] = Jw[i, a] * row_w[i] * row_w[i]
        gain = (H_inv @ A) @ T
        n_t, n_c = outward.shape[0], in_cam.shape[1]
        G_tag = np.zeros((n_p, n_t))
        G_img = np.zeros((n_p, 2, n_t))
        for a in range(n_p):
            for t in range(n_t):
                for k in range(8):
                    g = gain[a, 8 * t + k] / sigma
                    G_tag[a, t] += g * outward[t, k]
                    G_img[a, k % 2, t] += g
        G_cam = G_tag @ in_cam
        G_img_cam = np.empty((n_p, 2 * n_c))
        for a in range(n_p):
            for axis in range(2):
                for c in range(n_c):
                    acc = 0.0
                    for t in range(n_t):
                        acc += G_img[a, axis, t] * in_cam[t, c]
                    G_img_cam[a, axis * n_c + c] = acc
        cov += bias2[0] * (G_tag @ G_tag.T) + bias2[1] * (G_cam @ G_cam.T) + bias2[2] * (G_img_cam @ G_img_cam.T)
    per = np.empty(n_p)
    for j in range(n_p):
        if not finite:
            per[j] = math.inf * prior2[j]
            continue
        acc = 0.0
        for i in range(m):
            s = 0.0
            for k in range(n_p):
                s += J_px[i, k] * H_inv[k, j]
            acc += s * s
        per[j] = acc * prior2[j]
    return cov, per
