"""On-site calibration: boards and plates rendered by the simulator, calibrated as `toptag calibrate`
does, against the known truth, the issue's targets and the Cramér–Rao bounds; bad input refused in one
line; the calibration covariance carried into fixes."""
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim.image_model import ImageModel
from sim.render import PlacedVehicle, render
from sim.scene import bundled_vehicle
from sim.studies.calibration import (
    BOARD,
    FOCAL_TARGET,
    UNDISTORTION_TARGET_PX,
    VIEW_POSES,
    board_frames_model,
    extrinsics_trial,
    intrinsics_trial,
    study_camera,
)
from sim.targets import board_poses, plate_layout, render_board, surveyed_points
from toptag.calibration.boards import Board, BoardView
from toptag.calibration.extrinsics import perturbed
from toptag.calibration.intrinsics import CalibrationError, calibrate_intrinsics
from toptag.calibration.points import ControlPoint, ControlPoints
from toptag.camera import Camera
from toptag.inputs import InputError

REPO = Path(__file__).resolve().parents[1]


def _truth_views(camera, board, poses):
    views = []
    for i, (R, t) in enumerate(poses):
        p = cv2.projectPoints(board.object_points, cv2.Rodrigues(np.asarray(R))[0], t, camera.K, camera.dist)[0]
        p = p.reshape(-1, 2)
        inside = camera.in_image(p, 5)
        views.append(BoardView(np.flatnonzero(inside), p[inside], board.object_points[inside], f"v{i}"))
    return views


