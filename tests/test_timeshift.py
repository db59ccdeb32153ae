"""protocol.timeshift: a replay moves every timestamp of every message type by one offset, and
nothing else (durations, ids, poses, image bytes stay)."""
import pytest
from conftest import make_samples

from protocol import decode_any, encode
from protocol.messages import Approach, CoarsePosition
from protocol.timeshift import shift_times

pytestmark = pytest.mark.unit

TIMESTAMPS = {  # every timestamp field of every message type (nested ones by path)
    "Approach": {"reference_time_ns", "position.t_ns"}, "Leave": {"reference_time_ns"},
    "ActiveSessions": {"reference_time_ns", "sessions.0.reference_time_ns", "sessions.0.position.t_ns"},
    "PoseFix": {"capture_time_ns", "publish_time_ns"},
    "RsuStatus": {"reference_time_ns", "started_ns", "diagnoses.0.reference_time_ns", "diagnoses.0.flagged_since_ns"},
    "RsuDiagnosis": {"reference_time_ns", "flagged_since_ns"},
    "TagDetections": {"capture_time_ns"}, "Frame": {"capture_time_ns"}, "Imu": {"t_ns"}, "GroundTruth": {"t_ns"},
    "GnssFix": {"t_ns"}, "FusedPose": {"t_ns"},
}


def _flat(obj, prefix=""):
    out = {}
    for k, v in (obj.items() if isinstance(obj, dict) else enumerate(obj)):
        path = f"{prefix}{k}"
        if isinstance(v, (dict, list)):
            out.update(_flat(v, path + "."))
        else:
            out[path] = v
    return out


def _with_position(samples):
    a = samples["Approach"].model_copy(update={"position": CoarsePosition(t_ns=5_000, x=1.0, y=2.0, sigma_m=2.0)})
    samples["Approach"] = a
    samples["ActiveSessions"] = samples["ActiveSessions"].model_copy(update={"sessions": [a]})
    return samples


@pytest.mark.parametrize("name", sorted(TIMESTAMPS))
def test_every_timestamp_moves_by_the_offset_and_nothing_else(name):
    msg = _with_position(make_samples())[name]
    moved = shift_times(msg, 1_000_000_007)
    before, after = _flat(msg.model_dump()), _flat(moved.model_dump())
    changed = {k for k in before if before[k] != after[k]}
    assert changed == TIMESTAMPS[name]
    assert all(after[k] - before[k] == 1_000_000_007 for k in changed)
    assert decode_any(encode(moved)) == moved  # still a valid message
    assert getattr(moved, "image", None) == getattr(msg, "image", None)


def test_a_shift_before_the_epoch_is_refused():
    a = make_samples()["Approach"]
    with pytest.raises(ValueError, match="before the epoch"):
        shift_times(a, -a.reference_time_ns - 1)
    assert isinstance(shift_times(a, 0), Approach)
