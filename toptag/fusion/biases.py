"""The calibration bias of an RSU's fixes, as the bus filter models it.

A camera's calibration error (its pose off the surveyed one) moves every fix it makes by much the
same amount: a bias, not noise. Each fix states the covariance of that bias (`Fix.calib_cov`, what
the camera file's calibration covariance adds to the fix); taken as white noise it averages down with
every fix, and a filter fusing four biased RSUs so is over-confident (NEES 12.9 on the fusion study
with cameras off by 0.05 deg / 2 cm, where 3 is right).

So the filter keeps each such RSU's bias in its state (an augmented EKF, like the time offsets of
toptag.fusion.offsets), in normalised form: eps, 3 entries with prior N(0, I), and a fix k of that RSU
measures

    z_k = pose(t_k - delta) + L_k eps + n_k,    L_k L_k' = calib_cov_k,    n_k ~ N(0, cov_k - calib_cov_k)

(L_k the symmetric square root). The 3-dof bias is only a summary of a 6-dof camera error seen
through the bus's position in the image: how it moves a fix changes as the bus crosses the view (on
the fusion study about half of it varies over one pass). So eps is a first-order Gauss-Markov
process over the distance the bus drives: eps <- rho eps + sqrt(1 - rho^2) w, rho = exp(-|v| dt /
corr_m). Standing still, the bias stands still; over corr_m metres it is largely a new one (the
filter's prediction step does it: toptag.fusion.kernels.predict).

`FilterConfig.calib_bias`: "estimate" (the states are updated by the fixes: the filter learns the
RSUs' relative biases), "consider" (Schmidt: they are carried in the covariance, never updated:
consistent, and nothing is learnt), or "noise" (the calibration share stays white noise, as before).

Pure: no I/O."""
from __future__ import annotations

import numpy as np

BIAS_DIM = 3


def bias_root(calib_cov: np.ndarray) -> np.ndarray:
    """L with L L' = calib_cov (symmetric square root; negative eigenvalues, numerical, taken as 0)."""
    w, V = np.linalg.eigh(0.5 * (calib_cov + calib_cov.T))
    return (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


__all__ = ["BIAS_DIM", "bias_root"]
