"""Active sessions: a bus answers queries with its current Approach, so an RSU that starts late (or
missed the Approach) learns which buses it serves."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable

import zenoh

from protocol import codec, keys
from protocol.codec import ProtocolError
from protocol.messages import ActiveSessions, Approach
from protocol.transport.counters import ACCEPTED, REJECTED, MessageCounters
from protocol.transport.publishing import encoding_for

log = logging.getLogger(__name__)

def serve_session(session: zenoh.Session, approach: Approach | Callable[[], Approach | None], *,
                  responder_id: str | None = None, logger: logging.Logger | None = None) -> zenoh.Queryable:
    """A bus answers queries on keys.sessions(intersection, bus) with ActiveSessions holding its current
    Approach (``approach`` may be a callable returning the current one, or None when not in session)."""
    lg = logger or log
    first = approach() if callable(approach) else approach
    if first is None:
        raise ValueError("serve_session needs an Approach (or a callable returning one now)")
    intersection, bus = first.intersection_id, first.bus_id
    key = keys.sessions(intersection, bus)

    def on_query(query: zenoh.Query) -> None:
        try:
            a = approach() if callable(approach) else approach
            sessions = [a] if a is not None else []
            reply = ActiveSessions(intersection_id=intersection, responder_id=responder_id or bus,
                                   reference_time_ns=time.time_ns(), sessions=sessions)
            query.reply(key, codec.encode(reply), encoding=encoding_for(ActiveSessions))
        except Exception as e:
            lg.error("cannot answer session query %s: %s: %s", query.selector, type(e).__name__, e)

    return session.declare_queryable(key, zenoh.handlers.Callback(on_query))


def query_sessions(session: zenoh.Session, intersection: str, *, timeout: float = 1.0,
                   counters: MessageCounters | None = None,
                   logger: logging.Logger | None = None) -> dict[str, Approach]:
    """Ask every responder at an intersection for its active sessions: {bus_id: Approach}. Bad replies
    are logged and counted (rejected), never raised."""
    lg = logger or log
    counters = counters if counters is not None else MessageCounters()
    key = keys.sessions(intersection, keys.ANY)
    found: dict[str, Approach] = {}
    for reply in session.get(key, timeout=timeout):
        sample = reply.ok
        if sample is None:
            err = reply.err
            counters.inc(REJECTED, "ActiveSessions", key, reason="reply_error")
            lg.warning("session query %s: error reply: %s", key,
                       err.payload.to_string() if err is not None else "?")
            continue
        try:
            msg = codec.decode(sample.payload, ActiveSessions, key=str(sample.key_expr))
        except ProtocolError as e:
            counters.inc(REJECTED, "ActiveSessions", key, reason=e.reason, error=str(e))
            lg.warning("rejected session reply on %s: %s", sample.key_expr, e)
            continue
        counters.inc(ACCEPTED, "ActiveSessions", key)
        for a in msg.sessions:
            if a.intersection_id == intersection:
                prev = found.get(a.bus_id)
                if prev is None or a.reference_time_ns >= prev.reference_time_ns:
                    found[a.bus_id] = a
    return found
