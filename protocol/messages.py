"""The toptag wire messages (protocol version 1).

Every message is a frozen pydantic model carrying ``version`` (the protocol version) and ``type`` (its
wire name). Units follow SPEC.md: metres, radians, timestamps and durations in integer nanoseconds
(``*_ns``; timestamps since the Unix epoch). Yaw is wrapped to (-pi, pi] on the way in.

Where a V2X perception message (ETSI CPM, SAE J3224 SDSM) has an equivalent, the docstrings name it:
``rsu_id`` is the sender's station id / sourceID, ``bus_id`` the perceived object id, ``capture_time_ns``
the measurement time, ``publish_time_ns`` the generation (reference) time, their difference the
measurement delta time, and ``covariance`` replaces the CPM confidence fields.

Build messages with keyword arguments; ``version`` and ``type`` fill themselves. Encode and decode them
only through :mod:`protocol.codec`.
"""
from __future__ import annotations

import math
import re
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from toptag.fix import clearly_covariance
from toptag.geometry import wrap_angle
from toptag.vehicle import VehicleFile

PROTOCOL_VERSION = 1

# Characters an id may not contain: they are key-expression syntax in Zenoh ('/' separates chunks,
# '*' and '$' are wildcards, '?' and '#' are reserved for selectors).
FORBIDDEN_ID_CHARS = "/*$?#"
MAX_ID_LENGTH = 64


# Whitespace (re's \s is str.isspace) or a forbidden character: the fast path's test of check_id.
_ID_BAD = re.compile(r"[\s" + re.escape(FORBIDDEN_ID_CHARS) + "]")


def check_id(value: str) -> str:
    """Return ``value`` if it can be one chunk of a key expression, else raise ValueError saying why."""
    # Fast path (every id of every message decoded or built): the same tests as below, in C.
    if type(value) is str and 0 < len(value) <= MAX_ID_LENGTH and value.isprintable() and not _ID_BAD.search(value):
        return value
    if not isinstance(value, str):
        raise ValueError(f"id must be a string, got {type(value).__name__}")
    if not value:
        raise ValueError("id must not be empty")
    if len(value) > MAX_ID_LENGTH:
        raise ValueError(f"id longer than {MAX_ID_LENGTH} characters")
    bad = sorted({c for c in value if c in FORBIDDEN_ID_CHARS})
    if bad:
        raise ValueError(f"id {value!r} contains forbidden character(s) {' '.join(bad)}")
    if any(c.isspace() or not c.isprintable() for c in value):
        raise ValueError(f"id {value!r} contains whitespace or control characters")
    return value


Id = Annotated[str, AfterValidator(check_id)]


class _EpochTime:
    """Marks a field as a timestamp (ns since the epoch), as opposed to a duration: a replay that
    shifts a recording to the present moves exactly these fields (protocol.timeshift)."""

    def __repr__(self) -> str:
        return "EPOCH_TIME"


EPOCH_TIME = _EpochTime()
TimeNs = Annotated[int, Field(ge=0, description="integer nanoseconds since the Unix epoch"), EPOCH_TIME]
DurationNs = Annotated[int, Field(ge=0, description="integer nanoseconds")]
Count = Annotated[int, Field(ge=0)]


def _check_covariance(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 3 or any(len(row) != 3 for row in v):
        raise ValueError("must be a 3x3 matrix")
    if clearly_covariance(v):
        return v
    c = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(c)):
        raise ValueError("must be finite")
    scale = max(1.0, float(np.max(np.abs(c))))
    if np.max(np.abs(c - c.T)) > 1e-9 * scale:
        raise ValueError("must be symmetric")
    if np.min(np.linalg.eigvalsh(c)) < -1e-9 * scale:
        raise ValueError("must be positive semi-definite")
    return v


Yaw = Annotated[float, AfterValidator(wrap_angle), Field(description="rad, wrapped to (-pi, pi]")]
Covariance3 = Annotated[list[list[float]], AfterValidator(_check_covariance),
                        Field(description="3x3 covariance of (x [m], y [m], yaw [rad]), row-major")]


