"""Typed publishers: one message type on one concrete key, with that type's QoS and encoding.

Facts this module relies on (eclipse-zenoh 1.10):
- Frames are published with CongestionControl.BLOCK: with DROP, 1-8 MiB frames were lost through a
  router (team measurement: 83/100 at 1 MiB). On an idle loopback here DROP lost none, and BLOCK cost
  nothing measurable (1 MiB x 100 and 8 MiB x 20 through a router: all arrived either way).
- Frames go at Priority.DATA_LOW and pose fixes at INTERACTIVE_HIGH (express): with both at DATA, while
  one client streamed 8 MiB frames through a router, 14-45 of 300 fixes were dropped and p99 latency
  was 22-36 ms; with the split, 300/300 arrived, p99 5-10 ms (tests: -k bench, TOPTAG_BENCH=1).
- A put right when Publisher.matching_status turns True can be lost (measured 15/30): the route
  updates just after the status. wait_matching() waits a little longer (``settle``). One-shot messages
  that matter (Approach) must be repeated anyway.
"""
from __future__ import annotations

import time
from typing import Generic, NamedTuple, TypeVar

import zenoh

from protocol import codec, keys
from protocol.messages import Approach, Frame, FusedPose, Imu, ImuBatch, Leave, Message, PoseFix
from toptag.waiting import wait_until

M = TypeVar("M", bound=Message)

# Measured (zenoh 1.10, two peers on loopback, publisher declared before the subscriber was known): a
# put issued right when Publisher.matching_status turns True was lost 15-16/30 times; 0.1 ms later
# 1/30; 0.3 ms or more later 0/30. Hence a settle delay after matching.
MATCH_SETTLE_S = 0.05

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
    ImuBatch: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH),
    Approach: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_LOW),
    Leave: Qos(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_LOW),
}


def qos_for(msg_type: type[Message]) -> Qos:
    return QOS.get(msg_type, Qos())


def encoding_for(msg_type: type[Message]) -> zenoh.Encoding:
    binary = codec.is_binary(msg_type)
    base = zenoh.Encoding.APPLICATION_OCTET_STREAM if binary else zenoh.Encoding.APPLICATION_JSON
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

    def put_encoded(self, payload: bytes) -> None:
        """Publish a payload already encoded as this publisher's type for its key (the bus agent's FusedPose:
        protocol.convert.fused_pose_payload, 50 times a second without building the message)."""
        self._pub.put(payload)
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


def imu_publisher(session: zenoh.Session, bus_id: str, per_message: int) -> MessagePublisher:
    """A bus's IMU sender: its samples per_message to an ImuBatch on keys.imu_batch, or with 1 each an Imu on
    keys.imu (the bus agent takes both)."""
    if per_message > 1:
        return MessagePublisher(session, keys.imu_batch(bus_id), ImuBatch)
    return MessagePublisher(session, keys.imu(bus_id), Imu)


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


