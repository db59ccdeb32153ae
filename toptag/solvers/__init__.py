"""Vehicle pose from roof-tag corners: the paper's Bas., H.Opt. and S.Opt. (SPEC.md) and the level-roof
solver ("level": x, y, yaw and roof height with its prior, edge-line corner noise, garbled tags weighed
down, optionally estimating every camera's extrinsic correction), multi-tag and multi-camera, with
honest covariances, an outlier-tag test, plausibility checks and the Cramér–Rao bound.

    from toptag.solvers import solve, position_crlb
    sol = solve(vehicle, observations, "level")  # or "sopt", weighting="principled"
    sol = solve(vehicle, two_rsus, "level", calib_rot_sigma=math.radians(0.05), calib_trans_sigma=0.02)
    if sol.ok: sol.x, sol.y, sol.yaw, sol.covariance
"""
from toptag.solvers.api import METHODS, canonical_method, solve
from toptag.solvers.common import SIGMA_H_DEFAULT, PoseSolution
from toptag.solvers.crlb import Crlb, position_crlb
from toptag.solvers.level import DETECTOR_BIAS, NO_BIAS, TURN_RATIO, DetectorBias
from toptag.solvers.robust import Limits

__all__ = ["solve", "PoseSolution", "Limits", "position_crlb", "Crlb", "METHODS", "canonical_method",
           "SIGMA_H_DEFAULT", "TURN_RATIO", "DetectorBias", "DETECTOR_BIAS", "NO_BIAS"]
