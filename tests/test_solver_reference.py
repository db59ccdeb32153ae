"""Every solver against its own outputs as captured before the solvers were made faster (main at
1212831, tests/data/solver_reference.json): the same poses, covariances, dropped tags and verdicts
within a small fraction of each pose's own uncertainty (a faster route to the optimum may stop a hair
elsewhere; it must not change what the RSU reports)."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from sim.scene import bundled_vehicle, rsu_camera
from toptag.detection import TagObservation
from toptag.geometry import wrap_angle
from toptag.solvers import solve

pytestmark = pytest.mark.unit

REFERENCE = json.loads((Path(__file__).parent / "data" / "solver_reference.json").read_text())
CAMERAS = {"rsu-sw": rsu_camera("sw", 960, 720), "rsu-se": rsu_camera("se", 960, 720)}
BUS = bundled_vehicle(REFERENCE["vehicle"])
TOL = 0.02  # of the reference's own sigma


def _observations(case):
    return [TagObservation(o["tag"], np.asarray(o["corners"], float), CAMERAS[o["camera"]])
            for o in case["observations"]]


@pytest.mark.parametrize("method", ["level", "hopt", "sopt", "bas"])
def test_solvers_reproduce_their_reference_outputs(method):
    assert {c["camera"] for case in REFERENCE["cases"] for c in case["observations"]} <= set(CAMERAS)
    for i, case in enumerate(REFERENCE["cases"]):
        ref = case["solutions"][method]
        got = solve(BUS, _observations(case), method=method, weighting="principled", **case["kwargs"]).to_dict()
        where = f"case {i} ({case['set']}, {case['variant']}), {method}"
        assert got["ok"] == ref["ok"], (where, got["error"], ref["error"])
        assert sorted((d["tag"], d["camera"]) for d in got["dropped_tags"]) == \
            sorted((d["tag"], d["camera"]) for d in ref["dropped_tags"]), where
        if not ref["ok"]:
            continue
        assert got["ambiguous"] == ref["ambiguous"] and got["tags"] == ref["tags"], where
        C = np.asarray(ref["covariance"], float)
        s = np.sqrt(np.diag(C))
        assert abs(got["x"] - ref["x"]) <= TOL * s[0] and abs(got["y"] - ref["y"]) <= TOL * s[1], where
        assert abs(wrap_angle(got["yaw"] - ref["yaw"])) <= TOL * s[2], where
        assert abs(got["z"] - ref["z"]) <= max(1e-6, 0.02 * abs(ref["z"] - BUS.height) + 1e-4), where
        G = np.asarray(got["covariance"], float)
        assert np.all(np.abs(G - C) <= 0.02 * np.outer(s, s)), (where, G, C)
        assert got["sigma_px"] == pytest.approx(ref["sigma_px"], rel=0.02), where
        assert got["rms_px"] == pytest.approx(ref["rms_px"], rel=0.02, abs=1e-4), where
        assert got["n_corners"] == ref["n_corners"] and math.isfinite(got["x"]), where
