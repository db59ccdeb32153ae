"""Liveliness: a bus's token for its session at an intersection, and watchers that see tokens appear
and vanish.

Facts this module relies on (eclipse-zenoh 1.10):
- Existing liveliness tokens are learnt reliably with liveliness().declare_subscriber(history=True)
  (team measurement: liveliness().get() right after declaring such a subscriber returned nothing).
- A LivelinessToken that is garbage-collected is undeclared: keep a reference.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from protocol import keys
from protocol.transport.counters import HANDLER_ERROR, MessageCounters

log = logging.getLogger(__name__)

def declare_alive(session: zenoh.Session, intersection: str, bus: str) -> zenoh.LivelinessToken:
    """The bus's liveliness token for its session at an intersection; undeclare() it (or close the
    session, or die) and watchers see it vanish. Keep a reference: a token that is garbage-collected
    is undeclared (measured)."""
    return session.liveliness().declare_token(keys.alive(intersection, bus))


class LivelinessWatcher:
    """Calls on_appear(key) / on_vanish(key) for liveliness tokens matching ``pattern``, starting with
    the tokens that already exist (history=True). Duplicate reports are filtered; callback exceptions
    are logged and counted, never raised into zenoh."""

    def __init__(self, session: zenoh.Session, pattern: str, on_appear: Callable[[str], Any] | None = None,
                 on_vanish: Callable[[str], Any] | None = None, *, logger: logging.Logger | None = None,
                 counters: MessageCounters | None = None):
        self.pattern = str(pattern)
        self.on_appear, self.on_vanish = on_appear, on_vanish
        self.log = logger or log
        self.counters = counters if counters is not None else MessageCounters()
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._closed = False
        self._sub = session.liveliness().declare_subscriber(
            self.pattern, zenoh.handlers.Callback(self._on_sample), history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        appear = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if self._closed:
                return
            if appear == (key in self._alive):
                return  # duplicate (e.g. history reported twice)
            (self._alive.add if appear else self._alive.discard)(key)
        cb = self.on_appear if appear else self.on_vanish
        if cb is None:
            return
        try:
            cb(key)
        except Exception as e:
            self.counters.inc(HANDLER_ERROR, "liveliness", self.pattern, error=repr(e))
            self.log.error("liveliness %s callback for %s failed: %s: %s",
                           "appear" if appear else "vanish", key, type(e).__name__, e, exc_info=True)

    @property
    def alive(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def close(self) -> None:
        with self._lock:
            self._closed = True
        try:
            self._sub.undeclare()
        except Exception:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def watch_buses(session: zenoh.Session, intersection: str, on_appear: Callable[[str], Any] | None = None,
                on_vanish: Callable[[str], Any] | None = None, *,
                logger: logging.Logger | None = None) -> LivelinessWatcher:
    """Watch the buses in session at an intersection; the callbacks get the bus id."""
    def bus_of(key: str) -> str:
        return keys.parse(key)["bus"]
    return LivelinessWatcher(
        session, keys.alive(intersection, keys.ANY),
        (lambda k: on_appear(bus_of(k))) if on_appear else None,
        (lambda k: on_vanish(bus_of(k))) if on_vanish else None, logger=logger)
