"""Compiled kernels (numba) of the bus filter's IMU step: the prediction over one interval, the yaw
rate's random step and the gyro/wheel update (toptag.fusion.filter: `_predict`, `_yaw_rate_noise`,
`_imu_update`, `_kalman`), a pose fix's prediction, gate and Kalman update (`_apply_fix`, `_gate`;
toptag.fusion.offsets.pose_before), and the growth of an estimate's covariance beyond the newest IMU
sample (`_unmeasured_motion`), which the bus agent asks for at 50 Hz, and the drift detector's arithmetic
(toptag.fusion.trust: `DriftRule.accumulate`, `_deviation`; `drift_accumulate`, `drift_deviation`).
`fix_step` is a trusted RSU's fix while tracking (nearly every fix) as one call of those: the bus agent runs
the filter every 20 ms, and code run once after a sleep is cold, so the number of calls counts more there than
their speed.

Why compiled. A fix arriving ~100 ms late re-runs the ~10 IMU steps after its capture time; at 40
fixes/s that is 4-5 steps per IMU sample received. Each step is a few dozen numpy calls on a state of
7 + 4 (time offsets) + 3 per calibration-bias block entries, 1-3 µs each: most of the bus agent's CPU
(`toptag bench bus`). As one compiled loop a step costs a few µs. The arithmetic is the numpy code's
(F P F' by rows then columns, the Joseph form expanded, the gain by Gaussian elimination with partial
pivoting as LAPACK's gesv), so results agree to rounding (tests/test_filter_reference.py).

Cached on disk like the solvers' kernels (toptag.jit.compiled); `python -m
toptag.solvers.warmup` compiles them ahead (`warm_up`)."""
from __future__ import annotations

import math

import numpy as np

from toptag.jit import compiled, solve_small

# Layout of `q`, the filter's constants, one array so that a call converts one argument, not ten.
Q_POS, Q_YAW, Q_V, Q_B, Q_K, Q_D, Q_A, R_G, R_W, CORR_M, Q_J = range(11)
Q_LEN = 11
_PI = math.pi
_TWO_PI = 2.0 * math.pi


@compiled
def wrap(a):
    """toptag.geometry.wrap_angle of a float: (-pi, pi], the same value as its math.remainder for |a| <=
    3 pi (one subtraction of 2 pi is exact there); beyond, by rounding a / 2 pi."""
    if -3.0 * _PI <= a <= 3.0 * _PI:
        w = a
        if w > _PI:
            w -= _TWO_PI
        elif w < -_PI:
            w += _TWO_PI
    else:
        w = a - np.rint(a / _TWO_PI) * _TWO_PI
    return _PI if w == -_PI else w


@compiled
def predict(x, P, dt, a, q, n_clocks):
    """(x, P) dt seconds on (filter._predict's model; x, P are not changed): constant forward
    acceleration a and yaw rate, midpoint heading; F P F' + Q, the time offsets' walk, the calibration
    biases' decorrelation over the distance driven."""
    n = x.shape[0]
    th, v, w = x[2], x[3], x[4]
    thm = th + 0.5 * w * dt
    c, s = math.cos(thm), math.sin(thm)
    d = v * dt + 0.5 * a * dt * dt
    xn = x.copy()
    xn[0] += d * c
    xn[1] += d * s
    xn[2] = wrap(th + w * dt)
    xn[3] = v + a * dt
    # F is the identity but for its rows x, y, yaw: rows 0, 1, 2 of F P, then columns 0, 1, 2 of (F P) F'
    f02, f03, f04 = -d * s, dt * c, -d * s * 0.5 * dt
    f12, f13, f14 = d * c, dt * s, d * c * 0.5 * dt
    f24 = dt
    Pn = P.copy()
    for j in range(n):
        p0, p1, p2, p3, p4 = P[0, j], P[1, j], P[2, j], P[3, j], P[4, j]
        Pn[0, j] = p0 + f02 * p2 + f03 * p3 + f04 * p4
        Pn[1, j] = p1 + f12 * p2 + f13 * p3 + f14 * p4
        Pn[2, j] = p2 + f24 * p4
    for i in range(n):
        p0, p1, p2, p3, p4 = Pn[i, 0], Pn[i, 1], Pn[i, 2], Pn[i, 3], Pn[i, 4]
        Pn[i, 0] = p0 + f02 * p2 + f03 * p3 + f04 * p4
        Pn[i, 1] = p1 + f12 * p2 + f13 * p3 + f14 * p4
        Pn[i, 2] = p2 + f24 * p4
    Pn[0, 0] += q[Q_POS] * dt
    Pn[1, 1] += q[Q_POS] * dt
    Pn[2, 2] += q[Q_YAW] * dt
    Pn[3, 3] += q[Q_V] * dt
    Pn[5, 5] += q[Q_B] * dt
    Pn[6, 6] += q[Q_K] * dt
    if n > 7:
        no = 7 + n_clocks
        for k in range(7, no):
            Pn[k, k] += q[Q_D] * dt
        corr_m = q[CORR_M]
        if no < n and corr_m != math.inf:  # toptag.fusion.biases.correlation and decorrelate
            rho = math.exp(-abs(v + 0.5 * a * dt) * dt / corr_m)
            if rho < 1.0:
                for k in range(no, n):
                    xn[k] *= rho
                for k in range(no, n):
                    for j in range(n):
                        Pn[k, j] *= rho
                for i in range(n):
                    for k in range(no, n):
                        Pn[i, k] *= rho
                for k in range(no, n):
                    Pn[k, k] += 1.0 - rho * rho
    return xn, Pn


