"""The one place where toptag messages become bytes and back.

- Frame: a 16-byte binary prefix, a compact JSON header, then the raw image bytes (no base64):

      offset 0  4 bytes  magic b"TTFR"
      offset 4  uint32   header length H (big endian)
      offset 8  uint64   image length N (big endian)
      offset 16 H bytes  UTF-8 JSON header (every Frame field but ``image``; same checks as any message)
      offset 16+H  N bytes  image

- Imu (100 samples a second per bus; the bus agent's most frequent input): a fixed binary layout, read
  with one struct.unpack (big endian):

      offset 0   4 bytes  magic b"TTIM"
      offset 4   uint8    protocol version
      offset 5   uint8    flags: bit 0 wheel_speed present, bit 1 seq present (absent: 0 in its slot)
      offset 6   uint64   t_ns
      offset 14  7 x float64  gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z, wheel_speed
      offset 70  uint64   seq
      offset 78  uint16   bus_id length L
      offset 80  L bytes  bus_id, UTF-8

  The decoder checks what pydantic would (version, flags, length, finite numbers, the id) and builds the
  model without pydantic's validation: a JSON decode of an Imu cost ~60 us of CPU on the agent's
  every-20-ms wake-up, cold (docs/architecture.md). Imu in JSON, as sent before this layout, still
  decodes (recordings made before it replay).
- ImuBatch (several Imu samples of one bus; what the simulator sends): a header, the bus_id, then N
  records of an Imu's fields (big endian):

      offset 0   4 bytes  magic b"TTIB"
      offset 4   uint8    protocol version
      offset 5   uint8    flags: bit 1 seq present (absent: 0 in its slot)
      offset 6   uint64   seq
      offset 14  uint16   sample count N (1 to IMU_BATCH_MAX)
      offset 16  uint16   bus_id length L
      offset 18  L bytes  bus_id, UTF-8
      then N x 73 bytes   uint8 flags, uint64 t_ns, 7 x float64, uint64 seq: as in Imu's layout

  checked as an Imu's, and the samples' times strictly increasing, as pydantic would.
- Every other message: compact UTF-8 JSON from pydantic (``model_dump_json``).

``decode`` raises ProtocolError, whose str() is one line naming the problem (wrong version, malformed
JSON, missing field, bad frame prefix...) and whose ``reason`` is a short code for counters.
"""
from __future__ import annotations

import json
import math
import struct
from typing import TypeVar

from pydantic import ValidationError

from protocol import keys as _keys
from protocol.messages import IMU_BATCH_MAX, MESSAGE_TYPES, PROTOCOL_VERSION, Frame, Imu, ImuBatch, Message, check_id
from toptag.errors import ProtocolError
from toptag.inputs import describe_validation_error

FRAME_MAGIC = b"TTFR"
_FRAME_PREFIX = struct.Struct(">4sIQ")
FRAME_PREFIX_SIZE = _FRAME_PREFIX.size  # 16
MAX_FRAME_HEADER = 64 * 1024
IMU_MAGIC = b"TTIM"
_IMU = struct.Struct(">4sBBQ7dQH")
IMU_FIXED_SIZE = _IMU.size  # 80, then the bus_id
_IMU_WHEEL, _IMU_SEQ = 1, 2
_IMU_FLOATS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z", "wheel_speed")
_IMU_FIELDS = tuple(Imu.model_fields)
IMU_BATCH_MAGIC = b"TTIB"
_IMU_BATCH = struct.Struct(">4sBBQHH")
IMU_BATCH_FIXED_SIZE = _IMU_BATCH.size  # 18, then the bus_id, then the samples
_IMU_RECORD = struct.Struct(">BQ7dQ")  # one sample of a batch: Imu's fields from its flags to its seq
_IMU_BATCH_SEQ = 2
_IMU_BATCH_FIELDS = tuple(ImuBatch.model_fields)
# Messages with a binary layout, by magic (the first 4 bytes; JSON starts with '{').
BINARY: dict[bytes, type[Message]] = {FRAME_MAGIC: Frame, IMU_MAGIC: Imu, IMU_BATCH_MAGIC: ImuBatch}
WIRE = {"wire": True}  # validation context: version and type must be on the wire

