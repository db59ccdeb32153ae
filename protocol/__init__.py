"""toptag's wire contract: messages (pydantic, versioned), key expressions, and the codec.

    from protocol import keys, codec, PoseFix
    payload = codec.encode(fix)
    fix = codec.decode(payload, PoseFix, key=sample_key)
"""
from protocol import codec, keys
from protocol.codec import ProtocolError, decode, decode_any, encode
from protocol.messages import (
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    ActiveSessions,
    Approach,
    ClockInfo,
    CoarsePosition,
    Frame,
    FusedPose,
    FusionHealth,
    GnssFix,
    GroundTruth,
    Imu,
    ImuBatch,
    Leave,
    Message,
    PoseFix,
    RsuDiagnosis,
    RsuStatus,
    TagDetections,
    check_id,
)

__all__ = [
    "MESSAGE_TYPES", "PROTOCOL_VERSION", "ActiveSessions", "Approach", "ClockInfo", "CoarsePosition", "Frame", "FusedPose",
    "FusionHealth", "GnssFix", "GroundTruth", "Imu", "ImuBatch", "Leave", "Message", "PoseFix", "ProtocolError",
    "RsuDiagnosis", "RsuStatus", "TagDetections", "check_id", "codec", "decode", "decode_any", "encode", "keys",
]