@compiled
def kalman(x, P, PHt, S, nu, freeze_lo, freeze_hi):
    """filter._kalman with PHt = P H' and S = H P H' + R given: the gain (its rows freeze_lo:freeze_hi
    zeroed), x + K nu (yaw wrapped) and the Joseph form expanded, P - K PHt' - PHt K' + K S K',
    symmetrised."""
    n, m = PHt.shape
    # K' = S^-1 PHt': Gaussian elimination with partial pivoting (gesv) on [S | PHt']
    A = S.copy()
    B = PHt.T.copy()
    for col in range(m):
        piv = col
        for r in range(col + 1, m):
            if abs(A[r, col]) > abs(A[piv, col]):
                piv = r
        if piv != col:
            for j in range(m):
                A[col, j], A[piv, j] = A[piv, j], A[col, j]
            for j in range(n):
                B[col, j], B[piv, j] = B[piv, j], B[col, j]
        for r in range(col + 1, m):
            f = A[r, col] / A[col, col]
            for j in range(col + 1, m):
                A[r, j] -= f * A[col, j]
            for j in range(n):
                B[r, j] -= f * B[col, j]
    K = np.empty((n, m))
    for col in range(m - 1, -1, -1):
        for j in range(n):
            t = B[col, j]
            for k in range(col + 1, m):
                t -= A[col, k] * K[j, k]
            K[j, col] = t / A[col, col]
    for i in range(freeze_lo, freeze_hi):
        for k in range(m):
            K[i, k] = 0.0
    xn = x.copy()
    for i in range(n):
        t = 0.0
        for k in range(m):
            t += K[i, k] * nu[k]
        xn[i] += t
    xn[2] = wrap(xn[2])
    KS = _matmul(K, S)
    Pn = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            kp = 0.0
            kpt = 0.0
            ks = 0.0
            for k in range(m):
                kp += K[i, k] * PHt[j, k]
                kpt += K[j, k] * PHt[i, k]
                ks += KS[i, k] * K[j, k]
            Pn[i, j] = P[i, j] - kp - kpt + ks
    for i in range(n):
        for j in range(i + 1, n):
            t = 0.5 * (Pn[i, j] + Pn[j, i])
            Pn[i, j] = t
            Pn[j, i] = t
        Pn[i, i] = 0.5 * (Pn[i, i] + Pn[i, i])
    return xn, Pn


@compiled
def imu_update(x, P, dt, q, gyro, wheel, has_wheel, freeze_lo):
    """The end of an IMU step (filter._yaw_rate_noise then _imu_update): the yaw rate's random step over
    the interval dt, then the gyro (yaw_rate + gyro_bias) and, if has_wheel, the wheel speed ((1 +
    wheel_scale) speed) update; the states from freeze_lo on are not moved (consider states)."""
    n = x.shape[0]
    if dt > 0:
        qw = q[Q_A] * dt
        P = P.copy()
        P[2, 2] += qw * dt * dt / 4
        P[2, 4] += qw * dt / 2
        P[4, 2] += qw * dt / 2
        P[4, 4] += qw
    m = 2 if has_wheel else 1
    PHt = np.empty((n, m))
    S = np.empty((m, m))
    nu = np.empty(m)
    nu[0] = gyro - x[4] - x[5]
    for i in range(n):
        PHt[i, 0] = P[i, 4] + P[i, 5]
    S[0, 0] = PHt[4, 0] + PHt[5, 0] + q[R_G]
    if has_wheel:
        h3, h6 = 1.0 + x[6], x[3]
        nu[1] = wheel - (1.0 + x[6]) * x[3]
        for i in range(n):
            PHt[i, 1] = h3 * P[i, 3] + h6 * P[i, 6]
        S[0, 1] = PHt[4, 1] + PHt[5, 1]
        S[1, 0] = h3 * PHt[3, 0] + h6 * PHt[6, 0]
        S[1, 1] = h3 * PHt[3, 1] + h6 * PHt[6, 1] + q[R_W]
    return kalman(x, P, PHt, S, nu, freeze_lo, n)