M = TypeVar("M", bound=Message)

# reason codes
R_EMPTY, R_UTF8, R_JSON, R_OBJECT, R_VERSION, R_TYPE, R_FIELD, R_FRAME, R_KEY, R_LAYOUT = (
    "empty", "utf8", "json", "not_object", "version", "type", "field", "frame", "key", "layout")


# A payload that is not a valid message of the expected type raises toptag.errors.ProtocolError.


def _as_bytes(payload) -> bytes | memoryview:
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return payload
    to_bytes = getattr(payload, "to_bytes", None)  # zenoh.ZBytes
    if to_bytes is not None:
        return to_bytes()
    raise TypeError(f"payload must be bytes-like or zenoh.ZBytes, not {type(payload).__name__}")


# ---- encode -----------------------------------------------------------------------------------

def is_binary(msg_type: type[Message]) -> bool:
    """Whether ``msg_type`` goes on the wire in a binary layout (else JSON)."""
    return msg_type in BINARY.values()


def encode(msg: Message) -> bytes:
    """Serialise a message for the wire."""
    if not isinstance(msg, Message):
        raise TypeError(f"encode() takes a protocol message, not {type(msg).__name__}")
    if isinstance(msg, Frame):
        header = msg.model_dump_json().encode()
        return b"".join((_FRAME_PREFIX.pack(FRAME_MAGIC, len(header), len(msg.image)), header, msg.image))
    if isinstance(msg, Imu):
        return _encode_imu(msg)
    if isinstance(msg, ImuBatch):
        return _encode_imu_batch(msg)
    return msg.model_dump_json().encode()


def encode_as(msg: Message, like) -> bytes:
    """``msg`` encoded in the form ``like`` (a payload of the same type) has: JSON for an Imu recorded before
    its binary layout, so that a shifted replay sends what its recording's encoding says (an ImuBatch was
    binary from the start)."""
    if isinstance(msg, Imu) and bytes(_as_bytes(like)[:4]) != IMU_MAGIC:
        return msg.model_dump_json().encode()
    return encode(msg)


def _imu_values(m: Imu) -> tuple:
    """An Imu's fields in its layout's order, from its flags to its seq."""
    flags = (_IMU_WHEEL if m.wheel_speed is not None else 0) | (_IMU_SEQ if m.seq is not None else 0)
    return (flags, m.t_ns, m.gyro_x, m.gyro_y, m.gyro_z, m.accel_x, m.accel_y, m.accel_z, m.wheel_speed or 0.0,
            m.seq or 0)


def _encode_imu(m: Imu) -> bytes:
    bus_id = m.bus_id.encode()
    try:
        head = _IMU.pack(IMU_MAGIC, PROTOCOL_VERSION, *_imu_values(m), len(bus_id))
    except struct.error as e:  # t_ns or seq beyond 64 bits
        raise ValueError(f"Imu: does not fit its binary layout: {e}") from None
    return head + bus_id


def _encode_imu_batch(m: ImuBatch) -> bytes:
    bus_id = m.bus_id.encode()
    try:
        parts = [_IMU_BATCH.pack(IMU_BATCH_MAGIC, PROTOCOL_VERSION, _IMU_BATCH_SEQ if m.seq is not None else 0,
                                 m.seq or 0, len(m.samples), len(bus_id)), bus_id]
        parts += [_IMU_RECORD.pack(*_imu_values(s)) for s in m.samples]
    except struct.error as e:  # t_ns or seq beyond 64 bits
        raise ValueError(f"ImuBatch: does not fit its binary layout: {e}") from None
    return b"".join(parts)


# ---- decode -----------------------------------------------------------------------------------

