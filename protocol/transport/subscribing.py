"""Safe subscribers: every sample is decoded through protocol.codec; a bad payload or a failing handler
is counted and logged (rate-limited), never fatal.

Facts this module relies on (eclipse-zenoh 1.10):
- A callback subscriber whose callback does the work queues without bound on the Python side (100 x
  1 MiB frames were all buffered behind a 20 ms handler): use latest_only for frames.
- latest_only keeps the newest sample in a slot, filled by a callback that only swaps it (nothing is
  decoded or copied there) and wakes the reader (a pull receiver's recv, or the handler's worker
  thread). A RingChannel(1) would also keep only the newest, but it has no recv with a timeout, polling
  its try_recv every millisecond cost an idle RSU ~1.4 % of a core and up to a millisecond of latency
  per frame, and it hides its overwrites. The slot tells frames overwritten while the reader was busy
  (skipped) from gaps in the sender's sequence that never arrived (missing).
- A Subscriber whose handler.recv() is blocked in another thread cannot be undeclared
  ("Already borrowed"): block on ``sub.handler`` (a separate object), never on ``sub``.
- A callback subscriber runs its callback on a Python thread of its own (zenoh-python's default,
  ``indirect``): every sample is a thread wake-up and a GIL hand-off. A pull receiver's channel is filled
  in Zenoh's own thread without Python: a consumer that drains it on its own schedule (``drain``) takes
  many samples for one wake-up. The bus agent's IMU (100 Hz) and fixes, taken at its 50 Hz step: ~3.5 %
  of a core for its IMU-callback thread alone (`toptag bench bus`, docs/architecture.md).
- A FifoChannel that is full blocks the Zenoh thread that fills it (every subscription of the session
  stalls behind a stalled consumer); a RingChannel (``drop_oldest``) drops its oldest sample instead, and
  tells nobody: ``drain`` notices a ring it finds full (counted ``full``, one log line per 10 s) and counts
  what it lost (``dropped``) by the gap in the messages' ``seq`` where they carry one (Imu).
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from protocol import codec
from protocol.codec import ProtocolError
from protocol.messages import Frame, Message
from protocol.transport.counters import (
    ACCEPTED,
    DROPPED,
    FULL,
    HANDLER_ERROR,
    IGNORED,
    MISSING,
    REJECTED,
    SKIPPED,
    LogLimiter,
    MessageCounters,
)

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)

class SafeSubscriber(Generic[M]):
    """Subscribe to ``key`` for messages of ``msg_type``; every sample is decoded with protocol.codec
    (including the key/ids check). A bad payload is logged (one line, rate-limited) and counted as
    ``rejected``; an exception in ``handler`` is logged and counted as ``handler_error``; neither stops
    the subscription.

    Modes:
    - handler, latest_only=False: handler(msg) runs for every sample on a zenoh callback thread.
    - handler, latest_only=True: a worker thread runs handler(msg) on the newest sample (the slot,
      see the module doc) whenever it is free; older ones are overwritten, never decoded.
    - handler=None: a pull receiver; call recv(timeout) / try_recv() / drain() / deliver(handler) (latest_only: a slot
      holding the newest sample, see the module doc; else a FIFO of ``capacity``, which drops its oldest
      sample when full with ``drop_oldest`` instead of blocking Zenoh's thread).
    """

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M],
                 handler: Callable[[M], Any] | None = None, *, counters: MessageCounters | None = None,
                 logger: logging.Logger | None = None, latest_only: bool = False, capacity: int = 256,
                 check_key: bool = True, drop_oldest: bool = False):
        self.key = str(key)
        self.msg_type = msg_type
        self.handler = handler
        self.counters = counters if counters is not None else MessageCounters()
        self.log = logger or log
        self.latest_only = latest_only
        self._check_key = check_key
        self._limit = LogLimiter()
        self._ring = capacity if drop_oldest and handler is None and not latest_only else 0
        self._full_limit = LogLimiter(burst=1, window_s=10.0)
        self._last_seq: dict[str, int] = {}
        self._closed = threading.Event()
        self._worker: threading.Thread | None = None
        name = msg_type.__name__
        self._name = name
        self._slot: zenoh.Sample | None = None  # latest-only pull: the newest sample, not yet taken
        self._overwritten = 0  # samples the slot lost since the last one taken
        self.arrived = 0  # latest-only pull: samples that reached the slot
        self._slot_arrival_ns = 0
        self.taken_arrival_ns = 0  # latest-only pull: when the sample taken last reached the slot (time.time_ns)
        self._arrived = threading.Condition()
        if latest_only:
            self._sub = session.declare_subscriber(self.key, zenoh.handlers.Callback(self._keep_newest))
            if handler is not None:
                self._worker = threading.Thread(target=self._run_worker, name=f"sub-{name}-{self.key}",
                                                daemon=True)
                self._worker.start()
        elif handler is not None:
            self._sub = session.declare_subscriber(self.key, zenoh.handlers.Callback(self._on_sample))
        else:
            channel = zenoh.handlers.RingChannel if drop_oldest else zenoh.handlers.FifoChannel
            self._sub = session.declare_subscriber(self.key, channel(capacity))
            self._channel = self._sub.handler  # block on this, never on self._sub (see module doc)

    def _keep_newest(self, sample: zenoh.Sample) -> None:
        with self._arrived:
            if self._slot is not None:
                self._overwritten += 1
                self.counters.inc(SKIPPED, self._name, self.key)
            self._slot, self._slot_arrival_ns = sample, time.time_ns()
            self.arrived += 1
            self._arrived.notify()

    def _take(self, timeout: float | None) -> tuple[zenoh.Sample | None, int]:
        """The newest sample (waiting up to ``timeout``; None: until one comes or the receiver closes) and
        how many the slot lost before it."""
        with self._arrived:
            if self._slot is None and not self._closed.is_set():
                self._arrived.wait_for(lambda: self._slot is not None or self._closed.is_set(), timeout)
            sample, lost = self._slot, self._overwritten
            self._slot, self._overwritten = None, 0
            if sample is not None:
                self.taken_arrival_ns = self._slot_arrival_ns
            return sample, lost

    # -- decoding and accounting
    def _decode(self, sample: zenoh.Sample, overwritten: int = 0, skey: str | None = None,
                count: bool = True) -> M | None:
        """The sample's message, or None (counted and logged); ``count=False``: the caller counts it accepted."""
        if sample.kind == zenoh.SampleKind.DELETE:
            self.counters.inc(IGNORED, self._name, self.key)
            return None
        if skey is None:
            skey = str(sample.key_expr)
        try:
            msg = codec.decode(sample.payload, self.msg_type, key=skey if self._check_key else None)
        except ProtocolError as e:
            self.counters.inc(REJECTED, self._name, self.key, reason=e.reason, error=str(e))
            self._limit(self.log, logging.WARNING, "rejected payload on %s (%d bytes): %s",
                        skey, len(sample.payload), e)
            return None
        except Exception as e:  # a codec bug must not kill the service either
            self.counters.inc(REJECTED, self._name, self.key, reason="internal", error=repr(e))
            self._limit(self.log, logging.ERROR, "cannot decode payload on %s: %s: %s",
                        skey, type(e).__name__, e)
            return None
        if count:
            self.counters.inc(ACCEPTED, self._name, self.key)
        if self.latest_only:
            seq = getattr(msg, "seq", None)
            if isinstance(seq, int):
                last = self._last_seq.get(skey)
                if last is not None and seq > last + 1 + overwritten:
                    self.counters.inc(MISSING, self._name, self.key, seq - last - 1 - overwritten)
                self._last_seq[skey] = seq
        return msg

    def _call(self, msg: M, handler: Callable[[M], Any] | None = None) -> None:
        try:
            (handler or self.handler)(msg)  # type: ignore[misc]
        except Exception as e:
            self.counters.inc(HANDLER_ERROR, self._name, self.key, error=repr(e))
            self._limit(self.log, logging.ERROR, "handler for %s on %s failed: %s: %s",
                        self._name, self.key, type(e).__name__, e, exc_info=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._closed.is_set():
            return
        msg = self._decode(sample)
        if msg is not None:
            self._call(msg)

    def _run_worker(self) -> None:
        while not self._closed.is_set():
            sample, lost = self._take(None)
            msg = None if sample is None else self._decode(sample, lost)
            if msg is not None and not self._closed.is_set():
                self._call(msg)

    # -- pull interface
    def try_recv(self) -> M | None:
        """The next (latest_only: the newest) valid message if one is waiting, else None."""
        if self.handler is not None:
            raise RuntimeError("this subscriber delivers to its handler; recv() is for handler=None")
        if self.latest_only:
            sample, lost = self._take(0)
            return None if sample is None else self._decode(sample, lost)
        while True:
            try:
                sample = self._channel.try_recv()
            except Exception:
                return None
            if sample is None:
                return None
            msg = self._decode(sample)
            if msg is not None:
                return msg

    def drain(self) -> list[M]:
        """Every valid message waiting, oldest first, without blocking (not for latest_only: its slot holds
        one; try_recv takes it)."""
        if self.latest_only:
            raise RuntimeError("a latest-only receiver holds one sample: use try_recv()")
        if not self._ring:
            out = []
            while (msg := self.try_recv()) is not None:
                out.append(msg)
            return out
        out, taken, first_seq, newest_seq = [], 0, {}, {}
        while True:
            try:
                sample = self._channel.try_recv()
            except Exception:
                break
            if sample is None:
                break
            taken += 1
            skey = str(sample.key_expr)
            msg = self._decode(sample, skey=skey, count=False)
            if msg is not None:
                out.append(msg)
                seq = getattr(msg, "seq", None)
                if type(seq) is int:
                    first_seq.setdefault(skey, seq)
                    newest_seq[skey] = seq
        if out:  # one count per drain, not per message
            self.counters.inc(ACCEPTED, self._name, self.key, len(out))
        if taken >= self._ring:
            self._full(taken, first_seq)
        self._last_seq.update(newest_seq)
        return out

    def _full(self, taken: int, first_seq: dict[str, int]) -> None:
        """A drain found the ring full: its consumer had not drained it for ``capacity`` samples (the bus
        agent's step stalled ~10 s) and the ring dropped its oldest meanwhile. Counted, with how many where
        ``seq`` tells (the gap from the newest of the drain before to the oldest of this one), and logged."""
        dropped = sum(max(0, first - last - 1) for key, first in first_seq.items()
                      if (last := self._last_seq.get(key)) is not None)
        self.counters.inc(FULL, self._name, self.key)
        if dropped:
            self.counters.inc(DROPPED, self._name, self.key, dropped)
        self._full_limit(self.log, logging.WARNING, "%s receiver on %s was full when drained (%d samples): its "
                         "consumer fell behind and the oldest were dropped (%s)", self._name, self.key, taken,
                         f"{dropped} by seq" if first_seq else "how many unknown: no seq")

    def deliver(self, handler: Callable[[M], Any]) -> int:
        """drain() to handler, one message at a time, each call guarded as a callback subscriber's (an
        exception is counted as handler_error and logged, and the next message is delivered); returns how
        many were delivered."""
        msgs = self.drain()
        for msg in msgs:
            self._call(msg, handler)
        return len(msgs)

    def recv(self, timeout: float | None = None, poll_s: float = 0.001) -> M | None:
        """Wait for the next valid message; None on timeout or once closed. Invalid payloads are
        counted and skipped."""
        if self.handler is not None:
            raise RuntimeError("this subscriber delivers to its handler; recv() is for handler=None")
        if self.latest_only:
            deadline = None if timeout is None else time.monotonic() + timeout
            while not self._closed.is_set():
                left = None if deadline is None else max(0.0, deadline - time.monotonic())
                sample, lost = self._take(left)
                if sample is not None:
                    msg = self._decode(sample, lost)
                    if msg is not None:
                        return msg
                elif deadline is not None and time.monotonic() >= deadline:
                    return None
            return None
        if timeout is None:
            while not self._closed.is_set():
                try:
                    sample = self._channel.recv()
                except Exception:
                    return None
                msg = self._decode(sample)
                if msg is not None:
                    return msg
            return None
        deadline = time.monotonic() + timeout
        while not self._closed.is_set():
            msg = self.try_recv()
            if msg is not None:
                return msg
            if time.monotonic() >= deadline:
                return None
            time.sleep(poll_s)
        return None

    # -- lifecycle
    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        with self._arrived:
            self._arrived.notify_all()
        try:
            self._sub.undeclare()
        except Exception:
            pass
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def subscribe_messages(session: zenoh.Session, key: str, msg_type: type[M],
                       handler: Callable[[M], Any] | None = None, counters: MessageCounters | None = None,
                       logger: logging.Logger | None = None, *, latest_only: bool = False,
                       capacity: int = 256, check_key: bool = True, drop_oldest: bool = False) -> SafeSubscriber[M]:
    return SafeSubscriber(session, key, msg_type, handler, counters=counters, logger=logger,
                          latest_only=latest_only, capacity=capacity, check_key=check_key, drop_oldest=drop_oldest)


def latest_receiver(session: zenoh.Session, key: str, msg_type: type[M] = Frame,
                    counters: MessageCounters | None = None,
                    logger: logging.Logger | None = None) -> SafeSubscriber[M]:
    """Pull receiver that only ever holds the newest message (the slot, see the module doc): recv()
    returns the latest frame, skipping those that arrived while the caller was busy."""
    return SafeSubscriber(session, key, msg_type, None, counters=counters, logger=logger, latest_only=True)