@compiled
def imu_step(x, P, dt, a, q, n_clocks, has_u, gyro, wheel, has_wheel, freeze_lo):
    """One whole IMU step without a fix in it: predict over dt, then imu_update (none if not has_u)."""
    xn, Pn = predict(x, P, dt, a, q, n_clocks)
    return _step_end(xn, Pn, dt, q, has_u, gyro, wheel, has_wheel, freeze_lo)


@compiled
def _step_end(x, P, dt, q, has_u, gyro, wheel, has_wheel, freeze_lo):
    """An IMU step's end after its prediction (P, fresh from it, is changed): imu_update, or without IMU
    input the yaw rate's random step alone (filter._yaw_rate_noise)."""
    if has_u:
        return imu_update(x, P, dt, q, gyro, wheel, has_wheel, freeze_lo)
    if dt > 0:
        qw = q[Q_A] * dt
        P[2, 2] += qw * dt * dt / 4
        P[2, 4] += qw * dt / 2
        P[4, 2] += qw * dt / 2
        P[4, 4] += qw
    return x, P


@compiled
def imu_steps(x, P, inputs, q, n_clocks, freeze_lo):
    """imu_step (with IMU input) over a run of steps without a fix among them, one row of `inputs` per step:
    (dt, the step before's forward acceleration, gyro, wheel, has_wheel 1 or 0). Returns the states (m, n) and
    covariances (m, n, n) after each step. A late fix re-runs the ~10 steps after it: one call for them
    instead of ten, whose dispatch and boxing of two arrays each cost about what a step's arithmetic does."""
    m = inputs.shape[0]
    n = x.shape[0]
    Xs = np.empty((m, n))
    Ps = np.empty((m, n, n))
    for k in range(m):
        dt, a, gyro, wheel, has_wheel = inputs[k, 0], inputs[k, 1], inputs[k, 2], inputs[k, 3], inputs[k, 4] != 0.0
        if k == 0:
            xk, Pk = imu_step(x, P, dt, a, q, n_clocks, True, gyro, wheel, has_wheel, freeze_lo)
        else:
            xk, Pk = imu_step(Xs[k - 1], Ps[k - 1], dt, a, q, n_clocks, True, gyro, wheel, has_wheel, freeze_lo)
        Xs[k] = xk
        Ps[k] = Pk
    return Xs, Ps


@compiled
def pose_before(x, delta, accel):
    """toptag.fusion.offsets.pose_before (its doc has the model): (h, H_state 3x5, H_delta)."""
    v, th, w = x[3], x[2], x[4]
    d = v * delta - 0.5 * accel * delta * delta
    dd = v - accel * delta  # d(d)/d(delta)
    phi = th - 0.5 * w * delta
    c, s = math.cos(phi), math.sin(phi)
    h = np.empty(3)
    h[0], h[1], h[2] = x[0] - d * c, x[1] - d * s, wrap(th - w * delta)
    Hs = np.zeros((3, 5))
    Hs[0, 0] = Hs[1, 1] = Hs[2, 2] = 1.0
    Hs[0, 2], Hs[1, 2] = d * s, -d * c
    Hs[0, 3], Hs[1, 3] = -delta * c, -delta * s
    Hs[0, 4], Hs[1, 4] = -0.5 * delta * d * s, 0.5 * delta * d * c
    Hs[2, 4] = -delta
    Hd = np.empty(3)
    Hd[0], Hd[1], Hd[2] = -dd * c - 0.5 * w * d * s, -dd * s + 0.5 * w * d * c, -w
    return h, Hs, Hd


@compiled
def _matmul(A, B):
    """A B in loops: on the filter's few-by-twenty matrices faster than a BLAS call, and summed in one
    fixed order."""
    p, q = A.shape
    r = B.shape[1]
    C = np.zeros((p, r))
    for i in range(p):
        for k in range(r):
            t = 0.0
            for l in range(q):
                t += A[i, l] * B[l, k]
            C[i, k] = t
    return C


