"""Detection restricted to code bags, on rendered frames through the real detector: buses of different
tag families in one frame, and the RSU pipeline with both announced."""
from __future__ import annotations

import numpy as np
import pytest

from sim.image_model import ImageModel
from sim.render import PlacedVehicle, render
from sim.scene import rsu_camera
from toptag.detection import TagDetector, detect_vehicle_tags
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.vehicle import Vehicle

pytestmark = pytest.mark.unit


def bus(family: str, vid: str, ids=(3, 7)) -> Vehicle:
    return Vehicle.from_dict({"id": vid, "height": 3.0, "family": family, "length": 6.0, "width": 2.0,
                              "tags": [{"id": ids[0], "size": 1.6, "center": [1.5, 0.0]},
                                       {"id": ids[1], "size": 1.6, "center": [-1.5, 0.0]}]})


def two_buses_frame(family_b: str, seed: int = 3):
    """The south-west RSU sees a tag36h11 bus and a `family_b` bus side by side, 9-12 m away."""
    cam = rsu_camera("sw")
    a, b = bus("tag36h11", "bus-a"), bus(family_b, "bus-b", (5, 6))
    pa = PlacedVehicle(a, -4.0, -2.0, 0.3)
    pb = PlacedVehicle(b, -1.0, -6.5, 0.2)
    img = render(cam, [pa, pb], model=ImageModel(), rng=np.random.default_rng(seed))
    return cam, (a, pa), (b, pb), img


@pytest.mark.parametrize("family_b", ["tag25h9", "tag16h5"])
def test_one_detector_finds_tags_of_two_families_in_one_frame(family_b):
    cam, (a, pa), (b, pb), img = two_buses_frame(family_b)
    det = TagDetector(("tag36h11", family_b))
    try:
        found = detect_vehicle_tags(det, img, cam, [a, b])
    finally:
        det.close()
    assert sorted(o.tag_id for o in found[a.id]) == [3, 7]
    assert sorted(o.tag_id for o in found[b.id]) == [5, 6]
    for v, pv in ((a, pa), (b, pb)):
        for o in found[v.id]:
            truth = cam.project(pv.tag_corners_world(o.tag_id))
            assert np.abs(o.raw_corners - truth).max() < 1.0


def test_detector_families_are_checked():
    with pytest.raises(ValueError, match="tag99h1"):
        TagDetector(("tag36h11", "tag99h1"))
    with pytest.raises(ValueError, match="at least one"):
        TagDetector(())


@pytest.mark.parametrize("family_b", ["tag25h9", "tag16h5"])
def test_rsu_with_buses_of_two_families_announced_locates_both(family_b):
    """The blinding bug: announcing a tag25h9 or tag16h5 bus at an RSU used to make every tag36h11 bus
    there disappear (pupil-apriltags built a detector for one family only)."""
    cam, (a, pa), (b, pb), img = two_buses_frame(family_b, seed=5)
    p = RsuPipeline(cam, PipelineSettings(tracking=False, workers=1))
    p.add_vehicle(a)
    first = p.process(img, 0).vehicles[a.id].solution
    assert first is not None and first.ok
    p.add_vehicle(b)
    res = p.process(img, 1)
    for v, pv in ((a, pa), (b, pb)):
        sol = res.vehicles[v.id].solution
        assert sol is not None and sol.ok, (v.family, sol)
        assert np.hypot(sol.x - pv.x, sol.y - pv.y) < 0.1


def test_a_crop_is_detected_in_place_as_its_copy_is_and_never_written_to():
    """The C detector reads a crop where it lies in the frame (the frame's row stride, no copy): the same
    detections as on a contiguous copy of the crop; the frame is left as it was, also with quad_sigma,
    where the library blurs its undecimated input in place (it is then given a copy)."""
    from toptag.detection import DetectorSettings

    cam, (a, pa), (b, pb), img = two_buses_frame("tag25h9")
    x0, y0 = 40, 200
    crop = img[y0:, x0:]
    assert not crop.flags.c_contiguous
    for settings in (DetectorSettings(), DetectorSettings(quad_sigma=0.8), DetectorSettings(quad_decimate=2.0)):
        det = TagDetector(("tag36h11", "tag25h9"), settings)
        before = img.copy()
        try:
            in_place = det.detect_raw(crop, (x0, y0))
            copied = det.detect_raw(np.ascontiguousarray(crop), (x0, y0))
        finally:
            det.close()
        assert np.array_equal(img, before)
        assert len(in_place) >= 3
        assert [(d.family, d.tag_id) for d in in_place] == [(d.family, d.tag_id) for d in copied]
        for d, c in zip(in_place, copied):
            assert np.array_equal(d.corners, c.corners) and d.decision_margin == c.decision_margin


