"""`toptag eval paper`: a small real run (rendered images, the RSU pipeline, every solver, both cores),
the shape of results.json, the figures, and the study's own models (bound, edge noise). The level-roof
solver the study built is the core's method "level" (tests/test_solvers.py)."""
import io
import json
import math

import cv2
import numpy as np
import pytest

from sim.image_model import ImageModel
from sim.scene import bundled_vehicle, rsu_camera
from sim.studies import paper
from sim.studies.paper_models import (
    EdgeNoise,
    edge_components,
    measure_noise,
    pose_bound,
)
from toptag.detection import TagObservation
from toptag.geometry import vehicle_to_world
from toptag.progress import Progress
from toptag.solvers import SIGMA_H_DEFAULT, Limits, position_crlb, solve
from toptag.solvers.level import edge_whitener

# One worker for the module: under pytest-xdist each worker would run small_run (~30 s) for itself.
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("study_paper")]

SAMPLES = 16  # one per whole-metre bin, 5..20 m


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    err = io.StringIO()
    import contextlib

    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()) as stdout:
        code = paper.main(["--out", str(out), "--samples", str(SAMPLES), "--seed", "3",
                           "--cases", "low_flat,low_bounce", "--workers", "2", "--calibration-pool", "2"])
    assert code == 0
    return out, json.loads((out / "results.json").read_text()), err.getvalue(), stdout.getvalue()


def test_results_json_has_the_issue_shape(small_run):
    _, r, _, _ = small_run
    assert set(r["cases"]) == {"low_flat", "low_bounce"}
    assert r["image_model"]["describe"] and r["image_model"]["noise_sigma"] == ImageModel().noise_sigma  # the default
    for case in ("low_flat", "low_bounce"):
        sec = r["cases"][case]
        assert {"bas", "hopt", "sopt", "sopt_principled", "sopt_level", "sopt_2cam", "sopt_level_2cam"} <= set(sec)
        for solver, by_d in sec.items():
            assert list(by_d) == [str(d) for d in range(5, 21)]
            for d, row in by_d.items():
                assert {"n", "detected", "pos_rms_m", "pos_max_m", "yaw_rms_deg"} <= set(row)
                assert row["n"] == SAMPLES // 16
        crlb = r["crlb"][case]
        assert list(crlb) == [str(d) for d in range(5, 21)]
        for row in crlb.values():
            assert 0.0 < row["sigma_px"] < 0.5 and row["edge_offset_px"] > 0.0 and row["edge_turn_px"] > 0.0
            # real-camera corner noise (calibrated image model): the bound is 2.7 cm at 20 m (low_bounce)
            assert 0.0 < row["pos_rms_m"] < 0.08 and row["pos_rms_2cam_m"] <= row["pos_rms_m"] * 1.0001
            assert row["pos_rms_calib_m"] > row["pos_rms_m"]  # calibration error only adds
    assert set(r["calibration"]) == {"low_flat", "low_bounce"}
    # the calibration case uses the errors the on-site procedure left, not an assumed 0.05 deg / 2 cm
    proc = r["calibration_procedure"]
    assert proc["calibrations_per_camera"] == 2 and set(proc["roof_mapping_rms_m"]) == {"rsu-sw", "rsu-se", "rsu-nw"}
    assert all(0.001 < v < 0.05 for v in proc["roof_mapping_rms_m"].values())
    assert "toptag calibrate extrinsics" in r["calibration_error"]
    assert r["samples_per_case"] == SAMPLES and "eval paper" in r["command"]


def test_detection_is_the_rsus_and_complete(small_run):
    _, r, _, _ = small_run
    for case, det in r["detection"].items():
        assert sum(v["found"] for v in det.values()) / sum(v["n"] for v in det.values()) >= 0.99, case
        assert r["targets"][f"detection.{case}"]["met"]


