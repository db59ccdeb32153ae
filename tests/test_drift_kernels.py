"""The drift detector's compiled arithmetic (toptag.fusion.kernels.drift_accumulate, drift_deviation) gives
what its numpy expressions gave (kept here as they stood in toptag.fusion.trust before it was compiled),
to rounding, on random innovations with and without the view-dependent error and the calibration bias."""
import math
import sys

import numpy as np
import pytest

from toptag.fusion.trust import MAX_VIEW_SHARE_OF_VARIANCE, DriftRule, RsuRecord, _sqrtm
from toptag.units import s_from_ns

pytestmark = pytest.mark.unit


def _chi2(d: np.ndarray, C: np.ndarray) -> float:  # the numpy reference of kernels.chi2
    try:
        return float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return 0.0


def numpy_accumulate(rule: DriftRule, rec: RsuRecord, t_ns, nu, S, B=None, R=None, xy=None):
    B = np.zeros((3, 3)) if B is None else B
    d2 = _chi2(nu, S + rule._floor)
    if d2 > rule.clip_d2:
        nu = nu * math.sqrt(rule.clip_d2 / d2)
    view = rule.view_bias_share > 0 and R is not None and xy is not None
    if view:
        S = S - min(rule.view_bias_share ** 2, MAX_VIEW_SHARE_OF_VARIANCE) * R
    Si = np.linalg.inv(S)
    X = Si @ _sqrtm(R) if view else None
    if rec.A is None:
        A, A2, b, sw, sw2, Bs = Si, Si, Si @ nu, 1.0, 1.0, B
    else:
        w = math.exp(-s_from_ns(max(0, t_ns - rec.last_t)) / rule.window_s)
        A, A2, b = w * rec.A + Si, (w * w) * rec.A2 + Si, w * rec.b + Si @ nu
        sw, sw2, Bs = w * rec.sums[0] + 1.0, w * w * rec.sums[1] + 1.0, w * rec.Bs + B
    Q = H = None
    if view and (rec.A is None or rec.H is None):
        Q, H = X @ X.T, X
    elif view:
        gap = 0.0 if rec.view_xy is None else math.hypot(xy[0] - rec.view_xy[0], xy[1] - rec.view_xy[1])
        Hp = (w * math.exp(-gap / rule.view_corr_m)) * rec.H
        cross = X @ Hp.T
        Q, H = (w * w) * rec.Q + X @ X.T + cross + cross.T, Hp + X
    Ai = np.linalg.inv(A)
    bias = Bs / sw + rule.bias_floor
    if Q is not None:
        bias = bias + rule.view_bias_share ** 2 * (Ai @ Q @ Ai)
    return dict(A=A, A2=A2, b=b, stat=_chi2(b, A2), n_eff=sw * sw / sw2, m=Ai @ b, C=Ai @ A2 @ Ai, Bs=Bs, Q=Q, H=H,
                bias_c=bias)


def _rule(view_share: float) -> DriftRule:
    return DriftRule(5.0, 21.1, 6.25, 0.03, math.radians(0.1), 2.0, 100.0, 10.0, 0.01, 2,
                     np.diag([0.005 ** 2, 0.005 ** 2, math.radians(0.02) ** 2]), 3.0, 120.0, 0.0, 0.5, math.inf,
                     view_share, 6.35)


def _cov(rng, pos_sigma, yaw_sigma):
    R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    sig = np.array([pos_sigma, pos_sigma, yaw_sigma]) * rng.uniform(0.3, 3.0, 3)
    return (R * sig ** 2) @ R.T


def _close(a, b, what):
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(np.abs(b).max(), 1e-300)
    assert np.abs(a - b).max() <= 1e-9 * scale, what


@pytest.mark.parametrize("view_share", [0.0, 0.76])
def test_compiled_drift_arithmetic_matches_numpy(view_share):
    rng = np.random.default_rng(7)
    rule = _rule(view_share)
    recs = {r: RsuRecord(last_t=0, clock_known=True) for r in ("a", "b", "c", "d")}
    t = 10 ** 9
    xy = np.array([0.0, 0.0])
    for k in range(400):
        rsu = "abcd"[rng.integers(4)]
        t += int(rng.integers(1, 60_000_000))
        xy = xy + rng.normal(0.0, 0.3, 2)
        R = _cov(rng, 0.02, 0.004)
        S = R + _cov(rng, 0.01, 0.002)
        B = _cov(rng, 0.01, 0.001) if k % 3 else None
        nu = rng.multivariate_normal(np.zeros(3), S) * (30.0 if k % 50 == 7 else 1.0)  # some clipped
        if rsu == "d":
            nu = nu + np.array([0.05, -0.03, 0.002])  # one RSU off
        rec = recs[rsu]
        want = numpy_accumulate(rule, rec, t, nu, S, B, R, tuple(xy))
        got = rule.accumulate(rec, t, nu, S, B, R, tuple(xy))
        for name, v in want.items():
            if v is None:
                assert getattr(got, name) is None, name
            elif isinstance(v, float):
                assert getattr(got, name) == pytest.approx(v, rel=1e-9), name
            else:
                _close(getattr(got, name), v, name)
        recs[rsu] = got
        ready = [r for r, x in recs.items() if x.m is not None]
        if len(ready) >= 3:  # the deviation from the others, as _deviation computed it in numpy
            others = [recs[r] for r in ready if r != rsu]
            kk = len(others)
            mo = sum(o.m for o in others) / kk
            Cn = got.C + sum(o.C for o in others) / (kk * kk)
            Cb = rule.bias_cov(got) + sum(rule.bias_cov(o) for o in others) / (kk * kk)
            d, T_d, mo_got, n, current = rule._deviation(got, others, t)
            _close(d, got.m - mo, "d")
            _close(mo_got, mo, "others' mean")
            _close(current[1], Cn, "noise covariance")
            assert T_d == pytest.approx(_chi2(got.m - mo, Cn + Cb), rel=1e-9)
            recs[rsu] = rule.decide(recs, rsu, t)
    assert all(recs[r].deviation is not None for r in "abcd")  # every RSU was compared with the others


def test_compiled_hypot_is_pythons():
    """drift_accumulate's distance between views takes kernels.py_hypot: CPython 3.11's math.hypot, bit for bit
    there (the C library's hypot, numba's math.hypot, differs in the last bit for ~0.2 % of arguments), so the
    detector's numbers are those its Python computed; within an ulp on another CPython."""
    from toptag.fusion.kernels import py_hypot
    rng = np.random.default_rng(3)
    a = rng.normal(size=20_000) * 10.0 ** rng.uniform(-6, 3, 20_000)
    b = rng.normal(size=20_000) * 10.0 ** rng.uniform(-6, 3, 20_000)
    b[::7] = a[::7] * 1e-9
    b[::11] = 0.0
    exact = sys.version_info[:2] == (3, 11)
    for x, y in zip(a.tolist(), b.tolist()):
        want, got = math.hypot(x, y), py_hypot(x, y)
        assert got == want if exact else abs(got - want) <= math.ulp(want), (x, y)
    assert py_hypot(0.0, -0.0) == 0.0 and py_hypot(-3.0, 4.0) == 5.0
    assert py_hypot(math.inf, math.nan) == math.inf and math.isnan(py_hypot(1.0, math.nan))
