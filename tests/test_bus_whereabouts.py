"""The bus's whereabouts in its Approach (position, velocity and their sigmas) and the RSU's use of them:
a bus that cannot reach the view is not searched (its frame not even decoded), one that can is, and a
bus entering the view is acquired no later than without them."""
import math

import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.convert import reported_position
from protocol.messages import Approach, CoarsePosition, GnssFix
from services.bus.agent import announced_position
from services.rsu.bench import simulated_pass
from toptag.fusion.filter import BusFilter
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.rsu.whereabouts import GNSS_SIGMA_FLOOR_M, MAX_ACCEL_MPS2, ReportedPosition

S = 1_000_000_000
pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def bus_pass():
    return simulated_pass(960, 720, frames=30, fps=10.0, seed=3)


class Decoder:
    """The frame as a function that counts how often the pipeline decodes it."""

    def __init__(self, img):
        self.img, self.calls = img, 0

    def __call__(self):
        self.calls += 1
        return self.img


def test_a_report_is_moved_on_at_its_velocity_and_widened_honestly_for_its_age():
    top = 10.0
    r = ReportedPosition(0, 10.0, 20.0, 0.5, velocity=(4.0, -3.0), velocity_sigma=0.2)
    x, y, rad = r.disc_at(S // 2, top)
    assert (x, y) == pytest.approx((12.0, 18.5))
    assert rad == pytest.approx(3 * math.hypot(0.5, 0.1) + 0.5 * MAX_ACCEL_MPS2 * 0.25)
    assert r.disc_at(0, top)[2] == pytest.approx(1.5)
    # older and older: wider, but never wider than the top speed allows from where it was
    assert r.disc_at(5 * S, top) == (10.0, 20.0, pytest.approx(1.5 + 50.0))
    # a speed without a direction: a disc around the report, as far as that speed (and acceleration) goes
    g = ReportedPosition(0, 10.0, 20.0, 2.0, speed=5.0)
    assert g.disc_at(S, top) == (10.0, 20.0, pytest.approx(6.0 + 5.0 + 0.5 * MAX_ACCEL_MPS2))
    assert ReportedPosition(0, 10.0, 20.0, 2.0).disc_at(S, top) == (10.0, 20.0, pytest.approx(16.0))


def test_the_agent_announces_its_filters_pose_with_velocity_else_gnss_with_speed():
    f = BusFilter()
    yaw, speed = 0.6, 6.0
    f.initialize(0, 5.0, -3.0, yaw, pos_sigma=0.3, yaw_sigma=0.02, speed=speed, speed_sigma=0.2, trusted=True)
    for k in range(1, 51):  # half a second of straight driving
        f.add_imu(k * S // 100, 0.0, 0.0, 0.0, speed)
    est = f.estimate()
    gnss = GnssFix(bus_id="bus-17", t_ns=0, x=4.0, y=-2.0, sigma_m=2.0)
    c = announced_position(est, gnss, speed, est.t_ns)
    assert c.source == "fused" and (c.x, c.y) == (est.x, est.y)
    assert (c.vx, c.vy) == pytest.approx((speed * math.cos(yaw), speed * math.sin(yaw)), abs=0.2)
    assert 0 < c.velocity_sigma_mps < 1.0 and c.yaw == est.yaw and 0 < c.yaw_sigma_rad < 0.1
    assert est.health.pos_sigma_m < c.sigma_m < est.health.pos_sigma_m + 0.2  # never below a floor
    g = announced_position(None, gnss, -speed, S)  # before a fix has started the filter
    assert g.source == "gnss" and g.speed_mps == speed and g.vx is None
    assert announced_position(None, gnss, speed, 6 * S) is None  # GNSS too old, no filter: nothing


def test_whereabouts_travel_in_the_approach_and_old_peers_still_read_it(bus_pass):
    _, bus, _ = bus_pass
    pos = CoarsePosition(t_ns=1, x=1.0, y=2.0, sigma_m=0.4, source="fused", vx=3.0, vy=-1.0, velocity_sigma_mps=0.3)
    a = Approach(bus_id=bus.id, intersection_id="x1", vehicle=bus.spec, reference_time_ns=2, position=pos)
    assert decode(encode(a), Approach).position == pos
    old = a.model_copy(update={"position": CoarsePosition(t_ns=1, x=1.0, y=2.0, sigma_m=2.0)})
    assert decode(encode(old), Approach).position.vx is None  # what an older bus sends
    with pytest.raises(ValueError):
        CoarsePosition(t_ns=1, x=1.0, y=2.0, sigma_m=0.4, vx=3.0)  # half a velocity


def _velocity(frames, i):
    (t0, _, a, _), (t1, _, b, _) = frames[max(i - 1, 0)], frames[max(i, 1)]
    return ((b[0] - a[0]) / ((t1 - t0) / S), (b[1] - a[1]) / ((t1 - t0) / S))


def test_a_bus_that_cannot_reach_the_view_is_not_searched_one_that_can_is(bus_pass):
    camera, bus, frames = bus_pass
    shown = [i for i, f in enumerate(frames) if f[3]]
    i = shown[len(shown) // 2]
    t_ns, img, truth, _ = frames[i]
    away = RsuPipeline(camera)
    away.add_vehicle(bus)
    # 0.4 s ago, 45 m behind the south-west RSU and driving away from it: it cannot be in view
    away.coarse_position(bus.id, t_ns - 4 * S // 10, -45.0, -40.0, 0.5, velocity=(-5.0, -5.0), velocity_sigma=0.3)
    frame = Decoder(img)
    res = away.process(frame, t_ns)
    assert res.vehicles[bus.id].mode == "out_of_view" and not res.acquired and frame.calls == 0
    # The bus's true position 0.4 s ago and its velocity: predicted into view, searched and found.
    j = max(i - 4, 0)
    near = RsuPipeline(camera)
    near.add_vehicle(bus)
    near.coarse_position(bus.id, frames[j][0], frames[j][2][0], frames[j][2][1], 0.5,
                         velocity=_velocity(frames, j), velocity_sigma=0.3)
    res = near.process(Decoder(img), t_ns)
    assert res.acquired and res.vehicles[bus.id].fix is not None
    # Far, but uncertain (a lost filter's 12 m): it may be in view, so it is searched (this camera alone: at
    # once, not held back for a likelier RSU's fix, PipelineSettings.acquire_defer_frames).
    vague = RsuPipeline(camera, PipelineSettings(acquire_defer_frames=0))
    vague.add_vehicle(bus)
    vague.coarse_position(bus.id, t_ns, truth[0] + 25.0, truth[1] + 25.0, 12.0, velocity=(0.0, 0.0),
                          velocity_sigma=0.5)
    assert vague.process(Decoder(img), t_ns).acquired


def test_a_sure_report_with_heading_is_cropped_for_like_another_rsus_fix(bus_pass):
    """A fused pose with heading, 0.3 s old and sure to a few cm: the RSU crops where the tags must be
    (no search); out of view, it does not even decode; after a few fruitless crops, it searches again."""
    camera, bus, frames = bus_pass
    shown = [i for i, f in enumerate(frames) if f[3]]
    i = shown[len(shown) // 2]
    t_ns, img, truth, _ = frames[i]
    j = i - 3
    vel = _velocity(frames, j)
    p = RsuPipeline(camera)
    p.add_vehicle(bus)
    p.coarse_position(bus.id, frames[j][0], frames[j][2][0], frames[j][2][1], 0.05, velocity=vel, velocity_sigma=0.1,
                      yaw=frames[j][2][2], yaw_sigma=0.01)
    res = p.process(Decoder(img), t_ns)
    vr = res.vehicles[bus.id]
    assert vr.mode == "hinted" and not res.acquired and vr.fix is not None
    assert np.hypot(vr.fix.x - truth[0], vr.fix.y - truth[1]) < 0.3
    # The same report, 40 m off behind the camera: no tag region in the image, nothing decoded.
    q = RsuPipeline(camera)
    q.add_vehicle(bus)
    q.coarse_position(bus.id, t_ns, -50.0, -45.0, 0.05, velocity=(-3.0, -3.0), velocity_sigma=0.1, yaw=-2.4,
                      yaw_sigma=0.01)
    frame = Decoder(img)
    assert q.process(frame, t_ns).vehicles[bus.id].mode == "out_of_view" and frame.calls == 0
    # A report that is wrong (the bus 7 m from where it says, both in view): crops find nothing; after
    # three frames, the bus is searched for again, and found.
    w = RsuPipeline(camera)
    w.add_vehicle(bus)
    modes = []
    for k in range(i, min(i + 8, len(frames))):
        t_k, img_k, pose, _ = frames[k]
        aim = camera.backproject_to_plane(np.array([[480.0, 360.0]]), pose[3])[0, :2] - np.asarray(pose[:2])
        off = 7.0 * aim / np.linalg.norm(aim)  # toward the image's centre: the wrong place is in view too
        w.coarse_position(bus.id, t_k, pose[0] + off[0], pose[1] + off[1], 0.05, velocity=(0.0, 0.0),
                          velocity_sigma=0.1, yaw=pose[2], yaw_sigma=0.01)
        res = w.process(img_k, t_k)
        modes.append(res.vehicles[bus.id].mode)
        if res.vehicles[bus.id].fix is not None:
            break
    assert modes[:3] == ["searching"] * 3 and w.tracks[bus.id].found


def test_a_bus_entering_the_view_is_acquired_as_soon_as_without_its_whereabouts(bus_pass):
    """The whole pass with the RSU's pipeline: once without any position, once with the bus's reports
    every 0.2 s (its true pose 0.1 s old, 1 m off, sigma 0.5 m, as its filter would say). The first fix comes
    on the same frame; before its tags are in view, the reports narrow the searches."""
    camera, bus, frames = bus_pass
    blind, told = RsuPipeline(camera), RsuPipeline(camera)
    for p in (blind, told):
        p.add_vehicle(bus)
    first = {}
    searched = {"blind": 0, "told": 0}  # pixels, before the tags are in view
    for i, (t_ns, img, truth, visible) in enumerate(frames):
        if i % 2 == 0 and i > 0:
            t_rep, _, pose, _ = frames[i - 1]
            told.coarse_position(bus.id, t_rep, pose[0] + 0.7, pose[1] - 0.7, 0.5, velocity=_velocity(frames, i - 1),
                                 velocity_sigma=0.3)
        for name, p in (("blind", blind), ("told", told)):
            res = p.process(img, t_ns)
            if "seen" not in first and not visible:
                searched[name] += res.pixels_searched
            if res.vehicles[bus.id].fix is not None:
                first.setdefault(name, i)
        if visible:
            first.setdefault("seen", i)
    assert "blind" in first and first["told"] <= first["blind"]
    assert first["seen"] >= 3 and searched["told"] < searched["blind"]


def test_a_gnss_report_is_trusted_no_better_than_the_floor(bus_pass):
    """A satellite fix 11 m off that claims 0.3 m (multipath near buildings): at its stated sigma it rules
    out the part of the image where the bus is; with the RSU's floor on a GNSS sigma (3 x 2 m) the bus is
    searched for there and found. A fused pose (an RSU-fixed filter's) keeps its own sigma."""
    camera, bus, frames = bus_pass
    shown = [i for i, f in enumerate(frames) if f[3]]
    t_ns, img, truth, _ = frames[shown[len(shown) // 2]]
    off = np.asarray(truth[:2]) + 11.0 * np.array([-1.0, 1.0]) / np.sqrt(2)  # off toward the view's edge
    found = {}
    for source in ("fused", "gnss"):
        c = CoarsePosition(t_ns=t_ns, x=float(off[0]), y=float(off[1]), sigma_m=0.3, source=source)
        r = reported_position(c)
        assert r.sigma_m == (GNSS_SIGMA_FLOOR_M if source == "gnss" else 0.3)
        p = RsuPipeline(camera, PipelineSettings(acquire_defer_frames=0))  # searched at once where it may be
        p.add_vehicle(bus)
        p.report_position(bus.id, r)
        found[source] = p.process(Decoder(img), t_ns).vehicles[bus.id].fix is not None
    assert found == {"fused": False, "gnss": True}
    assert reported_position(CoarsePosition(t_ns=1, x=0.0, y=0.0, sigma_m=9.0)).sigma_m == 9.0  # wider: kept