def decode(payload, expected_type: type[M], *, key: str | None = None) -> M:
    """Parse a payload as ``expected_type``; if ``key`` (the key the sample came on) is given, also check
    that the ids in the key match the message's. Raises ProtocolError."""
    data = _as_bytes(payload)
    name = expected_type.__name__
    if expected_type is Frame:
        msg = _decode_frame(data)
    elif expected_type is Imu and data[:4] == IMU_MAGIC:
        msg = _decode_imu(data)
    elif expected_type is ImuBatch and data[:4] == IMU_BATCH_MAGIC:
        msg = _decode_imu_batch(data)
    else:
        if len(data) == 0:
            raise ProtocolError(f"{name}: empty payload", R_EMPTY, name)
        other = BINARY.get(bytes(data[:4]))
        if other is not None:
            raise ProtocolError(f"{name}: got a binary {other.TYPE} payload", R_TYPE, name)
        if isinstance(data, memoryview):
            data = data.tobytes()
        try:
            msg = expected_type.model_validate_json(data, context=WIRE)
        except ValidationError as e:
            _diagnose_json(data, expected_type, e)
            raise AssertionError("unreachable")  # _diagnose_json always raises
    if key is not None:
        check_key(msg, key)
    return msg  # type: ignore[return-value]


def _parse_object(data, name: str) -> dict:
    """UTF-8 -> JSON -> dict, or a ProtocolError naming which step failed."""
    try:
        text = bytes(data).decode("utf-8")
    except UnicodeDecodeError as e:
        raise ProtocolError(f"{name}: payload is not UTF-8 (byte {e.start})", R_UTF8, name) from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise ProtocolError(f"{name}: malformed JSON at line {e.lineno} column {e.colno}: {e.msg}",
                            R_JSON, name) from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"{name}: expected a JSON object, got {type(obj).__name__}", R_OBJECT, name)
    return obj


def _diagnose_json(data, expected_type: type[Message], err: ValidationError | None):
    """Turn a failed validation into the most useful one-line ProtocolError."""
    name = expected_type.__name__
    obj = _parse_object(data, name)
    if "version" not in obj:
        raise ProtocolError(f"{name}: missing field 'version'", R_VERSION, name)
    if type(obj["version"]) is not int or obj["version"] != PROTOCOL_VERSION:
        raise ProtocolError(f"{name}: wrong protocol version {obj['version']!r} "
                            f"(this build speaks {PROTOCOL_VERSION})", R_VERSION, name)
    if obj.get("type") != expected_type.TYPE:
        got = obj.get("type")
        raise ProtocolError(f"{name}: wrong message type {got!r} (expected {expected_type.TYPE!r})"
                            if got is not None else f"{name}: missing field 'type'", R_TYPE, name)
    if err is None:
        try:
            expected_type.model_validate(obj, context=WIRE)
            return
        except ValidationError as e:
            err = e
    raise ProtocolError(f"{name}: {_describe(err)}", R_FIELD, name) from None


def _describe(e: ValidationError) -> str:
    """describe_validation_error, with 'Field required' spelled as 'missing field'."""
    first = e.errors()[0]
    if first.get("type") == "missing" and e.error_count() == 1:
        return "missing field '" + ".".join(str(x) for x in first["loc"]) + "'"
    return describe_validation_error(e)


