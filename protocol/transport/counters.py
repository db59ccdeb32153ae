"""Counts of what a process received (accepted, rejected, ...) and a log limiter, so that a flood of
bad payloads is counted in full but logged in moderation."""
from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict

ACCEPTED, REJECTED, HANDLER_ERROR, IGNORED, SKIPPED = "accepted", "rejected", "handler_error", "ignored", "skipped"
MISSING = "missing"
DROPPED, FULL = "dropped", "full"


class MessageCounters:
    """Thread-safe counts of (event, message type, subscription key) plus rejection reasons.

    Events: accepted, rejected (bad payload), handler_error, ignored (DELETE samples), skipped (frames
    overwritten unseen in a latest-only receiver: the reader was busy), missing (gaps in a latest-only
    receiver's sequence that it never received: the sender skipped them, or they were lost), full (a
    drop_oldest receiver found full when drained: it had dropped its oldest, or was about to), dropped (how
    many it dropped, by the gap in the messages' ``seq`` where they carry one)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._counts: dict[tuple[str, str, str], int] = defaultdict(int)
        self._reasons: dict[tuple[str, str], int] = defaultdict(int)
        self.last_error: str | None = None

    def inc(self, event: str, msg_type: str, key: str, n: int = 1, *, reason: str | None = None,
            error: str | None = None) -> None:
        with self._lock:
            self._counts[(event, msg_type, key)] += n
            if reason is not None:
                self._reasons[(msg_type, reason)] += n
            if error is not None:
                self.last_error = error

    def get(self, event: str, msg_type: str | type | None = None, key: str | None = None) -> int:
        if isinstance(msg_type, type):
            msg_type = msg_type.__name__
        with self._lock:
            return sum(n for (e, t, k), n in self._counts.items()
                       if e == event and (msg_type is None or t == msg_type) and (key is None or k == key))

    def reason(self, reason: str, msg_type: str | type | None = None) -> int:
        if isinstance(msg_type, type):
            msg_type = msg_type.__name__
        with self._lock:
            return sum(n for (t, r), n in self._reasons.items()
                       if r == reason and (msg_type is None or t == msg_type))

    def snapshot(self) -> dict[str, int]:
        """{'rejected|PoseFix|toptag/v1/fix/x1/*/*': 3, ...}"""
        with self._lock:
            return {"|".join(k): n for k, n in sorted(self._counts.items())}


class LogLimiter:
    """At most ``burst`` log lines per ``window_s`` seconds; then one line saying how many were
    suppressed. Counting is never limited, only logging."""

    def __init__(self, burst: int = 20, window_s: float = 10.0):
        self.burst, self.window_s = burst, window_s
        self._lock = threading.Lock()
        self._start = 0.0
        self._used = 0
        self._suppressed = 0

    def __call__(self, logger: logging.Logger, level: int, msg: str, *args, **kw) -> None:
        with self._lock:
            now = time.monotonic()
            if now - self._start > self.window_s:
                if self._suppressed:
                    logger.log(level, "(%d similar messages suppressed in the last %.0f s)",
                               self._suppressed, self.window_s)
                self._start, self._used, self._suppressed = now, 0, 0
            if self._used >= self.burst:
                self._suppressed += 1
                return
            self._used += 1
        logger.log(level, msg, *args, **kw)