@compiled
def _hpht(H, P):
    """(P H', H P H')."""
    PHt = _matmul(P, H.T)
    return PHt, _matmul(H, PHt)


@compiled
def fix_model(x, P, pose, i, accel, j, L):
    """A pose fix's prediction from the state (filter._apply_fix): the pose (x, y, yaw) its RSU's time
    offset x[i] before (toptag.fusion.offsets; i < 0: the state's own pose) and, with the RSU's bias
    block at j (j < 0: none), that pose plus L eps. Returns (nu_pose: the innovation against the pose,
    nu: against the prediction with the bias, H, P H', H P H', H_pose P H_pose' (the same as H P H'
    without a bias block), H_delta (zeros without an offset))."""
    n = x.shape[0]
    H = np.zeros((3, n))
    if i >= 0:
        h, Hs, Hd = pose_before(x, x[i], accel)
        for k in range(3):
            for c in range(5):
                H[k, c] = Hs[k, c]
            H[k, i] = Hd[k]
    else:
        h = x[:3].copy()
        Hd = np.zeros(3)
        H[0, 0] = H[1, 1] = H[2, 2] = 1.0
    nu_pose = pose - h
    nu_pose[2] = wrap(nu_pose[2])
    if j < 0:
        PHt, HPHt = _hpht(H, P)
        return nu_pose, nu_pose, H, PHt, HPHt, HPHt, Hd
    HPHt_pose = _hpht(H, P)[1]
    for k in range(3):
        for c in range(3):
            H[k, j + c] = L[k, c]
    nu = nu_pose.copy()
    for k in range(3):
        t = 0.0
        for c in range(3):
            t += L[k, c] * x[j + c]
        nu[k] -= t
    nu[2] = wrap(nu[2])
    PHt, HPHt = _hpht(H, P)
    return nu_pose, nu, H, PHt, HPHt, HPHt_pose, Hd


@compiled
def _quadratic_form(C, d):
    """(d' C^-1 d, C invertible)."""
    y, ok = solve_small(C, d)
    s = 0.0
    if ok:
        for k in range(d.shape[0]):
            s += d[k] * y[k]
    return s, ok


@compiled
def mahalanobis(S, nu):
    """nu' S^-1 nu (NaN where S is singular)."""
    d2, ok = _quadratic_form(S, nu)
    return d2 if ok else math.nan


@compiled
def capped_d2(HPHt, R, cap, off_var, nu):
    """The tracking gate's d² (filter._gate): the filter's own pose covariance in H P H' capped at cap
    per axis (the offset's share, off_var, is not), plus R."""
    m = nu.shape[0]
    f = np.empty(m)
    for k in range(m):
        sd = math.sqrt(max(HPHt[k, k], 1e-300))
        f[k] = min(1.0, math.sqrt(cap[k] ** 2 + off_var[k]) / sd)
    S = np.empty((m, m))
    for k in range(m):
        for l in range(m):
            S[k, l] = HPHt[k, l] * (f[k] * f[l]) + R[k, l]
    return mahalanobis(S, nu)


# fix_step's scalars in one array `s` (a call converts one argument, not twenty-five: FS_*), and its small
# results in one array `info` (FI_*)
FS_DT, FS_A, FS_I, FS_J, FS_X, FS_Y, FS_YAW, FS_THR, FS_LO, FS_HI, FS_CLOCKS, FS_TAIL, FS_DT2, FS_DT_IMU, FS_HAS_U, \
    FS_GYRO, FS_WHEEL, FS_HAS_WHEEL, FS_FREEZE, FS_DRIFT, FS_W, FS_VIEW, FS_FIRST, FS_VIEW_FIRST, FS_VX, \
    FS_VY = range(26)
FS_LEN = 26
FI_D2, FI_OK, FI_VAR_I, FI_DRIFT_OK, FI_XY = 0, 1, 2, 3, 4
FI_LEN = 6


