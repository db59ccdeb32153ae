"""The codec's fast paths (covariance check in pure Python, id check in C, keys parsed once) decide
exactly as the full checks they skip, and the bytes on the wire are those of the full path."""
import numpy as np
import pytest

from protocol import codec, keys
from protocol.codec import ProtocolError
from protocol.messages import (
    FORBIDDEN_ID_CHARS,
    MAX_ID_LENGTH,
    ClockInfo,
    FusedPose,
    FusionHealth,
    Imu,
    PoseFix,
    _check_covariance,
    check_id,
)
from toptag.fix import Fix, clearly_covariance, covariance_problem

pytestmark = pytest.mark.unit


def _numpy_check(v) -> bool:
    """_check_covariance's numpy tests, as they stood before the fast path."""
    c = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(c)):
        return False
    scale = max(1.0, float(np.max(np.abs(c))))
    if np.max(np.abs(c - c.T)) > 1e-9 * scale:
        return False
    return not np.min(np.linalg.eigvalsh(c)) < -1e-9 * scale


def _matrices(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for k in range(n):
        sig = 10 ** rng.uniform(-5, 2, size=3)
        R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
        C = R @ np.diag(sig ** 2) @ R.T
        kind = k % 7
        if kind == 1:
            C = C + rng.standard_normal((3, 3)) * 1e-12 * np.abs(C).max()  # not quite symmetric
        elif kind == 2:  # asymmetric around the tolerance
            C[0, 1] += rng.uniform(-2, 2) * 1e-9 * max(1.0, np.abs(C).max())
        elif kind == 3:
            C = -C
        elif kind == 4:  # smallest eigenvalue around zero, either side
            C = C - np.eye(3) * sig.min() ** 2 * rng.uniform(0.9, 1.1)
        elif kind == 5:
            u = rng.standard_normal(3)
            C = np.outer(u, u)  # rank one: PSD, not definite
        elif kind == 6:
            C[rng.integers(3), rng.integers(3)] = rng.choice([np.inf, np.nan])
        yield C.tolist()


def test_covariance_fast_path_decides_as_numpy():
    fast = 0
    for v in _matrices(30000):
        if clearly_covariance(v):
            fast += 1
            assert _numpy_check(v), v
        try:
            _check_covariance(v)
            ok = True
        except ValueError:
            ok = False
        assert ok == _numpy_check(v), v
    assert fast > 5000  # it does take the fast path for ordinary covariances


def test_fix_problem_fast_path_decides_as_numpy():
    fast = 0
    for v in _matrices(30000, seed=1):
        fast += clearly_covariance(v)
        assert Fix(t_ns=1, x=0.0, y=0.0, yaw=0.0, cov=v).problem() == covariance_problem(np.asarray(v)), v
    assert fast > 5000


def test_id_fast_path_decides_as_the_full_check():
    ids = ["bus-42", "rsu-sw", "x1", "é", "ok_1.2", "", "x" * MAX_ID_LENGTH, "x" * (MAX_ID_LENGTH + 1),
           "a b", "a\tb", "a\x1cb", "a\u00a0b", "a\u2028b", "a\x7fb", "\u200b"]
    ids += [f"a{c}b" for c in FORBIDDEN_ID_CHARS]
    ids += [chr(c) for c in range(0, 0x3000, 7)]
    for value in ids:
        printable = all(c.isprintable() and not c.isspace() for c in value)
        expect = 0 < len(value) <= MAX_ID_LENGTH and printable and not set(value) & set(FORBIDDEN_ID_CHARS)
        if expect:
            assert check_id(value) == value
        else:
            with pytest.raises(ValueError):
                check_id(value)


def test_key_check_is_the_same_on_every_call():
    fix = PoseFix(bus_id="bus-42", rsu_id="rsu-sw", intersection_id="x1", capture_time_ns=1, publish_time_ns=2,
                  x=1.0, y=2.0, z=3.0, yaw=0.1, covariance=[[1e-3, 0, 0], [0, 1e-3, 0], [0, 0, 1e-5]], method="h_opt",
                  tags_used=[12], reprojection_rms_px=0.4, frame_seq=1)
    for _ in range(3):
        codec.check_key(fix, keys.pose_fix("x1", "bus-42", "rsu-sw"))
        codec.check_key(fix, "not/a/toptag/key")
        with pytest.raises(ProtocolError, match="rsu_id 'rsu-sw' does not match"):
            codec.check_key(fix, keys.pose_fix("x1", "bus-42", "rsu-ne"))
        with pytest.raises(ProtocolError, match="bus_id"):
            codec.decode(codec.encode(fix), PoseFix, key=keys.pose_fix("x1", "bus-17", "rsu-sw"))


def test_wire_bytes_unchanged():
    """The bytes of these messages, as main (17ae43a) encoded them before the fast paths, and a
    decode-encode round trip gives them back."""
    cov = [[1.2224372351546352e-05, 4.5469830378466607e-07, -5.872563300976176e-07],
           [4.54698303784666e-07, 5.0580676481678915e-05, -4.155987240081278e-09],
           [-5.872563300976176e-07, -4.155987240081278e-09, 1.2903115804880092e-06]]
    fused = FusedPose(bus_id="bus-42", t_ns=1700000000000000000, x=-12.5, y=3.25, yaw=0.5, speed=4.0,
                      yaw_rate=0.01, covariance=cov, health=FusionHealth(status="ok", accepted_fixes=7))
    fix = PoseFix(bus_id="bus-42", rsu_id="rsu-sw", intersection_id="x1", capture_time_ns=5, publish_time_ns=6,
                  x=1.0, y=2.0, z=3.0, yaw=-0.25, covariance=cov, method="h_opt", tags_used=[12, 13], reprojection_rms_px=0.4, frame_seq=2,
                  clock=ClockInfo(source="sim", sync_uncertainty_ns=1000000), calibration_covariance=cov)
    imu = Imu(bus_id="bus-42", t_ns=7, gyro_z=0.1, accel_x=-0.5, wheel_speed=4.0, seq=3)
    expected = {
        FusedPose: b'{"version":1,"type":"fused_pose","bus_id":"bus-42","t_ns":1700000000000000000,"x":-12.5,'
                   b'"y":3.25,"yaw":0.5,"speed":4.0,"yaw_rate":0.01,"covariance":[[0.000012224372351546352,'
                   b'4.5469830378466607e-7,-5.872563300976176e-7],[4.54698303784666e-7,0.000050580676481678915,'
                   b'-4.155987240081278e-9],[-5.872563300976176e-7,-4.155987240081278e-9,1.2903115804880092e-6]],'
                   b'"health":{"status":"ok","accepted_fixes":7,"rejected_fixes":0,"since_last_fix_ns":null,'
                   b'"last_fix_delay_ns":null,"last_fix_rsu":null,"too_old_fixes":0,"future_fixes":0,'
                   b'"flagged_rsu_fixes":0,"unknown_clock_fixes":0,"other_fixes":0,"flagged_rsus":[]}}',
    }
    for msg in (fused, fix, imu):
        wire = codec.encode(msg)
        if type(msg) in expected:
            assert wire == expected[type(msg)]
        back = codec.decode(wire, type(msg), key=keys.key_of(msg))
        assert back == msg and codec.encode(back) == wire


def _states(n: int, seed: int = 1):
    """FusedStates as a filter makes them, and the odd ones: no fix yet (inf, nan), a yaw to wrap, numpy and int
    numbers, flagged RSUs, counts and ids the wire refuses, covariances the fast test cannot decide or refuses."""
    from toptag.fusion.state import FusedState, Health
    rng = np.random.default_rng(seed)
    mats = list(_matrices(n, seed))
    for k in range(n):
        cov = np.asarray(mats[k])
        since, delay = (float(rng.uniform(0, 2)), float(rng.uniform(0, 0.3))) if k % 5 else (np.inf, np.nan)
        h = Health(str(rng.choice(["acquiring", "ok", "degraded", "lost"])), since, delay,
                   None if k % 7 == 0 else ("rsu-bad/1" if k % 53 == 0 else f"rsu-{k % 4}"), 0.1,
                   int(rng.integers(0, 50)), 0, int(rng.integers(-1 if k % 41 == 0 else 0, 5000)), 0.02, 0.01, 0.0,
                   too_old=int(rng.integers(0, 3)), future=int(rng.integers(0, 3)), from_flagged_rsu=k % 3,
                   unknown_clock=int(rng.integers(0, 100)), other=k % 11,
                   flagged_rsus=("rsu-1",) if k % 13 == 0 else ())
        yaw = float(rng.uniform(-4, 4)) if k % 3 else np.float64(rng.uniform(-3, 3))
        x = int(rng.integers(-100, 100)) if k % 17 == 0 else float(rng.normal(0, 50))
        y = np.float64(rng.normal(0, 50)) if k % 19 == 0 else (np.nan if k % 97 == 0 else float(rng.normal(0, 50)))
        yield FusedState(1_700_000_000_000_000_000 + k * 20_000_000, x, y, yaw, float(rng.uniform(0, 15)),
                         float(rng.normal(0, 0.1)), 0.0, 1.0, cov, np.eye(7), h)


def test_fused_pose_payload_is_the_messages_bytes():
    """The bus agent's FusedPose, serialised from a dict, is byte for byte what building and encoding the
    messages gives; where they refuse a state, so does it, with their error."""
    from protocol.convert import fused_pose_payload, fused_to_message
    refused = 0
    for st in _states(3000):
        try:
            expected = codec.encode(fused_to_message(st, "bus-42"))
        except ValueError as e:
            refused += 1
            with pytest.raises(type(e)):
                fused_pose_payload(st, "bus-42")
            continue
        assert fused_pose_payload(st, "bus-42") == expected
    assert 0 < refused < 2000  # the planted bad ones: covariances (3 kinds of 7), counts, ids, a nan
    with pytest.raises(ValueError, match="forbidden character"):
        fused_pose_payload(next(_states(1)), "bus/42")
