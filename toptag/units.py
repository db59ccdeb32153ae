"""Units and time, in one place.

Inside toptag everything is SI (metres, radians, seconds, m/s). Timestamps and durations that cross a
module boundary are integer nanoseconds (``*_ns``; timestamps since the Unix epoch, SPEC.md), so that
two stamps of one frame compare exactly. These are the only conversions between the two.
"""
from __future__ import annotations

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000


def s_from_ns(ns):
    """Nanoseconds (int, or a numpy array) to seconds (float)."""
    return ns * 1e-9


def ms_from_ns(ns):
    """Nanoseconds (int, or a numpy array) to milliseconds (float)."""
    return ns * 1e-6


def ns_from_s(s: float) -> int:
    """Seconds to integer nanoseconds (rounded to the nearest)."""
    return int(round(s * NS_PER_S))


def ns_from_ms(ms: float) -> int:
    """Milliseconds to integer nanoseconds (rounded to the nearest)."""
    return int(round(ms * NS_PER_MS))


def mps_from_kmh(kmh: float) -> float:
    return kmh / 3.6


def kmh_from_mps(mps: float) -> float:
    return mps * 3.6
