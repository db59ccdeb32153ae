"""`compiled`: numba's njit as toptag's kernels use it (the solvers', toptag/solvers/kernels.py, the lens
model's, toptag/lens.py, and the bus filter's, toptag/fusion/kernels.py), and `solve_small`, the small
dense solve both the solvers and the filter use, in a module of their own so that the filter's kernels do
not import the solvers (and scipy) with them. `python -m
toptag.solvers.warmup` fills the cache of all."""
from __future__ import annotations

import math
import os
import tempfile

import numba
from numba import njit


def compiled(f):
    """numba's njit with numpy's float semantics (x / 0 is inf or NaN, as the numpy code gave; Python's
    would raise), the machine code cached on disk: beside the kernel's file, else in numba's user-wide cache
    directory, else (a read-only installation and home, such as a read-only container) in the
    temporary directory; where none is writable, compiled in every process."""
    try:
        return njit(cache=True, error_model="numpy")(f)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        pass
    if not numba.config.CACHE_DIR:
        numba.config.CACHE_DIR = os.path.join(tempfile.gettempdir(), "toptag-numba-cache")
        try:
            return njit(cache=True, error_model="numpy")(f)
        except RuntimeError:
            pass
    return njit(error_model="numpy")(f)


@compiled
def solve_small(A, b):
    """x with A x = b (n ≤ a few) by Gaussian elimination with partial pivoting; (x, solvable)."""
    n = len(b)
    a = A.copy()
    x = b.copy()
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if not (a[p, k] != 0.0 and math.isfinite(a[p, k])):
            return x, False
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k, n):
                a[i, j] -= f * a[k, j]
            x[i] -= f * x[k]
    for k in range(n - 1, -1, -1):
        acc = x[k]
        for j in range(k + 1, n):
            acc -= a[k, j] * x[j]
        x[k] = acc / a[k, k]
    return x, True