@compiled
def fix_step(x, P, L, R, Rd, B, prev, q, cap, floors, consts, s):
    """A trusted RSU's fix while tracking, as the filter applies it (filter._advance, _apply_fix, _gate,
    _observe; then, with s[FS_TAIL], the rest of its IMU step, _imu_step), in one call: the prediction to
    the fix, its model, the capped gate's d², and if it passes the Kalman update, with s[FS_DRIFT] the drift
    detector's drift_accumulate (its innovation against the pose before the update, with the fix's own noise
    Rd and bias share B, its record before `prev`), and the prediction to the step's end and its IMU update.
    Returns (XP: the state in row 0 and its covariance below, at the fix or at the step's end; the drift
    record, DA_ layout; info, FI_ layout: d², passed 1 / 0, the RSU's offset variance before the update, the
    drift arithmetic's ok, where the bus was for it). Not passed: XP is empty and the filter takes its Python
    gate (consensus: rare). Paced as in the bus agent each call's first run after a 20 ms sleep is cold: one
    call for what were seven."""
    n = x.shape[0]
    info = np.zeros(FI_LEN)
    dt, a = s[FS_DT], s[FS_A]
    i, j = int(s[FS_I]), int(s[FS_J])
    n_clocks = int(s[FS_CLOCKS])
    if dt > 0:
        x, P = predict(x, P, dt, a, q, n_clocks)
    pose = np.empty(3)
    pose[0], pose[1], pose[2] = s[FS_X], s[FS_Y], s[FS_YAW]
    nu_pose, nu, H, PHt, HPHt, HPHt_pose, Hd = fix_model(x, P, pose, i, a, j, L)
    off_var = np.zeros(3)
    if i >= 0:
        off_var = Hd * Hd * P[i, i]
        info[FI_VAR_I] = P[i, i]
    d2 = capped_d2(HPHt, R, cap, off_var, nu)
    info[FI_D2] = d2
    blk = prev
    if not d2 <= s[FS_THR]:
        return np.empty((0, n)), blk, info
    info[FI_OK] = 1.0
    x, P = kalman(x, P, PHt, HPHt + R, nu, int(s[FS_LO]), int(s[FS_HI]))
    if s[FS_DRIFT] != 0.0:
        xy = np.empty(4)
        xy[0], xy[1], xy[2], xy[3] = s[FS_X] - nu_pose[0], s[FS_Y] - nu_pose[1], s[FS_VX], s[FS_VY]
        info[FI_XY], info[FI_XY + 1] = xy[0], xy[1]
        blk, ok = drift_accumulate(nu_pose, HPHt_pose + Rd, B, Rd, prev, floors, consts, s[FS_W], xy,
                                   s[FS_VIEW] != 0.0, s[FS_FIRST] != 0.0, s[FS_VIEW_FIRST] != 0.0)
        info[FI_DRIFT_OK] = 1.0 if ok else 0.0
    if s[FS_TAIL] != 0.0:
        if s[FS_DT2] > 0:
            x, P = predict(x, P, s[FS_DT2], a, q, n_clocks)
        x, P = _step_end(x, P, s[FS_DT_IMU], q, s[FS_HAS_U] != 0.0, s[FS_GYRO], s[FS_WHEEL], s[FS_HAS_WHEEL] != 0.0,
                         int(s[FS_FREEZE]))
    XP = np.empty((n + 1, n))
    XP[0] = x
    XP[1:] = P
    return XP, blk, info


@compiled
def unmeasured_motion(P, v, th, q, tau):
    """filter._unmeasured_motion: P (not changed) grown by tau seconds of white yaw acceleration (q[Q_A])
    and white jerk (q[Q_J]) at speed v and heading th."""
    Pn = P.copy()
    if tau <= 0:
        return Pn
    qa, qj = q[Q_A], q[Q_J]
    e0, e1 = math.cos(th), math.sin(th)  # along the track
    n0, n1 = -e1, e0  # across it
    t2, t3, t4, t5 = tau ** 2, tau ** 3, tau ** 4, tau ** 5
    Pn[4, 4] += qa * tau
    Pn[2, 2] += qa * t3 / 3
    Pn[2, 4] += qa * t2 / 2
    Pn[4, 2] += qa * t2 / 2
    cn, ce = v * v * qa * t5 / 20, qj * t5 / 20
    Pn[0, 0] += cn * (n0 * n0) + ce * (e0 * e0)
    Pn[0, 1] += cn * (n0 * n1) + ce * (e0 * e1)
    Pn[1, 0] += cn * (n1 * n0) + ce * (e1 * e0)
    Pn[1, 1] += cn * (n1 * n1) + ce * (e1 * e1)
    for k in range(3):
        if k == 0:
            col, f, u0, u1 = 2, v * qa * t4 / 8, n0, n1
        elif k == 1:
            col, f, u0, u1 = 4, v * qa * t3 / 6, n0, n1
        else:
            col, f, u0, u1 = 3, qj * t4 / 8, e0, e1
        c0, c1 = f * u0, f * u1
        Pn[0, col] += c0
        Pn[1, col] += c1
        Pn[col, 0] += c0
        Pn[col, 1] += c1
    Pn[3, 3] += qj * t3 / 3
    return Pn


