"""The wire contract without a network: messages, keys, codec."""
from __future__ import annotations

import json
import math
import struct

import pytest
import zenoh
from conftest import key_for, make_samples
from pydantic import ValidationError

from protocol import (
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    Approach,
    Frame,
    FusedPose,
    Imu,
    ImuBatch,
    Leave,
    PoseFix,
    ProtocolError,
    codec,
    decode,
    decode_any,
    encode,
    keys,
)

pytestmark = pytest.mark.unit

SAMPLES = make_samples()


def test_samples_cover_every_message_type():
    assert set(SAMPLES) == {cls.__name__ for cls in MESSAGE_TYPES.values()}


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_round_trip(name):
    msg = SAMPLES[name]
    payload = encode(msg)
    assert isinstance(payload, bytes)
    back = decode(payload, type(msg), key=key_for(msg))
    assert back == msg
    assert type(back) is type(msg)
    assert decode_any(payload) == msg
    if not codec.is_binary(type(msg)):
        obj = json.loads(payload)
        assert obj["version"] == PROTOCOL_VERSION and obj["type"] == type(msg).TYPE
        assert b'", "' not in payload and b'": ' not in payload and b", " not in payload  # compact JSON


def test_frame_is_header_plus_raw_bytes_without_base64():
    image = bytes(range(256)) * 4000  # ~1 MB, not valid UTF-8
    f = Frame(rsu_id="rsu-sw", capture_time_ns=5, seq=1, encoding="jpeg", width=960, height=720, image=image)
    payload = encode(f)
    assert payload[:4] == codec.FRAME_MAGIC
    assert payload.endswith(image)
    assert len(payload) - len(image) < 200
    magic, hlen, ilen = struct.unpack_from(">4sIQ", payload)
    assert ilen == len(image)
    header = json.loads(payload[16:16 + hlen])
    assert header["version"] == PROTOCOL_VERSION and header["type"] == "frame" and "image" not in header
    assert decode(payload, Frame).image == image


def test_raw_frame_size_is_checked():
    Frame(rsu_id="r", capture_time_ns=0, seq=0, encoding="bgr8", width=4, height=2, image=bytes(24))
    with pytest.raises(ValidationError, match="needs 24 bytes"):
        Frame(rsu_id="r", capture_time_ns=0, seq=0, encoding="bgr8", width=4, height=2, image=bytes(23))


def _fix_payload() -> bytes:
    return encode(SAMPLES["PoseFix"])


def _json_with(**changes) -> bytes:
    obj = json.loads(_fix_payload())
    for k, v in changes.items():
        if v is ...:
            del obj[k]
        else:
            obj[k] = v
    return json.dumps(obj).encode()


BAD_JSON = [
    # (payload, reason code, text in the one-line message)
    (b"", "empty", "empty payload"),
    (b'{"version":1,"type":"pose_f', "json", "malformed JSON"),
    (b"\xff\xfe\x00", "utf8", "not UTF-8"),
    (b"[1, 2]", "not_object", "expected a JSON object, got list"),
    (_json_with(version=2), "version", "wrong protocol version 2 (this build speaks 1)"),
    (_json_with(version="1"), "version", "wrong protocol version '1'"),
    (_json_with(version=...), "version", "missing field 'version'"),
    (_json_with(type="leave"), "type", "wrong message type 'leave' (expected 'pose_fix')"),
    (_json_with(type=...), "type", "missing field 'type'"),
    (_json_with(x=...), "field", "missing field 'x'"),
    (_json_with(x="east"), "field", "x:"),
    (_json_with(covariance=[[1, 0], [0, 1]]), "field", "covariance"),
    (_json_with(covariance=[[1, 2, 0], [0, 1, 0], [0, 0, 1]]), "field", "symmetric"),
    (_json_with(bus_id="bus/17"), "field", "forbidden character"),
    (_json_with(extra_field=1), "field", "extra_field"),
    (_json_with(capture_time_ns=-1), "field", "capture_time_ns"),
    (encode(SAMPLES["Frame"]), "type", "binary frame"),
]


@pytest.mark.parametrize("payload,reason,text", BAD_JSON, ids=[b[2] for b in BAD_JSON])
def test_bad_json_payloads_are_rejected_with_one_clear_line(payload, reason, text):
    with pytest.raises(ProtocolError) as ei:
        decode(payload, PoseFix)
    e = ei.value
    assert e.reason == reason
    assert text in str(e)
    assert "\n" not in str(e)
    assert str(e).startswith("PoseFix: ")


