"""The live simulator: the scenario file and the world (no Zenoh), and `toptag sim run` as a real
process publishing over real Zenoh sessions (peer, multicast scouting off, tcp/127.0.0.1:<free port>)."""
from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import REPO, clean_env

from sim.motion import bus_trajectory
from sim.scenario import Scenario, bundled_scenario_path, leg_seed, load_scenario
from sim.world import World
from toptag.inputs import InputError
from toptag.waiting import wait_until
from toptag.units import NS_PER_S, ns_from_s

DEMO = REPO / "toptag" / "data" / "demo"
TOPTAG = ["-c", "from toptag.cli import main; main()"]


@pytest.fixture(scope="module")
def bundled() -> World:
    return World(load_scenario(bundled_scenario_path()))


def _write(tmp_path: Path, data: dict, name: str = "scenario.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


def _short_scenario(**over) -> dict:
    """Two RSUs (rsu-ne at 5 fps), two buses driving west->east 3 s apart, starting 34 m out (GNSS
    fixes until the shadow); paths absolute (into the bundled demo site)."""
    data = {
        "intersection_id": "x1", "map": str(DEMO / "map.json"),
        "rsus": [str(DEMO / "rsu-sw.json"), {"camera": str(DEMO / "rsu-ne.json"), "fps": 5}],
        "fps": 10, "imu_hz": 100, "truth_hz": 20, "gnss_hz": 5, "gnss_sigma_m": 2.0, "seed": 3,
        "buses": [
            {"vehicle": str(DEMO / "bus-17.json"),
             "legs": [{"route": "straight", "approach": "w", "start_s": 0, "speed": 8, "start_dist": 34,
                       "end_dist": 40}]},
            {"vehicle": str(DEMO / "bus-42.json"),
             "legs": [{"route": "straight", "approach": "w", "start_s": 3, "speed": 8, "start_dist": 34,
                       "end_dist": 40}]},
        ],
    }
    data.update(over)
    return data


# ---- scenario files -----------------------------------------------------------------------------

@pytest.mark.unit
def test_a_scenario_batches_no_more_imu_samples_than_a_message_holds():
    from protocol.messages import IMU_BATCH_MAX
    from sim.scenario import IMU_PER_MESSAGE_MAX
    assert IMU_PER_MESSAGE_MAX == IMU_BATCH_MAX


@pytest.mark.unit
def test_bundled_scenario_loads_with_package_paths(bundled):
    sc = bundled.scenario
    assert bundled_scenario_path().is_file()
    assert sc.loop and sc.intersection_id == "x1" and sc.fps == 10
    assert bundled.rsu_ids == ["rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"]
    assert bundled.bus_ids == ["bus-17", "bus-42"]
    assert all(c.width == 960 and c.height == 720 for c in bundled.cameras)
    assert Path(sc.map).is_absolute() and Path(sc.map).parent == bundled_scenario_path().parent
    routes = {(b.id, lr.leg.route, lr.leg.approach) for b in bundled.buses for lr in b.legs}
    assert ("bus-17", "left", "n") in routes and ("bus-42", "straight", "e") in routes
    assert any(lr.leg.route == "stop" or lr.leg.stop for b in bundled.buses for lr in b.legs)
    # each bus comes back every 25-32 s
    P = bundled.period_ns / NS_PER_S
    for b in bundled.buses:
        starts = sorted(lr.start_ns / NS_PER_S for lr in b.legs)
        gaps = np.diff(starts + [starts[0] + P])
        assert np.all((gaps > 24) & (gaps < 32)), (b.id, gaps)


@pytest.mark.unit
def test_bundled_buses_never_collide(bundled):
    assert bundled.conflicts(step_s=0.05) == []  # sim.sampling.footprints_overlap, 0.5 m clearance
    assert bundled.conflicts(step_s=0.05, conservative=False, clearance=1.0) == []


@pytest.mark.unit
def test_every_bundled_leg_is_seen_by_several_rsus(bundled):
    for b in bundled.buses:
        for lr in b.legs:
            seen = {r: 0.0 for r in bundled.rsu_ids}
            for t in range(lr.start_ns, lr.end_ns, NS_PER_S // 5):
                for r in bundled.rsu_ids:
                    if bundled.tags_in_view(r, t).get(b.id):
                        seen[r] += 0.2
            assert sum(s >= 2.0 for s in seen.values()) >= 2, (b.id, lr.index, seen)
            # the demo's poles share a leg between them, each its stretch of the road: one sees 3 s of it
            assert max(seen.values()) >= 3.0, (b.id, lr.index, seen)


@pytest.mark.parametrize("change, expected", [
    (lambda d: d.update(colour=1), "colour: Extra inputs are not permitted"),
    (lambda d: d["buses"][0]["legs"][0].update(route="uturn"), "buses.0.legs.0.route"),
    (lambda d: d["buses"][0]["legs"][0].update(speed=20), "buses.0.legs.0.speed"),
    (lambda d: d["buses"][0]["legs"].append({"route": "left", "approach": "n", "start_s": 2}),
     "buses[0].legs[1]: starts at 2 s, before legs[0] ends"),
    (lambda d: d["buses"][0]["legs"][0].update(route="stop", start_dist=12),
     "stop too close to the start"),
    (lambda d: d.update(image_model={"noise_sigma": -1}), "image_model.noise_sigma"),
    (lambda d: d.update(rsus=[]), "rsus: List should have at least 1 item"),
    (lambda d: d.update(imu_per_message=101), "imu_per_message: Input should be less than or equal to 100"),
])
@pytest.mark.unit
def test_bad_scenarios_give_one_line_naming_the_field(tmp_path, change, expected):
    data = _short_scenario()
    change(data)
    with pytest.raises(InputError) as e:
        load_scenario(_write(tmp_path, data))
    msg = str(e.value)
    assert expected in msg and "\n" not in msg and "scenario file" in msg


@pytest.mark.unit
def test_relative_paths_resolve_against_the_scenario_file(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    for f in ("map.json", "rsu-sw.json", "bus-17.json"):
        (site / f).write_text((DEMO / f).read_text())
    data = _short_scenario(map="site/map.json", rsus=["site/rsu-sw.json"])
    data["buses"] = [dict(data["buses"][0], vehicle="site/bus-17.json")]
    sc = load_scenario(_write(tmp_path, data))
    assert sc.map == str(site / "map.json") and sc.rsus[0].camera == str(site / "rsu-sw.json")
    assert World(sc).bus_ids == ["bus-17"]
    data["rsus"] = ["site/nowhere.json"]
    with pytest.raises(InputError, match="nowhere.json: no such file"):
        World(load_scenario(_write(tmp_path, data)))
    with pytest.raises(InputError, match="no intersection 'x9'"):
        World(load_scenario(_write(tmp_path, dict(data, rsus=["site/rsu-sw.json"], intersection_id="x9"))))


# ---- the world ----------------------------------------------------------------------------------

@pytest.mark.unit
def test_truth_follows_sim_motion_and_buses_exist_only_during_legs(bundled):
    w = World(bundled.scenario)
    t0 = 1_800_000_000_000_000_000
    w.start(t0)
    sc = w.scenario
    P = w.period_ns
    for a, bus in enumerate(sc.buses):
        vid = w.bus_ids[a]
        for i, leg in enumerate(bus.legs):
            traj = bus_trajectory(leg.route, leg.approach, speed=leg.speed, stop=leg.stop,
                                  stop_wait_s=leg.stop_wait_s, turn_speed=leg.turn_speed,
                                  bounce_amplitude=bus.bounce_amplitude, seed=leg_seed(sc.seed, 0, a, i),
                                  start_dist=leg.start_dist, end_dist=leg.end_dist,
                                  t0_ns=t0 + P + int(round(leg.start_s * NS_PER_S)))  # second loop pass
            for t in np.linspace(0.0, traj.duration, 13):
                t_ns = traj.t_ns(t)
                s, ref = w.state(vid, t_ns), traj.state_at_ns(t_ns)
                assert s is not None and s.leg == i and s.cycle == 1
                assert abs(s.x - ref.x) < 1e-6 and abs(s.y - ref.y) < 1e-6 and abs(s.yaw - ref.yaw) < 1e-9
                assert abs(s.z - (3.0 + ref.roof_dz)) < 1e-9 and abs(s.speed - ref.speed) < 1e-9
            assert w.state(vid, traj.t_ns(traj.duration) + 10_000_000) is None  # parked away between legs
            assert w.state(vid, traj.t0_ns - 10_000_000) is None
    assert w.truth_at(t0 - 1) == {}
    # between the last leg end and the loop repeat nobody is on the road
    assert w.truth_at(t0 + w.legs_end_ns + NS_PER_S) == {}
    assert w.vehicles_at(t0 + w.legs_end_ns + NS_PER_S) == []
    placed = w.vehicles_at(t0 + 10 * NS_PER_S)
    truth = w.truth_at(t0 + 10 * NS_PER_S)
    assert {p.vehicle.id for p in placed} == set(truth)
    for p in placed:
        s = truth[p.vehicle.id]
        assert (p.x, p.y, p.yaw, p.roof_z, p.speed, p.yaw_rate) == (s.x, s.y, s.yaw, s.z, s.speed, s.yaw_rate)


@pytest.mark.unit
def test_imu_carries_the_noise_model_and_follows_the_truth(bundled):
    w = World(bundled.scenario)
    w.start(0)
    bus = "bus-42"
    lr = w.actor(bus).legs[1]  # the stop leg: braking, standstill, accelerating
    chunks = []
    t = lr.start_ns - NS_PER_S
    while t < lr.end_ns + NS_PER_S:  # in 10 ms windows, like the live loop
        chunks.append(w.imu_between(bus, t, t + 10_000_000))
        t += 10_000_000
    # a window reaching back is clipped: no sample twice
    assert len(w.imu_between(bus, lr.start_ns, lr.end_ns)) == 0
    t_ns = np.concatenate([c.t_ns for c in chunks])
    seq = np.concatenate([c.seq for c in chunks])
    assert np.all(np.diff(t_ns) == 10_000_000) and np.all(np.diff(seq) == 1)
    assert t_ns[0] >= lr.start_ns and t_ns[-1] <= lr.end_ns and abs(len(t_ns) - lr.duration_ns / 1e7) <= 1
    st = lr.trajectory.state_at((t_ns - lr.start_ns) * 1e-9)
    gyro = np.concatenate([c.gyro_z for c in chunks])
    bias = np.concatenate([c.gyro_bias for c in chunks])
    m = w.scenario.imu_model
    sq = np.sqrt(w.scenario.imu_hz)
    assert np.std(gyro - st.yaw_rate - bias) == pytest.approx(m.gyro_noise_density * sq, rel=0.1)
    assert abs(bias[0]) < 5 * m.gyro_bias_sigma and np.ptp(bias) < 10 * m.gyro_bias_walk * np.sqrt(30)
    ax = np.concatenate([c.accel_x for c in chunks]) - chunks[0].accel_bias[0]
    assert np.std(ax - st.accel_long) == pytest.approx(m.accel_noise_density * sq, rel=0.1)
    wheel = np.concatenate([c.wheel_speed for c in chunks])
    assert np.std(wheel - chunks[0].wheel_scale * st.speed) == pytest.approx(m.wheel_speed_sigma, rel=0.1)
    assert st.speed.min() < 1e-6  # the stop is in there

    # with a perfect sensor the samples are the truth
    perfect = {k: 0.0 for k in m.model_dump()}
    wp = World(Scenario.model_validate(dict(bundled.scenario.model_dump(), imu_model=perfect)))
    b = wp.imu_between(bus, lr.start_ns, lr.start_ns + 3 * NS_PER_S)
    st = lr.trajectory.state_at((b.t_ns - lr.start_ns) * 1e-9)
    assert np.allclose(b.gyro_z, st.yaw_rate) and np.allclose(b.accel_y, st.accel_lat)
    assert np.allclose(b.wheel_speed, st.speed) and np.allclose(b.accel_x, st.accel_long)


@pytest.mark.unit
def test_gnss_only_outside_the_shadow_and_with_its_sigma(bundled):
    w = World(bundled.scenario)
    w.start(0)
    fixes = []
    for t in range(0, 2 * w.period_ns, NS_PER_S // 2):
        for b in w.bus_ids:
            fixes += w.gnss_between(b, t, t + NS_PER_S // 2)
    assert fixes
    shadow = w.intersection.gnss_shadow_radius
    err = []
    for g in fixes:
        s = w.state(g.bus_id, g.t_ns)
        assert s is not None and np.hypot(s.x, s.y) >= shadow and g.sigma_m == 2.0
        err += [g.x - s.x, g.y - s.y]
    assert np.std(err) == pytest.approx(2.0, rel=0.25)
    # each leg: fixes before entering and after leaving the shadow, none in between
    for b in w.buses:
        for lr in b.legs:
            ts = [g.t_ns for g in fixes if g.bus_id == b.id and lr.start_ns <= g.t_ns <= lr.end_ns]
            assert len(ts) >= 5, (b.id, lr.index, len(ts))
            assert max(np.diff(ts)) > 2 * NS_PER_S  # the silent stretch through the intersection (20 m of road)


@pytest.mark.unit
def test_frames_are_staggered_on_a_fixed_schedule(tmp_path):
    w = World(load_scenario(_write(tmp_path, _short_scenario())))
    w.start(1_000 * NS_PER_S)
    assert [w.frame_time(0, k) - 1_000 * NS_PER_S for k in range(3)] == [0, 100_000_000, 200_000_000]
    assert [w.frame_time("rsu-ne", k) - 1_000 * NS_PER_S for k in range(3)] == [100_000_000, 300_000_000, 500_000_000]
    for r in range(2):
        for t in (1_000 * NS_PER_S - 5, 1_000 * NS_PER_S + 123_456_789, 1_003 * NS_PER_S):
            k = w.frame_index_from(r, t)
            assert w.frame_time(r, k) >= t and (k == 0 or w.frame_time(r, k - 1) < t)


@pytest.mark.unit
def test_trucks_drive_their_legs_and_occlude(tmp_path):
    data = _short_scenario(trucks=[{"length": 9, "width": 2.5, "height": 3.8,
                                    "legs": [{"route": "straight", "approach": "e", "start_s": 1}]}])
    w = World(load_scenario(_write(tmp_path, data)))
    w.start(0)
    assert w.occluders_at(0) == [] and w.bus_ids == ["bus-17", "bus-42"]
    occ = w.occluders_at(5 * NS_PER_S)
    s = w.state("truck-1", 5 * NS_PER_S)
    assert len(occ) == 1 and (occ[0].x, occ[0].y, occ[0].height) == (s.x, s.y, 3.8)
    assert abs(s.yaw - np.pi) < 1e-9 and s.y > 0  # westbound, north half
    img = cv2.imdecode(np.frombuffer(w.render_jpeg("rsu-sw", 5 * NS_PER_S), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (720, 960)


# ---- the process --------------------------------------------------------------------------------

class Inbox:
    def __init__(self):
        self.items = []
        self.lock = threading.Lock()

    def __call__(self, msg):
        now = time.time_ns()
        with self.lock:
            self.items.append((now, msg))


@pytest.mark.integration
def test_sim_run_publishes_frames_imu_truth_and_gnss_on_schedule(tmp_path, launch, free_port, zenoh_session):
    from protocol import Frame, GnssFix, GroundTruth, Imu, ImuBatch, keys
    from protocol.transport import subscribe_messages

    # rsu-nw's pole looks down the eastbound lane the buses come in on
    rsus = [str(DEMO / "rsu-nw.json"), {"camera": str(DEMO / "rsu-ne.json"), "fps": 5}]
    path = _write(tmp_path, _short_scenario(rsus=rsus))
    world = World(load_scenario(path))
    ep = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh_session("peer", listen=[ep])
    boxes = {}
    subs = []
    for kind, key_fn, typ, ids in (("frame", keys.frame, Frame, world.rsu_ids), ("imu", keys.imu, Imu, world.bus_ids),
                                   ("imu_batch", keys.imu_batch, ImuBatch, world.bus_ids),
                                   ("truth", keys.ground_truth, GroundTruth, world.bus_ids),
                                   ("gnss", keys.gnss, GnssFix, world.bus_ids)):
        for i in ids:
            boxes[kind, i] = Inbox()
            subs.append(subscribe_messages(session, key_fn(i), typ, boxes[kind, i], capacity=4096))
    proc = launch([*TOPTAG, "sim", "run", "--scenario", str(path), "--duration", "6", "--connect", ep],
                  ready="sim running")
    t0 = int(re.search(r"t0_ns=(\d+)", proc.output()).group(1))
    proc.proc.wait(90)
    assert proc.proc.returncode == 0, proc.output()[-2000:]
    out = proc.output()
    assert "sim stopped after" in out and "Traceback" not in out
    for s in subs:
        s.close()
    world.start(t0)

    # frames: every tick of every RSU's schedule was published or (late, on a busy machine) skipped
    # and counted; what arrives is right-sized, stamped on the schedule, and arrives after its capture
    published = dict(re.findall(r"(rsu-\w+) (\d+)", re.search(r"sim stopped after .*?frames (.*?);", out).group(1)))
    skipped = int(re.search(r"sim stopped after .*?skipped (\d+)", out).group(1))
    ticks = {r: world.frame_index_from(r, t0 + 6 * NS_PER_S) for r in world.rsu_ids}
    assert sum(int(published[r]) for r in world.rsu_ids) + skipped == sum(ticks.values()), (published, skipped, ticks)
    for r in world.rsu_ids:
        items = boxes["frame", r].items
        assert 1 <= len(items) <= int(published[r]), (r, len(items), published)
        caps = np.array([m.capture_time_ns for _, m in items])
        seqs = np.array([m.seq for _, m in items])
        assert np.all(np.diff(seqs) >= 1)
        assert np.all(caps == [world.frame_time(r, int(k)) for k in seqs])
        assert all(a > m.capture_time_ns for a, m in items)
        for _, m in items[:: max(1, len(items) // 5)]:
            img = cv2.imdecode(np.frombuffer(m.image, np.uint8), cv2.IMREAD_GRAYSCALE)
            assert (m.encoding, m.width, m.height, img.shape) == ("jpeg", 960, 720, (720, 960))
    # the frame shows the bus where the truth puts it at the capture time
    from sim.raster import raster_for
    cam = world.camera("rsu-nw")
    bg = raster_for(cam).finished_background(world.model).astype(float)

    def centre_offset(m):  # where the truth puts bus-17's roof centre in that frame
        s = world.state("bus-17", m.capture_time_ns)
        return np.round(cam.project(np.array([[s.x, s.y, s.z]]))[0]).astype(int)

    last = min((m for _, m in boxes["frame", "rsu-nw"].items),
               key=lambda m: np.hypot(*(centre_offset(m) - [480, 360])))
    u, v = centre_offset(last)
    img = cv2.imdecode(np.frombuffer(last.image, np.uint8), cv2.IMREAD_GRAYSCALE).astype(float)
    assert 50 < u < 910 and 50 < v < 670
    assert np.abs(img - bg)[v - 40:v + 40, u - 40:u + 40].mean() > 20
    # elsewhere: background + sensor noise (mean |N(0, s)| = 0.8 s) and its JPEG
    assert np.abs(img - bg)[:80, :80].mean() < 0.8 * world.model.noise_sigma + 1.5

    # IMU: every 10 ms sample from the bus's leg start on, none missing (seq +1 per sample); bus-42
    # only from its leg start; four to a message (the scenario's default), each batch sent at its newest
    # sample's time, not before
    for bus, start in (("bus-17", 0), ("bus-42", 3)):
        batches = boxes["imu_batch", bus].items
        assert not boxes["imu", bus].items and all(1 <= len(m.samples) <= 4 for _, m in batches)
        assert sum(len(m.samples) == 4 for _, m in batches) >= 0.8 * len(batches)
        assert np.all(np.diff([m.seq for _, m in batches]) == 1)
        assert all(a >= m.samples[-1].t_ns for a, m in batches)
        items = [(a, s) for a, m in batches for s in m.samples]
        t = np.array([m.t_ns for _, m in items])
        seq = np.array([m.seq for _, m in items])
        assert t0 + start * NS_PER_S <= t.min() <= t0 + start * NS_PER_S + 10_000_000
        assert t.max() <= t0 + 6 * NS_PER_S and len(items) > 50, (bus, len(items))
        assert np.all(np.diff(seq) == 1) and np.all(np.diff(t) == 10_000_000)
        assert all(a >= m.t_ns for a, m in items)
        st = [world.state(bus, int(x)) for x in t]
        gyro = np.array([m.gyro_z for _, m in items]) - np.array([s.yaw_rate for s in st])
        assert abs(np.median(gyro)) < 0.03  # turn-on bias ~0.005 rad/s
        wheel = np.array([m.wheel_speed for _, m in items])
        assert np.median(wheel) == pytest.approx(8.0, rel=0.05)

    # ground truth at 20 Hz: sim.motion's trajectory of the leg
    sc = world.scenario
    for a, bus in enumerate(world.bus_ids):
        leg = sc.buses[a].legs[0]
        traj = bus_trajectory("straight", "w", speed=8, bounce_amplitude=0.10, seed=leg_seed(sc.seed, 0, a, 0),
                              start_dist=34, end_dist=40, t0_ns=t0 + int(leg.start_s * NS_PER_S))
        items = boxes["truth", bus].items
        first = t0 + ns_from_s(leg.start_s)
        assert first <= items[0][1].t_ns <= first + 50_000_000 and len(items) > 5
        for _, m in items:
            ref = traj.state_at_ns(m.t_ns)
            assert abs(m.x - ref.x) < 1e-6 and abs(m.y - ref.y) < 1e-6 and abs(m.yaw - ref.yaw) < 1e-9
            assert abs(m.z - (3.0 + ref.roof_dz)) < 1e-9 and abs(m.speed - ref.speed) < 1e-9
        assert np.all(np.diff([m.t_ns for _, m in items]) == 50_000_000)

    # GNSS: only outside the shadow radius (the first ~3 s of each leg here, and past it), with N(0, 2 m)
    shadow = world.intersection.gnss_shadow_radius
    for bus in world.bus_ids:
        items = boxes["gnss", bus].items
        states = [world.state(bus, t) for t in range(t0, t0 + 6 * NS_PER_S, NS_PER_S // 5)]  # its 5 Hz
        outside = sum(np.hypot(st.x, st.y) >= shadow for st in states if st is not None)
        assert 1 <= len(items) <= outside + 1, (bus, len(items), outside)
        for _, m in items:
            s = world.state(bus, m.t_ns)
            assert np.hypot(s.x, s.y) >= shadow and m.sigma_m == 2.0
            assert np.hypot(m.x - s.x, m.y - s.y) < 10.0


def _descendants(pid: int) -> set[int]:
    from services.processes import parent_pids
    parents = parent_pids()
    tree = {pid}
    while new := {p for p, pp in parents.items() if pp in tree} - tree:
        tree |= new
    return tree - {pid}


def _gone(pid: int) -> bool:
    """Exited (a zombie not yet reaped by whoever adopted it counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] == b"Z"
    except OSError:
        return True


def _render_pids(out: str) -> list[int]:
    return [int(p) for p in re.findall(r"pid (\d+)", re.search(r"render processes: (.*)", out).group(1))]


@pytest.mark.integration
def test_sim_run_stops_on_sigterm(tmp_path, launch, free_port):
    data = _short_scenario()
    proc = launch([*TOPTAG, "sim", "run", "--scenario", str(_write(tmp_path, data)),
                   "--listen", f"tcp/127.0.0.1:{free_port()}"], ready="sim running")
    renderers = _render_pids(proc.output())
    children = _descendants(proc.pid)
    assert renderers and set(renderers) <= children
    from services.processes import cpu_seconds, tree_cpu_seconds
    theirs = sum(cpu_seconds(p) or 0 for p in renderers)  # read first: CPU seconds only grow
    own = cpu_seconds(proc.pid)
    assert tree_cpu_seconds(proc.pid) >= own + theirs > own  # what bench demo counts as the simulator's
    assert proc.stop(timeout=60) == 0  # SIGTERM: a clean exit, not the SIGKILL that follows a timeout
    out = proc.output()
    assert "received SIGTERM" in out and "sim stopped after" in out and "Traceback" not in out
    wait_until(lambda: all(_gone(p) for p in children), 30, 0.05)  # multiprocessing's tracker sees EOF
    assert [p for p in children if not _gone(p)] == []  # every render process (and helper) ended with it


@pytest.mark.integration
def test_sim_run_render_processes_die_with_the_simulator(tmp_path, launch, free_port):
    proc = launch([*TOPTAG, "sim", "run", "--scenario", str(_write(tmp_path, _short_scenario())),
                   "--listen", f"tcp/127.0.0.1:{free_port()}"], ready="sim running")
    children = _descendants(proc.pid)
    assert set(_render_pids(proc.output())) <= children
    os.kill(proc.pid, signal.SIGKILL)
    proc.proc.wait(30)
    wait_until(lambda: all(_gone(p) for p in children), 30, 0.05)
    assert [p for p in children if not _gone(p)] == []


@pytest.mark.integration
@pytest.mark.parametrize("kind", ["field", "camera"])
def test_sim_run_bad_scenario_exits_2_with_one_line(tmp_path, kind):
    data = _short_scenario()
    if kind == "field":
        data["buses"][0]["legs"][0]["approach"] = "x"
    else:
        data["rsus"] = [str(tmp_path / "missing-camera.json")]
    path = _write(tmp_path, data)
    r = subprocess.run([sys.executable, *TOPTAG, "sim", "run", "--scenario", str(path), "--duration", "1"],
                       cwd=REPO, env=clean_env(), capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert ("approach" in lines[0]) if kind == "field" else ("missing-camera.json: no such file" in lines[0])
    assert r.stdout == ""


class _SlowWorld(World):
    """A world whose camera takes 250 ms per frame (module level: a render process unpickles it)."""

    def render_jpeg(self, rsu, t_ns, camera=None):
        time.sleep(0.25)
        return b"\xff\xd8 not really a jpeg \xff\xd9"


def _slow_world(path: str) -> World:
    return _SlowWorld(load_scenario(path))


@pytest.mark.integration
def test_slow_rendering_skips_ticks_and_never_drifts(tmp_path, zenoh_session, free_port):
    """run() in-process on a real session, its render process rendering in 250 ms at 10 fps: late ticks
    are skipped and counted; the frames that go out keep their scheduled capture times."""
    from protocol import Frame, Imu, ImuBatch, keys
    from protocol.transport import subscribe_messages
    from sim.live import run

    path = _write(tmp_path, _short_scenario(rsus=[str(DEMO / "rsu-sw.json")], imu_per_message=1))
    world = World(load_scenario(path))
    ep = f"tcp/127.0.0.1:{free_port()}"
    pub_side = zenoh_session("peer", listen=[ep])
    sub_side = zenoh_session("peer", connect=[ep])
    inbox, imu, batches = Inbox(), Inbox(), Inbox()
    subs = [subscribe_messages(sub_side, keys.frame("rsu-sw"), Frame, inbox),
            subscribe_messages(sub_side, keys.imu("bus-17"), Imu, imu),
            subscribe_messages(sub_side, keys.imu_batch("bus-17"), ImuBatch, batches)]
    stats = run(world, pub_side, threading.Event(), duration_s=2.0,
                make_world=functools.partial(_slow_world, str(path)))
    for sub in subs:
        sub.close()
    # imu_per_message 1: each IMU sample an Imu of its own, sent at its time
    assert len(imu.items) > 100 and not batches.items
    assert np.all(np.diff([m.seq for _, m in imu.items]) == 1) and all(a >= m.t_ns for a, m in imu.items)
    published, skipped = stats.published["rsu-sw"], stats.skipped["rsu-sw"]
    # a render takes 2.5 frame periods: at least one tick is skipped for each frame rendered
    assert published >= 1 and skipped >= published
    assert published + skipped == world.frame_index_from(0, world.t0_ns + 2 * NS_PER_S)  # every tick of the 2 s
    for arrival, m in inbox.items:
        assert m.capture_time_ns == world.frame_time(0, m.seq)
        assert arrival > m.capture_time_ns  # sent after its tick, never ahead of it


@pytest.mark.integration
@pytest.mark.parametrize("count", [1, 2])
def test_render_processes_render_the_frames_of_one_process_on_the_tick_grid(tmp_path, count):
    """The render processes (real spawned processes; one for both RSUs, or one each) render the very frames
    the World renders in this process (same seeds, same ticks, the scenario's faults per camera: a capture
    latency, a clock offset, a turned camera), stamped on each RSU's tick grid; each RSU's frames and
    skipped ranges cover every tick once, in order."""
    from sim.live import START_LEAD_NS, RenderProcesses, world_from_file

    faults = {"rsu-sw": {"capture_latency_ms": 30, "drift": {"yaw_deg": 0.5, "at_s": 0.3}},
              "rsu-ne": {"clock_offset_ms": -12.5}}
    path = str(_write(tmp_path, _short_scenario(faults=faults)))
    world = world_from_file(path)
    cams = RenderProcesses(functools.partial(world_from_file, path), world.rsu_ids, count)
    assert len(cams.procs) == count
    got = {r: [] for r in range(len(world.rsu_ids))}
    try:
        assert cams.wait_ready(threading.Event())
        t0 = time.time_ns() + START_LEAD_NS
        end = t0 + ns_from_s(1.5)
        cams.begin(t0, end)
        while time.time_ns() < end + NS_PER_S // 2:
            for msg in cams.receive(0.1):
                got[msg[1]].append(msg)
        assert all(p.is_alive() for p in cams.procs)  # past the last tick, until told to stop
    finally:
        cams.close()
    assert not any(p.is_alive() for p in cams.procs)
    world.start(t0)
    for r, msgs in got.items():
        k = 0
        for msg in msgs:
            if msg[0] == "skip":  # a busy machine: ticks skipped, never rendered late
                assert msg[2] == k and msg[3] > k
                k = msg[3]
                continue
            _, _, seq, tick, stamp, jpeg, _ms, _cpu_ms, _done = msg
            assert seq == k and tick == world.frame_time(r, seq)
            assert stamp == tick + round(world.faults[r].clock_offset_ms * 1e6)
            assert (jpeg, stamp) == world.capture(r, tick)
            k += 1
        assert k == world.frame_index_from(r, end), (world.rsu_ids[r], k)  # every tick before the end


@pytest.mark.integration
def test_frames_rendered_ahead_hold_at_most_the_byte_budget(tmp_path):
    """The render loop (in a thread here, on a real pipe) renders ahead of the ticks only while the frames
    sent and not yet due hold less than its byte budget: 3200x2400 JPEGs 5 s ahead would be ~300 MB."""
    from multiprocessing import Pipe

    from sim.live import START_LEAD_NS, _render_frames

    path = _write(tmp_path, _short_scenario())
    world, probe = World(load_scenario(path)), World(load_scenario(path))
    rsus = list(range(len(world.rsu_ids)))
    world.warm_up(rsus)
    t0 = time.time_ns() + START_LEAD_NS
    world.start(t0)
    probe.start(t0)
    budget = 3 * len(probe.capture(0, t0)[0])  # about three frames
    ours, theirs = Pipe()
    end = t0 + ns_from_s(1.0)
    loop = threading.Thread(target=_render_frames, args=(world, rsus, theirs, end, budget))
    loop.start()
    frames = []
    while loop.is_alive() or ours.poll():
        if ours.poll(0.05):
            msg = ours.recv()
            if msg[0] == "frame":
                frames.append(msg)
    loop.join()
    assert len(frames) >= 5
    for i, (_, _, _, tick, _, jpeg, _, _, done_ns) in enumerate(frames):
        not_due = sum(len(f[5]) for f in frames[:i + 1] if f[3] > done_ns)
        assert not_due < budget + len(jpeg), (i, not_due, budget)
    assert any(f[3] - f[8] > 0 for f in frames)  # it did render ahead of the ticks
