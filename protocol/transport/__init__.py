"""The Zenoh transport every toptag process shares: configuration and sessions (config), typed
publishers (publishing), safe subscribers (subscribing), receive counters (counters), liveliness
(liveliness) and the active-session query (sessions).

Written against eclipse-zenoh 1.10 (Python); each module states the measured facts it relies on.
Importing `protocol` alone never loads Zenoh; importing `protocol.transport` does."""
from protocol.transport.config import (
    ONE_ZENOH_THREAD,
    ZenohSetupError,
    add_zenoh_arguments,
    config_summary,
    open_session,
    split_endpoints,
    zenoh_config,
    zenoh_config_from_args,
)
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
from protocol.transport.liveliness import LivelinessWatcher, declare_alive, watch_buses
from protocol.transport.publishing import (
    MATCH_SETTLE_S,
    QOS,
    MessagePublisher,
    Qos,
    declare_publisher,
    encoding_for,
    imu_publisher,
    publish,
    qos_for,
    wait_matching,
)
from protocol.transport.sessions import query_sessions, serve_session
from protocol.transport.subscribing import SafeSubscriber, latest_receiver, subscribe_messages

__all__ = [
    "ACCEPTED", "DROPPED", "ONE_ZENOH_THREAD", "FULL", "HANDLER_ERROR", "IGNORED", "MATCH_SETTLE_S", "MISSING", "QOS", "REJECTED", "SKIPPED",
    "LivelinessWatcher", "LogLimiter", "MessageCounters", "MessagePublisher", "Qos", "SafeSubscriber",
    "ZenohSetupError", "add_zenoh_arguments", "config_summary", "declare_alive", "declare_publisher",
    "encoding_for", "imu_publisher", "latest_receiver", "open_session", "publish", "qos_for", "query_sessions",
    "serve_session", "split_endpoints", "subscribe_messages", "wait_matching", "watch_buses",
    "zenoh_config", "zenoh_config_from_args",
]
