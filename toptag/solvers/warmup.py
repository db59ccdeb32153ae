"""`warm_up`: compile the solvers' numba kernels (toptag/solvers/kernels.py), or load them from numba's
on-disk cache, before the first frame needs them; `warm_up_all`: those and the bus filter's
(toptag/fusion/kernels.py, which the bus agent loads at its start).

A process that solves without a cache compiles every kernel on its first solve (about 20 s of CPU on
the 2-core AMD EPYC of README's figures, 2026-11-23). The project's setup (`make setup`), the test
session and the Docker image build call warm_up_all once, so that RSU and bus processes find the cache;
a process with the cache loads the kernels in a few tenths of a second.

    python -m toptag.solvers.warmup      # prints the seconds it took
"""
from __future__ import annotations

import json
import math
import time
from importlib import resources

import numpy as np

from toptag import lens
from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.geometry import vehicle_to_world
from toptag.vehicle import Vehicle


def warm_up() -> float:
    """Solve a few synthetic frames with every solver and path that reaches a kernel (two tags, a
    garbled one that the outlier test screens, one tag, uncertain camera calibration), and undistort with
    the lens kernels (every detected tag's corners are). Returns the wall seconds it took."""
    from toptag.solvers.api import METHODS, solve

    t0 = time.perf_counter()
    lens.warm_up()
    cam = Camera.looking_at("warm-up", (-10.0, -10.0, 8.0), math.pi / 4, math.radians(40.0), math.radians(70.0),
                            960, 720)
    text = resources.files("toptag.data").joinpath("bus_double.json").read_text()
    bus = Vehicle.from_dict(json.loads(text), source="bundled vehicle bus_double")
    rng = np.random.default_rng(0)
    obs = [TagObservation(t, cam.project(vehicle_to_world(bus.tag_corners(t), 0.0, 0.0, 0.3, bus.height),
                                         distort=False) + rng.normal(0.0, 0.1, (4, 2)), cam)
           for t in bus.tag_ids]
    garbled = [obs[0], TagObservation(obs[1].tag_id, obs[1].corners + [[4.0, -3.0], [0, 0], [0, 0], [0, 0]], cam)]
    for method in METHODS:
        for frame in (obs, garbled, obs[:1]):
            solve(bus, frame, method, weighting="principled")
    solve(bus, obs, "level", weighting="principled", calib_rot_sigma=1e-3, calib_trans_sigma=0.02)
    return time.perf_counter() - t0


def warm_up_all() -> float:
    """warm_up, and the bus filter's kernels run once (toptag.fusion.kernels.warm_up): what the project's
    setup, the test session and the image build fill the cache with. Returns the wall seconds it took."""
    from toptag.fusion import kernels as fusion_kernels

    t0 = time.perf_counter()
    warm_up()
    fusion_kernels.warm_up()
    return time.perf_counter() - t0


def compiled_here() -> int:
    """How many kernel specialisations this process compiled, rather than loaded from numba's cache."""
    from numba.core.registry import CPUDispatcher

    from toptag.fusion import kernels as fusion_kernels
    from toptag.solvers import kernels

    return sum(sum(d.stats.cache_misses.values()) for m in (kernels, fusion_kernels, lens) for d in vars(m).values()
               if isinstance(d, CPUDispatcher))


if __name__ == "__main__":
    seconds = warm_up_all()
    print(f"toptag solvers' and filter's kernels ready in {seconds:.2f} s ({compiled_here()} compiled, the rest "
          "from the cache)")
