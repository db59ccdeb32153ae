"""`toptag record`: every sample under toptag/v1/** into an MCAP file, byte for byte.

    toptag record --out RUN.mcap [--keys EXPR]... [--frames] [--duration S] [zenoh options]

One MCAP channel per key (and Zenoh encoding), its topic the key itself; the Zenoh encoding is kept in
the channel's metadata. A toptag message type gets a JSON schema generated from its pydantic model
(schema encoding ``jsonschema``, message encoding ``json``), so Foxglove and other MCAP tools open the
file and show every field. Frames (binary: prefix, JSON header, image bytes; see protocol.codec) are
left out unless --frames: their channel has message encoding ``toptag-frame`` and the schema of the
header. Imu samples (a fixed binary layout, protocol.codec) have message encoding ``toptag-imu`` and the
schema of their fields; those recorded before that layout are JSON. Payloads are stored exactly as received (also those that are not valid toptag messages); the
log time is the recorder's clock at reception, strictly increasing, so the file's log-time order is the
order of reception. `toptag replay` plays it back; `toptag eval replay` re-runs the bus fusion on it.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import zenoh
from mcap.writer import CompressionType, Writer

from protocol import codec, keys
from protocol.messages import MESSAGE_TYPES, Frame, Message
from protocol.transport.runner import add_service_arguments, run_service

log = logging.getLogger(__name__)

PROFILE = "toptag"
JSON_ENCODING, BINARY_ENCODING = "json", "toptag-{}"  # binary: toptag-frame, toptag-imu
BINARY_BASE = "application/octet-stream"  # the Zenoh encoding of a binary layout (protocol.transport.encoding_for)
META_ZENOH_ENCODING, META_TYPE = "zenoh_encoding", "toptag_type"
# Kinds that are not put samples (liveliness tokens, session queries): never seen by a subscriber.
_NOT_SAMPLES = ("alive", "sessions")
PROGRESS_S = 5.0
CHUNK_BYTES = 256 * 1024


def message_type_of(encoding: str) -> type[Message] | None:
    """The toptag message type a Zenoh encoding names ('application/json;toptag/v1/pose_fix' -> PoseFix)."""
    _, _, schema = str(encoding).partition(";")
    prefix = keys.ROOT + "/"
    return MESSAGE_TYPES.get(schema[len(prefix):]) if schema.startswith(prefix) else None


def message_encoding(msg_type: type[Message], encoding: str) -> str:
    """The MCAP message encoding of a toptag type sent with this Zenoh encoding: ``json``, or for a binary
    layout (protocol.codec) ``toptag-<type>``. By the encoding, not the type: an Imu recorded before its
    binary layout is JSON."""
    return BINARY_ENCODING.format(msg_type.TYPE) if str(encoding).startswith(BINARY_BASE) else JSON_ENCODING


def json_schema(msg_type: type[Message]) -> bytes:
    schema = msg_type.model_json_schema(mode="serialization")
    schema["$id"] = f"{keys.ROOT}/{msg_type.TYPE}"
    if msg_type is Frame:
        schema["description"] = ("Header of a toptag Frame; on the wire the header follows a 16-byte prefix and "
                                 "precedes the raw image bytes (see protocol.codec).")
    elif codec.is_binary(msg_type):
        schema["description"] = (f"The fields of a toptag {msg_type.__name__}; on the wire (message encoding "
                                 f"{BINARY_ENCODING.format(msg_type.TYPE)}) a fixed binary layout: see protocol.codec. "
                                 "Recorded before it: JSON (message encoding json).")
    return json.dumps(schema, sort_keys=True).encode()


def is_frame_key(key: str) -> bool:
    try:
        return keys.parse(key).kind == "frame"
    except keys.KeyExprError:
        return False


def subscription_keys(key_exprs: list[str], frames: bool) -> list[str]:
    """What to subscribe to: without frames, the whole tree becomes one subscription per kind but
    frames, so that megabytes of images never travel to the recorder."""
    out = []
    for k in key_exprs:
        if k == keys.EVERYTHING and not frames:
            out += [f"{keys.ROOT}/{seg}/**" for kind, (seg, _) in keys.LAYOUT.items()
                    if kind != "frame" and kind not in _NOT_SAMPLES]
        else:
            out.append(k)
    return out


class McapLog:
    """An MCAP file being written: channels made on first use, thread-safe, log time strictly
    increasing in the order add() is called."""

    def __init__(self, path: str | Path, info: dict[str, str] | None = None):
        self.path = Path(path)
        self._file = open(self.path, "wb")
        # Small chunks: a recorder killed outright loses at most its last chunk.
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="toptag")
        if info:
            self._writer.add_metadata("toptag_recording", {k: str(v) for k, v in info.items()})
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._seq: Counter = Counter()
        self._last_ns = 0
        self.counts: Counter = Counter()  # per message type name (or "other")
        self.bytes = 0
        self.closed = False

    def _channel(self, key: str, encoding: str) -> int:
        cid = self._channels.get((key, encoding))
        if cid is not None:
            return cid
        msg_type = message_type_of(encoding)
        schema_id = 0
        if msg_type is not None:
            schema_id = self._schemas.get(msg_type.TYPE, 0)
            if not schema_id:
                schema_id = self._writer.register_schema(f"{keys.ROOT}/{msg_type.TYPE}", "jsonschema",
                                                         json_schema(msg_type))
                self._schemas[msg_type.TYPE] = schema_id
        wire = encoding if msg_type is None else message_encoding(msg_type, encoding)
        meta = {META_ZENOH_ENCODING: encoding}
        if msg_type is not None:
            meta[META_TYPE] = msg_type.TYPE
        cid = self._writer.register_channel(key, wire, schema_id, meta)
        self._channels[(key, encoding)] = cid
        return cid

    def add(self, key: str, encoding: str, payload: bytes, publish_time_ns: int | None = None,
            log_time_ns: int | None = None) -> int:
        """Append one sample, received now (or at ``log_time_ns``, for recordings made from other
        sources); returns its log time (ns since the epoch)."""
        with self._lock:
            if self.closed:
                return 0
            now = max(time.time_ns() if log_time_ns is None else int(log_time_ns), self._last_ns + 1)
            self._last_ns = now
            cid = self._channel(key, encoding)
            self._writer.add_message(cid, log_time=now, data=payload,
                                     publish_time=publish_time_ns if publish_time_ns is not None else now,
                                     sequence=self._seq[cid])
            self._seq[cid] += 1
            t = message_type_of(encoding)
            self.counts[t.__name__ if t is not None else "other"] += 1
            self.bytes += len(payload)
            return now

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._writer.finish()
            self._file.close()


class Recorder:
    """Subscribes to key expressions and writes every sample to an McapLog."""

    def __init__(self, session: zenoh.Session, out: McapLog, key_exprs: list[str], frames: bool = False):
        self.out = out
        self.frames = frames
        self.skipped_frames = 0
        self._stop = threading.Event()
        self._subs = [session.declare_subscriber(k, zenoh.handlers.Callback(self._on_sample))
                      for k in subscription_keys(key_exprs, frames)]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            return
        key = str(sample.key_expr)
        if not self.frames and is_frame_key(key):
            self.skipped_frames += 1
            return
        try:
            ts = sample.timestamp
            publish_ns = int(ts.get_time().timestamp() * 1e9) if ts is not None else None
        except Exception:
            publish_ns = None
        self.out.add(key, str(sample.encoding), sample.payload.to_bytes(), publish_ns)

    def summary(self) -> str:
        counts = ", ".join(f"{n} {t}" for t, n in sorted(self.out.counts.items()))
        return f"{sum(self.out.counts.values())} messages ({self.out.bytes / 1e6:.1f} MB): {counts or 'none'}"

    def run(self, duration: float | None = None) -> None:
        t_end = None if duration is None else time.monotonic() + duration
        while not self._stop.is_set():
            left = PROGRESS_S if t_end is None else min(PROGRESS_S, t_end - time.monotonic())
            if left <= 0 or self._stop.wait(left):
                break
            log.info("recording to %s: %s", self.out.path, self.summary())

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        self.out.close()
        log.info("recorded %s to %s", self.summary(), self.out.path)


@dataclass
class Recorded:
    """One message of a recording: its key, Zenoh encoding, payload and reception time."""
    key: str
    encoding: str
    payload: bytes
    log_time_ns: int
    message_type: type[Message] | None


class _KeyFilter:
    def __init__(self, key_exprs: list[str] | None, skip: list[str] | None):
        self.want = [zenoh.KeyExpr(k) for k in key_exprs or []]
        self.drop = [zenoh.KeyExpr(k) for k in skip or []]
        self._memo: dict[str, bool] = {}

    def __call__(self, key: str) -> bool:
        ok = self._memo.get(key)
        if ok is None:
            ok = self._memo[key] = ((not self.want or any(w.intersects(key) for w in self.want))
                                    and not any(d.intersects(key) for d in self.drop))
        return ok


def _encoding(channel) -> str:
    return channel.metadata.get(META_ZENOH_ENCODING, channel.message_encoding)


def _unreadable(path, e: BaseException) -> ValueError:
    if isinstance(e, FileNotFoundError):
        return ValueError(f"recording {path}: no such file")
    return ValueError(f"recording {path}: not a readable MCAP file ({type(e).__name__}: {e})")


_READ_ERRORS = (EOFError, ValueError, OSError, KeyError, AssertionError)


def _has_magic(path: str | Path) -> bool:
    with open(path, "rb") as f:
        return f.read(5) == b"\x89MCAP"  # MCAP's magic (then the major version, then \r\n)


def _stream_messages(path: str | Path):
    """(channel, message) of a file without a usable index (its writer was killed), in file order,
    up to the first incomplete record."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    channels = {}
    with open(path, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                yield channels[record.channel_id], record


def read_recording(path: str | Path, key_exprs: list[str] | None = None, skip: list[str] | None = None):
    """Yield the Recorded messages of an MCAP file in reception order, those whose key intersects one of
    ``key_exprs`` (default: all) and none of ``skip``. Raises ValueError for a file MCAP cannot read; a
    file cut short (the recorder was killed) yields its complete chunks, with a warning."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    keep = _KeyFilter(key_exprs, skip)
    n = 0

    def messages():
        with open(path, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
                yield channel, message

    source = messages()
    while True:
        try:
            for channel, message in source:
                if keep(channel.topic):
                    enc = _encoding(channel)
                    n += 1
                    yield Recorded(channel.topic, enc, message.data, message.log_time, message_type_of(enc))
            return
        except (McapError, *_READ_ERRORS) as e:
            if isinstance(e, FileNotFoundError):
                raise _unreadable(path, e) from None
            if n == 0 and source.__name__ == "messages" and _has_magic(path):
                log.warning("recording %s has no usable index (%s): reading it as a stream", path, type(e).__name__)
                source = _stream_messages(path)
                continue
            if n == 0:
                raise _unreadable(path, e) from None
            log.warning("recording %s ends early after %d messages (%s: %s)", path, n, type(e).__name__, e)
            return


def recording_channels(path: str | Path, key_exprs: list[str] | None = None,
                       skip: list[str] | None = None) -> list[Recorded]:
    """One Recorded per channel (payload empty; log time: the channel's first message), from the file's
    summary when it has one, else by reading it through."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    keep = _KeyFilter(key_exprs, skip)
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except FileNotFoundError as e:
        raise _unreadable(path, e) from None
    except (McapError, *_READ_ERRORS):
        summary = None  # no index: read it through (read_recording says why, or raises)
    if summary is None or summary.statistics is None or not summary.chunk_indexes:
        first: dict[tuple[str, str], Recorded] = {}
        for m in read_recording(path, key_exprs, skip):
            first.setdefault((m.key, m.encoding), Recorded(m.key, m.encoding, b"", m.log_time_ns, m.message_type))
        return list(first.values())
    start = summary.statistics.message_start_time
    out = []
    for cid, channel in summary.channels.items():
        if keep(channel.topic) and summary.statistics.channel_message_counts.get(cid, 0):
            enc = _encoding(channel)
            out.append(Recorded(channel.topic, enc, b"", start, message_type_of(enc)))
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag record", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, metavar="RUN.mcap", help="MCAP file to write (overwritten)")
    p.add_argument("--keys", action="append", default=None, metavar="EXPR",
                   help=f"key expression to record, repeatable (default {keys.EVERYTHING})")
    p.add_argument("--frames", action="store_true", help="record camera frames too (large)")
    add_service_arguments(p)
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    key_exprs = args.keys or [keys.EVERYTHING]

    def load() -> McapLog:
        for k in key_exprs:
            try:
                zenoh.KeyExpr(k)
            except Exception:
                raise ValueError(f"--keys {k!r} is not a valid key expression") from None
        out = Path(args.out)
        if not out.parent.is_dir():
            raise ValueError(f"--out {out}: directory {out.parent} does not exist")
        return McapLog(out, {"keys": " ".join(key_exprs), "frames": args.frames, "host": socket.gethostname(),
                             "pid": os.getpid(), "started_ns": time.time_ns()})

    return run_service("record", args, load, lambda session, out: Recorder(session, out, key_exprs, args.frames),
                       lambda out: f"recorder ({out.path}, {' '.join(key_exprs)}{', frames' if args.frames else ''})")