@compiled
def extrapolate(x, P, dt, a, q, n_clocks):
    """A prediction dt seconds beyond the newest IMU sample (filter.estimate): predict, then unmeasured_motion
    over the same dt, in one call (the bus agent asks for one every 20 ms)."""
    xn, Pn = predict(x, P, dt, a, q, n_clocks)
    return xn, unmeasured_motion(Pn, xn[3], xn[2], q, dt)


@compiled
def _inverse(A):
    """(A^-1, invertible) column by column with solve_small (Gaussian elimination, partial pivoting)."""
    n = A.shape[0]
    out = np.empty((n, n))
    e = np.zeros(n)
    for j in range(n):
        e[:] = 0.0
        e[j] = 1.0
        col, ok = solve_small(A, e)
        if not ok:
            return out, False
        for i in range(n):
            out[i, j] = col[i]
    return out, True


@compiled
def _matvec(A, v):
    n, m = A.shape
    out = np.zeros(n)
    for i in range(n):
        acc = 0.0
        for k in range(m):
            acc += A[i, k] * v[k]
        out[i] = acc
    return out


@compiled
def chi2(d, C):
    """d' C^-1 d, 0 where C is singular (the drift detector's test statistic, toptag.fusion.trust)."""
    s, ok = _quadratic_form(C, d)
    return s if ok else 0.0


@compiled
def sym_sqrt(R):
    """The symmetric square root of a covariance (negative eigenvalues, numerical, taken as 0): numpy's eigh
    and product as toptag.fusion.trust wrote them (_sqrtm), the same LAPACK and BLAS calls without numpy's
    per-call overhead: 12 µs for a 3x3 there, 2 µs here, and the drift detector takes one per fix applied."""
    w, V = np.linalg.eigh(R)
    return (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


_T27 = 134217729.0  # 2^27 + 1: Veltkamp's split of a double into two halves whose products are exact


@compiled
def py_hypot(a, b):
    """math.hypot(a, b) as CPython 3.11 computes it (Modules/mathmodule.c, vector_norm: scaled, squares split
    and summed with their rounding errors kept, one correction step), so that a compiled caller gets the bits
    the filter's Python got; the C library's hypot differs in the last bit for ~0.2 % of arguments."""
    x0, x1 = abs(a), abs(b)
    if math.isinf(x0) or math.isinf(x1):
        return math.inf
    if math.isnan(x0) or math.isnan(x1):
        return math.nan
    mx = max(x0, x1)
    if mx == 0.0:
        return mx
    e = math.frexp(mx)[1]
    if e < -1023:  # subnormal (CPython rescales by DBL_MIN first): far below any distance the filter sees
        return math.hypot(a, b)
    scale = math.ldexp(1.0, -e)
    csum, frac1, frac2, frac3 = 1.0, 0.0, 0.0, 0.0
    for k in range(2):
        x = (x0 if k == 0 else x1) * scale
        t = x * _T27
        hi = t - (t - x)
        lo = x - hi
        x = hi * hi
        old = csum
        csum += x
        frac1 += (old - csum) + x
        x = 2.0 * hi * lo
        old = csum
        csum += x
        frac2 += (old - csum) + x
        frac3 += lo * lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2 + frac3))
    t = h * _T27
    hi = t - (t - h)
    lo = h - hi
    x = -hi * hi
    old = csum
    csum += x
    frac1 += (old - csum) + x
    x = -2.0 * hi * lo
    old = csum
    csum += x
    frac2 += (old - csum) + x
    x = -lo * lo
    old = csum
    csum += x
    frac3 += (old - csum) + x
    x = csum - 1.0 + (frac1 + frac2 + frac3)
    return (h + x / (2.0 * h)) / scale


# drift_accumulate's record as one array (DA_LEN, 3, 3): its 3x3 sums and results, then a block of vectors whose
# rows are b, m and (sw, sw2, stat). One array: boxing each of thirteen results cost more than the arithmetic.
DA_A, DA_A2, DA_BS, DA_Q, DA_H, DA_C, DA_BIAS, DA_VEC = range(8)
DA_LEN = 8


