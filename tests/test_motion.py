"""Bus motion (sim/motion.py): routes through the SPEC intersection, smoothness, speed limit, stop,
roof bounce, and the synthetic IMU / odometry."""
import math

import numpy as np
import pytest

from sim.motion import (
    ImuModel,
    Path,
    RoofBounce,
    Segment,
    SpeedProfile,
    bus_trajectory,
    dead_reckon,
    route_path,
    turn_segments,
)
from sim.scene import LANE_WIDTH, ROAD_HALF_WIDTH
from toptag.limits import BUS_MAX_SPEED_MPS

pytestmark = pytest.mark.unit

KINDS = ["straight", "left", "right", "stop"]
APPROACHES = ["w", "s", "e", "n"]
DT = 1e-3


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def dense(traj, dt=DT):
    t = np.arange(0.0, traj.duration, dt)
    return t, traj.state_at(t)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("approach", APPROACHES)
def test_speed_limit_and_smoothness(kind, approach):
    traj = bus_trajectory(kind, approach)
    t, st = dense(traj)
    assert st.speed.max() <= BUS_MAX_SPEED_MPS + 1e-9 and st.speed.min() >= 0.0
    # continuous heading, speed, yaw rate (curvature) and acceleration: small steps at 1 ms
    assert np.max(np.abs(st.yaw_rate)) < 1.2 and np.max(np.abs(st.accel_long)) < 2.5
    assert np.max(np.abs(_wrap(np.diff(st.yaw)))) <= 1.001 * np.max(np.abs(st.yaw_rate)) * DT + 1e-12
    assert np.max(np.abs(np.diff(st.speed))) <= 1.001 * np.max(np.abs(st.accel_long)) * DT + 1e-12
    yaw_acc = np.max(np.abs(traj.yaw_accel_at(t)))
    assert yaw_acc < 3.5  # clothoids: bounded yaw acceleration, no curvature jump
    assert np.max(np.abs(np.diff(st.yaw_rate))) <= 1.001 * yaw_acc * DT + 1e-12
    assert np.max(np.abs(np.diff(st.accel_long))) < 1.5 * DT  # jerk <= 1.5 m/s³
    # the position moves with the reported speed and heading
    vx = np.diff(st.x) / DT
    vy = np.diff(st.y) / DT
    ym = st.yaw[:-1] + 0.5 * _wrap(np.diff(st.yaw))
    vm = 0.5 * (st.speed[1:] + st.speed[:-1])
    assert np.max(np.hypot(vx - vm * np.cos(ym), vy - vm * np.sin(ym))) < 1e-3
    # yaw rate and accelerations agree with finite differences of yaw and speed
    assert np.max(np.abs(_wrap(np.diff(st.yaw)) / DT - 0.5 * (st.yaw_rate[1:] + st.yaw_rate[:-1]))) < 1e-3
    assert np.max(np.abs(np.diff(st.speed) / DT - 0.5 * (st.accel_long[1:] + st.accel_long[:-1]))) < 1e-3
    assert np.allclose(st.accel_lat, st.speed * st.yaw_rate)


def _lane_ok(x, y, yaw):
    """Right-hand traffic: the bus is on the right half of its road, inside the carriageway."""
    c, s = math.cos(yaw), math.sin(yaw)
    if abs(c) > 0.99:  # along the x road, y is the lateral offset; right of travel is -y for eastbound
        lateral = -y * np.sign(c)
    else:
        lateral = x * np.sign(s)
    return 0.0 < lateral < ROAD_HALF_WIDTH


@pytest.mark.parametrize("approach", APPROACHES)
@pytest.mark.parametrize("kind,turn,lane", [("straight", 0.0, LANE_WIDTH / 2), ("stop", 0.0, LANE_WIDTH / 2),
                                            ("left", math.pi / 2, LANE_WIDTH / 2),
                                            ("right", -math.pi / 2, LANE_WIDTH / 2)])