class Message(BaseModel):
    """Base of every wire message: a version and a type tag, strict fields, finite numbers."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    TYPE: ClassVar[str] = ""
    version: int = Field(default=PROTOCOL_VERSION, strict=True)

    @model_validator(mode="before")
    @classmethod
    def _wire_header(cls, data, info: ValidationInfo):
        # On the wire (codec passes context {"wire": True}) version and type must be present;
        # in Python they default.
        if info.context and info.context.get("wire") and isinstance(data, dict):
            for f in ("version", "type"):
                if f not in data:
                    raise ValueError(f"missing field '{f}'")
        return data

    @field_validator("version")
    @classmethod
    def _version(cls, v: int) -> int:
        if v != PROTOCOL_VERSION:
            raise ValueError(f"wrong protocol version {v} (this build speaks {PROTOCOL_VERSION})")
        return v


# ---- sessions ---------------------------------------------------------------------------------

ClockSource = Literal["system", "ntp", "ptp", "gnss", "sim"]


class ClockInfo(BaseModel):
    """How the sender's clock is disciplined, so the receiver can judge whether timestamps compare.
    Filled from the host by toptag.hostclock (chrony or ptp4l where they run; otherwise "system" with
    no bound); "sim" is the simulator's own clock. A clock without a bound is an unknown clock."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    source: ClockSource = "system"
    sync_uncertainty_ns: DurationNs | None = Field(
        default=None, description="bound on |this clock - reference|, if known")


