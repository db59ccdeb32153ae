"""A small Levenberg–Marquardt for the solvers' 3- to 6-parameter problems, one at a time or a batch
of them at once.

scipy.optimize.least_squares costs about a millisecond of set-up per call; these problems have at
most a few dozen residuals, so a plain numpy loop with the analytic Jacobian is several times faster,
and an RSU solves every frame. Near the minimum, a step whose promised decrease (the linear model's)
is below PROMISED_RTOL of the cost ends the fit where it is: the pose is then within about 2e-3 of its
sigma of the minimum for these problems (whose cost is their residual's chi-square), and the model's
last evaluation, which the caller gets back (`extra`), is the one at the pose returned. Trying that
step would cost one more evaluation, most of a fit's remaining time, for nothing the noise would show.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

# The stopping rules, shared with the compiled level fit (kernels.fit_level, the same algorithm).
from toptag.solvers.kernels import COST_RTOL, LAMBDA0, PROMISED_RTOL

ResidualFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class LmResult:
    theta: np.ndarray
    converged: bool
    r: np.ndarray  # residuals and Jacobian at theta
    J: np.ndarray


def levenberg_marquardt(fun: ResidualFn, theta0, max_iter: int = 60, step_tol: float = 1e-11) -> LmResult:
    """Minimise |r(theta)|². `fun` returns (r, J); a non-finite r marks an invalid theta (for example
    a pose that puts corners behind a camera) and makes the step be refused."""

    def normal(thetas):
        r, J = fun(thetas[0])
        return np.array([r @ r]), (J.T @ J)[None], (J.T @ r)[None], (r[None], J[None])

    res = levenberg_marquardt_batch(normal, np.asarray(theta0, dtype=float)[None], max_iter, step_tol)
    return LmResult(res.theta[0], bool(res.converged[0]), res.extra[0][0], res.extra[1][0])


@dataclass
class LmBatch:
    """levenberg_marquardt_batch's result: one row per problem."""

    theta: np.ndarray  # (B, n)
    converged: np.ndarray  # (B,) bool
    extra: tuple  # what fun gave besides the normal equations, at each problem's theta


# thetas (B, n) -> (|r|² (B,), JᵀJ (B, n, n), Jᵀr (B, n), extra) of each problem's residuals r and
# Jacobian J; extra: a tuple of arrays with the problems along their first axis (anything the caller
# wants back at the solution, such as the model's residuals).
NormalFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, tuple]]


def levenberg_marquardt_batch(fun: NormalFn, theta0, max_iter: int = 60, step_tol: float = 1e-11) -> LmBatch:
    """Minimise B independent least-squares problems of n parameters at once, each step for step as alone:
    `fun` gives each one's normal equations at thetas (B, n), a non-finite cost marking that theta
    invalid (for example a pose that puts corners behind a camera), which makes the step be refused.
    The matrix work of all B is one numpy call each; the per-problem bookkeeping is plain Python (a
    handful of floats, cheaper than numpy calls on them)."""
    theta = np.array(theta0, dtype=float)
    n_b, n = theta.shape
    cost_v, A, g, extra = fun(theta)
    if n_b > 1:  # rows are replaced one by one below (a lone problem's arrays are only ever replaced whole)
        A, g, extra = A.copy(), g.copy(), tuple(e.copy() for e in extra)
    cost = cost_v.tolist()
    active = [math.isfinite(x) for x in cost]
    converged = [False] * n_b
    lam = [LAMBDA0] * n_b
    eye = np.eye(n)
    for _ in range(max_iter):
        if not any(active):
            break
        d = A.diagonal(0, 1, 2)
        # Marquardt scaling, with a floor so that a parameter the data does not see stays put.
        damping = np.array(lam)[:, None] * (d + 1e-12 * (d.sum(axis=1, keepdims=True) + 1.0))
        step, solved = _solve_batch(A + damping[:, :, None] * eye, -g)
        # The decrease the step promises, -g·step - step·A·step / 2, is within a factor 2 of -g·step / 2
        # for any damping (and equal to it undamped).
        promised = (-0.5 * (g * step).sum(axis=1)).tolist()
        steps, thetas = step.tolist(), theta.tolist()
        tried = []
        for b in range(n_b):
            if not active[b]:
                continue
            if not solved[b]:
                lam[b] *= 10.0
            elif lam[b] <= LAMBDA0 and promised[b] <= PROMISED_RTOL * cost[b]:
                converged[b], active[b] = True, False  # at the minimum, as far as any noise could tell
            else:
                tried.append(b)
        if not tried:
            continue
        small = [max(map(abs, steps[b])) < step_tol * (1.0 + max(map(abs, thetas[b]))) for b in range(n_b)]
        if len(tried) < n_b:
            idle = np.ones(n_b, dtype=bool)
            idle[tried] = False
            step[idle] = 0.0
        trial = theta + step
        cost_new_v, A_new, g_new, extra_new = fun(trial)
        cost_new = cost_new_v.tolist()
        better = [b for b in tried if cost_new[b] <= cost[b]]  # False for a non-finite cost
        if n_b == 1:
            if better:
                theta, A, g, extra = trial, A_new, g_new, extra_new
        elif len(better) == n_b:  # every problem moves: take the new arrays whole
            theta, A, g, extra = trial, A_new.copy(), g_new.copy(), tuple(e.copy() for e in extra_new)
        else:
            for b in better:
                theta[b], A[b], g[b] = trial[b], A_new[b], g_new[b]
                for e, e_new in zip(extra, extra_new):
                    e[b] = e_new[b]
        for b in tried:
            c_new, c_old = cost_new[b], cost[b]
            if c_new <= c_old:
                cost[b] = c_new
                lam[b] = max(lam[b] * 0.1, 1e-12)
                if small[b] or c_old - c_new <= COST_RTOL * c_old or c_new == 0.0:
                    converged[b], active[b] = True, False
            elif math.isfinite(c_new) and (c_new - c_old <= COST_RTOL * c_old or small[b]):
                # Rounding noise at the minimum: no step can decrease the cost any more.
                converged[b], active[b] = True, False
            else:
                lam[b] *= 10.0
                if lam[b] > 1e12:
                    active[b] = False
    return LmBatch(theta, np.array(converged), extra)


def _solve_batch(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, list[bool]]:
    """x (B, n) with A x = b per problem, and which problems' A was solvable."""
    try:
        return np.linalg.solve(A, b[..., None])[..., 0], [True] * len(A)
    except np.linalg.LinAlgError:
        x, ok = np.zeros_like(b), [True] * len(A)
        for i in range(len(A)):
            try:
                x[i] = np.linalg.solve(A[i], b[i])
            except np.linalg.LinAlgError:
                ok[i] = False
        return x, ok
