"""toptag.fusion.fix_hold: a fix waits for the filter as long as the recent fixes' delays ask, never longer
than the ceiling, and is given in the filter's order."""
import numpy as np
import pytest

from toptag.fix import Fix
from toptag.fusion.fix_hold import MIN_DELAYS, REFRESH_EVERY, FixHold

pytestmark = pytest.mark.unit

MS = 1_000_000
COV = np.diag([1e-4, 1e-4, 1e-4])


def fix(t_ns: int, source: str = "rsu-a") -> Fix:
    return Fix(t_ns, 1.0, 2.0, 0.1, COV, source)


def feed(hold: FixHold, delays_ms, t0: int = 10**12) -> int:
    """Fixes 25 ms apart arriving delays_ms after capture, each taken as it arrives; returns the last arrival."""
    now = t0
    for k, d in enumerate(delays_ms):
        t = t0 + k * 25 * MS
        now = t + int(d * MS)
        hold.add(fix(t, f"rsu-{k % 4}"), now)
        hold.due(now)
    return now


def test_until_enough_delays_are_known_the_hold_is_the_ceiling():
    hold = FixHold(150 * MS)
    feed(hold, [10.0] * (MIN_DELAYS - 1))
    assert hold.hold_ns == 150 * MS


@pytest.mark.parametrize("mean_ms, sd_ms, lo_ms, hi_ms", [
    (17.0, 5.0, 20.0, 35.0),  # the demo's network: held ~p95 (26 ms), not the ceiling
    (100.0, 30.0, 135.0, 150.0),  # the bench's: ~p95 = 149 ms, at most the ceiling
    (1000.0, 30.0, 150.0, 150.0),  # a slow network (or an RSU's clock behind): the ceiling
])
def test_the_hold_follows_the_recent_delays_up_to_the_ceiling(mean_ms, sd_ms, lo_ms, hi_ms):
    rng = np.random.default_rng(5)
    hold = FixHold(150 * MS)
    feed(hold, np.maximum(0.0, mean_ms + sd_ms * rng.standard_normal(20 * REFRESH_EVERY)))
    assert lo_ms * MS <= hold.hold_ns <= hi_ms * MS, hold.hold_ns / MS


def test_the_hold_drops_when_the_network_speeds_up_and_none_means_none():
    hold = FixHold(150 * MS)
    feed(hold, [120.0] * 1024)
    assert hold.hold_ns == 120 * MS
    feed(hold, [5.0] * 1024, t0=2 * 10**12)  # the window forgets the slow fixes
    assert hold.hold_ns == 5 * MS
    none = FixHold(0)
    now = feed(none, [120.0] * 100)
    assert none.hold_ns == 0 and none.held == [] and none.due(now) == []


def test_due_fixes_come_in_the_filters_order_and_the_young_stay():
    hold = FixHold(100 * MS)
    now = 10**12
    # captured 50 ms ago (young), 300 ms ago, 150 ms ago from two RSUs at one instant, and an hour ahead (the
    # RSU's clock is off: the filter judges it)
    for t, src in [(now - 50 * MS, "b"), (now - 300 * MS, "a"), (now - 150 * MS, "c"), (now - 150 * MS, "a"),
                   (now + 3600 * 10**9, "d")]:
        hold.add(fix(t, src), now)
    due = hold.due(now)
    assert [f.key for f in due] == sorted(f.key for f in due) and len(due) == 4
    assert [f.t_ns for f in hold.held] == [now - 50 * MS]
    assert hold.due(now + 49 * MS) == [] and [f.t_ns for f in hold.due(now + 50 * MS)] == [now - 50 * MS]
    assert hold.held == []


def test_a_negative_ceiling_is_refused():
    with pytest.raises(ValueError, match="longest hold"):
        FixHold(-1)
