"""Zenoh plumbing shared by every toptag service: config and session, typed publishers and safe
subscribers (decode through protocol.codec, count and log bad payloads, never die on a handler error),
latest-only frame receivers, liveliness helpers and the active-session query.

Written against eclipse-zenoh 1.10 (Python). Facts this module relies on:
- Frames are published with CongestionControl.BLOCK: with DROP, 1-8 MiB frames were lost through a
  router (team measurement: 83/100 at 1 MiB). On an idle loopback here DROP lost none, and BLOCK cost
  nothing measurable (1 MiB x 100 and 8 MiB x 20 through a router: all arrived either way).
- Frames go at Priority.DATA_LOW and pose fixes at INTERACTIVE_HIGH (express): with both at DATA, while
  one client streamed 8 MiB frames through a router, 14-45 of 300 fixes were dropped and p99 latency
  was 22-36 ms; with the split, 300/300 arrived, p99 5-10 ms (tests: -k bench, TOPTAG_BENCH=1).
- A subscriber on zenoh.handlers.RingChannel(1) keeps only the newest sample; skipped samples never
  reach Python, so an RSU that falls behind does not even copy the frames it skips. A callback
  subscriber, in contrast, queues without bound on the Python side (100 x 1 MiB frames were all
  buffered behind a 20 ms handler): use latest_only for frames.
- Existing liveliness tokens are learnt reliably with liveliness().declare_subscriber(history=True)
  (team measurement: liveliness().get() right after declaring such a subscriber returned nothing).
  A LivelinessToken that is garbage-collected is undeclared: keep a reference.
- A put right when Publisher.matching_status turns True can be lost (measured 15/30): the route
  updates just after the status. wait_matching() waits a little longer (``settle``). One-shot messages
  that matter (Approach) must be repeated anyway.
- A Subscriber whose handler.recv() is blocked in another thread cannot be undeclared
  ("Already borrowed"): block on ``sub.handler`` (a separate object), never on ``sub``.
- Client mode without a reachable router fails at open (immediately); peer mode opens and keeps
  retrying its connect endpoints in the background.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Generic, NamedTuple, TypeVar

import zenoh

from protocol import codec, keys
from protocol.codec import ProtocolError
from protocol.messages import (
    ActiveSessions,
    Approach,
    Frame,
    FusedPose,
    Imu,
    Leave,
    Message,
    PoseFix,
)

log = logging.getLogger("toptag.zenoh")

M = TypeVar("M", bound=Message)

# Measured (zenoh 1.10, two peers on loopback, publisher declared before the subscriber was known): a
# put issued right when Publisher.matching_status turns True was lost 15-16/30 times; 0.1 ms later
# 1/30; 0.3 ms or more later 0/30. Hence a settle delay after matching.
MATCH_SETTLE_S = 0.05

MODES = ("peer", "client", "router")
ENV_MODE = "TOPTAG_ZENOH_MODE"
ENV_CONNECT = "TOPTAG_ZENOH_CONNECT"
ENV_LISTEN = "TOPTAG_ZENOH_LISTEN"
ENV_CONFIG = "TOPTAG_ZENOH_CONFIG"
ENV_MULTICAST = "TOPTAG_ZENOH_MULTICAST"


class ZenohSetupError(RuntimeError):
    """A zenoh config or session cannot be made. str(e) is one line."""


# ---- config and session -----------------------------------------------------------------------

def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    # zenoh errors end with " at /root/.cargo/...rs:NN." - keep the message, drop the source location.
    cut = text.find(" at /")
    return text[:cut] if cut > 0 else text


def _check_endpoints(what: str, endpoints: Iterable[str]) -> list[str]:
    out = []
    for ep in endpoints:
        ep = str(ep).strip()
        if not ep:
            continue
        proto, sep, addr = ep.partition("/")
        if not sep or not proto or not addr:
            raise ZenohSetupError(f"{what}: endpoint {ep!r} is not of the form <protocol>/<address>, "
                                  f"e.g. tcp/127.0.0.1:7447")
        out.append(ep)
    return out


def split_endpoints(text: str | None) -> list[str]:
    """'tcp/a:1, tcp/b:2' -> ['tcp/a:1', 'tcp/b:2'] (env variables and repeated CLI options)."""
    if not text:
        return []
    return [p.strip() for p in text.replace(";", ",").split(",") if p.strip()]


def zenoh_config(mode: str | None = "peer", connect: Sequence[str] | None = None,
                 listen: Sequence[str] | None = None, multicast_scouting: bool | None = False,
                 config_file: str | os.PathLike | None = None,
                 extra: dict[str, Any] | None = None) -> zenoh.Config:
    """A zenoh.Config: start from ``config_file`` (JSON5) if given, then set every argument that is not
    None (``extra`` maps config paths such as "transport/link/tx/lease" to JSON-able values).

    Defaults suit toptag: peer mode, multicast scouting off (explicit endpoints only)."""
    if config_file is not None:
        try:
            conf = zenoh.Config.from_file(str(config_file))
        except Exception as e:  # zenoh raises ZError (or others) with a long message
            raise ZenohSetupError(f"zenoh config file {config_file}: {_one_line(e)}") from None
    else:
        conf = zenoh.Config()

    def put(path: str, value: Any) -> None:
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as e:
            raise ZenohSetupError(f"zenoh config {path}={value!r}: {_one_line(e)}") from None

    if mode is not None:
        if mode not in MODES:
            raise ZenohSetupError(f"zenoh mode {mode!r} is not one of {', '.join(MODES)}")
        put("mode", mode)
    if connect is not None:
        put("connect/endpoints", _check_endpoints("connect", connect))
    if listen is not None:
        put("listen/endpoints", _check_endpoints("listen", listen))
    if multicast_scouting is not None:
        put("scouting/multicast/enabled", bool(multicast_scouting))
    for path, value in (extra or {}).items():
        put(path, value)
    return conf


def config_summary(conf: zenoh.Config) -> str:
    """'mode=peer listen=[...] connect=[...]' for logs."""
    def get(path):
        try:
            return json.loads(conf.get_json(path))
        except Exception:
            return None
    mode = get("mode") or "peer"
    listen = get("listen/endpoints")
    if isinstance(listen, dict):
        listen = listen.get(mode, [])
    return f"mode={mode} listen={listen or []} connect={get('connect/endpoints') or []}"


def open_session(conf: zenoh.Config | None = None, **config_kwargs) -> zenoh.Session:
    """Open a zenoh session from ``conf`` or from zenoh_config(**config_kwargs). Raises
    ZenohSetupError (one line) if zenoh refuses (port in use, bad endpoint, no router in client mode)."""
    if conf is None:
        conf = zenoh_config(**config_kwargs)
    elif config_kwargs:
        raise TypeError("pass either a zenoh.Config or zenoh_config() keyword arguments, not both")
    try:
        return zenoh.open(conf)
    except Exception as e:
        raise ZenohSetupError(f"cannot open zenoh session ({config_summary(conf)}): {_one_line(e)}") from None


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer") -> None:
    """Add --zenoh-mode/--connect/--listen/--zenoh-config/--multicast-scouting to a service's CLI.
    Resolve them with zenoh_config_from_args()."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--zenoh-mode", choices=MODES, default=None,
                   help=f"zenoh mode (env {ENV_MODE}; default {default_mode})")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to, e.g. tcp/10.0.0.1:7447; repeatable or comma-separated "
                        f"(env {ENV_CONNECT})")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to listen on; repeatable or comma-separated (env {ENV_LISTEN})")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help=f"zenoh JSON5 config file to start from (env {ENV_CONFIG}); options above override it")
    g.add_argument("--multicast-scouting", action=argparse.BooleanOptionalAction, default=None,
                   help=f"zenoh multicast scouting (env {ENV_MULTICAST}=1/0; default off)")
    parser.set_defaults(_zenoh_default_mode=default_mode)