def _frame_payload() -> bytes:
    return encode(SAMPLES["Frame"])


def _frame_with_header(header: bytes, image: bytes = b"img") -> bytes:
    return struct.pack(">4sIQ", b"TTFR", len(header), len(image)) + header + image


BAD_FRAMES = [
    (_frame_payload()[:-1], "frame", "truncated payload"),
    (_frame_payload()[:100], "frame", "truncated payload"),
    (_frame_payload()[:9], "frame", "shorter than the 16-byte prefix"),
    (_frame_payload() + b"x", "frame", "1 trailing bytes"),
    (b"JPEG" + _frame_payload()[4:], "frame", "bad magic"),
    (struct.pack(">4sIQ", b"TTFR", 10**6, 0), "frame", "header length"),
    (_frame_with_header(b"{not json"), "json", "malformed header JSON"),
    (_frame_with_header(json.dumps({"version": 2, "type": "frame"}).encode()), "version",
     "wrong protocol version 2"),
    (_frame_with_header(json.dumps({"version": 1, "type": "frame", "rsu_id": "r", "seq": 0, "encoding": "jpeg",
                                    "width": 4, "height": 2}).encode()), "field",
     "missing field 'capture_time_ns'"),
    (_frame_with_header(json.dumps({"version": 1, "type": "frame", "rsu_id": "r", "seq": 0, "encoding": "gray8",
                                    "width": 4, "height": 2, "capture_time_ns": 1}).encode()), "field",
     "needs 8 bytes, got 3"),
]


@pytest.mark.parametrize("payload,reason,text", BAD_FRAMES, ids=[b[2] for b in BAD_FRAMES])
def test_bad_frames_are_rejected(payload, reason, text):
    with pytest.raises(ProtocolError) as ei:
        decode(payload, Frame)
    assert ei.value.reason == reason
    assert text in str(ei.value) and "\n" not in str(ei.value)


IMU = Imu(bus_id="bus-42", t_ns=7, gyro_z=0.1, accel_x=-0.5, wheel_speed=4.0, seq=3)
# The wire bytes of IMU, written out (protocol/codec.py's layout): magic, version, flags (wheel_speed and seq
# present), t_ns, the seven floats, seq, the bus_id's length and the bus_id.
IMU_BINARY = bytes.fromhex(
    "5454494d" "01" "03" "0000000000000007" "0000000000000000" "0000000000000000" "3fb999999999999a"
    "bfe0000000000000" "0000000000000000" "0000000000000000" "4010000000000000" "0000000000000003" "0006")
IMU_BINARY += b"bus-42"
# The same sample in JSON, as main (8acdd76) encoded it before the binary layout: recordings hold it.
IMU_JSON = (b'{"version":1,"type":"imu","bus_id":"bus-42","t_ns":7,"gyro_x":0.0,"gyro_y":0.0,"gyro_z":0.1,'
            b'"accel_x":-0.5,"accel_y":0.0,"accel_z":0.0,"wheel_speed":4.0,"seq":3}')


def test_imu_has_a_fixed_binary_layout_and_its_json_form_still_decodes():
    assert encode(IMU) == IMU_BINARY
    for payload in (IMU_BINARY, IMU_JSON):
        back = decode(payload, Imu, key=keys.imu("bus-42"))
        assert back == IMU and decode_any(payload) == IMU and hash(back) == hash(IMU)
        assert back.model_dump_json().encode() == IMU_JSON and encode(back) == IMU_BINARY
        assert back.model_copy(update={"seq": 4}).seq == 4 and back.seq == 3
        with pytest.raises(ValidationError, match="frozen"):
            back.seq = 5  # type: ignore[misc]
    bare = Imu(bus_id="b", t_ns=0, gyro_z=-0.0)  # optional fields absent: None again, not 0
    assert decode(encode(bare), Imu) == bare and decode(encode(bare), Imu).wheel_speed is None
    assert codec.encode_as(IMU, IMU_JSON) == IMU_JSON and codec.encode_as(IMU, IMU_BINARY) == IMU_BINARY
    with pytest.raises(ProtocolError, match="PoseFix: got a binary imu payload"):
        decode(IMU_BINARY, PoseFix)


def _imu_with(offset: int, raw: bytes) -> bytes:
    return IMU_BINARY[:offset] + raw + IMU_BINARY[offset + len(raw):]


