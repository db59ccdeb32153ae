"""`compiled`: numba's njit as toptag's kernels use it (the solvers', toptag/solvers/kernels.py, and the bus
filter's, toptag/fusion/kernels.py), in a module of its own so that the filter's kernels do not import the
solvers (and scipy) with it. `python -m toptag.solvers.warmup` fills the cache of both."""
from __future__ import annotations

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