def zenoh_config_from_args(args: argparse.Namespace, *, mode: str | None = None,
                           default_listen: Sequence[str] | None = None,
                           default_connect: Sequence[str] | None = None,
                           environ: dict[str, str] | None = None) -> zenoh.Config:
    """Config from add_zenoh_arguments() options. Precedence: command line > environment > config
    file > defaults (``mode`` forces the mode, e.g. "router")."""
    env = os.environ if environ is None else environ

    def endpoints(cli, env_name):
        if cli:
            return [e for item in cli for e in split_endpoints(item)]
        if env.get(env_name):
            return split_endpoints(env[env_name])
        return None

    config_file = args.zenoh_config or env.get(ENV_CONFIG) or None
    listen = endpoints(args.listen, ENV_LISTEN)
    connect = endpoints(args.connect, ENV_CONNECT)
    the_mode = mode or args.zenoh_mode or env.get(ENV_MODE) or None
    multicast = args.multicast_scouting
    if multicast is None and env.get(ENV_MULTICAST):
        multicast = env[ENV_MULTICAST].strip().lower() in ("1", "true", "yes", "on")
    if config_file is None:
        the_mode = the_mode or getattr(args, "_zenoh_default_mode", "peer")
        listen = listen if listen is not None else (list(default_listen) if default_listen else None)
        connect = connect if connect is not None else (list(default_connect) if default_connect else None)
        multicast = False if multicast is None else multicast
    else:
        # Only fill defaults the file does not set.
        base = zenoh_config(mode=None, multicast_scouting=None, config_file=config_file)
        unset = zenoh.Config()
        if listen is None and default_listen and base.get_json("listen/endpoints") == unset.get_json(
                "listen/endpoints"):
            listen = list(default_listen)
        if connect is None and default_connect and base.get_json("connect/endpoints") == unset.get_json(
                "connect/endpoints"):
            connect = list(default_connect)
        if multicast is None and json.loads(base.get_json("scouting/multicast/enabled")) is None:
            multicast = False  # toptag default, unless the file turns it on
    return zenoh_config(mode=the_mode, connect=connect, listen=listen, multicast_scouting=multicast,
                        config_file=config_file)