BAD_IMU = [
    (IMU_BINARY[:40], "layout", "binary payload of 40 bytes is shorter than the 80-byte layout"),
    (IMU_BINARY[:-1], "layout", "binary payload of 85 bytes, expected 86 (80 and a 6-byte bus_id)"),
    (IMU_BINARY + b"\0", "layout", "binary payload of 87 bytes, expected 86"),
    (_imu_with(4, b"\x02"), "version", "wrong protocol version 2 (this build speaks 1)"),
    (_imu_with(5, b"\x07"), "layout", "unknown flags 0x07"),
    (_imu_with(30, struct.pack(">d", math.nan)), "field", "gyro_z: must be a finite number, got nan"),
    (_imu_with(62, struct.pack(">d", -math.inf)), "field", "wheel_speed: must be a finite number, got -inf"),
    (_imu_with(80, b"bus/42"), "field", "bus_id: id 'bus/42' contains forbidden character(s) /"),
    (_imu_with(80, b"\xffus-42"), "utf8", "bus_id is not UTF-8 (byte 0)"),
    (_imu_with(78, b"\x00\x00")[:80], "field", "bus_id: id must not be empty"),
    (encode(SAMPLES["Frame"]), "type", "got a binary frame payload"),
]


BATCH = ImuBatch(bus_id="bus-42", seq=5, samples=[IMU, IMU.model_copy(update={"t_ns": 9, "seq": None,
                                                                               "wheel_speed": None})])
# The wire bytes of BATCH, written out (protocol/codec.py's layout): magic, version, flags (seq present), seq,
# the sample count, the bus_id's length, the bus_id, then each sample's flags, t_ns, seven floats and seq.
BATCH_BINARY = (bytes.fromhex("54544942" "01" "02" "0000000000000005" "0002" "0006") + b"bus-42"
                + IMU_BINARY[5:78] + bytes.fromhex("00" "0000000000000009") + IMU_BINARY[14:62]
                + bytes(8) + bytes(8))


def test_imu_batch_has_a_fixed_binary_layout_and_a_json_form():
    assert encode(BATCH) == BATCH_BINARY
    as_json = BATCH.model_dump_json().encode()
    for payload in (BATCH_BINARY, as_json):
        back = decode(payload, ImuBatch, key=keys.imu_batch("bus-42"))
        assert back == BATCH and decode_any(payload) == BATCH and back.samples[1].wheel_speed is None
        assert back.model_dump_json().encode() == as_json and encode(back) == BATCH_BINARY
    with pytest.raises(ProtocolError, match="Imu: got a binary imu_batch payload"):
        decode(BATCH_BINARY, Imu)


def test_an_imu_batch_is_of_one_bus_in_time_order():
    with pytest.raises(ValidationError, match="samples.1.: bus_id 'bus-43' is not the batch's 'bus-42'"):
        ImuBatch(bus_id="bus-42", samples=[IMU, IMU.model_copy(update={"t_ns": 9, "bus_id": "bus-43"})])
    with pytest.raises(ValidationError, match="samples.1.: t_ns 7 is not after the sample before .7."):
        ImuBatch(bus_id="bus-42", samples=[IMU, IMU])
    with pytest.raises(ValidationError, match="at least 1 item"):
        ImuBatch(bus_id="bus-42", samples=[])


def _batch_with(offset: int, raw: bytes) -> bytes:
    return BATCH_BINARY[:offset] + raw + BATCH_BINARY[offset + len(raw):]


BAD_BATCH = [
    (BATCH_BINARY[:10], "layout", "binary payload of 10 bytes is shorter than its 18-byte header"),
    (BATCH_BINARY[:-1], "layout",
     "binary payload of 169 bytes, expected 170 (18, a 6-byte bus_id and 2 samples of 73)"),
    (_batch_with(4, b"\x02"), "version", "wrong protocol version 2 (this build speaks 1)"),
    (_batch_with(5, b"\x01"), "layout", "unknown flags 0x01"),
    (_batch_with(14, b"\x00\x00")[:24], "field", "samples: 0 samples, must be 1 to 100"),
    (_batch_with(18, b"bus/42"), "field", "bus_id: id 'bus/42' contains forbidden character(s) /"),
    (_batch_with(24 + 73, b"\x04"), "layout", "samples[1]: unknown flags 0x04"),
    (_batch_with(24 + 73 + 1 + 8 + 16, struct.pack(">d", math.nan)), "field", "samples[1]: gyro_z: must be a finite"),
    (_batch_with(24 + 73 + 1, struct.pack(">Q", 7)), "field", "samples[1]: t_ns 7 is not after the sample before (7)"),
]


