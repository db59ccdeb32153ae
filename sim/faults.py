"""Faults the simulator injects per RSU: a clock offset, a capture latency, an extrinsic drift.

One model for the scenario file (`Scenario.faults`, keyed by RSU id), the live simulator
(sim.world / sim.live) and the fusion study (`toptag eval fusion --clock-offset-ms RSU=MS[,...]
--capture-latency-ms RSU=MS[,...] --drift-deg RSU=DEG[@T[/RAMP]][,...]`).

- clock_offset_ms: the RSU's clock reads this much late (positive) or early: every capture stamp is
  exposure + offset. Such an RSU's clock is undisciplined: it says so (its frames' ClockInfo is
  "system" with no bound).
- capture_latency_ms: the frame reaches the RSU this long after its exposure and is stamped on
  arrival (an IP camera's pipeline); the RSU's clock itself is right.
Both shift the stamp (stamp = exposure + latency + offset: the RSU's *time offset* that the bus
estimates); the latency also delays the frame.
- drift: the camera turns by `yaw_deg` about the vertical through its centre (counter-clockwise seen
  from above: the wind, the sun on a pole), at once at `at_s` (a step) or linearly over `ramp_s`
  seconds from `at_s`; `pitch_deg` tilts it down the same way. The RSU keeps its surveyed camera
  file, so its fixes turn the other way about its pole. Times are seconds after the scenario (or
  study run) start.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.camera import Camera
from toptag.inputs import InputError
from toptag.units import ns_from_ms


class Drift(BaseModel):
    """An extrinsic drift of one camera: a step (ramp_s = 0) or a ramp."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    yaw_deg: float = Field(default=0.0, ge=-10, le=10, description="turn about the vertical, deg (CCW from above)")
    pitch_deg: float = Field(default=0.0, ge=-10, le=10, description="extra tilt down, deg")
    at_s: float = Field(default=0.0, ge=0, description="start, s after the scenario start")
    ramp_s: float = Field(default=0.0, ge=0, description="0: a step; else reaches the full turn after ramp_s")

    def fraction(self, t_s: float) -> float:
        """How much of the drift has happened t_s after the start."""
        if t_s < self.at_s:
            return 0.0
        if self.ramp_s <= 0:
            return 1.0
        return min(1.0, (t_s - self.at_s) / self.ramp_s)

    def angles(self, t_s: float) -> tuple[float, float]:
        """(yaw, pitch) in rad at t_s."""
        f = self.fraction(t_s)
        return math.radians(self.yaw_deg) * f, math.radians(self.pitch_deg) * f


class RsuFault(BaseModel):
    """What is wrong with one RSU (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    clock_offset_ms: float = Field(default=0.0, ge=-400, le=400)
    capture_latency_ms: float = Field(default=0.0, ge=0, le=400)
    drift: Drift | None = None

    @property
    def time_offset_ns(self) -> int:
        """Stamp minus exposure: what the bus should estimate as this RSU's time offset."""
        return ns_from_ms(self.clock_offset_ms + self.capture_latency_ms)

    @property
    def clock_disciplined(self) -> bool:
        return self.clock_offset_ms == 0.0


def turned(camera: Camera, yaw: float, pitch: float = 0.0) -> Camera:
    """The camera turned by `yaw` about the world vertical through its centre and tilted `pitch` further
    down about its own horizontal axis (same intrinsics, same centre)."""
    if yaw == 0.0 and pitch == 0.0:
        return camera
    c = camera.center
    cz, sz = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])  # world rotation about +z
    cp, sp = math.cos(pitch), math.sin(pitch)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])  # camera x axis: a downward tilt
    R = Rx @ camera.R @ Rz.T
    return camera.with_extrinsics(R, -R @ c)