def _decode_frame(data) -> Frame:
    n = len(data)
    if n < FRAME_PREFIX_SIZE:
        raise ProtocolError(f"Frame: payload of {n} bytes is shorter than the {FRAME_PREFIX_SIZE}-byte prefix",
                            R_FRAME, "Frame")
    magic, hlen, ilen = _FRAME_PREFIX.unpack_from(data, 0)
    if magic != FRAME_MAGIC:
        raise ProtocolError(f"Frame: bad magic {bytes(magic)!r} (expected {FRAME_MAGIC!r})", R_FRAME, "Frame")
    if hlen > MAX_FRAME_HEADER:
        raise ProtocolError(f"Frame: header length {hlen} exceeds {MAX_FRAME_HEADER}", R_FRAME, "Frame")
    expected = FRAME_PREFIX_SIZE + hlen + ilen
    if n < expected:
        raise ProtocolError(f"Frame: truncated payload ({n} of {expected} bytes; image {ilen} bytes)",
                            R_FRAME, "Frame")
    if n > expected:
        raise ProtocolError(f"Frame: {n - expected} trailing bytes after the image", R_FRAME, "Frame")
    view = memoryview(data)
    header = view[FRAME_PREFIX_SIZE:FRAME_PREFIX_SIZE + hlen]
    try:
        head = json.loads(bytes(header).decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ProtocolError(f"Frame: header is not UTF-8 (byte {e.start})", R_UTF8, "Frame") from None
    except json.JSONDecodeError as e:
        raise ProtocolError(f"Frame: malformed header JSON at column {e.colno}: {e.msg}", R_JSON, "Frame") from None
    if not isinstance(head, dict):
        raise ProtocolError(f"Frame: header must be a JSON object, got {type(head).__name__}", R_OBJECT, "Frame")
    if "image" in head:
        raise ProtocolError("Frame: header must not contain 'image'", R_FIELD, "Frame")
    head["image"] = bytes(view[FRAME_PREFIX_SIZE + hlen:])
    try:
        return Frame.model_validate(head, context=WIRE)
    except ValidationError as e:
        _diagnose_json(bytes(header), Frame, e)
        raise AssertionError("unreachable")


def _decode_imu(data) -> Imu:
    """An Imu from its binary layout, checked as pydantic would check it (ProtocolError otherwise)."""
    n = len(data)
    if n < IMU_FIXED_SIZE:
        raise ProtocolError(f"Imu: binary payload of {n} bytes is shorter than the {IMU_FIXED_SIZE}-byte layout",
                            R_LAYOUT, "Imu")
    _, version, *values, id_len = _IMU.unpack_from(data, 0)
    if n != IMU_FIXED_SIZE + id_len:
        raise ProtocolError(f"Imu: binary payload of {n} bytes, expected {IMU_FIXED_SIZE + id_len} "
                            f"({IMU_FIXED_SIZE} and a {id_len}-byte bus_id)", R_LAYOUT, "Imu")
    _check_version(version, "Imu")
    return _imu(version, _bus_id(data[IMU_FIXED_SIZE:], "Imu"), values, "Imu", "Imu")


def _decode_imu_batch(data) -> ImuBatch:
    """An ImuBatch from its binary layout, checked as pydantic would check it (ProtocolError otherwise)."""
    n, name = len(data), "ImuBatch"
    if n < IMU_BATCH_FIXED_SIZE:
        raise ProtocolError(f"{name}: binary payload of {n} bytes is shorter than its {IMU_BATCH_FIXED_SIZE}-byte "
                            f"header", R_LAYOUT, name)
    _, version, flags, seq, count, id_len = _IMU_BATCH.unpack_from(data, 0)
    start = IMU_BATCH_FIXED_SIZE + id_len
    if n != start + count * _IMU_RECORD.size:
        raise ProtocolError(f"{name}: binary payload of {n} bytes, expected {start + count * _IMU_RECORD.size} "
                            f"({IMU_BATCH_FIXED_SIZE}, a {id_len}-byte bus_id and {count} samples of "
                            f"{_IMU_RECORD.size})", R_LAYOUT, name)
    _check_version(version, name)
    if flags & ~_IMU_BATCH_SEQ:
        raise ProtocolError(f"{name}: unknown flags 0x{flags:02x} in the binary layout", R_LAYOUT, name)
    if not 1 <= count <= IMU_BATCH_MAX:
        raise ProtocolError(f"{name}: samples: {count} samples, must be 1 to {IMU_BATCH_MAX}", R_FIELD, name)
    bus_id = _bus_id(data[IMU_BATCH_FIXED_SIZE:start], name)
    samples, t_prev = [], -1
    for i, values in enumerate(_IMU_RECORD.iter_unpack(data[start:])):
        if values[1] <= t_prev:
            raise ProtocolError(f"{name}: samples[{i}]: t_ns {values[1]} is not after the sample before ({t_prev})",
                                R_FIELD, name)
        t_prev = values[1]
        samples.append(_imu(version, bus_id, values, f"{name}: samples[{i}]", name))
    return _built(ImuBatch, _IMU_BATCH_FIELDS, {"version": version, "type": "imu_batch", "bus_id": bus_id,
                                               "samples": samples, "seq": seq if flags & _IMU_BATCH_SEQ else None})


def _check_version(version: int, name: str) -> None:
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"{name}: wrong protocol version {version} (this build speaks {PROTOCOL_VERSION})",
                            R_VERSION, name)