@compiled
def drift_accumulate(nu, S, B, R, prev, floors, consts, w, xy, view, first, view_first):
    """toptag.fusion.trust.DriftRule.accumulate's arithmetic on 3x3 blocks (the same expressions in the
    same order): the clipped innovation, its information added to the faded sums of `prev` (the record
    before, DA_ layout; not read when first, nor its Q and H when view_first), the view-error terms (H
    faded by w and by the distance from where the bus was at the RSU's last fix, xy[2:], NaN: unknown, to
    where it is, xy[:2]), then the mean, its covariance, the statistic and the bias covariance
    (DriftRule.bias_cov). floors: (the clip's floor, bias_floor); consts: (clip_d2, the white share of R
    taken out of S, view_bias_share², view_corr_m). Returns (the record, DA_ layout; ok), ok False where S
    or A is singular (np.linalg.inv raised there)."""
    floor, bias_floor = floors[0], floors[1]
    clip_d2, white_share2, view_share2 = consts[0], consts[1], consts[2]
    out = np.zeros((DA_LEN, 3, 3))
    d2 = chi2(nu, S + floor)
    if d2 > clip_d2:
        nu = nu * math.sqrt(clip_d2 / d2)
    if view:
        S = S - white_share2 * R
    Si, ok = _inverse(S)
    z3 = np.zeros((3, 3))
    if not ok:
        return out, False
    X = _matmul(Si, sym_sqrt(R)) if view else z3
    if first:
        A, A2, b, sw, sw2, Bs = Si, Si, _matvec(Si, nu), 1.0, 1.0, B
    else:
        A, A2, b = w * prev[DA_A] + Si, (w * w) * prev[DA_A2] + Si, w * prev[DA_VEC, 0] + _matvec(Si, nu)
        sw, sw2, Bs = w * prev[DA_VEC, 2, 0] + 1.0, w * w * prev[DA_VEC, 2, 1] + 1.0, w * prev[DA_BS] + B
    Q, H = z3, z3
    if view and view_first:
        Q, H = _matmul(X, X.T.copy()), X
    elif view:
        gap = 0.0 if math.isnan(xy[2]) else py_hypot(xy[0] - xy[2], xy[1] - xy[3])
        Hp = (w * math.exp(-gap / consts[3])) * prev[DA_H]
        cross = _matmul(X, Hp.T.copy())
        Q, H = (w * w) * prev[DA_Q] + _matmul(X, X.T.copy()) + cross + cross.T.copy(), Hp + X
    Ai, ok = _inverse(A)
    if not ok:
        return out, False
    stat = chi2(b, A2)
    m = _matvec(Ai, b)
    C = _matmul(_matmul(Ai, A2), Ai)
    Bc = Bs / sw + bias_floor
    if view:
        Bc = Bc + view_share2 * _matmul(_matmul(Ai, Q), Ai)
    out[DA_A], out[DA_A2], out[DA_BS], out[DA_Q], out[DA_H], out[DA_C], out[DA_BIAS] = A, A2, Bs, Q, H, C, Bc
    out[DA_VEC, 0], out[DA_VEC, 1] = b, m
    out[DA_VEC, 2, 0], out[DA_VEC, 2, 1], out[DA_VEC, 2, 2] = sw, sw2, stat
    return out, True


@compiled
def drift_deviation(m, C, Bc, Ms, Cs, Bcs):
    """toptag.fusion.trust.DriftRule._deviation's arithmetic: one RSU's mean innovation m (covariance C,
    bias covariance Bc) against k others' (rows of Ms, Cs, Bcs): (d = m - their mean, T_d, their mean, the
    noise covariance of d, the bias covariance of d)."""
    k = Ms.shape[0]
    mo = np.zeros(3)
    Cs_sum = np.zeros((3, 3))
    Bs_sum = np.zeros((3, 3))
    for j in range(k):
        mo = mo + Ms[j]
        Cs_sum = Cs_sum + Cs[j]
        Bs_sum = Bs_sum + Bcs[j]
    mo = mo / k
    Cn = C + Cs_sum / (k * k)
    Cb = Bc + Bs_sum / (k * k)
    d = m - mo
    return d, chi2(d, Cn + Cb), mo, Cn, Cb


