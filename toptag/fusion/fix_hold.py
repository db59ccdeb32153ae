"""When a late fix goes to the bus filter: once it is about as old as the fixes of the last seconds were
when they reached the bus (HOLD_QUANTILE of their capture-to-arrival delays, at most a ceiling), and then
with the others due in capture order.

The filter's result does not depend on the order in which it is given fixes (it applies each at its capture
time and replays what came after), but a fix older than one already applied makes it apply that one again.
Four RSUs' fixes arrive out of capture order (`toptag bench bus`: 100 +- 30 ms after capture): given on
arrival, 1851 applications for 1200 fixes; held 150 ms, 1507 (and 1218 decided together, add_fix's
decide=False). A hold costs freshness: the fix's correction reaches the fused pose that much later (the
fusion study: 1.01 cm at 100 +- 30 ms, 1.02 cm at 160 +- 8 ms; docs/real-time.md). A fixed hold fits one
network: where fixes arrive 17 ms after capture (the demo) a 150 ms hold would only delay them, so the hold
follows the delays seen, as high as most fixes need to arrive in order and no higher."""
from __future__ import annotations

from collections import deque

import numpy as np

from toptag.fix import Fix

HOLD_QUANTILE = 0.95  # a fix is held until this share of fixes would have arrived: ~5 % still come late
DELAY_WINDOW = 1024  # the recent delays the hold follows (~25 s of four RSUs at 10 Hz)
MIN_DELAYS = 32  # until this many delays are known the hold is the ceiling
REFRESH_EVERY = 32  # the quantile is taken again after this many delays, not at every fix


class FixHold:
    """The fixes taken in and not yet given to the filter, and the hold they wait (pure: times are passed in)."""

    def __init__(self, max_hold_ns: int, quantile: float = HOLD_QUANTILE, window: int = DELAY_WINDOW):
        if not max_hold_ns >= 0:
            raise ValueError(f"the longest hold must be >= 0 ns, got {max_hold_ns}")
        self.max_hold_ns = int(max_hold_ns)
        self.quantile = quantile
        self.delays_ns: deque[int] = deque(maxlen=window)  # capture to arrival of the latest fixes
        self.hold_ns = self.max_hold_ns
        self.held: list[Fix] = []
        self._new_delays = 0

    def add(self, fix: Fix, arrival_ns: int) -> None:
        """A fix taken in at arrival_ns (its delay joins those the hold follows)."""
        self.held.append(fix)
        self.delays_ns.append(int(arrival_ns) - fix.t_ns)
        self._new_delays += 1
        if self._new_delays >= REFRESH_EVERY and len(self.delays_ns) >= MIN_DELAYS:
            self._new_delays = 0
            q = float(np.quantile(np.fromiter(self.delays_ns, float, len(self.delays_ns)), self.quantile))
            self.hold_ns = int(min(self.max_hold_ns, max(q, 0.0)))

    def due(self, now_ns: int) -> list[Fix]:
        """The held fixes captured hold_ns before now_ns or earlier, in the filter's order (Fix.key), no longer
        held. One stamped after now_ns is due too: its RSU's clock is off, and the filter judges it (future)."""
        young = now_ns - self.hold_ns
        due = [f for f in self.held if not young < f.t_ns <= now_ns]
        if due:
            self.held = [f for f in self.held if young < f.t_ns <= now_ns]
            due.sort(key=lambda f: f.key)
        return due