BAD_BINARY_IMU = [(Imu, *b) for b in BAD_IMU] + [(ImuBatch, *b) for b in BAD_BATCH]


@pytest.mark.parametrize("msg_type,payload,reason,text", BAD_BINARY_IMU,
                         ids=[f"{b[0].__name__}: {b[3]}" for b in BAD_BINARY_IMU])
def test_bad_binary_imu_payloads_are_rejected_with_one_clear_line(msg_type, payload, reason, text):
    with pytest.raises(ProtocolError) as ei:
        decode(payload, msg_type)
    assert ei.value.reason == reason and text in str(ei.value)
    assert str(ei.value).startswith(f"{msg_type.__name__}: ") and "\n" not in str(ei.value)


def test_decode_accepts_zenoh_bytes_and_memoryview():
    p = _fix_payload()
    assert decode(zenoh.ZBytes(p), PoseFix) == SAMPLES["PoseFix"]
    assert decode(memoryview(p), PoseFix) == SAMPLES["PoseFix"]
    assert decode(bytearray(_frame_payload()), Frame) == SAMPLES["Frame"]


def test_key_check_rejects_ids_that_do_not_match_the_key():
    fix = SAMPLES["PoseFix"]
    with pytest.raises(ProtocolError, match="bus_id 'bus-17' does not match key") as ei:
        decode(encode(fix), PoseFix, key=keys.pose_fix("x1", "bus-18", "rsu-sw"))
    assert ei.value.reason == "key"
    with pytest.raises(ProtocolError, match="rsu_id"):
        decode(encode(SAMPLES["Frame"]), Frame, key=keys.frame("rsu-ne"))
    decode(encode(fix), PoseFix, key="some/other/key")  # not a toptag key: not checked


def test_decode_any_reports_unknown_type():
    with pytest.raises(ProtocolError, match="unknown message type 'teleport'"):
        decode_any(b'{"version":1,"type":"teleport"}')
    with pytest.raises(ProtocolError, match="missing field 'type'"):
        decode_any(b'{"version":1}')


def test_python_construction_fills_version_and_type_but_wire_requires_them():
    m = Leave(bus_id="b", intersection_id="x1", reference_time_ns=1)
    assert m.version == PROTOCOL_VERSION and m.type == "leave"
    with pytest.raises(ValidationError, match="wrong protocol version"):
        Leave(version=2, bus_id="b", intersection_id="x1", reference_time_ns=1)


def test_messages_are_immutable_and_finite():
    fix = SAMPLES["PoseFix"]
    with pytest.raises(ValidationError):
        fix.x = 3.0  # type: ignore[misc]
    assert fix.model_copy(update={"x": 3.0}).x == 3.0
    with pytest.raises(ValidationError):
        Imu(bus_id="b", t_ns=1, gyro_z=math.nan)
    with pytest.raises(ValidationError):
        Imu(bus_id="b", t_ns=1, gyro_z=math.inf)


def test_yaw_is_wrapped_to_minus_pi_pi():
    fix = SAMPLES["PoseFix"]
    assert fix.model_copy(update={"yaw": 4.0}).yaw == 4.0  # model_copy does not validate...
    d = fix.model_dump()
    for raw, wrapped in [(4.0, 4.0 - 2 * math.pi), (-math.pi, math.pi), (math.pi, math.pi), (7.0, 7.0 - 2 * math.pi)]:
        d["yaw"] = raw
        assert PoseFix.model_validate(d).yaw == pytest.approx(wrapped)


def test_covariance_must_be_symmetric_psd():
    d = SAMPLES["FusedPose"].model_dump()
    d["covariance"] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]]
    with pytest.raises(ValidationError, match="positive semi-definite"):
        FusedPose.model_validate(d)


def test_approach_vehicle_must_be_the_bus():
    a = SAMPLES["Approach"]
    with pytest.raises(ValidationError, match="differs from bus_id"):
        Approach(bus_id="bus-99", intersection_id="x1", vehicle=a.vehicle, reference_time_ns=1)


def test_pose_fix_measurement_delta():
    fix = SAMPLES["PoseFix"]
    assert fix.measurement_delta_ns == fix.publish_time_ns - fix.capture_time_ns == 35_000_000