@pytest.mark.integration
@pytest.mark.parametrize("spec", [BOARD, {"type": "chessboard", "squares_x": 9, "squares_y": 7, "square_size": 0.07}])
def test_rendered_board_corners_are_found_where_they_project(spec):
    camera, model = study_camera(), ImageModel()
    board = Board.from_dict(spec)
    pattern, texel, margin = board.pattern()
    levels = np.where(pattern > 127, model.tag_white, model.tag_black)
    R, t = board_poses(camera, (spec["squares_x"] * spec["square_size"], spec["squares_y"] * spec["square_size"]),
                       1, np.random.default_rng(5), grid=(1, 1), distance=(1.0, 1.1))[0]  # the whole board in view
    view = board.detect(render_board(camera, levels, texel, R, t, (margin, margin), model, np.random.default_rng(1)))
    assert view is not None and len(view.ids) >= 0.8 * len(board.object_points)
    truth = cv2.projectPoints(view.object_points, cv2.Rodrigues(R)[0], t, camera.K, camera.dist)[0].reshape(-1, 2)
    err = view.image_points - truth
    if spec["type"] == "chessboard":  # a symmetric board may be read turned by 180°
        flipped = view.image_points[::-1] - truth
        err = min(err, flipped, key=lambda e: np.abs(e).max())
    # The calibrated image model's corners (through its H.264 stream) are about as precise as real
    # photographs' (0.20-0.24 px median against saddle-point truth, docs/real-data.md): 0.18-0.25 px RMS
    # here. Now and then a ChArUco corner at the board's edge or beside a smeared marker is 1-2 px off
    # (1 of the A0 board's 366 here): calibrate_intrinsics leaves such outliers out.
    norm = np.linalg.norm(err, axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.3 and np.mean(norm < 1.0) >= 0.99 and norm.max() < 3.0


@pytest.mark.integration
def test_intrinsics_from_20_views_of_the_recommended_board_meet_the_targets():
    # The board README asks a site to print (A0, 24 x 17 squares of 48 mm), its views (0.6-1.0 m, tilted up
    # to 45°, into every image corner) and its frames (lossless snapshots; the calibrated image model
    # otherwise): `toptag eval calibration` runs 10 such trials; one here.
    camera = study_camera()
    trial, result = intrinsics_trial(camera, 20, board_frames_model(ImageModel()), np.random.default_rng(11))
    assert trial.views >= 18
    # the targets, with room: the focal length's Cramér-Rao bound is about 0.013 % (a quarter of the
    # target) where issue 12's first board (16 x 12 x 45 mm at 0.7-1.1 m, the stream) left it at 0.067 %
    assert trial.fx_bound_px / camera.K[0, 0] < 0.4 * FOCAL_TARGET
    assert abs(trial.focal_rel_error) <= FOCAL_TARGET
    assert trial.undistortion_max_px <= UNDISTORTION_TARGET_PX
    # a fair estimator: within 3 sigma of its bound, its own covariance about as large as the bound
    assert abs(trial.fx_error_px) <= 3 * trial.fx_bound_px
    assert trial.undistortion_rms_px <= 3 * trial.undistortion_bound_rms_px
    assert 0.5 < result.std["fx"] / trial.fx_bound_px < 2.0


@pytest.mark.unit
def test_the_printable_board_is_the_board_file_at_its_print_scale(tmp_path):
    board = Board.from_dict(BOARD)
    r = subprocess.run([sys.executable, "-m", "toptag", "calibrate", "board", "--board", str(REPO / "toptag/data/board_charuco_a0.json"),
                        "--out", str(tmp_path / "board.png"), "--dpi", "100"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "print at 100 % scale" in r.stdout
    raw = (tmp_path / "board.png").read_bytes()
    k = raw.index(b"pHYs")
    ppm = int.from_bytes(raw[k + 4:k + 8], "big")
    img = cv2.imread(str(tmp_path / "board.png"), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    # fits an A0 sheet (1189 x 841 mm) at the file's scale, squares as the board file says
    assert w / ppm <= 1.189 and h / ppm <= 0.841
    assert (w / ppm - BOARD["squares_x"] * BOARD["square_size"]) == pytest.approx(0.02, abs=0.002)
    view = board.detect(img)
    assert view is not None and len(view.ids) == len(board.object_points)
    corners_m = view.image_points / ppm  # the printed corners land on the board file's grid (plus the margin)
    assert np.abs(corners_m - corners_m[0] - (view.object_points[:, :2] - view.object_points[0, :2])).max() < 2 / ppm


@pytest.mark.unit
def test_intrinsics_refuse_too_few_views_and_an_uncovered_image():
    camera = study_camera()
    board = Board.from_dict(BOARD)
    size = (BOARD["squares_x"] * BOARD["square_size"], BOARD["squares_y"] * BOARD["square_size"])
    views = _truth_views(camera, board, board_poses(camera, size, 20, np.random.default_rng(2), **VIEW_POSES))
    with pytest.raises(CalibrationError, match=r"at least 10 views .* got 6 .*no board found in a\.png"):
        calibrate_intrinsics(views[:6], (camera.width, camera.height), names_without_board=["a.png"])
    # every view in the top-left quarter of the image
    corner = [BoardView(v.ids[m], v.image_points[m], v.object_points[m], v.name) for v in views
              if (m := (v.image_points[:, 0] < 400) & (v.image_points[:, 1] < 300)).sum() >= 8]
    corner = (corner * 3)[:12]
    with pytest.raises(CalibrationError, match="do not cover the image .*nothing in the .*bottom-right"):
        calibrate_intrinsics(corner, (camera.width, camera.height))


@pytest.mark.integration
def test_extrinsics_from_8_plates_reach_their_bound():
    camera, model = study_camera(), ImageModel()
    rng = np.random.default_rng(21)
    trials = [extrinsics_trial(camera, model, rng)[0] for _ in range(6)]
    # The two farthest plates (19 m, 36 x 17 px) are missed now and then on the calibrated image model
    # (7 images in 20 in one run): the tool names the missing plate, the other seven still calibrate.
    assert all(t.plates_found >= 7 for t in trials)
    rms = np.sqrt(np.mean([t.mapping_rms_m ** 2 for t in trials]))
    bound = np.sqrt(np.mean([t.bound_rms_m ** 2 for t in trials]))
    assert 0.005 < bound < 0.025  # about 1.3 cm for this layout (5 mm survey, 0.15 px corners)
    assert rms <= 1.2 * bound
    # and the single-points comparison is worse, as the issue measured
    assert np.sqrt(np.mean([t.single_points_pnp_rms_m ** 2 for t in trials])) > rms


@pytest.mark.unit
def test_extrinsics_refuse_degenerate_layouts_with_the_reason():
    from toptag.calibration.extrinsics import solve_extrinsics

    camera = study_camera()
    line = np.array([[x, 0.5 * x, 0.0] for x in np.linspace(-6, 6, 6)])
    pts = [ControlPoint(f"p{i}", w, np.full(3, 0.005), camera.project(w[None])[0]) for i, w in enumerate(line)]
    with pytest.raises(CalibrationError, match="collinear"):
        solve_extrinsics(camera, pts)
    with pytest.raises(CalibrationError, match="at least 4 control points with pixels; got 3"):
        solve_extrinsics(camera, pts[:3])


@pytest.mark.unit
@pytest.mark.parametrize("bad, message", [
    ({"survey_sigma": 0.005, "points": [{"id": "a", "world": [1, 2], "pixel": [3, 4]}]}, "points.0.world"),
    ({"survey_sigma": 0.005, "points": [{"id": "a", "world": [1, 2, float("nan")], "pixel": [3, 4]}]}, "points.0.world.2"),
    ({"points": [{"id": "a", "world": [1, 2, 3], "pixel": [3, 4]}]}, "points.0.sigma: missing"),
    ({"survey_sigma": 0.005, "plates": [{"id": "P", "tag_id": 1, "corners": [[0, 0, 0]] * 3}]}, "plates.0.corners"),
    ({"survey_sigma": 0.005, "points": [], "plates": []}, "no points and no plates"),
])
def test_points_file_errors_name_the_field(tmp_path, bad, message):
    f = tmp_path / "points.json"
    f.write_text(json.dumps(bad).replace("NaN", "NaN"))
    with pytest.raises(InputError) as e:
        ControlPoints.load(f)
    assert message in str(e.value) and "\n" not in str(e.value)


@pytest.mark.unit
def test_old_camera_files_stay_valid_and_the_calibration_block_is_checked(tmp_path):
    camera = study_camera()
    assert camera.calibration is None and camera.extrinsic_covariance is None
    data = json.loads(camera.to_json())
    data["calibration"] = {"extrinsics": {"covariance": (np.eye(6) * -1e-6).tolist()}}
    with pytest.raises(InputError, match="calibration.extrinsics.covariance: .*positive semi-definite"):
        Camera.from_dict(data)
    data["calibration"] = {"intrinsics": {"rms_px": 0.1, "views": 20, "sigma_px": 0.07, "coverage": 0.8}}
    with pytest.raises(InputError, match="extrinsics not calibrated yet"):
        Camera.from_dict(data).require_extrinsics("camera file")


@pytest.mark.integration
def test_fix_covariance_carries_the_camera_calibration():
    from toptag.rsu.pipeline import PipelineSettings, RsuPipeline

    camera = study_camera()
    bus = bundled_vehicle("bus_double")
    cam_pos = camera.center
    pv = PlacedVehicle(bus, cam_pos[0] + 11.0, cam_pos[1] + 11.0, 0.4)
    gray = render(camera, [pv], (), ImageModel(), np.random.default_rng(3))
    cov6 = np.diag([np.radians(0.03) ** 2] * 3 + [0.006 ** 2] * 3)
    calibrated = camera.with_calibration(Camera.from_dict({**json.loads(camera.to_json()), "calibration": {
        "extrinsics": {"covariance": cov6.tolist()}}}).calibration)
    sols = []
    for cam in (camera, calibrated):
        pl = RsuPipeline(cam, PipelineSettings(tracking=False))
        pl.add_vehicle(bus)
        sols.append(pl.process(gray, 0).vehicles[bus.id].solution)
    plain, carried = sols
    assert plain.ok and carried.ok and plain.x == pytest.approx(carried.x)
    added = carried.covariance - plain.covariance
    assert np.min(np.linalg.eigvalsh(added)) > -1e-12  # only ever adds uncertainty
    assert np.allclose(pl.process(gray, 0).vehicles[bus.id].fix.calib_cov, added)  # the fix says which share
    # as much as the pose really moves when the camera is off by draws of that covariance (the same
    # corners re-solved with perturbed cameras)
    from toptag.detection import TagObservation
    from toptag.solvers import solve

    obs = pl.process(gray, 0).vehicles[bus.id].observations
    rng = np.random.default_rng(0)
    moved = []
    for _ in range(60):
        cam = perturbed(camera, rng.multivariate_normal(np.zeros(6), cov6))
        s = solve(bus, [TagObservation(o.tag_id, cam.undistort(o.raw_corners), cam, o.raw_corners) for o in obs],
                  "level", weighting="principled")
        moved.append([s.x, s.y])
    empirical = np.sqrt(np.trace(np.cov(np.array(moved).T)))
    assert 0.7 * empirical < np.sqrt(added[0, 0] + added[1, 1]) < 1.4 * empirical
    assert empirical > 0.005  # centimetres: the calibration, not the pixels, dominates such a fix


@pytest.fixture(scope="module")
def site_images(tmp_path_factory):
    """12 board views and one plate image of the study camera, with the board and points files."""
    d = tmp_path_factory.mktemp("calib")
    camera, model = study_camera(), ImageModel()
    rng = np.random.default_rng(8)
    board = Board.from_dict(BOARD)
    (d / "board.json").write_text(json.dumps(BOARD))
    pattern, texel, margin = board.pattern()
    levels = np.where(pattern > 127, model.tag_white, model.tag_black)
    size = (BOARD["squares_x"] * BOARD["square_size"], BOARD["squares_y"] * BOARD["square_size"])
    snapshot = board_frames_model(model)
    for i, (R, t) in enumerate(board_poses(camera, size, 12, rng, **VIEW_POSES)):
        cv2.imwrite(str(d / f"board-{i:02d}.png"), render_board(camera, levels, texel, R, t, (margin, margin), snapshot, rng))
    plates = plate_layout(camera)
    cv2.imwrite(str(d / "plates.png"), render(camera, plates, (), model, rng))
    (d / "points.json").write_text(json.dumps(surveyed_points(plates, 0.005, rng)))
    # the same plates after the camera turned by 0.3° (a knock)
    knocked = perturbed(camera, [0.0, np.radians(0.3), 0.0, 0, 0, 0])
    cv2.imwrite(str(d / "plates-knocked.png"), render(knocked, plates, (), model, rng))
    return d


def _toptag(*args, cwd):
    return subprocess.run([sys.executable, "-m", "toptag", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.integration
def test_calibrate_commands_end_to_end(site_images):
    d = site_images
    boards = sorted(p.name for p in d.glob("board-*.png"))
    r = _toptag("calibrate", "intrinsics", "--board", "board.json", "--id", "rsu-sw", *boards, "--out", "intr.json", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "board found in 12 of 12 images" in r.stdout and "fx " in r.stdout
    truth = study_camera()
    intr = Camera.load(d / "intr.json")
    assert abs(intr.K[0, 0] / truth.K[0, 0] - 1) < 0.002
    r = _toptag("locate", "--camera", "intr.json", "--vehicle", REPO / "toptag/data/bus_double.json", "board-00.png",
                cwd=d)
    assert r.returncode == 2 and "extrinsics not calibrated yet" in r.stderr

    r = _toptag("calibrate", "extrinsics", "--camera", "intr.json", "--points", "points.json", "plates.png",
                "--out", "cam.json", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "P8.3" in r.stdout and "roof (z = 3 m) mapping sigma" in r.stdout
    cam = Camera.load(d / "cam.json")
    assert cam.extrinsic_covariance is not None and cam.calibration.intrinsics is not None
    assert np.linalg.norm(cam.center - truth.center) < 0.05

    ok = _toptag("calibrate", "check", "--camera", "cam.json", "--points", "points.json", "plates.png", cwd=d)
    assert ok.returncode == 0 and "OK: consistent" in ok.stdout, ok.stdout + ok.stderr
    moved = _toptag("calibrate", "check", "--camera", "cam.json", "--points", "points.json", "plates-knocked.png", cwd=d)
    assert moved.returncode == 1 and "MOVED" in moved.stdout, moved.stdout + moved.stderr

    # bad input: one line naming the problem, exit 2
    (d / "bad.json").write_text('{"survey_sigma": 0.005, "points": [{"id": "a", "world": [1, 2, NaN], "pixel": [1, 2]}]}')
    bad = _toptag("calibrate", "extrinsics", "--camera", "intr.json", "--points", "bad.json", "--out", "x.json", cwd=d)
    assert bad.returncode == 2 and "points.0.world.2" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    few = _toptag("calibrate", "intrinsics", "--board", "board.json", "--id", "x", *boards[:4], "plates.png",
                  "--out", "x.json", cwd=d)
    assert few.returncode == 2 and "at least 10 views" in few.stderr and "plates.png" in few.stderr


@pytest.mark.integration
def test_eval_calibration_prints_targets_and_ratios(tmp_path):
    r = subprocess.run([sys.executable, "-m", "toptag", "eval", "calibration", "--out", str(tmp_path),
                        "--intrinsic-trials", "0", "--extrinsic-trials", "2"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "× its bound" in r.stdout and "image model:" in r.stdout
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["summary"]["extrinsics"]["trials"] == 2
    assert (tmp_path / "calibration_extrinsics.png").stat().st_size > 10_000