@compiled
def drift_deviations(blk, blks):
    """drift_deviation of a record against others given as their drift_accumulate records (DA_ layout: m, C and
    the bias covariance in them), its results in one array (d, their mean and (T_d, 0, 0) as the rows of [0],
    the noise covariance [1], the bias covariance [2]): one array in, one out (each array boxed costs)."""
    k = blks.shape[0]
    Ms, Cs, Bcs = np.empty((k, 3)), np.empty((k, 3, 3)), np.empty((k, 3, 3))
    for j in range(k):
        Ms[j], Cs[j], Bcs[j] = blks[j, DA_VEC, 1], blks[j, DA_C], blks[j, DA_BIAS]
    d, T_d, mo, Cn, Cb = drift_deviation(blk[DA_VEC, 1].copy(), blk[DA_C].copy(), blk[DA_BIAS].copy(), Ms, Cs, Bcs)
    out = np.zeros((3, 3, 3))
    out[0, 0], out[0, 1], out[0, 2, 0], out[1], out[2] = d, mo, T_d, Cn, Cb
    return out


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the types the filter calls them with."""
    n = 11
    x = np.zeros(n)
    x[3] = 5.0
    P = np.eye(n)
    q = np.full(Q_LEN, 1e-3)
    q[CORR_M] = 20.0
    x1, P1 = imu_step(x, P, 0.01, 0.1, q, 4, True, 0.01, 5.0, True, n)
    imu_step(x1, P1, 0.01, 0.1, q, 2, False, 0.0, 0.0, False, n)
    Xs, Ps = imu_steps(x1, P1, np.array([[0.01, 0.1, 0.01, 5.0, 1.0], [0.01, 0.1, 0.01, 0.0, 0.0]]), q, 4, n)
    imu_steps(Xs[1], Ps[1], np.zeros((1, 5)), q, 4, n)
    x2, P2 = predict(x1, P1, 0.005, 0.1, q, 4)
    imu_update(x2, P2, 0.005, q, 0.01, 0.0, False, 9)
    H = np.zeros((3, n))
    H[0, 0] = H[1, 1] = H[2, 2] = 1.0
    PHt = P2 @ H.T
    kalman(x2, P2, PHt, H @ PHt + np.eye(3), np.zeros(3), 7, n)
    unmeasured_motion(P2, 5.0, 0.3, q, 0.004)
    extrapolate(x2, P2, 0.004, 0.1, q, 4)
    pose = np.array([0.1, 0.2, 0.3])
    L = np.eye(3) * 0.01
    for i, j in ((8, n - 3), (8, -1), (-1, -1)):
        nu_pose, nu, H, PHt, HPHt, HPHt_pose, Hd = fix_model(x2, P2, pose, i, 0.1, j, L)
        capped_d2(HPHt, np.eye(3), np.ones(3), np.zeros(3), nu)
        mahalanobis(HPHt + np.eye(3), nu)
    pose_before(x2, 0.01, 0.1)
    e3, z3 = np.eye(3), np.zeros((3, 3))
    prev, floors, consts = np.zeros((DA_LEN, 3, 3)), np.stack((e3, e3)), np.array([100.0, 0.5, 0.5, 6.0])
    for view, first in ((True, True), (True, False), (False, True), (False, False)):
        drift_accumulate(pose, e3, z3, e3, prev, floors, consts, 0.9, np.zeros(4), view, first, first)
    drift_deviation(pose, e3, e3, np.zeros((2, 3)), np.zeros((2, 3, 3)), np.zeros((2, 3, 3)))
    drift_deviations(prev, np.stack((prev, prev)))
    for tail in (0.0, 1.0):
        for i, j, has_u in ((8, n - 3, 1.0), (8, -1, 0.0), (-1, -1, 1.0)):
            sc = np.zeros(FS_LEN)
            sc[[FS_DT, FS_I, FS_J, FS_THR, FS_LO, FS_HI, FS_CLOCKS, FS_TAIL, FS_DT2, FS_DT_IMU, FS_HAS_U, FS_FREEZE,
                FS_DRIFT, FS_VIEW, FS_FIRST, FS_VIEW_FIRST]] = (0.004, i, j, 1e9, n, n, 4, tail, 0.006, 0.01, has_u, n,
                                                                 1.0, 1.0, 1.0, 1.0)
            fix_step(x2, P2, L, e3, e3, z3, prev, q, np.ones(3), floors, consts, sc)
    sym_sqrt(e3)


__all__ = ["Q_LEN", "capped_d2", "extrapolate", "fix_model", "fix_step", "imu_step", "imu_steps", "imu_update",
           "kalman", "mahalanobis", "pose_before", "predict", "py_hypot", "sym_sqrt", "unmeasured_motion", "warm_up",
           "wrap"]