def test_pose_fix_carries_the_ambiguity_flag():
    """A lone tag's mirrored pose (issue 11) reaches the bus: the flag survives the wire; a fix without it
    (as v1 senders wrote them) is not ambiguous."""
    fix = SAMPLES["PoseFix"]
    assert fix.ambiguous is False and decode(encode(fix), PoseFix).ambiguous is False
    flagged = fix.model_copy(update={"ambiguous": True})
    assert decode(encode(flagged), PoseFix).ambiguous is True
    d = json.loads(encode(fix))
    d.pop("ambiguous")
    assert decode(json.dumps(d).encode(), PoseFix).ambiguous is False


def test_pose_fix_carries_the_calibration_id():
    """A fix may say which calibration of its camera made it (the bus forgets the RSU's long run when it
    changes): stated, it survives the wire and reaches the core fix; unstated, the JSON is what v1 senders
    wrote (no null field for an older receiver to refuse), and such a message decodes without it."""
    from protocol.convert import fix_from_message

    fix = SAMPLES["PoseFix"]
    assert "calibration_id" not in json.loads(encode(fix)) and decode(encode(fix), PoseFix).calibration_id is None
    stated = fix.model_copy(update={"calibration_id": "914d84e886e0"})
    back = decode(encode(stated), PoseFix)
    assert back.calibration_id == "914d84e886e0" and fix_from_message(back).calib_id == "914d84e886e0"
    assert fix_from_message(decode(encode(fix), PoseFix)).calib_id is None


def test_approach_carries_the_roof_height_sigma():
    """The code bag's optional height_sigma (issue 11) rides the Approach: declared, it survives the wire
    and reaches the Vehicle the RSU builds; undeclared, the bag's JSON is byte for byte what v1 senders
    wrote (no null field for an older receiver to refuse) and the bus gets the default bounce prior; a
    bad value is refused naming the field."""
    from toptag.vehicle import HEIGHT_SIGMA_DEFAULT, Vehicle

    a = SAMPLES["Approach"]
    assert a.vehicle.height_sigma is None and "height_sigma" not in json.loads(encode(a))["vehicle"]
    assert Vehicle(decode(encode(a), Approach).vehicle).height_sigma == HEIGHT_SIGMA_DEFAULT
    rigid = a.model_copy(update={"vehicle": a.vehicle.model_copy(update={"height_sigma": 0.002})})
    got = decode(encode(rigid), Approach)
    assert got.vehicle.height_sigma == 0.002 and Vehicle(got.vehicle).height_sigma == 0.002
    d = json.loads(encode(a))
    d["vehicle"]["height_sigma"] = -0.01
    with pytest.raises(ProtocolError, match="height_sigma"):
        decode(json.dumps(d).encode(), Approach)


# ---- keys -------------------------------------------------------------------------------------

KEY_TABLE = [
    (keys.approach("x1", "bus-17"), "toptag/v1/approach/x1/bus-17"),
    (keys.leave("x1", "bus-17"), "toptag/v1/leave/x1/bus-17"),
    (keys.pose_fix("x1", "bus-17", "rsu-sw"), "toptag/v1/fix/x1/bus-17/rsu-sw"),
    (keys.frame("rsu-sw"), "toptag/v1/frame/rsu-sw"),
    (keys.rsu_status("rsu-sw"), "toptag/v1/status/rsu/rsu-sw"),
    (keys.imu("bus-17"), "toptag/v1/imu/bus-17"),
    (keys.ground_truth("bus-17"), "toptag/v1/truth/bus-17"),
    (keys.fused_pose("bus-17"), "toptag/v1/fused/bus-17"),
    (keys.alive("x1", "bus-17"), "toptag/v1/alive/x1/bus-17"),
    (keys.sessions("x1", "bus-17"), "toptag/v1/session/x1/bus-17"),
    (keys.sessions("x1"), "toptag/v1/session/x1/*"),
    (keys.pose_fix("x1", "bus-17", rsu=keys.ANY), "toptag/v1/fix/x1/bus-17/*"),
    (keys.pose_fix(keys.ANY, keys.ANY, keys.ANY), "toptag/v1/fix/*/*/*"),
]


@pytest.mark.parametrize("built,expected", KEY_TABLE, ids=[k[1] for k in KEY_TABLE])
def test_key_table(built, expected):
    assert built == expected
    assert str(zenoh.KeyExpr(built)) == expected  # valid, canonical zenoh key expression
    assert keys.is_pattern(built) == ("*" in expected)
    if not keys.is_pattern(built):
        parsed = keys.parse(built)
        assert keys.parse(built) == parsed and parsed.kind in keys.LAYOUT