def test_routes_start_and_end_where_expected(kind, turn, lane, approach):
    traj = bus_trajectory(kind, approach, start_dist=40.0, end_dist=35.0)
    s0, s1 = traj.state_at(0.0), traj.state_at(traj.duration)
    yaw_in = {"w": 0.0, "s": math.pi / 2, "e": math.pi, "n": -math.pi / 2}[approach]
    assert abs(_wrap(s0.yaw - yaw_in)) < 1e-9
    assert abs(_wrap(s1.yaw - yaw_in - turn)) < 1e-6
    # start: 40 m before the centre on the approach road, in the expected lane (right turns come
    # from the outer lane)
    fwd = np.array([math.cos(yaw_in), math.sin(yaw_in)])
    right = np.array([math.sin(yaw_in), -math.cos(yaw_in)])
    p0 = np.array([s0.x, s0.y])
    assert p0 @ fwd == pytest.approx(-40.0, abs=1e-6)
    assert p0 @ right == pytest.approx(lane if kind != "right" else 1.5 * LANE_WIDTH, abs=1e-6)
    # end: 35 m past the centre on the exit road, in the same kind of lane on its right side
    yaw_out = yaw_in + turn
    fwd2 = np.array([math.cos(yaw_out), math.sin(yaw_out)])
    right2 = np.array([math.sin(yaw_out), -math.cos(yaw_out)])
    p1 = np.array([s1.x, s1.y])
    assert p1 @ fwd2 == pytest.approx(35.0, abs=1e-6)
    assert p1 @ right2 == pytest.approx(lane, abs=1e-6)
    assert _lane_ok(s0.x, s0.y, s0.yaw) and _lane_ok(s1.x, s1.y, s1.yaw)


def test_turns_have_continuous_curvature_and_stay_on_the_road():
    for kind in ("left", "right"):
        traj = bus_trajectory(kind, "w")
        t, st = dense(traj, 0.01)
        k = st.yaw_rate / st.speed
        assert np.max(np.abs(np.diff(k))) < 0.01  # clothoids: no curvature jump
        assert abs(k[0]) < 1e-12 and abs(k[-1]) < 1e-12
        # inside the intersection box or on a road, the centre line >= 1.5 m from every kerb corner
        inside = (np.abs(st.x) <= ROAD_HALF_WIDTH) | (np.abs(st.y) <= ROAD_HALF_WIDTH)
        assert inside.all()
        h = ROAD_HALF_WIDTH
        for cx, cy in ((h, h), (h, -h), (-h, h), (-h, -h)):
            assert np.min(np.hypot(st.x - cx, st.y - cy)) > 1.5


def test_turn_speed_slows_for_the_turn_only():
    traj = bus_trajectory("right", "n", turn_speed=4.0)
    t, st = dense(traj, 0.01)
    turning = np.abs(st.yaw_rate) > 1e-6
    assert np.allclose(st.speed[turning], 4.0)
    assert st.speed[0] == pytest.approx(BUS_MAX_SPEED_MPS)
    after = np.argmax(turning) + np.sum(turning)
    assert np.all(np.diff(st.speed[after:]) >= 0) and st.speed[-1] > 6.0  # speeding up again
    assert np.max(np.abs(st.accel_lat)) < 2.5
    with pytest.raises(ValueError):
        bus_trajectory("left", stop=True, turn_speed=4.0)


def test_stop_decelerates_waits_and_goes():
    traj = bus_trajectory("stop", "s", stop_wait_s=3.0)
    t, st = dense(traj, 0.01)
    stopped = st.speed < 1e-9
    assert 2.9 < stopped.sum() * 0.01 < 3.2
    i = np.argmax(stopped)
    # at rest just before the stop line of the south approach (heading north, y < -ROAD_HALF_WIDTH)
    assert -ROAD_HALF_WIDTH - 3.0 < st.y[i] < -ROAD_HALF_WIDTH
    assert st.speed[0] == pytest.approx(BUS_MAX_SPEED_MPS) and st.speed[-1] == pytest.approx(BUS_MAX_SPEED_MPS)
    assert np.max(np.abs(st.accel_long)) < 3.5  # comfortable for a bus
    # a stop also works on a turn
    tl = bus_trajectory("left", "w", stop=True)
    assert np.min(tl.state_at(np.arange(0, tl.duration, 0.05)).speed) < 1e-9
    assert tl.duration > bus_trajectory("left", "w").duration + 3.0


def test_speed_limit_is_enforced():
    with pytest.raises(ValueError):
        SpeedProfile(10.0)
    with pytest.raises(ValueError):
        bus_trajectory("left", speed=9.0)
    with pytest.raises(ValueError):
        route_path("uturn")


def test_roof_bounce_band_limited_and_bounded():
    traj = bus_trajectory("straight", "w", seed=5, bounce_amplitude=0.10)
    t = np.arange(0.0, 60.0, 0.01)
    dz = traj.state_at(t).roof_dz
    assert np.max(np.abs(dz)) <= 0.10 + 1e-12
    assert np.max(np.abs(dz)) > 0.05  # it does move
    spec = np.abs(np.fft.rfft(dz)) ** 2
    f = np.fft.rfftfreq(len(dz), 0.01)
    assert spec[f > 3.0].sum() < 1e-3 * spec.sum()  # nothing above 3 Hz
    assert not np.allclose(RoofBounce(seed=1)(t), RoofBounce(seed=2)(t))
    flat = bus_trajectory("straight", "w", bounce_amplitude=0.0)
    assert np.all(flat.state_at(t).roof_dz == 0.0)