def seen_pose(surveyed: Camera, actual: Camera, x: float, y: float, yaw: float, z: float,
              half: float = 1.0) -> tuple[float, float, float]:
    """The pose (x, y, yaw) an RSU that believes `surveyed` reports for a roof at (x, y, yaw, height z)
    that its `actual` camera sees: points of the roof projected by the actual camera and back-projected
    by the surveyed one onto the roof plane, and a rigid 2-D fit to them. `half`: half-size of the
    square of roof points used (m)."""
    if actual is surveyed:
        return x, y, yaw
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[half, half], [half, -half], [-half, -half], [-half, half]])
    pts = np.column_stack([x + local[:, 0] * c - local[:, 1] * s, y + local[:, 0] * s + local[:, 1] * c,
                           np.full(4, z)])
    px = actual.project(pts, distort=False)
    back = surveyed.backproject_to_plane(px, z, distorted=False)[:, :2]
    a, b = pts[:, :2] - pts[:, :2].mean(0), back - back.mean(0)
    turn = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    cx, cy = back.mean(0)
    return float(cx), float(cy), float(math.remainder(yaw + turn, 2 * math.pi))


def _per_rsu(text: str, option: str, form: str, value):
    """'RSU=VALUE,RSU=VALUE' -> {RSU: value(VALUE)}; InputError naming the option and the form."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        rsu, eq, rest = part.partition("=")
        try:
            if not eq or not rsu.strip():
                raise ValueError
            out[rsu.strip()] = value(rest)
        except ValueError:
            raise InputError(f"{option}: expected {form}, got {part!r}") from None
    return out


def parse_ms(text: str, option: str) -> dict[str, float]:
    """'rsu-se=30,rsu-ne=-12.5' -> {'rsu-se': 30.0, 'rsu-ne': -12.5}."""
    return _per_rsu(text, option, "RSU=MS[,RSU=MS]", float)


def _drift(text: str) -> Drift:
    deg, _, when = text.partition("@")
    at, _, ramp = when.partition("/")
    return Drift(yaw_deg=float(deg), at_s=float(at or 0.0), ramp_s=float(ramp or 0.0))


def parse_drift(text: str, option: str = "--drift-deg") -> dict[str, Drift]:
    """'rsu-se=0.2@30,rsu-ne=0.5@10/60' -> a step of 0.2 deg at 30 s on rsu-se, a ramp of 0.5 deg over
    60 s from 10 s on rsu-ne (yaw)."""
    return _per_rsu(text, option, "RSU=DEG[@T[/RAMP]][,...]", _drift)


def faults_from_options(clock_offset_ms: str | None = None, capture_latency_ms: str | None = None,
                        drift_deg: str | None = None) -> dict[str, RsuFault]:
    """The per-RSU faults of the command-line options (`toptag eval fusion`)."""
    offsets = parse_ms(clock_offset_ms or "", "--clock-offset-ms")
    latencies = parse_ms(capture_latency_ms or "", "--capture-latency-ms")
    drifts = parse_drift(drift_deg or "")
    out = {}
    for rsu in sorted(set(offsets) | set(latencies) | set(drifts)):
        try:
            out[rsu] = RsuFault(clock_offset_ms=offsets.get(rsu, 0.0), capture_latency_ms=latencies.get(rsu, 0.0),
                                drift=drifts.get(rsu))
        except ValueError as e:
            raise InputError(f"fault of {rsu}: {str(e).splitlines()[-1].strip()}") from None
    return out


def describe(faults: dict[str, RsuFault]) -> str:
    parts = []
    for rsu, f in sorted(faults.items()):
        what = []
        if f.clock_offset_ms:
            what.append(f"clock {f.clock_offset_ms:+g} ms")
        if f.capture_latency_ms:
            what.append(f"latency {f.capture_latency_ms:g} ms")
        if f.drift is not None:
            d = f.drift
            turn = f"{d.yaw_deg:+g} deg yaw" + (f" {d.pitch_deg:+g} deg pitch" if d.pitch_deg else "")
            what.append(f"{turn} {'at' if not d.ramp_s else 'from'} {d.at_s:g} s"
                        + (f" over {d.ramp_s:g} s" if d.ramp_s else ""))
        parts.append(f"{rsu}: {', '.join(what) or 'none'}")
    return "; ".join(parts) or "none"



__all__ = ["Drift", "RsuFault", "describe", "faults_from_options", "parse_drift", "parse_ms", "seen_pose", "turned"]
