"""Camera and vehicle models against SPEC.md: projection, distortion, validation errors."""
import json

import numpy as np
import pytest

from sim.scene import bundled_vehicle, rsu_camera
from toptag.camera import Camera
from toptag.inputs import InputError
from toptag.vehicle import Vehicle

pytestmark = pytest.mark.unit

DIST = [-0.28, 0.09, 0.0007, -0.0004, -0.012]


def camera_dict(**change):
    d = rsu_camera("sw").to_model().model_dump()
    d.update(change)
    return d


def test_projection_matches_opencv_with_distortion():
    import cv2

    cam = rsu_camera("ne", dist=DIST)
    pts = np.random.default_rng(1).uniform([-8, -8, 0], [8, 8, 4], size=(50, 3))
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, np.asarray(DIST))
    assert np.max(np.abs(cam.project(pts) - ref.reshape(-1, 2))) < 1e-9


RATIONAL = [-0.31, 0.11, 0.0009, -0.0006, -0.015, 0.04, 0.008, 0.001]


@pytest.mark.parametrize("dist", [DIST, RATIONAL], ids=["5 terms", "rational 8 terms"])
def test_undistort_inverts_distortion(dist):
    cam = rsu_camera("sw", 3200, 2400, dist=dist)
    rng = np.random.default_rng(2)
    ideal = rng.uniform([0, 0], [3199, 2399], size=(200, 2))
    xn = (ideal - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    observed = cam.distort_normalized(xn) * np.diag(cam.K)[:2] + cam.K[:2, 2]
    assert np.max(np.abs(cam.undistort(observed) - ideal)) < 1e-6


@pytest.mark.parametrize("dist", [DIST, RATIONAL], ids=["5 terms", "rational 8 terms"])
def test_undistort_agrees_with_opencv(dist):
    """The compiled Newton inverse (toptag.lens) against OpenCV's own iterative undistortion."""
    import cv2

    cam = rsu_camera("ne", 960, 720, dist=dist)
    observed = np.random.default_rng(4).uniform([0, 0], [959, 719], size=(300, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ref = cv2.undistortPoints(observed.reshape(-1, 1, 2), cam.K, np.asarray(dist), None, None, None, criteria)
    assert np.max(np.abs(cam.normalized(observed) - ref.reshape(-1, 2))) < 1e-9


def test_backprojection_onto_plane_recovers_points():
    cam = rsu_camera("se", dist=DIST)
    pts = np.column_stack([np.random.default_rng(3).uniform(-6, 6, size=(30, 2)), np.full(30, 3.0)])
    assert np.max(np.abs(cam.backproject_to_plane(cam.project(pts), 3.0) - pts)) < 1e-7


def test_camera_json_round_trip(tmp_path):
    cam = rsu_camera("nw", dist=DIST)
    f = tmp_path / "cam.json"
    f.write_text(cam.to_model().model_dump_json())
    again = Camera.load(f)
    assert np.allclose(again.K, cam.K) and np.allclose(again.R, cam.R) and np.allclose(again.dist, DIST)


@pytest.mark.parametrize("change, field", [
    ({"K": [[700, 0, 480], [0, 0, 360], [0, 0, 1]]}, "K"),
    ({"R_wc": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}, "R_wc"),
    ({"R_wc": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}, "R_wc"),
    ({"width": 0}, "width"),
    ({"height": -5}, "height"),
    ({"T_wc": [1, 2]}, "T_wc"),
    ({"dist": [0.1, 0.2, 0.3]}, "dist"),
])
def test_bad_camera_names_the_field(change, field):
    with pytest.raises(InputError) as e:
        Camera.from_dict(camera_dict(**change))
    assert field in str(e.value) and "\n" not in str(e.value)


def test_missing_and_malformed_files_are_one_line_errors(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        Camera.load(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        Vehicle.load(bad)


def test_corners_follow_spec_order_at_yaw_zero():
    v = Vehicle.from_dict({"id": "b", "height": 3, "length": 6, "width": 2,
                           "tags": [{"id": 1, "size": 1.6, "center": [1.5, 0.0]}]})
    s = 0.8
    expected = np.array([[-s, s], [-s, -s], [s, -s], [s, s]]) + [1.5, 0.0]
    assert np.allclose(v.tag_corners(1)[:, :2], expected) and np.allclose(v.tag_corners(1)[:, 2], 0)


def test_tag_yaw_turns_corners_about_vehicle_z():
    v = Vehicle.from_dict({"id": "b", "height": 3, "length": 6, "width": 2,
                           "tags": [{"id": 1, "size": 1.0, "center": [0, 0], "yaw": np.pi / 2}]})
    # Printed top now faces vehicle +y: the bottom-left corner is at (-s/2, -s/2) turned by 90 deg.
    assert np.allclose(v.tag_corners(1)[0, :2], [-0.5, -0.5])


@pytest.mark.parametrize("name, n", [("bus_single", 1), ("bus_double", 2), ("bus_triple", 3), ("bus_long", 1)])
def test_bundled_layouts(name, n):
    v = bundled_vehicle(name)
    assert len(v.tag_ids) == n
    xy = v.corners(v.tag_ids)[:, :2]
    assert np.all(np.abs(xy[:, 0]) <= v.length / 2) and np.all(np.abs(xy[:, 1]) <= v.width / 2)


def test_long_tag_is_stretched_along_its_up_axis():
    v = bundled_vehicle("bus_long")
    c = v.tag_corners(v.tag_ids[0])
    assert np.isclose(np.ptp(c[:, 0]), 4.4) and np.isclose(np.ptp(c[:, 1]), 1.6)


@pytest.mark.parametrize("change, words", [
    ({"tags": [{"id": 1, "size": 1.6}, {"id": 1, "size": 1.6, "center": [2, 0]}]}, "duplicate"),
    ({"tags": [{"id": 1, "size": 0}]}, "size"),
    ({"tags": [{"id": 1, "size": -1.6}]}, "size"),
    ({"family": "tag99h99"}, "unknown tag family"),
    ({"height": 0}, "height"),
    ({"tags": []}, "tags"),
])
def test_bad_vehicle_rejected_with_reason(change, words):
    d = {"id": "bus", "height": 3.0, "family": "tag36h11", "length": 6, "width": 2,
         "tags": [{"id": 1, "size": 1.6}]}
    d.update(change)
    with pytest.raises(InputError) as e:
        Vehicle.from_dict(d)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_vehicle_round_trips_through_json():
    v = bundled_vehicle("bus_triple")
    again = Vehicle.from_dict(json.loads(json.dumps(v.to_dict())))
    assert np.allclose(again.corners(again.tag_ids), v.corners(v.tag_ids))
