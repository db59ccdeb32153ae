"""The bus agent takes its inputs in at its step: IMU samples, GNSS and PoseFixes wait in Zenoh's channels
(filled without a Python thread per message) and each step feeds everything received since the last one
to the filter (IMU and GNSS in arrival order, fixes once they are old enough, in capture order) before it
estimates. A real agent on
a real Zenoh peer session; the test session publishes as the bus's sensors and an RSU would."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

from protocol import keys
from protocol.messages import GnssFix, Imu, ImuBatch, PoseFix
from protocol.transport import MessagePublisher, subscribe_messages
from services.bus.agent import BusAgent, main as agent_main
from toptag.site import MapFile
from toptag.vehicle import Vehicle
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration

DEMO = Path(__file__).resolve().parents[1] / "toptag" / "data" / "demo"
T0 = 1_700_000_000_000_000_000
NS = 1_000_000_000


def _demo_agent(session, **settings) -> BusAgent:
    """The agent of the demo's bus-42 on the demo's map, on this session."""
    return BusAgent(session, Vehicle.load(DEMO / "bus-42.json"), MapFile.load(DEMO / "map.json"), **settings)


def test_the_agent_feeds_what_arrived_to_its_filter_at_its_step(peer_pair):
    a, b = peer_pair
    agent = _demo_agent(b)
    try:
        bus = agent.bus_id
        seen = []  # a callback subscriber of the agent's session: what has reached it
        watch = subscribe_messages(b, keys.imu(bus), Imu, seen.append)
        imu = MessagePublisher(a, keys.imu(bus), Imu)
        gnss = MessagePublisher(a, keys.gnss(bus), GnssFix)
        assert imu.wait_matching(30) and gnss.wait_matching(30)
        # 10 samples 10 ms apart, then one older than the newest (the filter refuses it: counted)
        stamps = [T0 + 10_000_000 * k for k in range(10)] + [T0 + 5_000_000]
        for k, t in enumerate(stamps):
            imu.put(Imu(bus_id=bus, t_ns=t, gyro_z=0.01, accel_x=0.1, wheel_speed=5.0, seq=k))
        gnss.put(GnssFix(bus_id=bus, t_ns=T0, x=1.0, y=2.0, sigma_m=2.0))
        assert wait_until(lambda: len(seen) == len(stamps), 60)
        assert agent.filter.counters()["imu_samples"] == 0 and agent._gnss is None  # nothing taken in yet
        agent.take_inputs()
        c = agent.filter.counters()
        assert c["imu_samples"] == 10 and c["imu_rejected"] == 1  # in arrival order: the late one refused
        assert agent._last_imu_ns == stamps[-1] and agent._wheel_speed == 5.0
        assert wait_until(lambda: (agent.take_inputs() or agent._gnss) is not None, 60)
        assert (agent._gnss.x, agent._gnss.y) == (1.0, 2.0)
        agent.take_inputs()  # nothing new: nothing changes
        assert agent.filter.counters()["imu_samples"] == 10
        watch.close()
        imu.close()
        gnss.close()
    finally:
        agent.close()


def test_the_agent_takes_imu_samples_several_to_a_message(peer_pair):
    """ImuBatch, as the simulator sends them: each batch's samples to the filter in order, as if one by one."""
    a, b = peer_pair
    agent = _demo_agent(b)
    try:
        bus = agent.bus_id
        seen = []
        watch = subscribe_messages(b, keys.imu_batch(bus), ImuBatch, seen.append)
        pub = MessagePublisher(a, keys.imu_batch(bus), ImuBatch)
        assert pub.wait_matching(30)
        batches = [ImuBatch(bus_id=bus, seq=k, samples=[
            Imu(bus_id=bus, t_ns=T0 + 10_000_000 * (4 * k + i), gyro_z=0.01, accel_x=0.1, wheel_speed=5.0 + k,
                seq=4 * k + i) for i in range(4)]) for k in range(3)]
        for m in batches:
            pub.put(m)
        assert wait_until(lambda: len(seen) == len(batches), 60)
        agent.take_inputs()
        c = agent.filter.counters()
        assert c["imu_samples"] == 12 and c["imu_rejected"] == 0
        assert agent._last_imu_ns == batches[-1].samples[-1].t_ns and agent._wheel_speed == 7.0
        watch.close()
        pub.close()
    finally:
        agent.close()


def test_the_agent_holds_each_fix_until_it_is_old_enough(peer_pair, samples):
    a, b = peer_pair
    hold_s = 60  # no fix of this test comes of age while it runs: it releases them itself, at a given time
    agent = _demo_agent(b, fix_hold_ms=1000 * hold_s)
    try:
        bus, inter = agent.bus_id, MapFile.load(DEMO / "map.json").intersections[0]
        agent._enter(inter)  # subscribes to the bus's fixes at the intersection
        template = samples["PoseFix"]
        seen = []
        watch = subscribe_messages(b, keys.pose_fix(inter.id, bus, keys.ANY), PoseFix, seen.append)
        pub = MessagePublisher(a, keys.pose_fix(inter.id, bus, template.rsu_id), PoseFix)
        assert pub.wait_matching(30)
        now = time.time_ns()
        # captured: now (held), long ago (released), a second ago (held), an hour ahead (its clock is off: released)
        stamps = [now, now - 2 * hold_s * NS, now - NS, now + 3600 * NS]
        for k, t in enumerate(stamps):
            fix = template.model_copy(update={"bus_id": bus, "intersection_id": inter.id, "capture_time_ns": t,
                                              "publish_time_ns": t, "frame_seq": k})
            # One at a time, each until the agent's session has it: a fix is sent with CongestionControl.DROP,
            # which on a starved machine may drop it (then no subscriber of the session saw it).
            for _ in range(5):
                pub.put(fix)
                if wait_until(lambda: len(seen) > k, 10):
                    break
        assert len(seen) == len(stamps)
        agent.take_inputs()
        assert agent.fixes_received == 4 and len(agent.fix_hold.delays_ns) == 4  # arrival: when taken in
        assert agent.filter.counters()["fixes"] == 2
        assert sorted(f.t_ns for f in agent.fix_hold.held) == [now - NS, now]
        agent._release_fixes(now + (hold_s - 1) * NS)  # the one captured a second before now has come of age
        assert agent.filter.counters()["fixes"] == 3 and [f.t_ns for f in agent.fix_hold.held] == [now]
        agent._release_fixes(now + hold_s * NS)
        assert agent.filter.counters()["fixes"] == 4 and agent.fix_hold.held == []
        watch.close()
        pub.close()
    finally:
        agent.close()


@pytest.mark.parametrize("hold", ["-5", "nan", "inf"])
def test_a_bad_fix_hold_is_one_line_before_any_session(hold, capsys):
    code = agent_main(["--vehicle", str(DEMO / "bus-42.json"), "--map", str(DEMO / "map.json"), "--fix-hold-ms", hold])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.splitlines() == [f"toptag bus: --fix-hold-ms must be a finite number >= 0, got {float(hold)}"]