def _bus_id(raw, name: str) -> str:
    try:
        return check_id(bytes(raw).decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ProtocolError(f"{name}: bus_id is not UTF-8 (byte {e.start})", R_UTF8, name) from None
    except ValueError as e:
        raise ProtocolError(f"{name}: bus_id: {e}", R_FIELD, name) from None


def _imu(version: int, bus_id: str, values, where: str, name: str) -> Imu:
    """The Imu of a layout's values (flags, t_ns, the 7 floats, seq), checked as pydantic would check them.
    where: what an error names (the message, or a batch's sample); name: the message type received."""
    flags, t_ns, gx, gy, gz, ax, ay, az, wheel, seq = values
    if flags & ~(_IMU_WHEEL | _IMU_SEQ):
        raise ProtocolError(f"{where}: unknown flags 0x{flags:02x} in the binary layout", R_LAYOUT, name)
    if not math.isfinite(gx + gy + gz + ax + ay + az + wheel):  # one test: finite but for NaN, inf or overflow
        for field, v in zip(_IMU_FLOATS, (gx, gy, gz, ax, ay, az, wheel)):
            if not math.isfinite(v):
                raise ProtocolError(f"{where}: {field}: must be a finite number, got {v}", R_FIELD, name)
    return _built(Imu, _IMU_FIELDS, {
        "version": version, "type": "imu", "bus_id": bus_id, "t_ns": t_ns, "gyro_x": gx, "gyro_y": gy,
        "gyro_z": gz, "accel_x": ax, "accel_y": ay, "accel_z": az,
        "wheel_speed": wheel if flags & _IMU_WHEEL else None, "seq": seq if flags & _IMU_SEQ else None})


def _built(cls: type[M], fields: tuple[str, ...], values: dict) -> M:
    """Every field checked by the caller: the model built as pydantic's model_construct builds it (without the
    loop over its fields: half the cold CPU of model_construct for an Imu)."""
    msg = _new(cls)
    _setattr(msg, "__dict__", values)
    _setattr(msg, "__pydantic_fields_set__", set(fields))
    _setattr(msg, "__pydantic_extra__", None)
    _setattr(msg, "__pydantic_private__", None)
    return msg


_new, _setattr = object.__new__, object.__setattr__


def decode_any(payload) -> Message:
    """Decode a payload of any toptag type (dispatch on the ``type`` field; binary layouts by their magic)."""
    data = _as_bytes(payload)
    binary = BINARY.get(bytes(data[:4]))
    if binary is not None:
        return decode(data, binary)
    obj = _parse_object(data, "message")
    t = obj.get("type")
    cls = MESSAGE_TYPES.get(t) if isinstance(t, str) else None
    if cls is None:
        raise ProtocolError(f"message: unknown message type {t!r}" if t is not None
                            else "message: missing field 'type'", R_TYPE, "message")
    return decode(data, cls)


_KEY_FIELDS: dict[str, tuple[tuple[str, str], ...]] = {}  # key -> (message field, id) pairs it names
_KEY_FIELDS_MAX = 4096


def _key_fields(key: str) -> tuple[tuple[str, str], ...]:
    """The (message field, value) pairs a key's ids name (none for a key that is not a toptag key);
    parsed once per key (a service sends and receives on a few keys, every message checks one)."""
    fields = _KEY_FIELDS.get(key)
    if fields is None:
        try:
            parsed = _keys.parse(key)
        except _keys.KeyExprError:
            fields = ()
        else:
            fields = tuple((_keys.ID_FIELDS[name], value) for name, value in parsed.ids.items()
                           if name in _keys.ID_FIELDS)
        if len(_KEY_FIELDS) < _KEY_FIELDS_MAX:
            _KEY_FIELDS[key] = fields
    return fields


def check_key(msg: Message, key: str) -> None:
    """Raise ProtocolError if an id in the toptag key differs from the message's (e.g. a fix for bus A
    published on bus B's key). Keys that are not toptag keys are not checked."""
    for field, value in _key_fields(str(key)):
        if not hasattr(msg, field):
            continue
        actual = getattr(msg, field)
        if actual != value:
            raise ProtocolError(f"{type(msg).__name__}: {field} {actual!r} does not match key {key!r}",
                                R_KEY, type(msg).__name__)
