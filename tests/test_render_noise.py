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