class CoarsePosition(BaseModel):
    """Where the bus thinks it is, roughly (GNSS or its fused pose): lets an RSU skip searching while
    the bus cannot be in its view yet."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    t_ns: TimeNs
    x: float
    y: float
    sigma_m: float = Field(gt=0)
    source: Literal["gnss", "fused"] = "gnss"
    # Optional (older peers send none): the bus's velocity at t_ns with the sigma of each component (its
    # filter's), or, without a velocity, its odometry's speed; either lets an RSU predict the position to
    # a frame's time instead of widening it by the top speed.
    vx: float | None = None
    vy: float | None = None
    velocity_sigma_mps: float | None = Field(default=None, ge=0)
    speed_mps: float | None = Field(default=None, ge=0)
    yaw: float | None = None  # heading (rad), with its sigma: a fused pose's; lets an RSU crop for the tags
    yaw_sigma_rad: float | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _velocity_whole(self) -> CoarsePosition:
        if (self.vx is None) != (self.vy is None) or (self.vx is not None and self.velocity_sigma_mps is None):
            raise ValueError("vx, vy and velocity_sigma_mps come together")
        if (self.yaw is None) != (self.yaw_sigma_rad is None):
            raise ValueError("yaw and yaw_sigma_rad come together")
        return self


class Approach(Message):
    """A bus announces that it approaches an intersection, with its code bag (the vehicle file).

    Published on keys.approach(intersection_id, bus_id); may be repeated (seq increments)."""

    TYPE: ClassVar[str] = "approach"
    type: Literal["approach"] = "approach"
    bus_id: Id
    intersection_id: Id
    vehicle: VehicleFile
    reference_time_ns: TimeNs = Field(description="bus clock when the message was generated")
    clock: ClockInfo = ClockInfo()
    seq: Count = 0
    position: CoarsePosition | None = None

    @model_validator(mode="after")
    def _bus_matches_vehicle(self) -> Approach:
        if self.vehicle.id != self.bus_id:
            raise ValueError(f"vehicle.id {self.vehicle.id!r} differs from bus_id {self.bus_id!r}")
        return self


class Leave(Message):
    """A bus has left the intersection: RSUs stop working for it. On keys.leave(intersection, bus)."""

    TYPE: ClassVar[str] = "leave"
    type: Literal["leave"] = "leave"
    bus_id: Id
    intersection_id: Id
    reference_time_ns: TimeNs
    reason: str | None = Field(default=None, max_length=200)


class ActiveSessions(Message):
    """Reply to a query on keys.sessions(intersection, ...): the approaches currently active there.

    A bus answers for itself (one entry); an aggregator may answer for many. A querier merges replies."""

    TYPE: ClassVar[str] = "active_sessions"
    type: Literal["active_sessions"] = "active_sessions"
    intersection_id: Id
    responder_id: Id
    reference_time_ns: TimeNs
    sessions: list[Approach] = Field(default_factory=list)

    @model_validator(mode="after")
    def _same_intersection(self) -> ActiveSessions:
        for a in self.sessions:
            if a.intersection_id != self.intersection_id:
                raise ValueError(f"sessions: approach of {a.bus_id!r} is for intersection "
                                 f"{a.intersection_id!r}, not {self.intersection_id!r}")
        return self


# ---- RSU -> bus -------------------------------------------------------------------------------

class PoseFix(Message):
    """One RSU's estimate of one bus's pose in the world frame at the frame's capture time.

    CPM/SDSM mapping: rsu_id = station id / sourceID, bus_id = object id, capture_time_ns = measurement
    time, publish_time_ns = generation (reference) time, measurement_delta_ns = their difference."""

    TYPE: ClassVar[str] = "pose_fix"
    type: Literal["pose_fix"] = "pose_fix"
    bus_id: Id
    rsu_id: Id
    intersection_id: Id
    capture_time_ns: TimeNs = Field(description="RSU clock at frame exposure: the time the pose holds")
    publish_time_ns: TimeNs = Field(description="RSU clock when the fix was sent")
    x: float
    y: float
    z: float = Field(description="tag plane (roof) height, m")
    yaw: Yaw
    covariance: Covariance3
    method: str = Field(min_length=1, max_length=32, description="solver, e.g. 'bas', 'h_opt', 's_opt'")
    tags_used: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    reprojection_rms_px: float = Field(ge=0)
    frame_seq: Count
    processing_ns: DurationNs | None = Field(default=None, description="RSU time spent detecting and solving "
                                                                        "this frame (part of the latency)")
    ambiguous: bool = Field(default=False, description="one tag whose mirrored pose fits as well: the covariance "
                                                       "covers both poses (added in v1, default false)")
    clock: ClockInfo | None = Field(default=None, description="the clock that stamped capture_time_ns "
                                                              "(None: not said, an unknown clock)")
    calibration_covariance: Covariance3 | None = Field(
        default=None, description="the share of covariance that the camera's calibration adds: common to every fix "
                                  "of this camera, a constant bias (added in v1; None: none stated)")
    calibration_id: str | None = Field(
        default=None, min_length=1, max_length=64, exclude_if=lambda v: v is None,
        description="which calibration of the camera made this fix (e.g. a digest of its camera file): a bus that "
                    "sees it change forgets what it learnt of this RSU's long-run disagreement with the others "
                    "(added in v1; None: not said, and not written, so a fix without it is what v1 senders wrote)")

    @property
    def measurement_delta_ns(self) -> int:
        """Processing delay at the RSU (publish - capture), the CPM measurementDeltaTime analogue."""
        return self.publish_time_ns - self.capture_time_ns

    def covariance_matrix(self) -> np.ndarray:
        return np.asarray(self.covariance, dtype=float)


class RsuDiagnosis(Message):
    """One bus's assessment of one RSU, on keys.rsu_diagnosis(intersection, rsu, bus), about once a second
    while the bus hears from it (toptag.fusion.trust.RsuAssessment): the RSU's time offset as the bus
    estimates it (capture stamp minus exposure, in the bus's time; clock offset plus unmodelled capture
    latency), whether the bus flags its camera for drift, and by how much its fixes disagree with the
    other RSUs' (through the fused track). The RSU shows it in its RsuStatus; `advice` says what to do."""

    TYPE: ClassVar[str] = "rsu_diagnosis"
    type: Literal["rsu_diagnosis"] = "rsu_diagnosis"
    bus_id: Id
    rsu_id: Id
    intersection_id: Id
    reference_time_ns: TimeNs
    time_offset_ns: int | None = Field(default=None, description="estimated time offset (signed, ns)")
    time_offset_sigma_ns: DurationNs | None = None
    clock_known: bool = Field(default=False, description="the RSU's fixes said how its clock is disciplined")
    drift_flagged: bool = False
    flagged_since_ns: TimeNs | None = None
    disagreement_m: float = Field(default=0.0, ge=0, description="horizontal disagreement of its fixes with the "
                                                                 "other RSUs' (through the fused track), m")
    disagreement_yaw_rad: float = Field(default=0.0, description="yaw disagreement: its fixes minus the others'")
    disagreement_statistic: float = Field(default=0.0, ge=0, description="chi-square (3 dof) of the disagreement")
    fixes_accepted: Count = 0
    fixes_gated: Count = 0
    fixes_refused: Count = Field(default=0, description="refused because the RSU is flagged")
    fixes_other: Count = 0
    policy: Literal["downweight", "refuse"] = "downweight"
    advice: str | None = Field(default=None, max_length=400)


