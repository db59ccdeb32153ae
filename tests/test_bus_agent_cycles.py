"""The bus agent's output steps and filter cycles: a cycle (inputs taken in, the filter's estimate of now
published) at every filter_every-th step, and the steps between publish the predictions that cycle made for
their instants; a step that wakes more than half a period off its predicted instant runs a cycle instead.
A real agent on a real Zenoh peer session; the test session subscribes to its FusedPose as the monitor does."""
from __future__ import annotations

from pathlib import Path

import pytest

from protocol import keys
from protocol.messages import FusedPose
from protocol.transport import subscribe_messages
from services.bus.agent import BusAgent, main as agent_main
from toptag.site import MapFile
from toptag.vehicle import Vehicle
from toptag.waiting import wait_until

pytestmark = pytest.mark.integration

DEMO = Path(__file__).resolve().parents[1] / "toptag" / "data" / "demo"
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def _started_agent(session, filter_every: int) -> BusAgent:
    """An agent whose filter has started (a surveyed start) and has 100 ms of IMU at 100 Hz, driving at 5 m/s."""
    agent = BusAgent(session, Vehicle.load(DEMO / "bus-42.json"), MapFile.load(DEMO / "map.json"),
                     filter_every=filter_every)
    agent.filter.initialize(T0, 500.0, 500.0, 0.0, pos_sigma=0.05, yaw_sigma=0.01, speed=5.0, speed_sigma=0.1,
                            trusted=True)
    for k in range(1, 11):
        agent.filter.add_imu(T0 + 10 * MS * k, 0.0, 0.0, wheel_speed=5.0)
    return agent


@pytest.mark.parametrize("filter_every", [1, 2, 3])
def test_a_cycle_every_nth_step_and_its_predictions_between(peer_pair, filter_every):
    a, b = peer_pair
    agent = _started_agent(b, filter_every)
    got: list[FusedPose] = []
    sub = subscribe_messages(a, keys.fused_pose(agent.bus_id), FusedPose, got.append)
    try:
        assert agent._fused_pub.wait_matching(30)
        t = T0 + 100 * MS
        wakes = [t + 20 * MS * k + 1 * MS for k in range(6)]  # each 1 ms after its instant: on time
        for now in wakes:
            agent.step(now)
        assert agent.cycles == 6 // filter_every
        assert wait_until(lambda: len(got) == 6, 30)
        # a cycle's output is of its wake's instant; a predicted one of the instant the cycle planned for it
        assert [m.t_ns for m in got] == [wakes[k - k % filter_every] + 20 * MS * (k % filter_every)
                                         for k in range(6)]
        # what a prediction says of its instant is what the filter says of it (no input came in between)
        est = agent.filter.estimate(got[-1].t_ns)
        assert got[-1].x == pytest.approx(est.x, abs=1e-9) and got[-1].y == pytest.approx(est.y, abs=1e-9)
        assert got[-1].x > got[0].x  # it drives on
    finally:
        sub.close()
        agent.close()


def test_a_late_step_runs_a_cycle_instead_of_an_old_prediction(peer_pair):
    a, b = peer_pair
    agent = _started_agent(b, 2)
    got: list[FusedPose] = []
    sub = subscribe_messages(a, keys.fused_pose(agent.bus_id), FusedPose, got.append)
    try:
        assert agent._fused_pub.wait_matching(30)
        t = T0 + 100 * MS
        agent.step(t)  # a cycle: predicts t + 20 ms
        agent.step(t + 20 * MS + 11 * MS)  # more than half a period late: a cycle of its own
        agent.step(t + 51 * MS)  # the prediction of that cycle, on time
        assert agent.cycles == 2
        assert wait_until(lambda: len(got) == 3, 30)
        assert [m.t_ns for m in got] == [t, t + 31 * MS, t + 51 * MS]
    finally:
        sub.close()
        agent.close()


def test_a_bad_filter_every_is_one_line_before_any_session(capsys):
    code = agent_main(["--vehicle", str(DEMO / "bus-42.json"), "--map", str(DEMO / "map.json"), "--filter-every", "0"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.splitlines() == ["toptag bus: --filter-every must be a whole number >= 1, got 0"]