def test_wildcard_patterns_match_concrete_keys():
    pattern = zenoh.KeyExpr(keys.pose_fix("x1", keys.ANY, keys.ANY))
    assert pattern.intersects(keys.pose_fix("x1", "bus-17", "rsu-ne"))
    assert not pattern.intersects(keys.pose_fix("x2", "bus-17", "rsu-ne"))
    assert zenoh.KeyExpr(keys.EVERYTHING).includes(keys.frame("rsu-ne"))


def test_key_of_every_message():
    assert keys.key_of(SAMPLES["PoseFix"]) == "toptag/v1/fix/x1/bus-17/rsu-sw"
    assert keys.key_of(SAMPLES["Frame"]) == "toptag/v1/frame/rsu-sw"
    assert keys.key_of(SAMPLES["RsuStatus"]) == "toptag/v1/status/rsu/rsu-sw"
    assert keys.key_of(SAMPLES["ActiveSessions"]) == "toptag/v1/session/x1/bus-17"
    for name, msg in SAMPLES.items():
        k = keys.key_of(msg)
        assert not keys.is_pattern(k)
        codec.check_key(msg, k)  # the ids in the key are the message's
        assert keys.parse(k).kind == ("sessions" if name == "ActiveSessions" else msg.TYPE)


def test_parse_round_trips():
    p = keys.parse("toptag/v1/fix/x1/bus-17/rsu-sw")
    assert p.kind == "pose_fix" and p.ids == {"intersection": "x1", "bus": "bus-17", "rsu": "rsu-sw"}
    assert p["rsu"] == "rsu-sw"
    assert keys.parse(keys.rsu_status("r1")).kind == "rsu_status"
    for bad in ["toptag/v2/frame/r", "toptag/v1/frame", "toptag/v1/frame/a/b", "toptag/v1/nope/a"]:
        with pytest.raises(keys.KeyExprError):
            keys.parse(bad)


@pytest.mark.parametrize("bad", ["", "a/b", "*b", "**", "x$", "what?", "#1", "has space", "tab\t", "x" * 65])
def test_ids_are_validated(bad):
    with pytest.raises(keys.KeyExprError):
        keys.frame(bad)
    with pytest.raises(ValidationError):
        Leave(bus_id=bad, intersection_id="x1", reference_time_ns=1)


def test_only_the_wildcard_chunk_is_allowed_as_pattern():
    assert keys.frame(keys.ANY) == "toptag/v1/frame/*"
    with pytest.raises(keys.KeyExprError):
        keys.frame("**")


def test_core_fix_to_wire_and_back_keeps_every_field():
    import numpy as np

    from protocol.convert import fix_from_message, fix_to_message
    from toptag.fix import Fix

    cov = np.array([[4e-4, 1e-5, 0.0], [1e-5, 9e-4, 0.0], [0.0, 0.0, 1e-5]])
    fix = Fix(t_ns=1_700_000_000_123_456_789, x=-5.5, y=3.25, yaw=2.5, cov=cov, source="rsu-sw", seq=41,
              z=3.02, method="level", tags=(3, 7), rms_px=0.08, calib_id="914d84e886e0")
    msg = fix_to_message(fix, "bus-17", "x1", publish_time_ns=fix.t_ns + 9_000_000, processing_ns=7_000_000)
    assert (msg.capture_time_ns, msg.rsu_id, msg.frame_seq, msg.tags_used) == (fix.t_ns, "rsu-sw", 41, [3, 7])
    back = fix_from_message(decode(encode(msg), PoseFix), arrival_ns=fix.t_ns + 12_000_000)
    assert back.arrival_ns == fix.t_ns + 12_000_000
    assert back.replace(arrival_ns=None).__dict__.keys() == fix.__dict__.keys()
    for name in ("t_ns", "x", "y", "yaw", "source", "seq", "z", "method", "tags", "rms_px", "calib_id"):
        assert getattr(back, name) == getattr(fix, name), name
    assert np.array_equal(back.cov, fix.cov)
    with pytest.raises(ValueError, match="lacks method, tags, rms_px"):
        fix_to_message(Fix(t_ns=1, x=0, y=0, yaw=0, cov=cov, source="rsu-sw", seq=1, z=3.0), "bus-17", "x1", 2)
