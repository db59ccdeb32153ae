"""Bus pose filter: EKF on IMU / wheel odometry, updated by delayed RSU pose fixes at their capture time.

Pure core: no I/O, no Zenoh, no clock. Every call carries integer-nanosecond timestamps.

State: x, y, yaw, speed, yaw_rate, gyro_bias, wheel_scale (toptag.fusion.state); each fix is a
toptag.fix.Fix, each estimate a toptag.fusion.state.FusedState.

Prediction runs at the IMU rate (100 Hz): the accelerometer's forward axis drives v, yaw_rate is a
random walk (continuous white yaw acceleration, so the yaw/yaw-rate coupling integrates the gyro with
the trapezoid rule), and each IMU sample updates yaw_rate + gyro_bias with the gyro and
(1 + wheel_scale) * v with the wheel speed. A pose fix updates (x, y, yaw) with its own covariance.
The prediction, the IMU update and the Kalman update are compiled (toptag.fusion.kernels): a late fix
re-runs the steps after it, and in numpy those steps were most of the bus agent's CPU.

Back-projection: the filter keeps a ring buffer (`FilterConfig.buffer_s`, >= 1 s) of states,
covariances, gate states and IMU inputs, one per IMU sample, and every fix in that window in the
canonical order (capture time, source, sequence). A fix stamped t is applied exactly at t (the step
containing t is split there) and every later step is re-propagated, lazily, when the present is next
needed. Gate decisions are re-taken during re-propagation, so the result depends only on the set of
fixes and IMU samples, never on their arrival order: an out-of-order replay reproduces the in-order
estimate to the last bit.

Gating: chi-square test on the innovation, d² = νᵀ S⁻¹ ν with S = H P Hᵀ + R, 3 dof. In tracking, the
filter's own pose covariance entering S is capped (`gate_max_pos_sigma`, `gate_max_yaw_sigma`): a long
run without accepted fixes cannot widen the gate without bound, so a wild fix stays rejected however
long the filter has been starved. Re-acquisition after a genuine drift needs a consensus: once no fix
has been accepted for `reacquire_after_s`, a rejected fix is applied (with the pose covariance
inflated by its innovation) only if at least `reacquire_min_fixes` recent rejected fixes from at least
`reacquire_min_sources` RSUs agree with it.

Time offsets (toptag.fusion.offsets): each RSU's time offset (its clock's offset from the bus's plus
the capture latency it does not know of) is a state of the filter, one slot per RSU, added when its
first fix is processed (prior 0 with `offset_sigma0_ms`, or `offset_sigma0_unknown_clock_ms` when the
fix's clock came without a bound; a random walk of `offset_walk_ms` per sqrt(s)). A fix stamped t is
predicted as the pose at t - offset; through that model the offset's uncertainty widens the RSU's
innovation covariance by the motion it implies (speed x sigma along the track, yaw rate x sigma in
yaw) and every fix refines the offset. At most `max_offset_slots` RSUs hold a slot; the one heard
from least recently gives its slot up (its estimate is remembered and seeds it when it returns).
The offsets' common part is seen only through the bus's turns and accelerations: while no RSU with a
known clock holds a slot, the first unknown-clock RSU is the time reference (known-clock prior), and
it is released, by an inflation, once one does (`_time_reference`).

Trust (toptag.fusion.trust): every RSU's innovations feed a drift detector that flags an RSU whose
fixes disagree persistently with the other RSUs and the filter (a turned camera, a moved pole);
while flagged its fixes are down-weighted or refused (`flagged_policy`). Offsets, flags and
disagreements are part of each buffered step, so they too are re-derived on re-propagation.
`rsu_assessments()` reports them per RSU.

Start-up: `initialize(...)` from a coarse prior (then fixes are gated against the full prior and the
first one is applied once `acquire_min_fixes` agree), or automatically from the first confident fix
(pose sigma <= `init_max_pos_sigma`). IMU samples received before start-up are kept and replayed.
"""
from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from types import MappingProxyType
from typing import Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.fix import Fix
from toptag.fusion import kernels
from toptag.fusion.biases import BIAS_DIM, bias_root
from toptag.fusion.offsets import motion_rate
from toptag.fusion.outcomes import FixOutcome, FixRecord, applied_count, count_outcomes
from toptag.fusion.state import (
    STATE_DIM,
    ST_GYRO_BIAS,
    ST_SPEED,
    ST_WHEEL_SCALE,
    ST_YAW,
    ST_YAW_RATE,
    FusedState,
    Health,
)
from toptag.fusion.trust import DriftRule, RsuAssessment, RsuRecord
from toptag.geometry import wrap_angle
from toptag.units import ns_from_s, s_from_ns

ACQUIRING, TRACKING = 1, 2
_MODE_NAMES = {ACQUIRING: "acquiring", TRACKING: "tracking"}
_EYES: dict[int, np.ndarray] = {}
_NO_RSUS = MappingProxyType({})
_NO_BIAS_ROOT = np.zeros((BIAS_DIM, BIAS_DIM))  # kernels.fix_model's L without a bias block
_Z33 = np.zeros((3, 3))  # kernels.fix_step's B without a bias share
_NO_RECORD = np.zeros((kernels.DA_LEN, 3, 3))  # ... and its drift arguments without the detector
_NO_FLOORS, _NO_CONSTS = np.zeros((2, 3, 3)), np.zeros(4)
# outcome counts' keys Health reads (FixOutcome's .value is a property: not read at every estimate)
_REJECTED, _TOO_OLD, _BEFORE_START, _FUTURE, _REFUSED = (o.value for o in (
    FixOutcome.REJECTED_GATE, FixOutcome.TOO_OLD, FixOutcome.BEFORE_START, FixOutcome.FUTURE,
    FixOutcome.REFUSED_FLAGGED))


def _eye(n: int) -> np.ndarray:
    e = _EYES.get(n)
    if e is None:
        e = _EYES[n] = np.eye(n)
    return e

# chi-square quantiles, 3 dof (avoid importing scipy in the service)
_CHI2_3 = {0.5: 2.3659738843753377, 0.9: 6.251388631170325, 0.95: 7.814727903251178,
           0.99: 11.344866730144373, 0.995: 12.838156466598647, 0.999: 16.26623619623813,
           0.9999: 21.10751340254392, 0.99999: 25.90174974567149, 0.999999: 30.66484970615427}


def chi2_3dof(p: float) -> float:
    if p in _CHI2_3:
        return _CHI2_3[p]
    from scipy.stats import chi2

    return float(chi2.ppf(p, 3))