# ---- counters and log limiting ----------------------------------------------------------------

ACCEPTED, REJECTED, HANDLER_ERROR, IGNORED, SKIPPED = "accepted", "rejected", "handler_error", "ignored", "skipped"


class MessageCounters:
    """Thread-safe counts of (event, message type, subscription key) plus rejection reasons.

    Events: accepted, rejected (bad payload), handler_error, ignored (DELETE samples), skipped (frames
    overwritten in a latest-only receiver, from sequence gaps)."""

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


# ---- publishing -------------------------------------------------------------------------------

class Qos(NamedTuple):
    congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.DROP
    priority: zenoh.Priority = zenoh.Priority.DATA
    express: bool = False


# Frames: BLOCK (DROP loses multi-MiB frames through a router) at a low priority so that small
# messages are not queued behind megabytes of image. Pose fixes: high priority, not batched.
QOS: dict[type, Qos] = {
    Frame: Qos(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA_LOW),
    PoseFix: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_HIGH, express=True),
    FusedPose: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH),
    Imu: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH),
    Approach: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_LOW),
    Leave: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_LOW),
}


def qos_for(msg_type: type[Message]) -> Qos:
    return QOS.get(msg_type, Qos())


def encoding_for(msg_type: type[Message]) -> zenoh.Encoding:
    base = zenoh.Encoding.APPLICATION_OCTET_STREAM if msg_type is Frame else zenoh.Encoding.APPLICATION_JSON
    return base.with_schema(f"{keys.ROOT}/{msg_type.TYPE}")


def _check_publish_key(key: str) -> str:
    key = str(key)
    if keys.is_pattern(key):
        raise ValueError(f"cannot publish on a key pattern: {key!r}")
    return key


class MessagePublisher(Generic[M]):
    """A zenoh Publisher for one message type on one concrete key, with that type's QoS.

    put() checks the type and that the message's ids match the key, then encodes and publishes."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M], *, qos: Qos | None = None):
        self.key = _check_publish_key(key)
        self.msg_type = msg_type
        self.qos = qos or qos_for(msg_type)
        self._pub = session.declare_publisher(
            self.key, encoding=encoding_for(msg_type), congestion_control=self.qos.congestion_control,
            priority=self.qos.priority, express=self.qos.express)
        self.published = 0

    def put(self, msg: M) -> None:
        if not isinstance(msg, self.msg_type):
            raise TypeError(f"publisher on {self.key} sends {self.msg_type.__name__}, not {type(msg).__name__}")
        codec.check_key(msg, self.key)
        self._pub.put(codec.encode(msg))
        self.published += 1

    @property
    def matching(self) -> bool:
        """True when at least one subscriber matches (routing information has arrived)."""
        return self._pub.matching_status.matching  # the status object itself is always truthy

    def wait_matching(self, timeout: float = 5.0, settle: float = MATCH_SETTLE_S) -> bool:
        """Wait until a subscriber matches, then ``settle`` seconds more (see MATCH_SETTLE_S)."""
        return wait_matching(self._pub, timeout, settle)

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except Exception:  # session already closed
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def declare_publisher(session: zenoh.Session, key: str, msg_type: type[M], *,
                      qos: Qos | None = None) -> MessagePublisher[M]:
    return MessagePublisher(session, key, msg_type, qos=qos)


def publish(session: zenoh.Session, key: str, msg: Message) -> None:
    """One-shot put with the QoS of the message's type (prefer a MessagePublisher for streams)."""
    key = _check_publish_key(key)
    codec.check_key(msg, key)
    q = qos_for(type(msg))
    session.put(key, codec.encode(msg), encoding=encoding_for(type(msg)),
                congestion_control=q.congestion_control, priority=q.priority, express=q.express)


