"""The bus agent takes its inputs in at its step: IMU samples, GNSS and PoseFixes wait in Zenoh's channels
(filled without a Python thread per message) and each step feeds everything received since the last one
to the filter (IMU and GNSS in arrival order, fixes in capture order) before it estimates. A real agent on
a real Zenoh peer session; the test session publishes as the bus's sensors and an RSU would."""
from __future__ import annotations

from pathlib import Path

import pytest

from protocol import keys
from protocol.messages import GnssFix, Imu
from protocol.transport import MessagePublisher, subscribe_messages
from services.bus.agent import BusAgent
from toptag.site import MapFile
from toptag.vehicle import Vehicle
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration

DEMO = Path(__file__).resolve().parents[1] / "toptag" / "data" / "demo"
T0 = 1_700_000_000_000_000_000


def test_the_agent_feeds_what_arrived_to_its_filter_at_its_step(peer_pair):
    a, b = peer_pair
    vehicle = Vehicle.load(DEMO / "bus-42.json")
    agent = BusAgent(b, vehicle, MapFile.load(DEMO / "map.json"))
    try:
        bus = vehicle.id
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
