"""Vehicle pose from roof-tag corners: the paper's Bas., H.Opt. and S.Opt. (SPEC.md), multi-tag and
multi-camera, with honest covariances, an outlier-tag test, plausibility checks and the Cramér–Rao bound.

    from toptag.solvers import solve, position_crlb
    sol = solve(vehicle, observations, "sopt", weighting="principled")
    if sol.ok: sol.x, sol.y, sol.yaw, sol.covariance
"""
from toptag.solvers.api import METHODS, canonical_method, solve
from toptag.solvers.common import SIGMA_H_DEFAULT, PoseSolution
from toptag.solvers.crlb import Crlb, position_crlb
from toptag.solvers.robust import Limits

__all__ = ["solve", "PoseSolution", "Limits", "position_crlb", "Crlb", "METHODS", "canonical_method",
           "SIGMA_H_DEFAULT"]
