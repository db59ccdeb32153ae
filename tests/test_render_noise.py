"""The sensor noise as the image model states it (N(0, noise_sigma²) per pixel, rounded, independent
per pixel and frame), now drawn from a per-camera bank of samples rather than afresh per frame: the
statistics the calibrated model was fitted with must be those of the old per-frame draw."""
import numpy as np
import pytest

from sim.image_model import ImageModel
from sim.render import render
from sim.scene import rsu_camera

pytestmark = pytest.mark.unit


def test_noise_field_has_the_model_statistics_within_and_across_frames():
    cam = rsu_camera("sw", 960, 720)
    model = ImageModel.ideal(noise_sigma=7.0)
    clean = render(cam, model=ImageModel.ideal()).astype(float)
    rng = np.random.default_rng(3)
    a = render(cam, model=model, rng=rng).astype(float) - clean
    b = render(cam, model=model, rng=rng).astype(float) - clean
    keep = (clean > 40) & (clean < 215)  # no clipping at 0 or 255
    assert keep.mean() > 0.5
    for e in (a, b):
        v = e[keep]
        # rounded N(0, 7²): variance 49 + 1/12; over ~0.5 M pixels the sample sigma is within 0.2 %
        assert abs(v.mean()) < 0.05 and v.std() == pytest.approx(np.sqrt(49 + 1 / 12), rel=0.01)
        # independent neighbours, horizontally and vertically
        for d0, d1 in ((e[:, 1:], e[:, :-1]), (e[1:, :], e[:-1, :])):
            m = keep[:, 1:] & keep[:, :-1] if d0.shape[1] != e.shape[1] else keep[1:, :] & keep[:-1, :]
            assert abs(np.corrcoef(d0[m], d1[m])[0, 1]) < 0.01
    # a fresh field every frame: the same pixel's noise in two frames is uncorrelated
    assert abs(np.corrcoef(a[keep], b[keep])[0, 1]) < 0.01 and not np.array_equal(a, b)
    # seeded: the same rng seed renders the same frame
    again = render(cam, model=model, rng=np.random.default_rng(3)).astype(float) - clean
    assert np.array_equal(again, a)


def test_a_live_jpeg_re_encodes_only_the_strips_vehicles_touch_and_decodes_to_the_plain_encoding():
    """render_jpeg (the live simulator's frames) splices cached 8-row strips of the static background
    with freshly encoded strips where vehicles are: decoded, exactly the pixels of a plain JPEG of the
    same noised frame, which is an ordinary baseline JPEG (what the RSU decodes)."""
    import cv2

    from sim.render import PlacedVehicle, _developed, _strips_for, encode_jpeg, render_jpeg
    from sim.scene import bundled_vehicle

    cam = rsu_camera("sw", 960, 720)
    model = ImageModel(noise_sigma=7.0, codec="jpeg", jpeg_quality=90)
    bus = PlacedVehicle(bundled_vehicle("bus_double"), -2.0, 6.0, 0.7, speed=6.0)
    for vehicles in ([bus], []):
        rast, out, rows = _developed(cam, vehicles, (), model, np.random.default_rng(1))
        strips = _strips_for(rast, model)
        data = strips.jpeg(out, rows, np.random.default_rng(5))
        choice = np.random.default_rng(5).integers(0, strips.choices, strips.n_strips)
        plain = strips._noised(out, 0, out.shape[0], choice)
        got = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        want = cv2.imdecode(np.frombuffer(encode_jpeg(plain, 90), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert got is not None and np.array_equal(got, want)
        if vehicles:
            assert rows is not None and 0 < rows[1] - rows[0] < out.shape[0] // 2  # a part re-encoded
            assert not np.array_equal(plain, strips._noised(strips.background, 0, out.shape[0], choice))
        else:
            assert rows is None
    # Frame after frame, a static strip's noise is one of the cached fields: it repeats now and then.
    rng = np.random.default_rng(7)
    a, b = (cv2.imdecode(np.frombuffer(render_jpeg(cam, [], (), model, rng), np.uint8), cv2.IMREAD_GRAYSCALE)
            for _ in range(2))
    same = [np.array_equal(a[8 * m:8 * m + 8], b[8 * m:8 * m + 8]) for m in range(90)]
    assert 0 < sum(same) < 20  # ~90 / 16
    assert np.std(a.astype(float) - b.astype(float)) > 7  # otherwise fresh noise