class RsuStatus(Message):
    """RSU heartbeat on keys.rsu_status(rsu_id). Counters are cumulative since ``started_ns``."""

    TYPE: ClassVar[str] = "rsu_status"
    type: Literal["rsu_status"] = "rsu_status"
    rsu_id: Id
    intersection_id: Id
    reference_time_ns: TimeNs
    started_ns: TimeNs
    active_buses: list[Id] = Field(default_factory=list)
    frames_received: Count = 0
    frames_processed: Count = 0
    frames_skipped: Count = Field(default=0, description="frames overwritten unprocessed because the RSU was busy")
    frames_missing: Count = Field(default=0, description="frames that never reached the RSU: gaps in the camera's "
                                                         "frame numbers (not sent, or lost; added in v1)")
    frames_idle: Count = Field(default=0, description="frames dropped undecoded because no bus was in session")
    frames_with_fix: Count = Field(default=0, description="frames that gave at least one PoseFix")
    fixes_published: Count = 0
    active_s: float = Field(default=0.0, ge=0, description="seconds with at least one bus in session")
    messages_rejected: Count = 0
    detection_ns_mean: DurationNs | None = None
    detection_ns_max: DurationNs | None = None
    clock: ClockInfo = ClockInfo()
    # What the buses think of this RSU (their RsuDiagnosis of the last seconds): time offset, drift flag.
    diagnoses: list[RsuDiagnosis] = Field(default_factory=list)
    drift_flagged: bool = Field(default=False, description="a bus flags this camera for drift: run toptag calibrate check")
    # The camera source (toptag.sources); absent from senders that predate them, None for Zenoh frames.
    source: str | None = Field(default=None, max_length=300, description="the camera source, e.g. 'stream rtsp://…'")
    source_connected: bool | None = None
    source_fps: float | None = Field(default=None, ge=0, description="frames read from the source per second")
    source_reconnects: Count = Field(default=0, description="times the source was reopened after a loss")
    source_last_error: str | None = Field(default=None, max_length=500, description="the source's last error, one line")