def test_the_unrefined_pass_runs_only_when_an_expected_tag_is_missed(monkeypatch):
    """A crop around tags found at a coarser level: the second decode pass (without edge refinement, to
    find what the first misses) runs only if the first pass missed one of the expected tags, and
    without edge refinement as the C library reads it (pupil's own view of the detector struct)."""
    cam, (a, pa), (b, pb), img = two_buses_frame("tag25h9")
    det = TagDetector(("tag36h11", "tag25h9"))
    calls = []
    real = TagDetector._detect
    monkeypatch.setattr(TagDetector, "_detect", lambda self, im: calls.append(
        self._detector.tag_detector_ptr.contents.refine_edges) or real(self, im))
    try:
        assert det._detector.tag_detector_ptr.contents.decode_sharpening == det.settings.decode_sharpening
        found = det.detect_raw(img, expected={("tag36h11", 3), ("tag25h9", 5)})
        assert calls == [1] and {("tag36h11", 3), ("tag25h9", 5)} <= {(d.family, d.tag_id) for d in found}
        calls.clear()
        again = det.detect_raw(img, expected={("tag36h11", 3), ("tag36h11", 4)})  # 4 is on no roof
        assert calls == [1, 0] and len(again) == len(found)
        assert det._detector.tag_detector_ptr.contents.refine_edges == 1
        calls.clear()
        det.detect_raw(img, unrefined_pass=False, expected={("tag36h11", 4)})
        assert len(calls) == 1
    finally:
        det.close()


def test_a_contrast_floor_leaves_out_tags_of_less_contrast_for_that_call_only():
    """min_contrast (AprilTag's min_white_black_diff) above the tags' black/white difference finds none of
    them; the next call without it finds them again (the floor is not left set in the detector)."""
    cam, (a, pa), (b, pb), img = two_buses_frame("tag25h9")
    det = TagDetector(("tag36h11", "tag25h9"))
    try:
        assert len(det.detect_raw(img)) == 4
        assert len(det.detect_raw(img, min_contrast=20)) == 4  # the default light: ~115 grey levels
        assert det.detect_raw(img, min_contrast=200) == []
        assert len(det.detect_raw(img)) == 4
    finally:
        det.close()


@pytest.mark.parametrize("decimate", [2.0, 4.0])
def test_a_decimation_for_one_call_finds_what_a_detector_built_for_it_finds(decimate):
    """One detector serves every pyramid level (the RSU builds one per thread, not one per level): a call
    with `decimate` gives exactly the detections of a detector whose settings say that decimation, and the
    next call without it is back at full resolution (the same as before)."""
    from toptag.detection import DetectorSettings

    cam, (a, pa), (b, pb), img = two_buses_frame("tag25h9")
    one = TagDetector(("tag36h11", "tag25h9"))
    built = TagDetector(("tag36h11", "tag25h9"), DetectorSettings(quad_decimate=decimate))
    try:
        full = one.detect_raw(img)
        coarse, reference = one.detect_raw(img, decimate=decimate), built.detect_raw(img)
        assert len(reference) == 4
        assert [(d.family, d.tag_id) for d in coarse] == [(d.family, d.tag_id) for d in reference]
        np.testing.assert_array_equal(np.array([d.corners for d in coarse]), np.array([d.corners for d in reference]))
        # full resolution and the coarse level do differ, so the comparison above can fail
        assert not np.array_equal(np.array([d.corners for d in coarse]), np.array([d.corners for d in full]))
        again = one.detect_raw(img)
        np.testing.assert_array_equal(np.array([d.corners for d in again]), np.array([d.corners for d in full]))
    finally:
        one.close()
        built.close()