def test_sopt_beats_the_papers_bound_at_every_distance(small_run):
    _, r, _, _ = small_run
    claim = r["paper_claims"]["sopt_low_bounce_16m"]
    for d, row in r["cases"]["low_bounce"]["sopt"].items():
        assert row["detected"] == row["n"], d
        assert row["pos_rms_m"] < claim["pos_rms_m"] and row["pos_max_m"] < claim["pos_max_m"], d
        assert row["yaw_rms_deg"] < claim["yaw_rms_deg"], d
    for d, row in r["cases"]["low_flat"]["bas"].items():
        assert row["pos_rms_m"] < 1.0, d  # "Bas. stays sub-metre"
    # The study's level solver is at the bound: one sample per bin is luck, 16 together are not.
    for case in ("low_flat", "low_bounce"):
        ratios = [v["crlb_ratio"] for v in r["cases"][case]["sopt_level"].values()]
        assert 0.6 < math.sqrt(np.mean(np.square(ratios))) < 1.5, (case, ratios)


def test_figures_are_valid_pngs_and_progress_is_shown(small_run):
    out, r, err, stdout = small_run
    for name in ("paper_low_flat.png", "paper_low_bounce.png", "paper_calibration.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 500 and img.shape[1] > 800, name
        assert img.std() > 10  # not blank
    assert r["figures"] == ["paper_low_flat.png", "paper_low_bounce.png", "paper_calibration.png"]
    assert "toptag eval paper [" in err and f"{2 * SAMPLES}/{2 * SAMPLES}" in err
    assert "low_bounce (cases)" in stdout


def test_bad_case_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        paper.main(["--out", str(tmp_path), "--cases", "low_flat,nope"])
    assert e.value.code == 2 and "nope" in capsys.readouterr().err


# ---- the models, on exact geometry ---------------------------------------------------------------
BUS = bundled_vehicle("bus_double")
CAM = rsu_camera("sw")


def _pose(d=14.0, bearing=0.1, yaw=0.7, dz=0.06):
    c = CAM.center
    head = np.arctan2(-c[1], -c[0]) + bearing
    return c[0] + d * np.cos(head), c[1] + d * np.sin(head), yaw, BUS.height + dz


def _observe(pose, rng=None, sigma=0.0, camera=CAM):
    x, y, yaw, z = pose
    out = []
    for tid in BUS.tag_ids:
        px = camera.project(vehicle_to_world(BUS.tag_corners(tid), x, y, yaw, z), distort=False)
        if rng is not None:
            px = px + rng.normal(0.0, sigma, px.shape)
        out.append(TagObservation(tid, px, camera))
    return out


def test_bound_with_iid_noise_is_position_crlbs():
    pose = _pose()
    for sigma_h in (SIGMA_H_DEFAULT, 1e-4):
        ours = pose_bound(BUS, [(CAM, BUS.tag_ids, 0.07)], pose, sigma_h)
        ref = position_crlb(BUS, [(CAM, BUS.tag_ids)], pose, 0.07, sigma_h)
        assert ours[0] == pytest.approx(ref.position_rms, rel=1e-9)
        assert ours[1] == pytest.approx(ref.yaw_rms, rel=1e-9)
    # More information never loosens it: a second RSU, no calibration error.
    one = pose_bound(BUS, [(CAM, BUS.tag_ids, 0.07)], pose, SIGMA_H_DEFAULT)
    two = pose_bound(BUS, [(CAM, BUS.tag_ids, 0.07), (rsu_camera("se"), BUS.tag_ids, 0.07)], pose, SIGMA_H_DEFAULT)
    cal = pose_bound(BUS, [(CAM, BUS.tag_ids, 0.07)], pose, SIGMA_H_DEFAULT, (np.radians(0.05), 0.02))
    assert two[0] < one[0] < cal[0] and cal[0] > 0.02  # a 2 cm camera-position error stays in the pose


def test_edge_noise_model_is_measured_from_corner_errors():
    rng = np.random.default_rng(0)
    true = CAM.project(vehicle_to_world(BUS.tag_corners(BUS.tag_ids[0]), *_pose()), distort=False)
    # i.i.d. corner noise on a near-rectangle: offset and turn each carry half the variance.
    tags = {10: [(true, rng.normal(0, 0.1, (4, 2))) for _ in range(400)], 11: [(true, np.zeros((4, 2)))]}
    n = measure_noise(tags)[10]
    assert n.sigma_px == pytest.approx(0.1, rel=0.05)
    assert n.offset_px == pytest.approx(0.1 / math.sqrt(2), rel=0.15)
    assert n.turn_px == pytest.approx(0.1 / math.sqrt(2), rel=0.15)
    # A whole edge moved along its normal is pure offset.
    u = true[1] - true[0]
    nrm = np.array([-u[1], u[0]]) / np.linalg.norm(u)
    err = np.zeros((4, 2))
    err[0] = err[1] = 0.2 * nrm
    o, w = edge_components(true, err)
    assert o[0] == pytest.approx(0.2) and abs(w[0]) < 1e-12
    assert measure_noise(tags)[11].pooled_m == 1  # one tag is too few: its neighbour lends
    # A garbled tag is set aside, not counted as noise.
    tags[10].append((true, np.full((4, 2), 3.0)))
    assert measure_noise(tags)[10].outlier_tags == 1


def test_study_level_solver_is_the_cores_at_the_bound():
    """The study's "S.Opt. level" is toptag.solvers' level method; on edge-model noise it sits at the
    study's bound (the edge-noise Cramér–Rao bound of the level roof)."""
    assert paper.SOLVERS["sopt_level"].method == "level"
    rng = np.random.default_rng(5)
    pose = _pose(d=16.0, dz=-0.07)
    offset = 0.03
    noise = EdgeNoise(2 * offset, offset, math.sqrt(3) * offset, (0, 0), 0, 0)
    bound = pose_bound(BUS, [(CAM, BUS.tag_ids, noise)], pose, SIGMA_H_DEFAULT)[0]
    errs = []
    for _ in range(40):
        obs = []
        for o in _observe(pose):
            W = edge_whitener(o.corners, math.sqrt(3))
            e = np.linalg.solve(W, rng.normal(0.0, offset, 8)).reshape(4, 2)
            obs.append(TagObservation(o.tag_id, o.corners + e, CAM))
        s = solve(BUS, obs, "level", sigma_h=SIGMA_H_DEFAULT, limits=Limits(max_position_sigma_m=math.inf))
        assert s.ok and s.tags == BUS.tag_ids
        errs.append(math.hypot(s.x - pose[0], s.y - pose[1]))
    assert 0.6 < math.sqrt(np.mean(np.square(errs))) / bound < 1.5


def test_progress_bar_draws_to_its_stream():
    buf = io.StringIO()
    bar = Progress(4, "x", stream=buf)  # the one progress bar of every long job (toptag.progress)
    for _ in range(4):
        bar.update()
    bar.close()
    text = buf.getvalue()
    assert "x [" in text and "4/4" in text and "100%" in text


@pytest.mark.parametrize("study", ["paper", "fusion"])
def test_eval_without_the_studies_extra_says_what_to_install(study, tmp_path):
    """The runtime install (and image) leaves matplotlib out: `toptag eval` says in one line what to
    install, before any work, instead of failing at the plots."""
    import subprocess
    import sys

    code = "import sys; sys.modules['matplotlib'] = None; from toptag.cli import main; main()"
    p = subprocess.run([sys.executable, "-c", code, "eval", study, "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode == 1, p.stderr  # the environment lacks something (toptag.errors.SetupError)
    assert p.stderr.strip().splitlines() == [p.stderr.strip()] and "pip install 'toptag[studies]'" in p.stderr
    assert not (tmp_path / "out").exists()