def wait_matching(publisher: zenoh.Publisher, timeout: float = 5.0, settle: float = MATCH_SETTLE_S) -> bool:
    """Wait until a plain zenoh Publisher has a matching subscriber (then ``settle`` s). False on timeout."""
    if not wait_until(lambda: publisher.matching_status.matching, timeout):
        return False
    if settle > 0:
        time.sleep(settle)
    return True


def wait_until(predicate: Callable[[], bool], timeout: float, interval: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(interval)


# ---- safe subscribing -------------------------------------------------------------------------

class SafeSubscriber(Generic[M]):
    """Subscribe to ``key`` for messages of ``msg_type``; every sample is decoded with protocol.codec
    (including the key/ids check). A bad payload is logged (one line, rate-limited) and counted as
    ``rejected``; an exception in ``handler`` is logged and counted as ``handler_error``; neither stops
    the subscription.

    Modes:
    - handler, latest_only=False: handler(msg) runs for every sample on a zenoh callback thread.
    - handler, latest_only=True: samples go to a RingChannel(1); a worker thread runs handler(msg) on
      the newest one whenever it is free (older ones are overwritten, never decoded).
    - handler=None: a pull receiver; call recv(timeout) / try_recv() (RingChannel(1) if latest_only,
      else a FIFO of ``capacity``).
    """

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M],
                 handler: Callable[[M], Any] | None = None, *, counters: MessageCounters | None = None,
                 logger: logging.Logger | None = None, latest_only: bool = False, capacity: int = 256,
                 check_key: bool = True):
        self.key = str(key)
        self.msg_type = msg_type
        self.handler = handler
        self.counters = counters if counters is not None else MessageCounters()
        self.log = logger or log
        self.latest_only = latest_only
        self._check_key = check_key
        self._limit = LogLimiter()
        self._last_seq: dict[str, int] = {}
        self._closed = threading.Event()
        self._worker: threading.Thread | None = None
        name = msg_type.__name__
        self._name = name
        if handler is not None and not latest_only:
            self._sub = session.declare_subscriber(self.key, zenoh.handlers.Callback(self._on_sample))
        else:
            channel = zenoh.handlers.RingChannel(1) if latest_only else zenoh.handlers.FifoChannel(capacity)
            self._sub = session.declare_subscriber(self.key, channel)
            self._channel = self._sub.handler  # block on this, never on self._sub (see module doc)
            if handler is not None:
                self._worker = threading.Thread(target=self._run_worker, name=f"sub-{name}-{self.key}",
                                                daemon=True)
                self._worker.start()

    # -- decoding and accounting
    def _decode(self, sample: zenoh.Sample) -> M | None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.counters.inc(IGNORED, self._name, self.key)
            return None
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
        self.counters.inc(ACCEPTED, self._name, self.key)
        if self.latest_only:
            seq = getattr(msg, "seq", None)
            if isinstance(seq, int):
                last = self._last_seq.get(skey)
                if last is not None and seq > last + 1:
                    self.counters.inc(SKIPPED, self._name, self.key, seq - last - 1)
                self._last_seq[skey] = seq
        return msg

    def _call(self, msg: M) -> None:
        try:
            self.handler(msg)  # type: ignore[misc]
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
            try:
                sample = self._channel.recv()
            except Exception:  # ZError: channel closed (undeclared or session closed)
                return
            msg = self._decode(sample)
            if msg is not None and not self._closed.is_set():
                self._call(msg)

    # -- pull interface
    def try_recv(self) -> M | None:
        """The next (latest_only: the newest) valid message if one is waiting, else None."""
        if self.handler is not None:
            raise RuntimeError("this subscriber delivers to its handler; recv() is for handler=None")
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

    def recv(self, timeout: float | None = None, poll_s: float = 0.001) -> M | None:
        """Wait for the next valid message; None on timeout or once closed. Invalid payloads are
        counted and skipped."""
        if self.handler is not None:
            raise RuntimeError("this subscriber delivers to its handler; recv() is for handler=None")
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
                       capacity: int = 256, check_key: bool = True) -> SafeSubscriber[M]:
    return SafeSubscriber(session, key, msg_type, handler, counters=counters, logger=logger,
                          latest_only=latest_only, capacity=capacity, check_key=check_key)


def latest_receiver(session: zenoh.Session, key: str, msg_type: type[M] = Frame,
                    counters: MessageCounters | None = None,
                    logger: logging.Logger | None = None) -> SafeSubscriber[M]:
    """Pull receiver that only ever holds the newest message (RingChannel(1)): recv() returns the latest
    frame, skipping those that arrived while the caller was busy."""
    return SafeSubscriber(session, key, msg_type, None, counters=counters, logger=logger, latest_only=True)


# ---- liveliness -------------------------------------------------------------------------------

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


# ---- active sessions (late-joining RSU) --------------------------------------------------------

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