def test_state_at_vectorised_equals_scalar_and_time_mapping():
    traj = bus_trajectory("right", "e")
    t = np.array([0.0, 1.234, 3.3, traj.duration])
    vec = traj.state_at(t)
    for i, ti in enumerate(t):
        sc = traj.state_at(float(ti))
        assert isinstance(sc.x, float)
        for name in ("x", "y", "yaw", "speed", "yaw_rate", "accel_long", "accel_lat", "roof_dz"):
            assert getattr(sc, name) == pytest.approx(getattr(vec, name)[i], abs=1e-12)
    t_ns = traj.t_ns(1.5)
    assert isinstance(t_ns, int) and traj.seconds(t_ns) == pytest.approx(1.5)
    assert traj.state_at_ns(t_ns).x == pytest.approx(traj.state_at(1.5).x)
    # beyond the ends: straight continuation
    after = traj.state_at(traj.duration + 1.0)
    end = traj.state_at(traj.duration)
    assert math.hypot(after.x - end.x, after.y - end.y) == pytest.approx(end.speed, rel=1e-6)


def test_path_geometry_is_exact_for_an_arc():
    r = 10.0
    p = Path(0.0, 0.0, 0.0, [Segment(r * math.pi / 2, 1.0 / r)])
    x, y, yaw, k = p.pose_at(np.linspace(0, p.length, 50))
    s = np.linspace(0, p.length, 50)
    assert np.allclose(x, r * np.sin(s / r), atol=1e-9) and np.allclose(y, r * (1 - np.cos(s / r)), atol=1e-9)
    assert np.allclose(k, 0.1)
    segs = turn_segments(math.pi / 2, 8.0, 4.0)  # the two clothoids turn 4 / 8 rad in 8 m
    assert sum(s.length for s in segs) == pytest.approx(8.0 * math.pi / 2 + 4.0)
    assert [s.k_end for s in segs] == [0.125, 0.125, 0.0]
    with pytest.raises(ValueError):
        turn_segments(math.pi / 2, 2.0, 10.0)


def test_imu_noise_free_integration_reproduces_the_trajectory():
    traj = bus_trajectory("left", "w")
    imu = ImuModel.perfect().synthesize(traj, 2.0, 7.0)
    assert np.allclose(np.diff(imu.t), 0.01) and len(imu) == 501
    assert np.all(np.diff(imu.t_ns) == 10_000_000)
    st = traj.state_at(imu.t)
    x, y, yaw = dead_reckon(imu, st.x[0], st.y[0], st.yaw[0])
    assert np.max(np.hypot(x - st.x, y - st.y)) < 0.01
    assert np.max(np.abs(_wrap(yaw - st.yaw))) < 1e-4
    assert np.allclose(imu.accel_x, st.accel_long) and np.allclose(imu.accel_y, st.speed * st.yaw_rate)


def test_imu_with_noise_integrates_close_and_has_the_stated_statistics():
    traj = bus_trajectory("left", "w")
    model = ImuModel()
    imu = model.synthesize(traj, 0.0, traj.duration, np.random.default_rng(3))
    again = model.synthesize(traj, 0.0, traj.duration, np.random.default_rng(3))
    assert np.array_equal(imu.gyro_z, again.gyro_z)  # seeded
    st = traj.state_at(imu.t)
    g_err = imu.gyro_z - st.yaw_rate - imu.gyro_bias
    assert np.std(g_err) == pytest.approx(model.gyro_noise_density * 10.0, rel=0.1)
    w_err = imu.wheel_speed - imu.wheel_scale * st.speed
    assert np.std(w_err) == pytest.approx(model.wheel_speed_sigma, rel=0.1)
    assert abs(imu.wheel_scale - 1.0) < 5 * model.wheel_scale_sigma
    # 3 s of dead reckoning with the true bias and scale removed stays within a few cm
    sel = (imu.t >= 3.0) & (imu.t <= 6.0)
    sub = type(imu)(imu.t[sel], imu.t_ns[sel], imu.gyro_z[sel] - imu.gyro_bias[sel], imu.accel_x[sel],
                    imu.accel_y[sel], imu.wheel_speed[sel] / imu.wheel_scale, imu.gyro_bias[sel], 1.0)
    s = traj.state_at(sub.t)
    x, y, _ = dead_reckon(sub, s.x[0], s.y[0], s.yaw[0])
    assert np.max(np.hypot(x - s.x, y - s.y)) < 0.05
    # raw (biased) dead reckoning drifts, but by metres at most over the whole route
    x, y, _ = dead_reckon(imu, st.x[0], st.y[0], st.yaw[0])
    assert np.max(np.hypot(x - st.x, y - st.y)) < 6.0