class FilterConfig(BaseModel):
    """Tuning (the [filter] table of `toptag bus --config`). Noise densities are continuous time; sigmas
    are per sample."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    buffer_s: float = Field(default=2.0, ge=1.0)  # history kept for delayed fixes (>= 1 s)
    # process noise
    pos_noise_density: float = 1e-3  # m/sqrt(s): unmodelled slip of the unicycle model
    yaw_noise_density: float = 2e-4  # rad/sqrt(s): unmodelled yaw motion
    accel_noise_density: float = 0.05  # m/s^2/sqrt(Hz): accelerometer noise + bias, drives v
    yaw_accel_density: float = 1.0  # rad/s^2/sqrt(Hz): yaw-rate random walk
    gyro_bias_walk: float = 2e-5  # rad/s/sqrt(s)
    wheel_scale_walk: float = 1e-5  # 1/sqrt(s)
    # IMU / odometry measurement noise (per sample)
    gyro_sigma: float = 5e-3  # rad/s
    wheel_sigma: float = 0.03  # m/s
    # priors at start-up
    gyro_bias_sigma0: float = 0.01  # rad/s
    wheel_scale_sigma0: float = 0.02
    speed_sigma0: float = 0.2  # m/s around the wheel reading (2.0 without any wheel reading)
    # gating
    gate_probability: float | None = 0.999  # None: no gate (every valid fix is applied)
    gate_max_pos_sigma: float = 0.5  # m: cap on the filter's own position sigma inside S
    gate_max_yaw_sigma: float = math.radians(3.0)
    reacquire_after_s: float = 1.0
    reacquire_window_s: float = 1.0
    reacquire_min_fixes: int = 4
    reacquire_min_sources: int = 2
    consensus_sigma: tuple[float, float, float] = (0.3, 0.3, math.radians(3.0))
    consensus_probability: float = 0.99
    acquire_min_fixes: int = 2
    acquire_min_sources: int = 1
    # start-up from a fix
    init_from_fix: bool = True
    init_max_pos_sigma: float = 0.5
    init_max_yaw_sigma: float = math.radians(10.0)
    # Beyond the newest IMU sample nothing measures the motion: the yaw rate walks with yaw_accel_density
    # and the acceleration with this jerk (m/s^3/sqrt(Hz)), and the pose's covariance says so.
    extrapolation_jerk_density: float = Field(default=1.0, ge=0)
    # admission
    max_future_s: float = 0.5  # a fix stamped later than newest IMU + this is refused
    # time offsets (toptag.fusion.offsets): one state per RSU
    time_offsets: bool = True  # False: fixes are taken at their stamps (offsets assumed zero)
    offset_sigma0_ms: float = Field(default=5.0, gt=0)  # prior: unmodelled capture latency (clock bound added)
    offset_sigma0_unknown_clock_ms: float = Field(default=50.0, gt=0)  # prior when the clock has no bound
    offset_walk_ms: float = Field(default=0.1, ge=0)  # ms/sqrt(s): clock wander, latency drift
    max_offset_slots: int = Field(default=8, ge=1)
    # calibration biases (toptag.fusion.biases): a fix's calibration share (Fix.calib_cov) is its RSU's
    # bias, a state per RSU ("estimate"), carried but never updated ("consider", Schmidt), or white noise
    # as before ("noise"); it decorrelates over calib_bias_corr_m metres driven (the bias a 6-dof camera
    # error makes changes as the bus crosses the view).
    calib_bias: Literal["estimate", "consider", "noise"] = "consider"
    calib_bias_corr_m: float = Field(default=20.0, gt=0)
    # drift detection (toptag.fusion.trust)
    drift_detection: bool = True
    drift_window_s: float = Field(default=5.0, gt=0)  # time constant of the detector's forgetting
    drift_false_alarm: float = Field(default=1e-5, gt=0, lt=0.5)  # per test, chi-square 3 dof
    drift_clear_probability: float = Field(default=0.9, gt=0, lt=1)
    # A smaller disagreement is never drift (a floor under the test below): 3 cm / 0.1 deg, which a 0.2 deg
    # turn (5-8 cm and up to 0.2 deg at the demo's ranges) exceeds. It was 10 cm / 0.3 deg while the test
    # counted a live camera's fixes of one view as independent evidence (bus-42 standing ~6 s 21 m from
    # rsu-se flagged it in compose): the view-dependent error below now weighs them as one view.
    drift_min_pos_m: float = Field(default=0.03, ge=0)
    drift_min_yaw_deg: float = Field(default=0.1, ge=0)
    # A healthy RSU's constant bias (1 sigma per axis) beyond its fixes' stated calibration covariance:
    # the test weighs a disagreement against it as against the noise (toptag.fusion.trust). The live RSU
    # pipeline's own per-RSU bias on the demo's frames, weighted as the filter weighs fixes, is at most
    # 0.3 cm and 0.013 deg (`toptag eval livefix`: weighted_mean_cm_deg, docs/time-and-trust.md).
    drift_bias_sigma_m: float = Field(default=0.005, ge=0)
    drift_bias_sigma_deg: float = Field(default=0.02, ge=0)
    # A fix's view-dependent error: the live pipeline's fixes of a bus seen from one place (far, grazing
    # tags; a bus standing) err alike, so fixes taken within about drift_view_corr_m metres driven do not
    # average it down: the test weighs an error of this share of each fix's noise sigma, correlating as
    # exp(-distance driven / drift_view_corr_m) between its fixes, and the rest of its variance as white
    # (0: all white). 0.76 over 6.35 m: 58 % of a live fix's error variance is shared, decorrelating over
    # 6.35 m driven (`toptag eval livefix --bus bus-17,bus-42 --seconds 120`: view_correlation,
    # docs/time-and-trust.md), as the fusion study draws its fixes' errors.
    drift_view_bias_share: float = Field(default=0.76, ge=0)
    drift_view_corr_m: float = Field(default=6.35, gt=0)
    # A fix's calibration share (Fix.calib_cov) is its RSU's constant bias, not noise; False: counted as
    # noise, as the detector did before (which flags a healthy RSU whose calibration is off within its
    # stated uncertainty, given enough fixes).
    drift_calibration_is_bias: bool = True
    drift_isolation_ratio: float = Field(default=2.0, ge=1)
    drift_min_fixes: float = Field(default=10.0, ge=1)  # effective number of fixes before a flag
    # effective fixes another RSU needs in the window to be compared with (None: drift_min_fixes). 3: with
    # 10 a live bus on a shared machine (each RSU delivering 3-6 fixes a second) had two others to compare
    # with only on its fourth pass (the 0.2 deg scenario, docs/time-and-trust.md); their means' noise and
    # view errors are weighed in the test.
    drift_min_other_fixes: float | None = Field(default=3.0, ge=1)
    # An RSU's deviation from the others in one pass (one filter) adds to the next pass's for the same
    # bus, fading with this time constant (0: each pass decides on its own): a busy machine's passes may
    # each bring too few fixes to decide.
    drift_past_window_s: float = Field(default=120.0, ge=0)
    # The change test (toptag.fusion.trust): each RSU's deviation from the others over the bus's passes,
    # fading over this time constant (0: no change test), against which this pass's is compared (its
    # constant bias cancels); and the share of its bias that may differ between where the bus was seen
    # in those passes and in this one. Off by default until it is tried on live fixes over many passes (a
    # live RSU's own bias changes across its view too, and the test weighs only the stated calibration
    # and the floor above); the fusion study, whose fixes follow their covariances, turns it on (a day).
    drift_baseline_window_s: float = Field(default=0.0, ge=0)
    drift_change_bias_share: float = Field(default=0.5, ge=0)
    drift_change_false_alarm: float = Field(default=1e-4, gt=0, lt=0.5)  # per test, chi-square 3 dof
    drift_max_offset_sigma_ms: float = Field(default=10.0, gt=0)  # no flag while the RSU's offset is this uncertain
    drift_min_others: int = Field(default=2, ge=1)  # other RSUs seeing the bus meanwhile, to tell who is wrong
    # one fix's innovation counts at most this many sigmas (of its covariance plus the thresholds above)
    drift_clip_sigma: float = Field(default=10.0, gt=0)
    flagged_policy: Literal["downweight", "refuse"] = "downweight"
    flagged_cov_scale: float = Field(default=4.0, ge=1)  # downweight: R -> scale * (R + bias bias^T)
    # health
    degraded_after_s: float = 1.0
    degraded_pos_sigma: float = 0.5
    lost_after_s: float = 10.0
    lost_pos_sigma: float = 2.0

    @property
    def gate_threshold(self) -> float:
        return math.inf if self.gate_probability is None else chi2_3dof(self.gate_probability)


class _Cand(NamedTuple):
    """A fix that was not applied, remembered for consensus."""
    t_ns: int
    source: str
    nu: np.ndarray  # innovation (x, y, yaw) against the filter at t_ns
    R: np.ndarray
    p_diag: np.ndarray  # diagonal of the filter's pose covariance at t_ns


class _Gate(NamedTuple):
    mode: int
    last_accept_ns: int | None  # capture time of the last applied fix (or trusted start)
    consecutive: int  # fixes refused since
    cands: tuple  # refused fixes kept for consensus
    last_delay_ns: int | None = None  # arrival - capture of the last applied fix
    last_source: str | None = None
    clocks: tuple = ()  # RSUs holding a time-offset slot, in state order (index STATE_DIM + i)
    rsus: MappingProxyType | dict = _NO_RSUS  # RSU id -> toptag.fusion.trust.RsuRecord (copy-on-write)
    time_ref: str | None = None  # the unknown-clock RSU whose time the filter follows while no clock is known
    last_trusted_ns: int | None = None  # capture time of the last applied fix from an RSU not flagged (or start)
    # RSUs holding a calibration-bias block (toptag.fusion.biases), in state order: after the offsets,
    # BIAS_DIM entries each (index STATE_DIM + len(clocks) + BIAS_DIM * j)
    biases: tuple = ()


class _Step:
    __slots__ = ("t", "u", "x", "P", "g")

    def __init__(self, t, u, x, P, g):
        self.t, self.u, self.x, self.P, self.g = t, u, x, P, g


class BusFilter:
    """Delayed-fix EKF. See the module docstring.

    add_imu(t_ns, gyro_z, accel_x, accel_y=None, wheel_speed=None) -> bool   (alias: predict)
    add_fix(fix: Fix, arrival_ns=None) -> FixOutcome
    initialize(t_ns, x, y, yaw, cov=None, pos_sigma=5.0, yaw_sigma=pi, speed=None, speed_sigma=None,
               trusted=False)
    estimate(t_ns=None) -> FusedState | None           (None before start-up)
    counters() -> dict                                (final outcome counts, totals and per source)
    fix_outcomes() -> list[(key, FixOutcome, d2)]      (fixes still in the buffer)
    rsu_assessments() -> dict[rsu, RsuAssessment]      (time offset, drift flag, disagreement, counts)
    memory() -> dict[rsu, RsuRecord]                   (what a new filter may start from: BusFilter(memory=))
    """

    def __init__(self, config: FilterConfig | None = None, memory: dict[str, RsuRecord] | None = None):
        self.cfg = config or FilterConfig()
        c = self.cfg
        self._offsets = c.time_offsets
        self._var0_known = (c.offset_sigma0_ms * 1e-3) ** 2
        self._var0_unknown = (c.offset_sigma0_unknown_clock_ms * 1e-3) ** 2
        self._q_d = (c.offset_walk_ms * 1e-3) ** 2
        self._healthy_ns = ns_from_s(c.degraded_after_s)
        self._calm_stat = chi2_3dof(c.drift_clear_probability)
        self._drift = DriftRule(c.drift_window_s, chi2_3dof(1.0 - c.drift_false_alarm),
                                self._calm_stat, c.drift_min_pos_m,
                                math.radians(c.drift_min_yaw_deg), c.drift_isolation_ratio, c.drift_clip_sigma ** 2,
                                c.drift_min_fixes, c.drift_max_offset_sigma_ms * 1e-3, c.drift_min_others,
                                np.diag([c.drift_bias_sigma_m ** 2, c.drift_bias_sigma_m ** 2,
                                         math.radians(c.drift_bias_sigma_deg) ** 2]),
                                c.drift_min_other_fixes, c.drift_past_window_s, c.drift_baseline_window_s,
                                c.drift_change_bias_share, chi2_3dof(1.0 - c.drift_change_false_alarm),
                                c.drift_view_bias_share, c.drift_view_corr_m) \
            if c.drift_detection else None
        # RSUs remembered from a previous filter (their offsets and flags), in the start-up step.
        self._memory = MappingProxyType(dict(memory)) if memory else _NO_RSUS
        self._biases = c.calib_bias != "noise"
        self._consider = c.calib_bias == "consider"
        self._gate_thr = c.gate_threshold
        self._buffer_ns = ns_from_s(c.buffer_s)
        self._q_pos = c.pos_noise_density ** 2
        self._q_yaw = c.yaw_noise_density ** 2
        self._q_v = c.accel_noise_density ** 2
        self._q_a = c.yaw_accel_density ** 2
        self._q_b = c.gyro_bias_walk ** 2
        self._q_k = c.wheel_scale_walk ** 2
        self._r_g = c.gyro_sigma ** 2
        self._r_w = c.wheel_sigma ** 2
        q = np.empty(kernels.Q_LEN)  # the compiled steps' constants (toptag.fusion.kernels)
        q[[kernels.Q_POS, kernels.Q_YAW, kernels.Q_V, kernels.Q_B, kernels.Q_K, kernels.Q_D, kernels.Q_A, kernels.R_G,
           kernels.R_W, kernels.CORR_M, kernels.Q_J]] = [self._q_pos, self._q_yaw, self._q_v, self._q_b, self._q_k,
                                                        self._q_d, self._q_a, self._r_g, self._r_w, c.calib_bias_corr_m,
                                                        c.extrapolation_jerk_density ** 2]
        self._q = q
        self._cap = np.array([c.gate_max_pos_sigma, c.gate_max_pos_sigma, c.gate_max_yaw_sigma])
        self._cons_var = np.asarray(c.consensus_sigma, dtype=float) ** 2
        self._cons_thr = chi2_3dof(c.consensus_probability)
        self._steps: list[_Step] = []
        self._dirty = 0  # index of the first step that needs re-computation (len(steps) when clean)
        self._fix_t: list[int] = []
        self._fix_keys: list[tuple] = []
        self._fix_recs: list[FixRecord] = []
        self._seen: set[tuple] = set()
        self._pre_imu: list[tuple[int, tuple]] = []
        self._pre_imu_dropped_ns: int | None = None  # newest IMU sample dropped from the start-up buffer
        self._last_imu_t: int | None = None
        self._start_ns: int | None = None
        self._archived: dict[str, int] = count_outcomes([])
        self._archived_src: dict[str, dict[str, int]] = {}
        self._archived_flagged = 0
        self._totals_memo: tuple | None = None  # _totals until an outcome changes
        # The buffer's fixes by outcome and from flagged RSUs, kept as decisions change (not counted over the
        # ~80 buffered fixes at every estimate after a fix)
        self._buffered = count_outcomes([])
        self._buffered_flagged = 0
        self._unknown_clock = 0
        self._imu_rejected = 0
        self._imu_count = 0
        self._last_rx_delay_ns: int | None = None

    # ------------------------------------------------------------------ public API
    @property
    def initialized(self) -> bool:
        return bool(self._steps)

    @property
    def head_ns(self) -> int | None:
        """Time of the newest state (newest IMU sample, or the start-up time)."""
        return self._steps[-1].t if self._steps else None

    @property
    def buffer_start_ns(self) -> int | None:
        return self._steps[0].t if self._steps else None

    def predict(self, t_ns: int, gyro_z: float, accel_x: float, accel_y: float | None = None,
                wheel_speed: float | None = None) -> bool:
        """Alias of add_imu."""
        return self.add_imu(t_ns, gyro_z, accel_x, accel_y, wheel_speed)

    def add_imu(self, t_ns: int, gyro_z: float, accel_x: float, accel_y: float | None = None,
                wheel_speed: float | None = None) -> bool:
        """One IMU/odometry sample (100 Hz). Samples must come in increasing time; a sample not
        newer than the previous one is counted and ignored (returns False). accel_y is accepted
        for completeness and not used (planar model: it is v * yaw_rate)."""
        t_ns = int(t_ns)
        bad = not (math.isfinite(gyro_z) and math.isfinite(accel_x)) or \
            (wheel_speed is not None and not math.isfinite(wheel_speed))
        if bad or (self._last_imu_t is not None and t_ns <= self._last_imu_t):
            self._imu_rejected += 1
            return False
        self._last_imu_t = t_ns
        self._imu_count += 1
        u = (float(gyro_z), float(accel_x), None if wheel_speed is None else float(wheel_speed))
        if not self._steps:
            self._pre_imu.append((t_ns, u))
            cut = t_ns - self._buffer_ns
            if self._pre_imu[0][0] < cut:
                self._pre_imu_dropped_ns = max(p[0] for p in self._pre_imu if p[0] < cut)
                self._pre_imu = [p for p in self._pre_imu if p[0] >= cut]
            return True
        if t_ns <= self._steps[-1].t:  # start-up time after this sample
            return True
        # Computed when next needed (_ensure_clean): with the other samples the bus agent takes in at each
        # step and the steps a late fix re-computes, in one compiled call (kernels.imu_steps), not one each.
        self._steps.append(_Step(t_ns, u, None, None, None))
        self._prune()
        return True

    def initialize(self, t_ns: int, x: float, y: float, yaw: float, cov=None, pos_sigma: float = 5.0,
                   yaw_sigma: float = math.pi, speed: float | None = None, speed_sigma: float | None = None,
                   trusted: bool = False):
        """Start from a prior. By default the prior is coarse (e.g. GNSS-grade, metres): fixes are
        gated against its full covariance and the first is applied once `acquire_min_fixes` fixes
        agree with each other. `trusted=True` starts tracking at once, as if a fix had been applied
        at t_ns (a surveyed start, or dead reckoning). `cov` (3x3 of x, y, yaw) overrides the sigmas."""
        if self._steps:
            raise RuntimeError("filter already started")
        P3 = np.diag([pos_sigma ** 2, pos_sigma ** 2, yaw_sigma ** 2]) if cov is None else \
            np.asarray(cov, dtype=float).reshape(3, 3)
        t_ns = int(t_ns)
        gate = _Gate(TRACKING, t_ns, 0, (), last_trusted_ns=t_ns) if trusted else _Gate(ACQUIRING, None, 0, ())
        self._start(t_ns, np.array([x, y, wrap_angle(yaw)]), P3, gate, speed, speed_sigma)

    def add_fix(self, fix: Fix, arrival_ns: int | None = None, decide: bool = True) -> FixOutcome:
        """A pose fix (capture time fix.t_ns). `arrival_ns` (or fix.arrival_ns; default the newest
        IMU time) only feeds the health report. Returns the decision taken now; a fix applied in the
        past may be re-decided when earlier fixes arrive later (counters() has the final word).
        decide=False: a fix the buffer takes is decided when the filter is next asked (estimate, counters,
        ...), with every fix added meanwhile, and returned PENDING: a bus agent adding a step's fixes so
        re-runs the steps after the oldest once, not once per fix (the same estimates)."""
        if not isinstance(fix, Fix):  # a wire message goes through protocol.convert.fix_from_message
            raise TypeError(f"add_fix takes a toptag.fix.Fix, not {type(fix).__name__}")
        arrival = arrival_ns if arrival_ns is not None else fix.arrival_ns
        if arrival is None:
            arrival = self._last_imu_t
        if fix.clock_bound_ns is None:
            self._unknown_clock += 1
        if fix.problem() is not None:
            return self._count_now(fix, FixOutcome.INVALID)
        if arrival is not None:
            self._last_rx_delay_ns = int(arrival) - fix.t_ns
        if not self._steps:
            return self._maybe_start_from(fix, arrival)
        if (fix.seq is not None and (fix.source, "seq", fix.seq) in self._seen) or \
                (fix.source, "t", fix.t_ns) in self._seen:
            return self._count_now(fix, FixOutcome.DUPLICATE)
        if fix.t_ns <= self._start_ns:
            return self._count_now(fix, FixOutcome.BEFORE_START)
        if fix.t_ns <= self._steps[0].t:
            return self._count_now(fix, FixOutcome.TOO_OLD)
        head = self._steps[-1].t
        if fix.t_ns > head + ns_from_s(self.cfg.max_future_s):
            return self._count_now(fix, FixOutcome.FUTURE)
        key = fix.key
        # the bias root once per fix, not at every replay that passes it
        rec = FixRecord(fix, key, FixOutcome.PENDING, arrival_ns=None if arrival is None else int(arrival),
                        bias_root=self._bias_of(fix))
        i = bisect_right(self._fix_keys, key)
        self._fix_keys.insert(i, key)
        self._fix_t.insert(i, fix.t_ns)
        self._fix_recs.insert(i, rec)
        self._buffered[rec.outcome._value_] += 1
        self._totals_memo = None
        self._seen.add((fix.source, "seq", fix.seq))
        self._seen.add((fix.source, "t", fix.t_ns))
        if fix.t_ns > head:
            return FixOutcome.PENDING
        k = self._step_index_before(fix.t_ns)  # largest k with t_k < t_fix
        self._dirty = min(self._dirty, k + 1)
        if decide:
            self._ensure_clean(k + 1)
        return rec.outcome

    def estimate(self, t_ns: int | None = None) -> FusedState | None:
        """Fused pose at t_ns (default: the newest IMU time). Beyond the newest sample the state is
        predicted (constant acceleration input, constant yaw rate) and its covariance grows by the
        motion nobody measured (_unmeasured_motion: on a starved machine the IMU lags and a bus agent's
        estimate of now is such a prediction); inside the buffer it is interpolated by prediction from
        the state before. None before start-up."""
        if not self._steps:
            return None
        self._ensure_clean()
        head = self._steps[-1]
        t_ns = head.t if t_ns is None else int(t_ns)
        if t_ns >= head.t:
            base = head
        else:
            if t_ns < self._steps[0].t:
                raise ValueError("estimate requested before the start of the buffer")
            k = self._step_index_at_or_before(t_ns)
            base = self._steps[k]
        if t_ns == base.t:
            x, P, g = base.x, base.P, base.g
        elif base is head and (not self._fix_t or self._fix_t[-1] <= head.t):  # no fix pending: one call
            x, g = head.x, head.g
            x, P = kernels.extrapolate(x, head.P, s_from_ns(t_ns - head.t), head.u[1] if head.u is not None else 0.0,
                                       self._q, len(g.clocks))
        else:
            x, P, g, _ = self._advance(base.x, base.P, base.g, base.t, base.u, t_ns, record=False)
            if base is head:
                P = self._unmeasured_motion(x, P, s_from_ns(t_ns - base.t))
            else:
                P = self._yaw_rate_noise(P, s_from_ns(t_ns - base.t))
        return self._fused(t_ns, x, P, g, max(0, t_ns - head.t))

    def _unmeasured_motion(self, x, P, tau: float):
        """The covariance of a prediction tau seconds beyond the newest IMU sample, where no gyro holds
        the yaw rate and no accelerometer the acceleration: white yaw acceleration (yaw_accel_density)
        integrated into the yaw rate, the yaw and, at the speed v, across the track; white jerk
        (extrapolation_jerk_density) into the speed and along the track. Held constant instead, as the
        prediction holds them, a turn or a braking that began after the last sample is a surprise the
        covariance did not allow for: 0.5 s ahead, fused poses claimed 1.4 cm and were 8 cm RMS and up to
        48 cm off (NEES 54)."""
        if tau <= 0:
            return P
        return kernels.unmeasured_motion(P, float(x[ST_SPEED]), float(x[ST_YAW]), self._q, tau)

    def _totals(self) -> tuple[dict[str, int], int, tuple[int, ...]]:
        """Fix outcome counts, fixes from flagged RSUs, and Health's counts of them (accepted, rejected,
        too_old, future, other): the archived ones plus the buffer's (not to be modified: kept until a fix
        is added, decided again or archived, as every estimate reads them)."""
        if self._totals_memo is None:
            buffered = self._buffered
            counts = {k: n + buffered[k] for k, n in self._archived.items()}
            accepted = applied_count(counts)
            rejected = counts[_REJECTED]
            too_old = counts[_TOO_OLD] + counts[_BEFORE_START]
            future = counts[_FUTURE]
            other = sum(counts.values()) - accepted - rejected - too_old - future - counts[_REFUSED]
            self._totals_memo = (counts, self._archived_flagged + self._buffered_flagged,
                                 (accepted, rejected, too_old, future, other))
        return self._totals_memo

    def counters(self) -> dict:
        """Counts of fix outcomes (final decisions), per source as well, plus IMU counts."""
        self._ensure_clean()
        total, flagged, _ = self._totals()
        total = dict(total)
        per_src: dict[str, dict[str, int]] = {s: dict(v) for s, v in self._archived_src.items()}
        for r in self._fix_recs:
            d = per_src.setdefault(r.fix.source, count_outcomes([]))
            d[r.outcome.value] += 1
        total["fixes"] = sum(total[o.value] for o in FixOutcome)
        total["applied"] = applied_count(total)
        total["from_flagged_rsu"] = flagged
        total["unknown_clock"] = self._unknown_clock
        total["imu_samples"] = self._imu_count
        total["imu_rejected"] = self._imu_rejected
        total["per_source"] = {s: {k: v for k, v in d.items() if v} for s, d in sorted(per_src.items())}
        return total

    def fix_outcomes(self) -> list[tuple[tuple, FixOutcome, float]]:
        """(key, outcome, d2) of every fix still in the buffer, in canonical order."""
        self._ensure_clean()
        return [(r.key, r.outcome, r.d2) for r in self._fix_recs]

    # ------------------------------------------------------------------ start-up
    def _maybe_start_from(self, fix: Fix, arrival: int | None) -> FixOutcome:
        """Start from a confident fix, unless its RSU is flagged for drift (remembered from an earlier
        filter: the filter would follow the turned camera and judge the healthy ones against it) or the
        IMU history around its time is gone (a fix older than the start-up buffer, late on a busy machine:
        the first step would dead-reckon over the gap with one sample's input)."""
        c = self.cfg
        sd = np.sqrt(np.diag(fix.cov))
        if not c.init_from_fix or max(sd[0], sd[1]) > c.init_max_pos_sigma or sd[2] > c.init_max_yaw_sigma:
            return self._count_now(fix, FixOutcome.NOT_INITIALIZED)
        remembered = self._memory.get(fix.source)
        if remembered is not None and remembered.flagged:
            self._archive(fix, FixOutcome.NOT_INITIALIZED, flagged=True)
            return FixOutcome.NOT_INITIALIZED
        if self._pre_imu_dropped_ns is not None and fix.t_ns <= self._pre_imu_dropped_ns:
            return self._count_now(fix, FixOutcome.TOO_OLD)
        delay = None if arrival is None else int(arrival) - fix.t_ns
        gate = _Gate(TRACKING, fix.t_ns, 0, (), delay, fix.source, last_trusted_ns=fix.t_ns)
        self._start(fix.t_ns, fix.pose, fix.cov, gate, None, None, first=fix)
        self._seen.add((fix.source, "seq", fix.seq))
        self._seen.add((fix.source, "t", fix.t_ns))
        return self._count_now(fix, FixOutcome.INITIALIZED)

    def _start(self, t0: int, pose: np.ndarray, P3: np.ndarray, gate: _Gate, speed, speed_sigma,
               first: Fix | None = None):
        """The first step at t0. `first`: the fix the filter starts from; its RSU's time offset gets
        its slot at once, correlated with the pose (the pose is that fix's, offset included)."""
        c = self.cfg
        u0 = None
        for t, u in self._pre_imu:
            if t <= t0:
                u0 = u
        ref = u0 if u0 is not None else (self._pre_imu[0][1] if self._pre_imu else None)
        x = np.zeros(STATE_DIM)
        P = np.zeros((STATE_DIM, STATE_DIM))
        x[:3] = pose
        x[ST_YAW] = wrap_angle(x[ST_YAW])
        P[:3, :3] = P3
        if speed is not None:
            x[ST_SPEED] = speed
            P[ST_SPEED, ST_SPEED] = (c.speed_sigma0 if speed_sigma is None else speed_sigma) ** 2
        elif ref is not None and ref[2] is not None:
            x[ST_SPEED] = ref[2]
            P[ST_SPEED, ST_SPEED] = c.speed_sigma0 ** 2 + (ref[2] * c.wheel_scale_sigma0) ** 2
        else:
            P[ST_SPEED, ST_SPEED] = 2.0 ** 2
        sb2 = c.gyro_bias_sigma0 ** 2
        if ref is not None:
            x[ST_YAW_RATE] = ref[0]
            P[ST_YAW_RATE, ST_YAW_RATE] = sb2 + self._r_g
            P[ST_YAW_RATE, ST_GYRO_BIAS] = P[ST_GYRO_BIAS, ST_YAW_RATE] = -sb2
        else:
            P[ST_YAW_RATE, ST_YAW_RATE] = 0.5 ** 2
        P[ST_GYRO_BIAS, ST_GYRO_BIAS] = sb2
        P[ST_WHEEL_SCALE, ST_WHEEL_SCALE] = c.wheel_scale_sigma0 ** 2
        gate = gate._replace(rsus=self._memory)
        if first is not None and self._offsets:
            x, P, gate = self._add_slot(x, P, gate, first)
            i = STATE_DIM + gate.clocks.index(first.source)
            # pose = true pose at t0 - delta = true pose(t0) - J delta: error -J delta, correlated with delta's.
            J, var, d0 = motion_rate(x), P[i, i], x[i]
            x[:3] += J * d0  # the pose at t0 is the fix's plus the motion over the offset
            x[ST_YAW] = wrap_angle(x[ST_YAW])
            P[:3, :3] += var * np.outer(J, J)
            P[:3, i] = P[i, :3] = J * var
        L = None if first is None else self._bias_of(first)
        if L is not None:
            # pose error = L eps + noise: the pose is correlated with that RSU's bias
            x, P, gate = self._add_bias(x, P, gate, first)
            j = self._bias_index(gate, first.source)
            P[:3, j:j + BIAS_DIM] = L
            P[j:j + BIAS_DIM, :3] = P[:3, j:j + BIAS_DIM].T
        self._start_ns = t0
        self._steps = [_Step(t0, u0, x, P, gate)]
        self._dirty = 1
        pre, self._pre_imu = self._pre_imu, []
        for t, u in pre:
            if t > t0:
                self._steps.append(_Step(t, u, *self._imu_step(self._steps[-1], t, u)))
        self._dirty = len(self._steps)
        self._prune()

    # ------------------------------------------------------------------ buffer
    def _step_index_before(self, t_ns: int) -> int:
        """Largest k with steps[k].t < t_ns."""
        return bisect_left(_StepTimes(self._steps), t_ns) - 1

    def _step_index_at_or_before(self, t_ns: int) -> int:
        return bisect_right(_StepTimes(self._steps), t_ns) - 1

    def _ensure_clean(self, upto: int | None = None):
        steps = self._steps
        n = len(steps)
        upto = n - 1 if upto is None else min(upto, n - 1)
        i = max(self._dirty, 1)
        while i <= upto:
            j = self._fix_free_run(i, upto)
            if j > i:
                self._imu_steps(i, j)
                i = j + 1
                continue
            cur = steps[i]
            cur.x, cur.P, cur.g = self._imu_step(steps[i - 1], cur.t, cur.u)
            i += 1
        self._dirty = max(self._dirty, upto + 1)

    def _fix_free_run(self, i: int, upto: int) -> int:
        """The last step of the run from step i (to upto at most) with no buffered fix in it (i - 1: step i
        has one)."""
        steps = self._steps
        lo = bisect_right(self._fix_t, steps[i - 1].t)
        t_fix = self._fix_t[lo] if lo < len(self._fix_t) else None
        j = i - 1
        while j < upto and (t_fix is None or steps[j + 1].t < t_fix) and steps[j + 1].u is not None:
            j += 1
        return j

    def _imu_steps(self, i: int, j: int):
        """Steps i..j, none with a fix in it, re-computed in one compiled call (kernels.imu_steps: the same
        arithmetic as _imu_step's, step by step)."""
        steps = self._steps
        prev = steps[i - 1]
        g = prev.g
        a = prev.u[1] if prev.u is not None else 0.0
        t = prev.t
        rows = []
        for s in steps[i:j + 1]:
            u = s.u
            rows.append((s_from_ns(s.t - t), a, u[0], 0.0 if u[2] is None else u[2], u[2] is not None))
            a, t = u[1], s.t
        n = len(prev.x)
        X, P = kernels.imu_steps(prev.x, prev.P, np.array(rows, dtype=float), self._q, len(g.clocks),
                                 self._freeze_lo(g, n))
        for k, s in enumerate(steps[i:j + 1]):
            s.x, s.P, s.g = X[k], P[k], g

    def _prune(self):
        steps = self._steps
        cut = steps[-1].t - self._buffer_ns
        n = 0
        while n + 1 < len(steps) and steps[n + 1].t <= cut:
            n += 1
        if n == 0:
            return
        if self._dirty <= n:  # the fixes archived below go with their final outcomes
            self._ensure_clean(n)
        del steps[:n]
        self._dirty = max(1, self._dirty - n)
        t0 = steps[0].t
        m = bisect_right(self._fix_t, t0)
        for r in self._fix_recs[:m]:
            self._archive(r.fix, r.outcome, r.flagged)
            self._buffered[r.outcome._value_] -= 1
            self._buffered_flagged -= r.flagged
            self._seen.discard((r.fix.source, "seq", r.fix.seq))
            self._seen.discard((r.fix.source, "t", r.fix.t_ns))
        del self._fix_t[:m], self._fix_keys[:m], self._fix_recs[:m]

    def _archive(self, fix: Fix, outcome: FixOutcome, flagged: bool = False):
        self._totals_memo = None
        self._archived[outcome._value_] += 1  # _value_: .value is a property
        self._archived_flagged += flagged
        d = self._archived_src.get(fix.source)
        if d is None:
            d = self._archived_src[fix.source] = count_outcomes([])
        d[outcome._value_] += 1

    def _count_now(self, fix: Fix, outcome: FixOutcome) -> FixOutcome:
        self._archive(fix, outcome)
        return outcome

    # ------------------------------------------------------------------ propagation
    def _imu_step(self, prev: _Step, t_ns: int, u):
        """(x, P, gate) of the step at t_ns with IMU input u, from the step before: the prediction with
        every buffered fix in between applied, the yaw rate's random step and the IMU update. Without a
        fix in between (most steps) one compiled call."""
        dt = s_from_ns(t_ns - prev.t)
        g = prev.g
        if bisect_right(self._fix_t, prev.t) == bisect_right(self._fix_t, t_ns) and t_ns > prev.t:
            a = prev.u[1] if prev.u is not None else 0.0
            n = len(prev.x)
            if u is None:
                x, P = kernels.imu_step(prev.x, prev.P, dt, a, self._q, len(g.clocks), False, 0.0, 0.0, False, n)
            else:
                x, P = kernels.imu_step(prev.x, prev.P, dt, a, self._q, len(g.clocks), True, u[0],
                                        0.0 if u[2] is None else u[2], u[2] is not None, self._freeze_lo(g, n))
            return x, P, g
        x, P, g, ended = self._advance(prev.x, prev.P, g, prev.t, prev.u, t_ns, record=True, step=(dt, u))
        if ended:
            return x, P, g
        if u is None:
            return x, self._yaw_rate_noise(P, dt), g
        n = len(x)
        x, P = kernels.imu_update(x, P, dt, self._q, u[0], 0.0 if u[2] is None else u[2], u[2] is not None,
                                  self._freeze_lo(g, n))
        return x, P, g

    def _advance(self, x, P, g, t_from: int, u, t_to: int, record: bool, step=None):
        """From the state at t_from to t_to, applying every buffered fix in (t_from, t_to]; (x, P, gate,
        ended). step: (dt, the IMU input) of the step ending at t_to, whose end (the IMU update) the last
        fix's compiled call may take too (ended: it did)."""
        a = u[1] if u is not None else 0.0
        lo = bisect_right(self._fix_t, t_from)
        hi = bisect_right(self._fix_t, t_to)
        t = t_from
        ended = False
        for j in range(lo, hi):
            rec = self._fix_recs[j]
            tf = rec.fix.t_ns
            if self._offsets and rec.fix.source not in g.clocks:  # kept whatever becomes of the fix
                x, P, g = self._add_slot(x, P, g, rec.fix)
            if rec.fix.source not in g.biases and rec.bias_root is not None:
                x, P, g = self._add_bias(x, P, g, rec.fix)
            fast = self._fix_step(x, P, g, rec, a, t, t_to if j == hi - 1 else None, step)
            if fast is None:
                xf, Pf = self._predict(x, P, s_from_ns(tf - t), a, g) if tf > t else (x, P)
                xu, Pu, g, outcome, d2, flagged = self._apply_fix(xf, Pf, g, rec, a)
            else:
                xu, Pu, g, outcome, d2, flagged, ended = fast
            if outcome.applied:  # split the interval at the fix; a refused fix leaves it whole
                x, P, t = xu, Pu, (t_to if ended else tf)
            if record:
                if outcome is not rec.outcome or flagged != rec.flagged:
                    self._buffered[rec.outcome._value_] -= 1  # _value_: .value is a property
                    self._buffered[outcome._value_] += 1
                    self._buffered_flagged += flagged - rec.flagged
                    self._totals_memo = None
                rec.outcome, rec.d2, rec.flagged = outcome, d2, flagged
        if t_to > t:
            x, P = self._predict(x, P, s_from_ns(t_to - t), a, g)
        return x, P, g, ended

    def _predict(self, x, P, dt: float, a: float, g: _Gate):
        """(x, P) dt seconds on: constant forward acceleration a and yaw rate, midpoint heading; the time
        offsets' random walk and the calibration biases' decorrelation (toptag.fusion.kernels.predict)."""
        return kernels.predict(x, P, dt, a, self._q, len(g.clocks))

    def _yaw_rate_noise(self, P, dt: float):
        """The yaw rate's random step w (variance yaw_accel_density² * dt) over one interval of
        length dt between IMU samples, entering yaw as w * dt / 2: with the gyro update that follows,
        yaw is integrated with the trapezoid rule. Added once per interval (fixes inside an interval
        see yaw_k + yaw_rate_k * tau), so splitting an interval at a fix changes nothing else."""
        if dt <= 0:
            return P
        qw = self._q_a * dt
        P = P.copy()
        P[ST_YAW, ST_YAW] += qw * dt * dt / 4
        P[ST_YAW, ST_YAW_RATE] += qw * dt / 2
        P[ST_YAW_RATE, ST_YAW] += qw * dt / 2
        P[ST_YAW_RATE, ST_YAW_RATE] += qw
        return P

    def _considered(self, g: _Gate, n: int) -> slice | None:
        """The states no update may move: the calibration biases when they are only considered."""
        return slice(STATE_DIM + len(g.clocks), n) if self._consider and g.biases else None

    def _freeze_lo(self, g: _Gate, n: int) -> int:
        """The first state an IMU update may not move (_considered; n: none)."""
        return STATE_DIM + len(g.clocks) if self._consider and g.biases else n

    @staticmethod
    def _kalman(x, P, H, nu, R, PHt=None, S=None, freeze: slice | None = None):
        """Kalman update (Joseph form: right for any gain). `freeze`: states the update must leave
        alone (their gain rows zeroed, Schmidt "consider" states): the time offsets, which a flagged RSU's
        biased fixes would otherwise pull. Compiled: toptag.fusion.kernels.kalman."""
        if PHt is None:
            PHt = P @ H.T
            S = H @ PHt + R
        n = len(x)
        lo, hi = (n, n) if freeze is None else freeze.indices(n)[:2]
        return kernels.kalman(x, P, PHt, S, np.asarray(nu, dtype=float), lo, hi)

    # ------------------------------------------------------------------ time offsets
    def _offset_prior(self, fix: Fix) -> float:
        """Variance (s²) of a new RSU's time offset."""
        if fix.clock_bound_ns is None:
            return self._var0_unknown
        return self._var0_known + s_from_ns(fix.clock_bound_ns) ** 2

    def _time_reference(self, x, P, g: _Gate, fix: Fix) -> tuple[np.ndarray, np.ndarray, _Gate, bool]:
        """Which time the filter follows. The offsets' common part is seen only through the bus's
        accelerations and turns: with no RSU whose clock is known, it would wander within the unknown
        clocks' prior (50 ms is 35 cm at 7 m/s). So while no RSU holding a slot has a known clock, the
        first unknown-clock RSU is the time reference (its offset gets the known-clock prior; the others
        are estimated against it). When an RSU with a known clock takes a slot, the reference is
        released: the variance it was spared is given back to the common part of the unknown-clock
        offsets and to the pose along the motion (P += dv u u', u = 1 on each unknown-clock offset and
        the motion rate on the pose, as at start-up): an inflation, so the filter stays consistent.
        Returns (x, P, gate, whether the new slot is the reference)."""
        held = [k for k in g.clocks if k in g.rsus]
        if fix.clock_bound_ns is None:
            # An offset remembered from an earlier filter was learnt against that one's time: it is an
            # estimate, not a borrowed prior, and releasing it would throw what it learnt away.
            rec = g.rsus.get(fix.source)
            anchored = g.time_ref in g.clocks or any(g.rsus[k].clock_known for k in held) or \
                (rec is not None and rec.offset is not None)
            return x, P, (g if anchored else g._replace(time_ref=fix.source)), not anchored
        if g.time_ref not in g.clocks:
            return x, P, g._replace(time_ref=None), False
        u = np.zeros(len(x))
        u[:3] = motion_rate(x)
        for j, k in enumerate(g.clocks):
            if k == g.time_ref or (k in g.rsus and not g.rsus[k].clock_known):
                u[STATE_DIM + j] = 1.0
        return x, P + (self._var0_unknown - self._var0_known) * np.outer(u, u), g._replace(time_ref=None), False

    def _add_slot(self, x, P, g: _Gate, fix: Fix):
        """Give fix.source a time-offset slot (appended to the state). RSUs not heard from for a while
        give theirs up first (least recently heard first) while the slots are full; an RSU's estimate
        is remembered in its record and seeds its slot when it comes back."""
        rsus = dict(g.rsus)
        clocks = list(g.clocks)
        while len(clocks) >= self.cfg.max_offset_slots:
            j = min(range(len(clocks)), key=lambda k: (rsus[clocks[k]].last_t, clocks[k]))
            i = STATE_DIM + j
            rsus[clocks[j]] = rsus[clocks[j]]._replace(offset=(float(x[i]), float(P[i, i])), offset_t=fix.t_ns)
            keep = np.r_[0:i, i + 1:len(x)]
            x, P = x[keep], P[np.ix_(keep, keep)]
            del clocks[j]
        g = g._replace(clocks=tuple(clocks), rsus=MappingProxyType(rsus))
        x, P, g, reference = self._time_reference(x, P, g, fix)
        var0, d0 = (self._var0_known if reference else self._offset_prior(fix)), 0.0
        rec = rsus.get(fix.source)
        if rec is not None and rec.offset is not None:
            d, v = self._remembered_offset(rec, fix.t_ns)
            d0, var0 = d, min(v, var0)
        if rec is None:
            rsus[fix.source] = RsuRecord(last_t=fix.t_ns, clock_known=fix.clock_bound_ns is not None)
        # inserted after the other offsets, before the bias blocks
        i = STATE_DIM + len(g.clocks)
        x = np.insert(x, i, d0)
        Pn = np.insert(np.insert(P, i, 0.0, axis=0), i, 0.0, axis=1)
        Pn[i, i] = var0
        return x, Pn, g._replace(clocks=g.clocks + (fix.source,), rsus=MappingProxyType(rsus))

    # ------------------------------------------------------------------ calibration biases
    def _bias_of(self, fix: Fix) -> np.ndarray | None:
        """L (L L' = the fix's calibration share) when its bias is a state of the filter, else None."""
        if not self._biases or fix.calib_cov is None or not np.all(np.isfinite(fix.calib_cov)) \
                or not np.any(fix.calib_cov):
            return None
        return bias_root(fix.calib_cov)

    @staticmethod
    def _bias_index(g: _Gate, rsu: str) -> int:
        return STATE_DIM + len(g.clocks) + BIAS_DIM * g.biases.index(rsu)

    def _add_bias(self, x, P, g: _Gate, fix: Fix):
        """Give fix.source a calibration-bias block (prior N(0, I), appended). While the blocks are full
        (max_offset_slots) the oldest gives its block up: a bias is not remembered (it is seen again
        from another part of the view, where it differs)."""
        biases = list(g.biases)
        while len(biases) >= self.cfg.max_offset_slots:
            j = STATE_DIM + len(g.clocks)
            keep = np.r_[0:j, j + BIAS_DIM:len(x)]
            x, P = x[keep], P[np.ix_(keep, keep)]
            del biases[0]
        n = len(x)
        x = np.concatenate([x, np.zeros(BIAS_DIM)])
        Pn = np.zeros((n + BIAS_DIM, n + BIAS_DIM))
        Pn[:n, :n] = P
        Pn[n:, n:] = _eye(BIAS_DIM)
        return x, Pn, g._replace(biases=tuple(biases) + (fix.source,))

    # ------------------------------------------------------------------ gating
    def _fix_step(self, x, P, g: _Gate, frec: FixRecord, accel: float, t: int, t_end: int | None, step):
        """A trusted RSU's fix while tracking (nearly every fix) in one compiled call
        (toptag.fusion.kernels.fix_step) from the state at t: the prediction to it, _apply_fix's model, _gate's
        capped gate and update and _observe's drift arithmetic, and with t_end (the step's end, no fix after
        this one before it) the rest of the step (step: its dt and IMU input). Returns _advance's (x, P, gate,
        outcome, d2, flagged, ended), or None where _apply_fix decides: another mode, a flagged RSU, a gate
        that does not pass (consensus), an RSU flagged now (_distrust); the same arithmetic in steps there
        gives the same numbers."""
        fix = frec.fix
        rsu = fix.source
        rec = g.rsus.get(rsu)
        if g.mode != TRACKING or self._gate_thr == math.inf or (rec is not None and rec.flagged):
            return None
        n = len(x)
        i = STATE_DIM + g.clocks.index(rsu) if self._offsets else -1
        L = frec.bias_root if rsu in g.biases else None
        R, R_drift = self._noise(fix, L is not None)
        dt_imu, u = step if step is not None else (0.0, None)
        has_u = t_end is not None and u is not None
        drift = self._drift
        if drift is not None and self._healthy_ns >= 0:  # applied now: healthy (_observe)
            rec = self._observed_record(g, fix)
            first, w, view_first = drift.fading(rec, fix.t_ns)
            view = drift.view_bias_share > 0
            vx, vy = rec.view_xy or (math.nan, math.nan)
            prev = drift.previous(rec)
            calib = fix.calib_cov if self.cfg.drift_calibration_is_bias else None
            floors, consts = drift.constants
        else:
            drift, first, w, view_first, view, vx, vy, prev, calib = None, True, 0.0, True, False, 0.0, 0.0, None, None
            floors, consts = _NO_FLOORS, _NO_CONSTS
        XP, blk, info = kernels.fix_step(
            x, P, _NO_BIAS_ROOT if L is None else L, R, R_drift, _Z33 if calib is None else calib,
            _NO_RECORD if prev is None else prev, self._q, self._cap, floors, consts, np.array((
                s_from_ns(fix.t_ns - t) if fix.t_ns > t else 0.0, accel, i,
                -1 if L is None else self._bias_index(g, rsu),
                fix.x, fix.y, fix.yaw, self._gate_thr, self._freeze_lo(g, n), n, len(g.clocks), t_end is not None,
                s_from_ns(t_end - fix.t_ns) if t_end is not None and t_end > fix.t_ns else 0.0, dt_imu, has_u,
                u[0] if has_u else 0.0, u[2] if has_u and u[2] is not None else 0.0, has_u and u[2] is not None,
                self._freeze_lo(g, n), drift is not None, w, view, first, view_first, vx, vy), dtype=float))
        d2, passed, var_i, drift_ok, bx, by = info.tolist()
        if not passed:
            return None
        acc = None if drift is None else drift.accumulated(rec, fix.t_ns, blk, drift_ok, view, (bx, by))
        g2, flagged_now = self._observe(self._applied(g, fix, frec.arrival_ns, True), frec, None, None,
                                        None if i < 0 else var_i, None, accumulated=acc)
        if flagged_now:
            return None
        return XP[0], XP[1:], g2, FixOutcome.ACCEPTED, d2, False, t_end is not None

    def _noise(self, fix: Fix, bias_state: bool) -> tuple[np.ndarray, np.ndarray]:
        """The fix's covariance as the gate and update take it (without its calibration share when that is
        a state) and as the drift detector does (without it when it counts as the RSU's bias)."""
        calib = fix.calib_cov
        R = fix.cov if not bias_state else fix.cov - calib
        R_drift = fix.cov if calib is None or not self.cfg.drift_calibration_is_bias else fix.cov - calib
        return R, R_drift

    def _applied(self, g: _Gate, fix: Fix, arrival_ns: int | None, trusted: bool) -> _Gate:
        """The gate after applying the fix."""
        return g._replace(mode=TRACKING, last_accept_ns=fix.t_ns, consecutive=0, cands=() if trusted else g.cands,
                          last_delay_ns=None if arrival_ns is None else arrival_ns - fix.t_ns, last_source=fix.source,
                          last_trusted_ns=fix.t_ns if trusted else g.last_trusted_ns)

    def _apply_fix(self, x, P, g: _Gate, frec: FixRecord, accel: float):
        """Gate one buffered fix against the state at its capture time (its RSU's slot already in the
        state), apply it if it passes, and show it to the drift detector; returns (x, P, gate, outcome,
        d2, flagged: whether its RSU was flagged)."""
        fix = frec.fix
        rsu = fix.source
        n = len(x)
        i = STATE_DIM + g.clocks.index(rsu) if self._offsets else None
        L = frec.bias_root if rsu in g.biases else None
        # The prediction (toptag.fusion.kernels.fix_model): the pose its offset before (offsets.pose_before)
        # plus L eps with a bias block. The drift detector sees the fix against the pose (nu_pose: its bias
        # not taken out: it weighs the calibration share as a bias of its own, toptag.fusion.trust, and a
        # turn must not hide in it).
        nu_pose, nu, H, PHt, HPHt, HPHt_pose, Hd = kernels.fix_model(
            x, P, fix.pose, -1 if i is None else i, float(accel),
            -1 if L is None else self._bias_index(g, rsu), _NO_BIAS_ROOT if L is None else L)
        # the offset's share of the prediction's variance (of its covariance, Hd Hd' P[i, i]: _observe)
        off_var = np.zeros(3) if i is None else Hd * Hd * P[i, i]
        R = self._noise(fix, L is not None)[0]  # with L eps a state: the fix's noise
        rec = g.rsus.get(rsu)
        flagged = rec is not None and rec.flagged
        # A flagged RSU moves no time offset (consider states): a turned camera's bias along the track
        # would pass for a late clock, its own or, through the pose, another RSU's. Down-weighting does
        # not stop a bias that every fix repeats from adding up; the offsets keep what the RSUs that
        # agree taught them.
        offset_var = None if i is None else float(P[i, i])
        freeze = slice(STATE_DIM, n) if flagged and n > STATE_DIM else self._considered(g, n)
        x, P, g2, outcome, d2 = self._gate(x, P, g, fix, frec.arrival_ns, H, nu, R, PHt, HPHt, off_var, rec, freeze)
        if outcome is FixOutcome.REACQUIRED:
            # The filter jumps to a consensus it had rejected: every RSU's evidence was gathered against
            # the track before the jump (this fix's too), and weighed against evidence after it, it would
            # pass for a disagreement between RSUs. The detector starts afresh (flags kept).
            g2 = g2._replace(rsus=MappingProxyType({k: r.restart() for k, r in g2.rsus.items()}))
        elif outcome is not FixOutcome.UNCONFIRMED and not (g.mode == ACQUIRING and not outcome.applied):
            g2, flagged_now = self._observe(g2, frec, nu_pose, HPHt_pose, offset_var, Hd)
            if flagged_now and not flagged:
                x, P = self._distrust(x, P, i, g2.rsus[rsu], self._offset_prior(fix),
                                      None if L is None else self._bias_index(g2, rsu))
                # The others were judged against a filter that followed this RSU, and against this RSU:
                # they start afresh, earlier passes' deviations too.
                g2 = g2._replace(rsus=MappingProxyType({k: (r if k == rsu else r.restart(keep_past=False))
                                                        for k, r in g2.rsus.items()}))
        return x, P, g2, outcome, d2, flagged

    def _gate(self, x, P, g: _Gate, fix: Fix, arrival_ns, H, nu, R, PHt, HPHt, off_var, rec, freeze):
        """The gate and the update: (x, P, gate, outcome, d2). A flagged RSU's fix is gated with its
        known disagreement added to its covariance and applied with that covariance scaled
        (down-weighted), or refused; consensus uses the fix's own covariance.
        A flagged RSU's fixes are no evidence that the filter is on track: they neither join nor
        reset the consensus of rejected fixes, and the filter counts as starving (open to that
        consensus) from the last fix of an RSU not flagged. So when the filter was following the
        camera now flagged, the other RSUs, once they agree, take it back (a majority wins)."""
        rsu = fix.source
        R_gate = R  # the fix's noise covariance (without its calibration share when that is a state)
        trusted = rec is None or not rec.flagged
        if not trusted:
            if self.cfg.flagged_policy == "refuse":
                return x, P, g, FixOutcome.REFUSED_FLAGGED, float("nan")
            m = rec.disagreement()
            R_gate = R + np.outer(m, m)
            R = self.cfg.flagged_cov_scale * R_gate
        applied = self._applied(g, fix, arrival_ns, trusted)
        S = HPHt + R
        if self._gate_thr == math.inf:
            x, P = self._kalman(x, P, H, nu, R, PHt, S, freeze)
            return x, P, applied, FixOutcome.ACCEPTED, float("nan")
        if g.mode == ACQUIRING:
            d2 = kernels.mahalanobis(HPHt + R_gate, nu)
            if d2 > self._gate_thr:
                return x, P, g._replace(consecutive=g.consecutive + 1), FixOutcome.REJECTED_GATE, d2
            cand = _Cand(fix.t_ns, rsu, nu, fix.cov, np.diag(P[:3, :3]).copy())
            cands = self._window(g.cands, fix.t_ns) + (cand,)
            if self._consensus(cands, self.cfg.acquire_min_fixes, self.cfg.acquire_min_sources):
                x, P = self._kalman(x, P, H, nu, R, PHt, S, freeze)
                return x, P, applied, FixOutcome.ACCEPTED, d2
            return x, P, g._replace(cands=cands), FixOutcome.UNCONFIRMED, d2
        # tracking: the filter's own pose covariance is capped inside S (the offset's share is not)
        d2 = kernels.capped_d2(HPHt, R_gate, self._cap, off_var, nu)
        if d2 <= self._gate_thr:
            x, P = self._kalman(x, P, H, nu, R, PHt, S, freeze)
            return x, P, applied, FixOutcome.ACCEPTED, d2
        if not trusted:
            return x, P, g._replace(consecutive=g.consecutive + 1), FixOutcome.REJECTED_GATE, d2
        cand = _Cand(fix.t_ns, rsu, nu, fix.cov, np.diag(P[:3, :3]).copy())
        cands = self._window(g.cands, fix.t_ns) + (cand,)
        starving = g.last_trusted_ns is None or \
            fix.t_ns - g.last_trusted_ns >= ns_from_s(self.cfg.reacquire_after_s)
        if starving and self._consensus(cands, self.cfg.reacquire_min_fixes, self.cfg.reacquire_min_sources):
            P = P.copy()
            P[:3, :3] += np.diag(nu * nu)
            x, P = self._kalman(x, P, H, nu, R, freeze=freeze)
            return x, P, applied, FixOutcome.REACQUIRED, d2
        return x, P, g._replace(consecutive=g.consecutive + 1, cands=cands), FixOutcome.REJECTED_GATE, d2

    def _observe(self, g: _Gate, frec: FixRecord, nu, HPHt, offset_var, Hd, accumulated=None) -> tuple[_Gate, bool]:
        """The drift detector takes the fix's innovation (against the filter before the update, with
        the fix's own covariance: a down-weighting does not hide the disagreement) while the filter
        is healthy; returns the gate and whether the RSU is flagged now. What every fix of the RSU
        shares is its constant bias (toptag.fusion.trust), not noise: the fix's calibration share, and
        for a flagged RSU what its held time offset's uncertainty implies (along the track: Hd Hd' times
        its variance, offset_var; Hd: the prediction's derivative by the offset). accumulated: the RSU's
        record with the innovation taken already (kernels.fix_step)."""
        fix = frec.fix
        rsu = fix.source
        rec = self._observed_record(g, fix)
        rsus = dict(g.rsus)
        healthy = g.mode == TRACKING and g.last_accept_ns is not None and \
            fix.t_ns - g.last_accept_ns <= self._healthy_ns
        if self._drift is not None and healthy:
            if accumulated is None:
                calib = fix.calib_cov if self.cfg.drift_calibration_is_bias else None
                R = self._noise(fix, False)[1]
                # A flagged RSU's offset is held at its prior: what that implies is a constant bias of its
                # fixes (else it could not clear). Unflagged, the offset is learnt from them, and no flag is
                # raised while it is uncertain (drift_max_offset_sigma_ms).
                off_cov = np.outer(Hd, Hd) * offset_var if rec.flagged and offset_var is not None else None
                shares = [b for b in (calib, off_cov) if b is not None]
                accumulated = self._drift.accumulate(rec, fix.t_ns, nu, HPHt + R, sum(shares) if shares else None, R,
                                                     (fix.x - nu[0], fix.y - nu[1]))
            rsus[rsu] = accumulated
            sd = 0.0 if offset_var is None else math.sqrt(max(offset_var, 0.0))
            rec = self._drift.decide(rsus, rsu, fix.t_ns, sd)
        else:
            rec = rec._replace(last_t=fix.t_ns)
        rsus[rsu] = rec
        return g._replace(rsus=MappingProxyType(rsus)), rec.flagged

    @staticmethod
    def _observed_record(g: _Gate, fix: Fix) -> RsuRecord:
        """The record of the fix's RSU as the drift detector takes the fix: new for an RSU not seen before,
        with its clock flag as the fix says, and started afresh for a calibration other than its fixes' before."""
        rec = g.rsus.get(fix.source) or RsuRecord(last_t=fix.t_ns, clock_known=fix.clock_bound_ns is not None,
                                                  calib_id=fix.calib_id)
        known = fix.clock_bound_ns is not None
        if rec.clock_known != known:  # a NamedTuple copy only when it changes
            rec = rec._replace(clock_known=known)
        if rec.calib_id != fix.calib_id:  # recalibrated: what was learnt of the old calibration goes
            rec = rec.recalibrated(fix.calib_id)
        return rec

    @staticmethod
    def _distrust(x, P, i: int | None, rec: RsuRecord, prior_var: float, j: int | None = None):
        """What the filter took from a newly flagged RSU is suspect. Its pose is widened by the other
        RSUs' mean disagreement with it (large when the filter followed the flagged one, e.g. from
        its start), so that they can pull it back; the RSU's time offset goes back to its prior (0,
        its correlations dropped): its fixes' bias along the track passed for a clock offset (a turned
        camera's reads as tens of ms), and no earlier value is known to be free of it. While it is
        flagged that variance widens its innovations along the track, the offset is held and not
        reported (rsu_assessments), and once cleared it is learnt again from the prior. Its calibration
        bias (block at j) goes back to its prior too: it took up part of the turn."""
        x, P = x.copy(), P.copy()
        if rec.others_mean is not None:
            P[:3, :3] += np.diag(rec.others_mean ** 2)
        if i is not None:
            var = max(float(P[i, i]), prior_var)
            x[i] = 0.0
            P[i, :] = 0.0
            P[:, i] = 0.0
            P[i, i] = var
        if j is not None:
            k = slice(j, j + BIAS_DIM)
            x[k] = 0.0
            P[k, :] = 0.0
            P[:, k] = 0.0
            P[k, k] = _eye(BIAS_DIM)
        return x, P

    def _window(self, cands: tuple, t_ns: int) -> tuple:
        cut = t_ns - ns_from_s(self.cfg.reacquire_window_s)
        return tuple(c for c in cands if c.t_ns >= cut)

    def _agree(self, a: _Cand, b: _Cand) -> bool:
        """Two refused fixes tell the same story: equal innovations within fix noise, the filter's
        drift between their times and `consensus_sigma` (chi-square, `consensus_probability`)."""
        d = a.nu - b.nu
        d[2] = wrap_angle(d[2])
        C = a.R + b.R + np.diag(self._cons_var + np.abs(a.p_diag - b.p_diag))
        return float(d @ np.linalg.solve(C, d)) <= self._cons_thr

    def _consensus(self, cands: tuple, min_fixes: int, min_sources: int) -> bool:
        """Is the newest candidate part of a group of >= min_fixes mutually agreeing candidates from
        >= min_sources sources? (Greedy clique: candidates agreeing with the newest, nearest first,
        each kept only if it agrees with every one kept before.)"""
        if len(cands) < min_fixes:
            return False
        new = cands[-1]
        near = [c for c in cands[:-1] if self._agree(new, c)]
        if len(near) + 1 < min_fixes:
            return False
        near.sort(key=lambda c: float(np.sum((c.nu - new.nu) ** 2)))
        group = [new]
        for c in near:
            if all(self._agree(c, m) for m in group[1:]):
                group.append(c)
        return len(group) >= min_fixes and len({c.source for c in group}) >= min_sources

    # ------------------------------------------------------------------ output
    def _fused(self, t_ns: int, x, P, g: _Gate, extrap_ns: int) -> FusedState:
        c = self.cfg
        since = math.inf if g.last_accept_ns is None else s_from_ns(t_ns - g.last_accept_ns)
        a, b, c2 = float(P[0, 0]), float(P[1, 0]), float(P[1, 1])  # the larger eigenvalue of P[:2, :2] (lower half)
        pos_sigma = math.sqrt(max(0.5 * (a + c2) + math.sqrt(0.25 * (a - c2) ** 2 + b * b), 0.0))
        yaw_sigma = float(math.sqrt(max(P[ST_YAW, ST_YAW], 0.0)))
        if g.mode == ACQUIRING:
            status = "acquiring"
        elif since > c.lost_after_s or pos_sigma > c.lost_pos_sigma:
            status = "lost"
        elif since > c.degraded_after_s or pos_sigma > c.degraded_pos_sigma:
            status = "degraded"
        else:
            status = "ok"
        _, flagged_fixes, (accepted, rejected, too_old, future, other) = self._totals()
        delay = math.nan if g.last_delay_ns is None else s_from_ns(g.last_delay_ns)
        rx = math.nan if self._last_rx_delay_ns is None else s_from_ns(self._last_rx_delay_ns)
        health = Health(status, since, delay, g.last_source, rx, rejected, g.consecutive, accepted,
                        pos_sigma, yaw_sigma, s_from_ns(extrap_ns), too_old=too_old, future=future,
                        from_flagged_rsu=flagged_fixes, unknown_clock=self._unknown_clock, other=other,
                        flagged_rsus=tuple(sorted(k for k, r in g.rsus.items() if r.flagged)))
        n = STATE_DIM
        return FusedState(t_ns, *x[:n].tolist(), P[:3, :3].copy(), P[:n, :n].copy(), health)  # its fields: STATE_NAMES

    # ------------------------------------------------------------------ per RSU
    def rsu_assessments(self) -> dict[str, RsuAssessment]:
        """Every RSU the filter has heard from (since it started, or remembered from a previous filter),
        as it stands at the newest step: its time offset and sigma (None if it never had a slot), its
        drift flag and disagreement, its fixes' final outcomes. Empty before start-up."""
        if not self._steps:
            return {}
        self._ensure_clean()
        head = self._steps[-1]
        g = head.g
        per_src = self.counters()["per_source"]
        out = {}
        for rsu, rec in sorted(g.rsus.items()):
            if rec.flagged:  # excluded: its offset is held at its prior, not an estimate
                off = var = None
            elif rsu in g.clocks:
                off, var = _slot_offset(head, rsu)
            elif rec.offset is not None:
                off, var = self._remembered_offset(rec, head.t)
            else:
                off = var = None
            d, C, stat = rec.disagreement(), rec.bias()[1], rec.statistic()
            if rec.flagged_by == "change" and rec.change is not None:  # how far it moved from its own long run
                d, stat = rec.change, rec.change_stat
            out[rsu] = RsuAssessment(
                rsu, off, None if var is None else math.sqrt(max(var, 0.0)), rec.clock_known, rec.flagged,
                rec.flagged_since, (float(d[0]), float(d[1]), float(d[2])),
                tuple(float(math.sqrt(max(v, 0.0))) for v in np.diag(C)), float(stat), int(rec.last_t),
                dict(per_src.get(rsu, {})), self.cfg.flagged_policy, rec.flagged_by)
        return out

    def _remembered_offset(self, rec: RsuRecord, t_ns: int) -> tuple[float, float]:
        """An RSU's offset as remembered outside a slot, its variance grown by the walk since then."""
        off, var = rec.offset
        return off, var + self._q_d * max(0.0, s_from_ns(t_ns - rec.offset_t))

    def memory(self) -> dict[str, RsuRecord]:
        """What a new filter for the same bus may start from (BusFilter(config, memory=...)): every
        RSU's record with its time offset and flag (and a flagged RSU's disagreement) as they stand at
        the newest step, and each RSU's deviation from the others in this filter, added to the earlier
        passes' (the filter's error cancels in it). Not the innovations: they are against this filter,
        whose errors the next one does not share (e.g. the pull of a turned camera it followed before
        flagging it); weighed against the next filter's, they would pass for a disagreement between RSUs."""
        if not self._steps:
            return dict(self._memory)
        self._ensure_clean()
        head = self._steps[-1]
        out = {}
        for rsu, rec in head.g.rsus.items():
            if rsu in head.g.clocks:
                rec = rec._replace(offset=_slot_offset(head, rsu), offset_t=head.t)
            out[rsu] = rec.restart() if self._drift is None else self._drift.carry(rec)
        return out


def _slot_offset(step, rsu: str) -> tuple[float, float]:
    """An RSU's time offset and its variance from its slot in a step's state."""
    i = STATE_DIM + step.g.clocks.index(rsu)
    return float(step.x[i]), float(step.P[i, i])


class _StepTimes:
    """A read-only sequence view of step times, for bisect."""
    __slots__ = ("_s",)

    def __init__(self, steps):
        self._s = steps

    def __len__(self):
        return len(self._s)

    def __getitem__(self, i):
        return self._s[i].t


__all__ = ["BusFilter", "FilterConfig", "FixOutcome"]
