"""A small Levenberg–Marquardt for the solvers' 3- and 6-parameter problems.

scipy.optimize.least_squares costs about a millisecond of set-up per call; these problems have at
most a few dozen residuals, so a plain numpy loop with the analytic Jacobian is several times faster,
and an RSU solves every frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

COST_RTOL = 1e-10  # relative cost change that is rounding or negligible (~1e-5 sigma), not progress

ResidualFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class LmResult:
    theta: np.ndarray
    r: np.ndarray
    J: np.ndarray
    cost: float  # sum of squared residuals
    iterations: int
    converged: bool


def levenberg_marquardt(fun: ResidualFn, theta0, max_iter: int = 60, step_tol: float = 1e-11) -> LmResult:
    """Minimise |r(theta)|². `fun` returns (r, J); a non-finite r marks an invalid theta (for example
    a pose that puts corners behind a camera) and makes the step be refused."""
    theta = np.asarray(theta0, dtype=float).copy()
    r, J = fun(theta)
    cost = float(r @ r)
    if not np.isfinite(cost):
        return LmResult(theta, r, J, cost, 0, False)
    lam = 1e-4
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        A = J.T @ J
        g = J.T @ r
        # Marquardt scaling, with a floor so that a parameter the data does not see stays put.
        d = np.diag(A) + 1e-12 * (np.trace(A) + 1.0)
        try:
            step = np.linalg.solve(A + lam * np.diag(d), -g)
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        trial = theta + step
        r_new, J_new = fun(trial)
        cost_new = float(r_new @ r_new)
        small_step = np.max(np.abs(step)) < step_tol * (1.0 + np.max(np.abs(theta)))
        if np.isfinite(cost_new) and cost_new <= cost:
            stalled = cost - cost_new <= COST_RTOL * cost
            theta, r, J, cost = trial, r_new, J_new, cost_new
            lam = max(lam * 0.1, 1e-12)
            if small_step or stalled or cost == 0.0:
                converged = True
                break
        elif np.isfinite(cost_new) and (cost_new - cost <= COST_RTOL * cost or small_step):
            # Rounding noise at the minimum: no step can decrease the cost any more.
            converged = True
            break
        else:
            lam *= 10.0
            if lam > 1e12:
                converged = False
                break
    return LmResult(theta, r, J, cost, it, converged)