class DetectedTag(BaseModel):
    """One tag of an announced bus as an RSU detected it in one frame."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    bus_id: Id
    tag_id: int = Field(ge=0)
    corners: list[tuple[float, float]] = Field(
        min_length=4, max_length=4,
        description="observed pixels (x right, y down; OpenCV's pixel-centre convention, lens distortion "
                    "not removed), in the detector's corner order")
    used: bool = Field(default=True, description="the pose solver used this tag (False: screened out)")


class TagDetections(Message):
    """What an RSU found in one processed frame, on keys.detections(rsu_id): the tags of the announced
    buses, with their corners in the frame's pixels, so that an operator's view can draw them over the
    image. Sent for every frame processed while a bus is in session (an empty list: nothing found)."""

    TYPE: ClassVar[str] = "tag_detections"
    type: Literal["tag_detections"] = "tag_detections"
    rsu_id: Id
    capture_time_ns: TimeNs
    frame_seq: Count
    width: int = Field(gt=0, description="image size the corners refer to")
    height: int = Field(gt=0)
    tags: list[DetectedTag] = Field(default_factory=list)
    modes: dict[Id, str] = Field(default_factory=dict, description="per bus in session: the pipeline's mode "
                                                                    "(tracked, acquired, searching, ...)")
    processing_ns: DurationNs | None = None


# ---- camera -----------------------------------------------------------------------------------

FrameEncoding = Literal["jpeg", "png", "gray8", "bgr8", "rgb8"]
RAW_CHANNELS = {"gray8": 1, "bgr8": 3, "rgb8": 3}


class Frame(Message):
    """A camera image on keys.frame(rsu_id). On the wire: binary prefix + JSON header + raw image bytes
    (see protocol.codec); ``image`` never goes through JSON."""

    TYPE: ClassVar[str] = "frame"
    type: Literal["frame"] = "frame"
    rsu_id: Id
    capture_time_ns: TimeNs
    seq: Count
    encoding: FrameEncoding
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    image: bytes = Field(exclude=True, repr=False)
    clock: ClockInfo | None = Field(default=None, description="the clock that stamped capture_time_ns, when "
                                                              "the sender knows it (the simulator does)")

    @model_validator(mode="after")
    def _raw_size(self) -> Frame:
        ch = RAW_CHANNELS.get(self.encoding)
        if ch is not None and len(self.image) != self.width * self.height * ch:
            raise ValueError(f"image: {self.encoding} {self.width}x{self.height} needs "
                             f"{self.width * self.height * ch} bytes, got {len(self.image)}")
        if not self.image:
            raise ValueError("image: empty")
        return self


# ---- bus sensors, truth, fusion ---------------------------------------------------------------

class Imu(Message):
    """One IMU/odometry sample of a bus (vehicle frame: x forward, y left, z up) on keys.imu(bus_id)."""

    TYPE: ClassVar[str] = "imu"
    type: Literal["imu"] = "imu"
    bus_id: Id
    t_ns: TimeNs
    gyro_x: float = 0.0
    gyro_y: float = 0.0
    gyro_z: float = Field(description="yaw rate, rad/s")
    accel_x: float = 0.0
    accel_y: float = 0.0
    accel_z: float = 0.0
    wheel_speed: float | None = Field(default=None, description="m/s, from wheel odometry")
    seq: Count | None = None


# The most samples one ImuBatch holds: a second at 100 Hz (a sender's period is tens of ms).
IMU_BATCH_MAX = 100


class ImuBatch(Message):
    """Consecutive IMU/odometry samples of one bus, oldest first, on keys.imu_batch(bus_id): what a sender
    gathered over one period (the simulator: a bus agent's filter cycle, 4 samples at 100 Hz). Why: the
    agent takes its inputs in once a cycle anyway, and a message costs its receiver a wake-up of Zenoh's
    thread and a decode each, whatever it holds (`toptag bench bus`, docs/real-time.md). A sender that has
    one sample at a time sends Imu on keys.imu(bus_id); the agent takes both. seq: +1 per batch (the
    samples keep their own)."""

    TYPE: ClassVar[str] = "imu_batch"
    type: Literal["imu_batch"] = "imu_batch"
    bus_id: Id
    samples: list[Imu] = Field(min_length=1, max_length=IMU_BATCH_MAX)
    seq: Count | None = None

    @model_validator(mode="after")
    def _one_bus_in_order(self) -> ImuBatch:
        t_prev = -1
        for i, s in enumerate(self.samples):
            if s.bus_id != self.bus_id:
                raise ValueError(f"samples[{i}]: bus_id {s.bus_id!r} is not the batch's {self.bus_id!r}")
            if s.t_ns <= t_prev:
                raise ValueError(f"samples[{i}]: t_ns {s.t_ns} is not after the sample before ({t_prev})")
            t_prev = s.t_ns
        return self


class GroundTruth(Message):
    """The true state of one bus (simulator or survey-grade reference) on keys.ground_truth(bus_id)."""

    TYPE: ClassVar[str] = "ground_truth"
    type: Literal["ground_truth"] = "ground_truth"
    bus_id: Id
    t_ns: TimeNs
    x: float
    y: float
    z: float = 0.0
    yaw: Yaw
    speed: float = 0.0
    yaw_rate: float = 0.0


class GnssFix(Message):
    """A coarse satellite position of one bus on keys.gnss(bus_id): metres of error, and none at all
    where buildings and big vehicles shield the sky (the intersection). It tells the bus agent when it
    approaches an intersection and gives its filter a start-up prior."""

    TYPE: ClassVar[str] = "gnss"
    type: Literal["gnss"] = "gnss"
    bus_id: Id
    t_ns: TimeNs
    x: float
    y: float
    sigma_m: float = Field(gt=0)


class FusionHealth(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    status: Literal["acquiring", "ok", "degraded", "lost"] | None = Field(
        default=None, description="ok: recent accepted fixes; degraded: none for a while or uncertain; "
                                  "lost: too long or too uncertain to drive on")
    accepted_fixes: Count = 0
    rejected_fixes: Count = 0
    since_last_fix_ns: DurationNs | None = Field(
        default=None, description="t_ns minus the capture time of the last accepted fix; None before any")
    last_fix_delay_ns: DurationNs | None = Field(
        default=None, description="arrival minus capture time of the last accepted fix")
    last_fix_rsu: Id | None = None
    # Every fix's path (toptag.fusion.state.Health): accepted + rejected (gated) + too_old + future +
    # refused (from a flagged RSU) + other = every fix received.
    too_old_fixes: Count = 0
    future_fixes: Count = 0
    flagged_rsu_fixes: Count = Field(default=0, description="from an RSU flagged for drift (down-weighted or refused)")
    unknown_clock_fixes: Count = Field(default=0, description="from an RSU whose clock came without a bound")
    other_fixes: Count = Field(default=0, description="duplicates, invalid, before start-up, waiting")
    flagged_rsus: list[Id] = Field(default_factory=list)


class FusedPose(Message):
    """The bus's fused (IMU + RSU fixes) pose at t_ns, on keys.fused_pose(bus_id)."""

    TYPE: ClassVar[str] = "fused_pose"
    type: Literal["fused_pose"] = "fused_pose"
    bus_id: Id
    t_ns: TimeNs
    x: float
    y: float
    yaw: Yaw
    speed: float = 0.0
    yaw_rate: float = 0.0
    covariance: Covariance3
    health: FusionHealth = FusionHealth()

    def covariance_matrix(self) -> np.ndarray:
        return np.asarray(self.covariance, dtype=float)


MESSAGE_TYPES: dict[str, type[Message]] = {
    m.TYPE: m for m in (Approach, Leave, ActiveSessions, PoseFix, RsuStatus, RsuDiagnosis, TagDetections, Frame, Imu,
                        ImuBatch, GroundTruth, GnssFix, FusedPose)
}
