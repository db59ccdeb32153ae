"""`toptag eval fusion`: the bus filter against latency, clock offsets and drifted cameras, on the
simulator's truth.

A bus drives a route through the SPEC intersection at 30 km/h (sim.motion; default a left turn; several
routes, comma-separated, are driven in turn by the runs). Its IMU / wheel odometry is synthesised at
100 Hz (sim.motion.ImuModel). Corner RSUs at (±9, ±9, 8) send pose fixes at 10 Hz each while the bus
is within `range_m` of them, with the error model below, and every fix reaches the bus `latency +
jitter` later (delay = max(0, latency + N(0, jitter)), so fixes also arrive out of order).

Four estimators see the same data:
  fused           toptag.fusion.filter.BusFilter: each fix applied at its capture time, buffer re-propagated,
                  every RSU's time offset estimated, drifted cameras flagged
  plain           the same filter with offsets taken as zero and no drift detection (the filter before
                  issue 13; run only when faults are injected)
  naive           the same EKF, each fix applied on arrival as if it were current (no gate)
  dead reckoning  the same EKF from the true initial pose, IMU / odometry only

Fix error model (results.json `setup.fix_error_model` says which one a run used):
  view (the default, `LIVE_VIEW_ERROR`): as the live RSU pipeline's fixes on the demo's rendered frames,
       fitted by `toptag eval livefix` (docs/time-and-trust.md): sigmas by the bus's horizontal range from
       the RSU (0.4 cm / 0.04 deg near, 2 cm / 0.09 deg at 18 m, 5 cm / 0.2 deg at 22 m), 1.3x larger along
       the line of sight; a share `view_share` of each fix's error variance is one process per RSU that
       correlates as exp(-distance the bus drove / `view_corr_m`) (a standing bus's fixes share it; a
       moving bus's decorrelate within metres), the rest independent between fixes. The bus filter runs
       with its own drift settings (STUDY_VIEW_SETTINGS: only the change test on, for --passes).
  white (`--fix-errors white`, the study's model until 2026-11-23's sixth session): position sigma 3 cm
       at the RSU growing linearly to 5 cm at `range_m`, 1.3x larger along the line of sight; yaw sigma
       0.1 -> 0.2 deg; independent between fixes. The filter runs with STUDY_DRIFT_THRESHOLDS.
Either way the reported covariance is exactly the covariance of a fix's error. Fixes are made while the bus
is within `range_m` (22 m) of the RSU. Healthy RSUs stamp with a disciplined clock (a 1 ms bound,
chrony-grade).
Calibration error (`--calib-deg DEG --calib-cm CM`, default 0: none): each RSU's camera really stands
off its surveyed pose by a draw of sim.image_model.perturb_camera (DEG per camera axis, CM per world
axis; one draw per RSU and run), so its every fix carries the same bias (sim.faults.seen_pose), and
each fix states it as issue 12 wants: its covariance gains J Sigma_c J', J the pose's sensitivity to
the camera's pose (finite differences of seen_pose, roof plane at the bus's height), and `calib_cov`
says which share that is (toptag.fusion.trust weighs it as a constant bias).

Faults (sim.faults, per RSU): `--clock-offset-ms RSU=MS` (its clock is off and says it is not
disciplined), `--capture-latency-ms RSU=MS` (stamped on arrival of the frame), `--drift-deg
RSU=DEG[@T[/RAMP]]` (its camera turns by DEG about the vertical at T s, or over RAMP s from T; the
RSU keeps its surveyed camera, so its fixes turn the other way about its pole: sim.faults.seen_pose).
With faults, every latency is run twice on the same noise (common random numbers): fault-free and
faulted; results.json holds both cases and their ratios.

Passes (`--passes N`, default 1): each run is N passes of the same bus through the intersection (the
routes in turn), `--pass-gap-s` apart, seen by the same cameras (one calibration draw per run); each
pass's filter starts from what the last one learnt (BusFilter(memory=...), as a bus agent does), so the
drift detector has each RSU's long-run deviation from the others to compare a pass with (the change
test, toptag.fusion.trust). Times of faults and flags count from the run's start (its first pass).

Writes DIR/results.json and the plots (fusion_error_vs_latency.png, fusion_trajectory_error.png,
fusion_nees.png; with faults also fusion_offsets.png and fusion_drift.png).
Run: `python -m sim.studies.fusion --out DIR` (or `toptag eval fusion`).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from sim.faults import RsuFault, describe, faults_from_options, seen_pose, turned
from sim.image_model import ImageModel, perturb_camera
from sim.motion import DEFAULT_T0_NS, ImuModel, ImuSamples, Trajectory, bus_trajectory
from sim.scene import rsu_camera, rsu_mounts
from sim.studies import require_plotting
from toptag.errors import InputError, SetupError, report
from toptag.camera import Camera
from toptag.fix import Fix
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.fusion.outcomes import applied_count
from toptag.geometry import rodrigues, wrap_angle
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.progress import Progress
from toptag.units import NS_PER_MS, ns_from_ms, ns_from_s, s_from_ns

DEFAULT_LATENCIES_MS = (0, 50, 100, 200, 300)
ROUTES = ("left", "right", "straight", "stop")
HEALTHY_CLOCK_BOUND_NS = NS_PER_MS  # a chrony-disciplined RSU on the intersection's LAN
BUS_ROOF_Z = 3.0
TRUST_HZ = 5.0  # how often the fused filter's per-RSU assessments are sampled
OFFSET_TOLERANCE_MS = 3.0
FLAG_WITHIN_S = 10.0

# The drift thresholds for this study's white fix model (`--fix-errors white`), whose fixes carry no
# per-RSU bias but the calibration error they state (FixErrorModel.calib_*) and whose noise is independent
# between fixes: no bias floor and no view-dependent error, where the filter's defaults allow for the live
# RSU pipeline's (its own per-RSU bias, toptag eval livefix; its fixes from one part of the view erring
# alike), a minimum disagreement of 3 cm / 0.1 deg, and other RSUs compared with from 10 effective fixes (the
# filter's default until 2026-11-23's sixth session: the white study's figures are reproduced as they were).
# Its covariances are honest, so the change test (an RSU against its own long run over the passes, off in the
# filter's defaults) is on, with a day's memory.
STUDY_DRIFT_THRESHOLDS = {"drift_min_pos_m": 0.03, "drift_min_yaw_deg": 0.1,
                          "drift_bias_sigma_m": 0.0, "drift_bias_sigma_deg": 0.0,
                          "drift_view_bias_share": 0.0, "drift_min_other_fixes": 10.0,
                          "drift_baseline_window_s": 86400.0}
# With the view-dependent fix errors (the default model) the study runs the bus filter's own drift
# settings, as a bus does; only the change test is on (it needs passes, --passes).
STUDY_VIEW_SETTINGS = {"drift_baseline_window_s": 86400.0}
# The live RSU pipeline's fix errors on the demo's rendered frames, fitted by `toptag eval livefix --bus
# bus-17,bus-42 --seconds 120` (docs/time-and-trust.md, "The study's fixes, fitted to the live pipeline"):
# the share of a fix's error variance that is view-dependent and the distance driven over which it
# decorrelates (view_correlation.fit.all: 0.58, 6.35 m), and the size of the errors by range from the
# camera (size_by_range, stated sigmas, z-RMS ~1: position per axis / 1.15 for the line-of-sight factor;
# yaw): 0.4 cm / 0.04 deg up to ~12 m, 0.7 cm / 0.04 deg at 12-16 m, 2.4 cm / 0.09 deg at 16-20 m,
# 5.5 cm / 0.21 deg at 20-24 m.
LIVE_VIEW_ERROR = {"view_share": 0.58, "view_corr_m": 6.35,
                   "profile": ((0.0, 0.0036, 0.04), (10.0, 0.0036, 0.035), (14.0, 0.0065, 0.04),
                               (18.0, 0.021, 0.09), (22.0, 0.048, 0.21))}


@dataclass(frozen=True)
class FixErrorModel:
    """Noise of RSU pose fixes (see the module docstring)."""
    rate_hz: float = 10.0
    range_m: float = 22.0
    pos_sigma_near: float = 0.03
    pos_sigma_far: float = 0.05
    yaw_sigma_near_deg: float = 0.1
    yaw_sigma_far_deg: float = 0.2
    along_sight: float = 1.3  # sigma multiplier along the RSU's line of sight
    calib_rot_sigma_deg: float = 0.0  # each camera's calibration error per camera axis (one draw per run)
    calib_trans_sigma: float = 0.0  # and of its centre per world axis, m
    # the share of each fix's error variance that is view-dependent: one process per RSU, correlating as
    # exp(-distance driven / view_corr_m) between its fixes (0: every error independent, "white")
    view_share: float = 0.0
    view_corr_m: float = 4.0
    # sigmas by range instead of the linear near/far ones: ((range m, position sigma m, yaw sigma deg), ...),
    # interpolated linearly (None: pos_sigma_near/far, yaw_sigma_near/far_deg)
    profile: tuple[tuple[float, float, float], ...] | None = None

    def describe(self) -> str:
        """One line: which error model the fixes were drawn with."""
        noise = (f"{100 * self.pos_sigma_near:g}-{100 * self.pos_sigma_far:g} cm, "
                 f"{self.yaw_sigma_near_deg:g}-{self.yaw_sigma_far_deg:g} deg") if self.profile is None else \
            "sigmas by range " + ", ".join(f"{r:g} m {100 * p:.2g} cm / {y:g} deg" for r, p, y in self.profile)
        kind = "white" if self.view_share <= 0 else \
            f"{100 * self.view_share:.0f} % of each fix's variance view-dependent over {self.view_corr_m:g} m driven"
        calib = f"; calibration error {self.calib_rot_sigma_deg:g} deg / {100 * self.calib_trans_sigma:g} cm" \
            if self.calibrated else ""
        return f"study fixes {noise}, {kind}{calib}"

    @property
    def calibrated(self) -> bool:
        """Do the cameras carry a calibration error (and their fixes state it)?"""
        return self.calib_rot_sigma_deg > 0 or self.calib_trans_sigma > 0

    def calibration_covariance(self) -> np.ndarray:
        """6x6 over (rotation about the camera axes, rad; centre, m): the camera file's convention."""
        return np.diag([math.radians(self.calib_rot_sigma_deg) ** 2] * 3 + [self.calib_trans_sigma ** 2] * 3)

    def covariance(self, bus_xy: np.ndarray, rsu_xy: np.ndarray) -> np.ndarray:
        d_vec = bus_xy - rsu_xy
        d = float(np.hypot(*d_vec))
        if self.profile is not None:
            rr, ps, ys = zip(*self.profile)
            s, sy = float(np.interp(d, rr, ps)), math.radians(float(np.interp(d, rr, ys)))
        else:
            r = min(d / self.range_m, 1.0)
            s = self.pos_sigma_near + (self.pos_sigma_far - self.pos_sigma_near) * r
            sy = math.radians(self.yaw_sigma_near_deg + (self.yaw_sigma_far_deg - self.yaw_sigma_near_deg) * r)
        e = d_vec / d if d > 1e-9 else np.array([1.0, 0.0])
        C2 = s * s * (np.eye(2) + (self.along_sight ** 2 - 1) * np.outer(e, e))
        C = np.zeros((3, 3))
        C[:2, :2] = C2
        C[2, 2] = sy * sy
        return C


def draw_cameras(model: FixErrorModel, n_rsu: int, rng: np.random.Generator) -> dict[str, Camera]:
    """Where each RSU's camera really stands: its surveyed pose off by one draw of its calibration error."""
    im = ImageModel.ideal(calib_rot_sigma_deg=model.calib_rot_sigma_deg, calib_trans_sigma=model.calib_trans_sigma)
    return {m.id: perturb_camera(rsu_camera(m.id.removeprefix("rsu-")), im, rng) for m in rsu_mounts()[:n_rsu]}


def simulate_fixes(traj: Trajectory, model: FixErrorModel, n_rsu: int, rng: np.random.Generator,
                   fix_source=None, faults: dict[str, RsuFault] | None = None,
                   cameras: dict[str, Camera] | None = None, t_offset_s: float = 0.0) -> list[Fix]:
    """Capture-stamped fixes from the first n_rsu corner RSUs (no arrival time yet). A fix is made at
    each frame's exposure time; `faults` shift its stamp (clock offset + capture latency) and turn
    its pose (drift). The same rng draws are made with or without faults (common random numbers).
    `cameras`: the cameras as they really stand (draw_cameras; default: drawn here, with a calibration
    error); `t_offset_s`: the trajectory's start in the faults' time (a later pass)."""
    mounts = rsu_mounts()[:n_rsu]
    faults = faults or {}
    fixes = []
    period = 1.0 / model.rate_hz
    for m in mounts:
        fault = faults.get(m.id, RsuFault())
        calibrated = model.calibrated and fix_source is None
        surveyed = rsu_camera(m.id.removeprefix("rsu-")) if fault.drift is not None or calibrated else None
        actual = surveyed
        if calibrated and cameras is not None:
            actual = cameras[m.id]
        elif calibrated:  # drawn first, so a run's faulted and fault-free fixes share it
            actual = perturb_camera(surveyed, ImageModel.ideal(calib_rot_sigma_deg=model.calib_rot_sigma_deg,
                                                               calib_trans_sigma=model.calib_trans_sigma), rng)
        bound = HEALTHY_CLOCK_BOUND_NS if fault.clock_disciplined else None
        phase = rng.uniform(0.0, period)
        t = np.arange(phase, traj.duration, period)
        st = traj.state_at(t)
        driven = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(st.x), np.diff(st.y)))])
        view = _ViewError(model.view_share, model.view_corr_m) if model.view_share > 0 else None
        seq = 0
        for i in range(len(t)):
            bus = np.array([st.x[i], st.y[i]])
            if np.hypot(*(bus - m.position[:2])) > model.range_m:
                continue
            if fix_source is not None:
                out = fix_source(traj, float(t[i]), m, rng)
                if out is None:
                    continue
                pose, C = out
            else:
                C = model.covariance(bus, m.position[:2])
                n = np.linalg.cholesky(C) @ rng.standard_normal(3)
                if view is not None:  # the white part's share, plus the view-dependent part
                    n = math.sqrt(1.0 - view.share) * n + view.draw(C, float(driven[i]), rng)
                seen = (st.x[i], st.y[i], st.yaw[i])
                camera = actual
                if fault.drift is not None:
                    yaw, pitch = fault.drift.angles(float(t[i]) + t_offset_s)
                    camera = turned(actual, yaw, pitch)
                if camera is not surveyed:
                    seen = seen_pose(surveyed, camera, *seen, BUS_ROOF_Z)
                if calibrated:
                    calib = calibration_share(surveyed, (st.x[i], st.y[i], st.yaw[i]), model.calibration_covariance())
                    C = C + calib
                if not (all(map(math.isfinite, seen)) and np.all(np.isfinite(C))):
                    continue  # behind the camera: it cannot see there (the noise was drawn all the same)
                pose = (seen[0] + n[0], seen[1] + n[1], wrap_angle(seen[2] + n[2]))
            fixes.append(Fix(traj.t_ns(t[i]) + fault.time_offset_ns, pose[0], pose[1], pose[2], C, m.id, seq,
                             clock_bound_ns=bound, calib_cov=calib if calibrated else None))
            seq += 1
    fixes.sort(key=lambda f: f.t_ns)
    return fixes


class _ViewError:
    """One RSU's view-dependent fix error: u (3, unit variance per axis) an Ornstein-Uhlenbeck process in
    the distance the bus drove, so u of two fixes correlates as exp(-distance / corr_m); a fix of covariance
    C errs by sqrt(share) C^1/2 u (the symmetric root, as the drift detector takes it)."""

    def __init__(self, share: float, corr_m: float):
        self.share, self.corr_m = min(max(share, 0.0), 1.0), corr_m
        self.u: np.ndarray | None = None
        self.s = 0.0

    def draw(self, C: np.ndarray, driven_m: float, rng: np.random.Generator) -> np.ndarray:
        e = rng.standard_normal(3)
        if self.u is None:
            self.u = e
        else:
            rho = math.exp(-abs(driven_m - self.s) / self.corr_m)
            self.u = rho * self.u + math.sqrt(max(0.0, 1.0 - rho * rho)) * e
        self.s = driven_m
        w, V = np.linalg.eigh(C)
        return math.sqrt(self.share) * ((V * np.sqrt(np.maximum(w, 0.0))) @ V.T) @ self.u


def calibration_share(surveyed: Camera, pose, cov6: np.ndarray) -> np.ndarray:
    """3x3 covariance of the pose (x, y, yaw) an RSU reports for a roof at `pose`, from its camera's
    calibration covariance cov6 (rotation about the camera axes, centre): J cov6 J', J by central
    differences of seen_pose."""
    J = np.zeros((3, 6))
    steps = (1e-4,) * 3 + (1e-3,) * 3
    for k, h in enumerate(steps):
        out = []
        for sgn in (1.0, -1.0):
            dv = np.zeros(6)
            dv[k] = sgn * h
            R = rodrigues(dv[:3]) @ surveyed.R
            cam = surveyed.with_extrinsics(R, -R @ (surveyed.center + dv[3:]))
            out.append(np.array(seen_pose(surveyed, cam, *pose, BUS_ROOF_Z)))
        diff = out[0] - out[1]
        diff[2] = wrap_angle(diff[2])
        J[:, k] = diff / (2 * h)
    return J @ cov6 @ J.T


@dataclass
class RunInput:
    """One Monte Carlo run's data, shared by every latency and case."""
    traj: Trajectory
    imu: ImuSamples
    fixes: list[Fix]  # fault-free
    faulted: list[Fix] | None  # the same frames with the faults (None without faults)
    run: int = 0  # the run it is a pass of
    pass_index: int = 0
    run_t0_ns: int | None = None  # the run's start (its first pass's), None: this one's

    @property
    def start_ns(self) -> int:
        return self.traj.t0_ns if self.run_t0_ns is None else self.run_t0_ns

    @property
    def t0_ns(self) -> int:
        return self.traj.t0_ns


@dataclass
class RunTrace:
    t: np.ndarray  # output times, s
    truth: np.ndarray  # (n, 3) x, y, yaw
    fused: np.ndarray  # (n, 3)
    fused_cov: np.ndarray  # (n, 3, 3)
    naive: np.ndarray
    dead: np.ndarray
    counters: dict
    delays_ms: np.ndarray
    plain: np.ndarray | None = None  # offsets not estimated, no drift detection (faulted cases)
    # the fused filter's view of each RSU, sampled at TRUST_HZ: times (s) and per RSU
    trust_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    offsets: dict = field(default_factory=dict)  # rsu -> (n, 2) offset, sigma (s; NaN before its slot)
    stats: dict = field(default_factory=dict)  # rsu -> (n,) drift statistic
    flags: dict = field(default_factory=dict)  # rsu -> [s since start at which it was flagged]
    final: dict = field(default_factory=dict)  # rsu -> RsuAssessment at the end
    plain_counters: dict | None = None  # the plain filter's outcome counts (with per_source)
    memory: dict | None = None  # what the fused filter's next pass starts from


def _feed(filters, imu_rows, arrivals, out_every: int, t_out_ns: list, on_output=None):
    """Drive filters with IMU rows and fix arrivals in time order; collect estimates every
    `out_every` IMU samples. `arrivals`: list per filter of (arrival_ns, fix) sorted by arrival."""
    outs = [[] for _ in filters]
    ptr = [0] * len(filters)
    for k, (t_ns, g, ax, ay, w) in enumerate(imu_rows):
        for j, f in enumerate(filters):
            arr = arrivals[j]
            while ptr[j] < len(arr) and arr[ptr[j]][0] < t_ns:
                f.add_fix(arr[ptr[j]][1], arrival_ns=arr[ptr[j]][0])
                ptr[j] += 1
            f.add_imu(t_ns, g, ax, ay, w)
        if k % out_every == 0:
            if len(outs[0]) == len(t_out_ns):
                t_out_ns.append(t_ns)
            for j, f in enumerate(filters):
                outs[j].append(f.estimate(t_ns))
        if on_output is not None:
            on_output(k, t_ns)
    return outs


def _pose_array(ests) -> tuple[np.ndarray, np.ndarray]:
    xs = np.full((len(ests), 3), np.nan)
    covs = np.full((len(ests), 3, 3), np.nan)
    for i, e in enumerate(ests):
        if e is not None:
            xs[i] = (e.x, e.y, e.yaw)
            covs[i] = e.cov
    return xs, covs


class _TrustLog:
    """Samples the fused filter's per-RSU assessments (offsets, drift statistics, flags)."""

    def __init__(self, flt: BusFilter, t0_ns: int, every: int):
        self.flt, self.t0_ns, self.every = flt, t0_ns, every
        self.t: list[float] = []
        self.rows: list[dict] = []
        self.flags: dict[str, list[float]] = {}
        self._since: dict[str, int | None] = {}

    def __call__(self, k: int, t_ns: int) -> None:
        if k % self.every or not self.flt.initialized:
            return
        a = self.flt.rsu_assessments()
        self.t.append(s_from_ns(t_ns - self.t0_ns))
        self.rows.append(a)
        for rsu, v in a.items():
            if v.flagged_since_ns is not None and v.flagged_since_ns != self._since.get(rsu):
                self.flags.setdefault(rsu, []).append(s_from_ns(v.flagged_since_ns - self.t0_ns))
            self._since[rsu] = v.flagged_since_ns

    def series(self):
        rsus = sorted({r for row in self.rows for r in row})
        offsets = {r: np.full((len(self.rows), 2), np.nan) for r in rsus}
        stats = {r: np.full(len(self.rows), np.nan) for r in rsus}
        for i, row in enumerate(self.rows):
            for r, v in row.items():
                if v.offset_s is not None:
                    offsets[r][i] = (v.offset_s, v.offset_sigma_s)
                stats[r][i] = v.statistic
        return np.asarray(self.t), offsets, stats


def fix_arrivals(fixes: list[Fix], delays_ms: np.ndarray, faults: dict[str, RsuFault]) -> list[tuple[int, Fix]]:
    """(arrival on the bus's clock, fix): a fix leaves the RSU when the frame has arrived (exposure +
    capture latency = stamp - clock offset) and travels delay ms."""
    out = []
    for f, d in zip(fixes, delays_ms):
        clock_ns = ns_from_ms(faults[f.source].clock_offset_ms) if f.source in faults else 0
        out.append((f.t_ns - clock_ns + ns_from_ms(d), f))
    return sorted(out, key=lambda a: a[0])


def run_once(inp: RunInput, fixes: list[Fix], latency_ms: float, jitter_ms: float, rng: np.random.Generator,
             cfg: FilterConfig, dead: np.ndarray | None, faults: dict[str, RsuFault] | None = None,
             plain: bool = False, out_hz: float = 50.0, memory: dict | None = None) -> RunTrace:
    traj, imu = inp.traj, inp.imu
    faults = faults or {}
    delays = np.maximum(0.0, latency_ms + jitter_ms * rng.standard_normal(len(fixes)))
    arrivals = fix_arrivals(fixes, delays, faults)
    naive_arr = [(a, f.replace(t_ns=a)) for a, f in arrivals]
    fused = BusFilter(cfg, memory=memory)
    naive = BusFilter(cfg.model_copy(update={"gate_probability": None, "time_offsets": False,
                                             "drift_detection": False}))
    filters, arr = [fused, naive], [arrivals, naive_arr]
    if plain:
        filters.append(BusFilter(cfg.model_copy(update={"time_offsets": False, "drift_detection": False})))
        arr.append(arrivals)
    st0 = traj.state_at(0.0)
    if dead is None:
        dr = BusFilter(cfg)
        dr.initialize(traj.t0_ns, st0.x, st0.y, st0.yaw, pos_sigma=0.01, yaw_sigma=math.radians(0.1),
                      speed=imu.wheel_speed[0], speed_sigma=0.1, trusted=True)
        filters.append(dr)
        arr.append([])
    rate = 1.0 / float(np.median(np.diff(imu.t)))
    every = max(1, int(round(rate / out_hz)))
    trust = _TrustLog(fused, inp.start_ns, max(1, int(round(rate / TRUST_HZ))))
    t_out: list[int] = []
    outs = _feed(filters, imu.rows(), arr, every, t_out, trust)
    t = traj.seconds(np.array(t_out))
    st = traj.state_at(t)
    truth = np.stack([st.x, st.y, st.yaw], axis=1)
    fx, fc = _pose_array(outs[0])
    nx, _ = _pose_array(outs[1])
    px = _pose_array(outs[2])[0] if plain else None
    dx = _pose_array(outs[-1])[0] if dead is None else dead
    tt, offsets, stats = trust.series()
    return RunTrace(t, truth, fx, fc, nx, dx, fused.counters(), delays, px, tt, offsets, stats, trust.flags,
                    fused.rsu_assessments(), filters[2].counters() if plain else None, fused.memory())


def _errors(est: np.ndarray, truth: np.ndarray):
    e = est - truth
    e[:, 2] = wrap_arr(e[:, 2])
    return e


def wrap_arr(a):
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


def _rms(v):
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if len(v) else float("nan")


def study_config(fix_model: FixErrorModel, overrides: dict | None = None) -> FilterConfig:
    """The bus filter the study runs: on view-dependent fixes the filter's own drift settings (the change
    test on), on white fixes STUDY_DRIFT_THRESHOLDS; `overrides` on top."""
    base = STUDY_VIEW_SETTINGS if fix_model.view_share > 0 else STUDY_DRIFT_THRESHOLDS
    return FilterConfig(**(base | (overrides or {})))


def _inputs(routes, speed, runs, seed, imu_model, fix_model, n_rsu, fix_source, faults, passes: int = 1,
            gap_s: float = 60.0) -> list[RunInput]:
    """Each run's route (cycling through `routes`), IMU and fixes (with and without faults, same noise);
    with passes > 1, each run's passes in turn."""
    ss = np.random.SeedSequence(seed)
    if passes > 1:
        return [p for r, s in enumerate(ss.spawn(runs))
                for p in _passes(r, s, routes, speed, seed, imu_model, fix_model, n_rsu, fix_source, faults, passes,
                                 gap_s)]
    out = []
    for r, s in enumerate(ss.spawn(runs)):
        traj = bus_trajectory(routes[r % len(routes)], "w", speed=speed, seed=seed)
        g_imu, g_fix = [np.random.default_rng(x) for x in s.spawn(2)]
        imu = imu_model.synthesize(traj, 0.0, traj.duration, g_imu)
        state = g_fix.bit_generator.state
        fixes = simulate_fixes(traj, fix_model, n_rsu, g_fix, fix_source)
        faulted = None
        if faults:
            g_fix.bit_generator.state = state  # the same draws: only the faults differ
            faulted = simulate_fixes(traj, fix_model, n_rsu, g_fix, fix_source, faults)
        out.append(RunInput(traj, imu, fixes, faulted))
    return out


def _passes(r, s, routes, speed, seed, imu_model, fix_model, n_rsu, fix_source, faults, passes, gap_s) -> list[RunInput]:
    """One run of `passes` passes: the same cameras, one route after another, gap_s apart."""
    g_cam, *gens = [np.random.default_rng(x) for x in s.spawn(1 + 2 * passes)]
    cameras = draw_cameras(fix_model, n_rsu, g_cam) if fix_model.calibrated else None
    out, t0 = [], None
    for p in range(passes):
        g_imu, g_fix = gens[2 * p], gens[2 * p + 1]
        start = DEFAULT_T0_NS if t0 is None else t0
        traj = bus_trajectory(routes[(r + p) % len(routes)], "w", speed=speed, seed=seed, t0_ns=start)
        imu = imu_model.synthesize(traj, 0.0, traj.duration, g_imu)
        offset = s_from_ns(traj.t0_ns - DEFAULT_T0_NS)
        state = g_fix.bit_generator.state
        fixes = simulate_fixes(traj, fix_model, n_rsu, g_fix, fix_source, cameras=cameras, t_offset_s=offset)
        faulted = None
        if faults:
            g_fix.bit_generator.state = state
            faulted = simulate_fixes(traj, fix_model, n_rsu, g_fix, fix_source, faults, cameras=cameras,
                                     t_offset_s=offset)
        out.append(RunInput(traj, imu, fixes, faulted, r, p, DEFAULT_T0_NS))
        t0 = traj.t0_ns + ns_from_s(traj.duration + gap_s)
    return out


def run(out_dir, latencies_ms=DEFAULT_LATENCIES_MS, jitter_ms: float = 30.0, seed: int = 0, runs: int = 16,
        n_rsu: int = 4, route: str = "left", speed: float = BUS_MAX_SPEED_MPS, settle_s: float = 1.5,
        imu_model: ImuModel | None = None, fix_model: FixErrorModel | None = None,
        config: FilterConfig | None = None, fix_source=None, plots: bool = True, log=print,
        progress: bool = True, faults: dict[str, RsuFault] | None = None, passes: int = 1,
        pass_gap_s: float = 60.0) -> dict:
    """The study. Returns the results dict also written to out_dir/results.json. `route`: one of
    ROUTES, or several separated by commas (the runs drive them in turn). `plots`: True, False, or
    "trust" (only the offset and drift figures of the faulted case)."""
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    imu_model = imu_model or ImuModel()
    fix_model = fix_model or FixErrorModel(**LIVE_VIEW_ERROR)
    cfg = config or study_config(fix_model)
    faults = dict(faults or {})
    routes = [r.strip() for r in route.split(",") if r.strip()]
    rsus = [m.id for m in rsu_mounts()[:n_rsu]]
    unknown = sorted(set(faults) - set(rsus))
    if unknown:
        raise InputError(f"faults name RSUs the study does not have: {', '.join(unknown)} (RSUs: {', '.join(rsus)})")
    latencies = [float(l) for l in latencies_ms]
    inputs = _inputs(routes, speed, runs, seed, imu_model, fix_model, n_rsu, fix_source, faults, passes, pass_gap_s)
    cases = [("fault_free", False)] + ([("faulted", True)] if faults else [])
    per_case: dict[str, dict[float, list[RunTrace]]] = {c: {l: [] for l in latencies} for c, _ in cases}
    dead_cache: list[np.ndarray | None] = [None] * len(inputs)
    results: dict = {"latency_ms": {}}
    bar = Progress(len(latencies) * len(inputs) * len(cases), "toptag eval fusion") if progress else None
    for lat in latencies:
        t0 = time.perf_counter()
        for name, faulted in cases:
            memory = None
            for r, inp in enumerate(inputs):
                rng = np.random.default_rng([seed, r, int(lat * 1000)])  # same delays in both cases
                tr = run_once(inp, inp.faulted if faulted else inp.fixes, lat, jitter_ms, rng, cfg, dead_cache[r],
                              faults if faulted else None, plain=faulted, memory=memory if inp.pass_index else None)
                memory = tr.memory
                dead_cache[r] = tr.dead
                per_case[name][lat].append(tr)
                if bar:
                    bar.update(note=f"{lat:g} ms {name.replace('_', '-')}")
        res = _summarise(per_case["fault_free"][lat], inputs, settle_s, {})
        results["latency_ms"][_key(lat)] = res
        line = (f"latency {lat:5.0f} ms  jitter {jitter_ms:.0f} ms  runs {runs}: "
                f"fused {res['fused_pos_rms_m'] * 100:6.2f} cm  naive {res['naive_pos_rms_m'] * 100:7.2f} cm  "
                f"dead-reckoning {res['dead_reckoning_pos_rms_m'] * 100:7.2f} cm"
                f"  NEES {res['nees_mean']:.2f} (band {res['nees_band_95'][0]:.2f}-{res['nees_band_95'][1]:.2f})")
        if faults:
            fr = _summarise(per_case["faulted"][lat], inputs, settle_s, faults)
            fr["fused_over_fault_free"] = fr["fused_pos_rms_m"] / res["fused_pos_rms_m"]
            fr["plain_over_fault_free"] = fr["plain_pos_rms_m"] / res["fused_pos_rms_m"]
            results.setdefault("faulted", {"faults": {k: v.model_dump() for k, v in faults.items()},
                                           "description": describe(faults), "latency_ms": {}})
            results["faulted"]["latency_ms"][_key(lat)] = fr
            line += (f"\n   faulted ({describe(faults)}): fused {fr['fused_pos_rms_m'] * 100:.2f} cm "
                     f"({fr['fused_over_fault_free']:.2f}x fault-free), offsets not estimated "
                     f"{fr['plain_pos_rms_m'] * 100:.2f} cm; false flags {fr['false_flags']}")
        log(line + f"  [{time.perf_counter() - t0:.1f} s]")
    if bar:
        bar.close()
    zero = results["latency_ms"].get(_key(min(latencies)))
    for k, res in results["latency_ms"].items():
        res["fused_ratio_to_min_latency"] = res["fused_pos_rms_m"] / zero["fused_pos_rms_m"]
        res["naive_over_fused"] = res["naive_pos_rms_m"] / res["fused_pos_rms_m"]
    if "200" in results["latency_ms"] and min(latencies) == 0:
        r = results["latency_ms"]["200"]
        results["target"] = {
            "fused_200_over_fused_0": r["fused_ratio_to_min_latency"],
            "fused_200_le_1p2x_fused_0": bool(r["fused_ratio_to_min_latency"] <= 1.2),
            "naive_200_over_fused_200": r["naive_over_fused"],
            "nees_mean_in_band_all_latencies": all(
                v["nees_band_95"][0] <= v["nees_mean"] <= v["nees_band_95"][1] for v in results["latency_ms"].values()),
        }
    if faults:
        results["time_and_trust"] = _verdicts(results, faults)
    data_s = sum(inp.traj.duration for inp in inputs)
    results["setup"] = {
        "routes": routes, "route": routes[0], "speed_mps": speed, "durations_s": [inp.traj.duration for inp in inputs],
        "duration_s": inputs[0].traj.duration, "data_s_per_latency": data_s, "runs": runs, "seed": seed,
        "jitter_ms": jitter_ms, "delay_model": "max(0, latency + N(0, jitter))", "n_rsu": n_rsu, "rsus": rsus,
        "settle_s": settle_s, "output_hz": 50, "passes_per_run": passes, "pass_gap_s": pass_gap_s,
        "fix_model": "live (fix_source)" if fix_source else asdict(fix_model), "imu_model": asdict(imu_model),
        "fix_error_model": "live RSU pipeline (fix_source)" if fix_source else fix_model.describe(),
        "healthy_clock_bound_ns": HEALTHY_CLOCK_BOUND_NS, "faults": describe(faults),
        "filter": cfg.model_dump(),
        "plain": "the same filter with time offsets taken as zero and no drift detection",
        "naive": "same EKF, each fix applied at its arrival time as if current, no gate",
        "dead_reckoning": "same EKF from the true initial pose, IMU/odometry only",
        "nees": "3-dof (x, y, yaw); band = 95% chi-square band of the run-averaged NEES at one time",
    }
    results["runtime_s"] = time.perf_counter() - t_start
    if plots:
        from sim.studies.fusion_plots import plots as make_plots

        results["figures"] = make_plots(out, per_case, results, settle_s, inputs, faults, trust_only=plots == "trust")
    (out / "results.json").write_text(json.dumps(results, indent=2, default=_json_default))
    results["runtime_s"] = time.perf_counter() - t_start
    return results


def _key(lat: float) -> str:
    return str(int(lat)) if float(lat).is_integer() else str(lat)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def eval_mask(tr: RunTrace, inp: RunInput, settle_s: float) -> np.ndarray:
    """Output times evaluated: from `settle_s` after the first fix's capture."""
    first = s_from_ns(inp.fixes[0].t_ns - inp.t0_ns) if inp.fixes else 0.0
    return tr.t >= first + settle_s


def nees_series(tr: RunTrace) -> np.ndarray:
    e = _errors(tr.fused, tr.truth)
    out = np.full(len(e), np.nan)
    for i in range(len(e)):
        if np.all(np.isfinite(e[i])):
            out[i] = float(e[i] @ np.linalg.solve(tr.fused_cov[i], e[i]))
    return out


def _summarise(traces: list[RunTrace], inputs: list[RunInput], settle_s: float, faults: dict[str, RsuFault]) -> dict:
    from scipy.stats import chi2

    fpos, npos, dpos, ppos, fyaw, nyaw, nees_rows = [], [], [], [], [], [], []
    counters: dict[str, int] = {}
    delays = []
    for tr, inp in zip(traces, inputs):
        m = eval_mask(tr, inp, settle_s)
        ef, en, ed = (_errors(a, tr.truth)[m] for a in (tr.fused, tr.naive, tr.dead))
        fpos.append(np.hypot(ef[:, 0], ef[:, 1]))
        npos.append(np.hypot(en[:, 0], en[:, 1]))
        dpos.append(np.hypot(ed[:, 0], ed[:, 1]))
        if tr.plain is not None:
            ep = _errors(tr.plain, tr.truth)[m]
            ppos.append(np.hypot(ep[:, 0], ep[:, 1]))
        fyaw.append(ef[:, 2])
        nyaw.append(en[:, 2])
        nees_rows.append(nees_series(tr)[m])
        delays.append(tr.delays_ms)
        for k, v in tr.counters.items():
            if isinstance(v, int):
                counters[k] = counters.get(k, 0) + v
    n = min(len(r) for r in nees_rows)
    N = np.array([r[:n] for r in nees_rows])
    M = N.shape[0]
    avg = np.nanmean(N, axis=0)
    band = (float(chi2.ppf(0.025, 3 * M) / M), float(chi2.ppf(0.975, 3 * M) / M))
    fp = np.concatenate(fpos)
    out = {
        "fused_pos_rms_m": _rms(fp),
        "naive_pos_rms_m": _rms(np.concatenate(npos)),
        "dead_reckoning_pos_rms_m": _rms(np.concatenate(dpos)),
        "fused_pos_max_m": float(np.nanmax(fp)),
        "fused_yaw_rms_deg": math.degrees(_rms(np.concatenate(fyaw))),
        "naive_yaw_rms_deg": math.degrees(_rms(np.concatenate(nyaw))),
        "nees_mean": float(np.nanmean(np.concatenate(nees_rows))),
        "nees_band_95": band,
        "nees_frac_times_in_band": float(np.mean((avg >= band[0]) & (avg <= band[1]))),
        "nees_dof": 3,
        "n_samples": int(np.isfinite(fp).sum()),
        "delay_ms_mean": float(np.mean(np.concatenate(delays))),
        "fixes": {k: counters.get(k, 0) for k in ("fixes", "accepted", "rejected_gate", "reacquired", "initialized",
                                                  "before_start", "too_old", "future", "duplicate", "pending",
                                                  "refused_flagged", "from_flagged_rsu", "unknown_clock")},
    }
    if ppos:
        out["plain_pos_rms_m"] = _rms(np.concatenate(ppos))
    hours = sum(inp.traj.duration for inp in inputs) / 3600.0
    out.update(_trust_summary(*_by_run(traces, inputs), faults, hours))
    return out


def _in_view_s(inp: RunInput, rsu: str, after_s: float) -> float | None:
    """First exposure time (s) >= after_s of a fix of `rsu` (the bus in its view), None if none."""
    for f in inp.fixes:
        if f.source == rsu:
            t = s_from_ns(f.t_ns - inp.start_ns)
            if t >= after_s:
                return t
    return None


def _by_run(traces: list[RunTrace], inputs: list[RunInput]) -> tuple[list[RunTrace], list[RunInput]]:
    """The passes of each run as one trace and input, for the RSU figures: flags (times from the run's
    start; a flag carried into the next pass counted once), fix counts added up, the last pass's
    assessments, every pass's fixes."""
    if all(inp.run_t0_ns is None for inp in inputs):
        return traces, inputs
    runs: dict[int, list[tuple[RunTrace, RunInput]]] = {}
    for tr, inp in zip(traces, inputs):
        runs.setdefault(inp.run, []).append((tr, inp))
    out_t, out_i = [], []
    for passes in runs.values():
        flags: dict[str, list[float]] = {}
        for tr, _ in passes:
            for rsu, times in tr.flags.items():
                flags[rsu] = sorted(set(flags.get(rsu, [])) | set(times))
        last, first = passes[-1][0], passes[0][1]
        out_t.append(RunTrace(last.t, last.truth, last.fused, last.fused_cov, last.naive, last.dead,
                              _add_counters([tr.counters for tr, _ in passes]), last.delays_ms, last.plain,
                              flags=flags, final=last.final,
                              plain_counters=None if last.plain_counters is None else
                              _add_counters([tr.plain_counters for tr, _ in passes])))
        out_i.append(RunInput(first.traj, first.imu, [f for _, inp in passes for f in inp.fixes], None, first.run, 0,
                              first.start_ns))
    return out_t, out_i


def _add_counters(counters: list[dict]) -> dict:
    """Fix outcome counts of several filters, per source too."""
    out: dict = {"per_source": {}}
    for c in counters:
        for k, v in c.items():
            if isinstance(v, int):
                out[k] = out.get(k, 0) + v
        for src, d in c.get("per_source", {}).items():
            mine = out["per_source"].setdefault(src, {})
            for k, v in d.items():
                mine[k] = mine.get(k, 0) + v
    return out


def _trust_summary(traces: list[RunTrace], inputs: list[RunInput], faults: dict[str, RsuFault],
                   hours: float | None = None) -> dict:
    """Per RSU: the final offset estimates against the injected offset, drift flags and when they came,
    false flags (RSUs flagged without an injected drift)."""
    rsus = sorted({r for tr in traces for r in tr.final} | set(faults))
    offsets, flagged, used = {}, {}, {}
    false_flags = false_flag_runs = 0
    for rsu in rsus:
        fault = faults.get(rsu, RsuFault())
        injected_ms = fault.time_offset_ns / NS_PER_MS
        finals = [(1e3 * a.offset_s, 1e3 * a.offset_sigma_s) for tr in traces
                  if (a := tr.final.get(rsu)) is not None and a.offset_s is not None]
        if finals:
            est = np.array(finals)
            err = est[:, 0] - injected_ms
            offsets[rsu] = {"injected_ms": injected_ms, "final_ms_mean": float(est[:, 0].mean()),
                            "sigma_ms_mean": float(est[:, 1].mean()), "error_ms_rms": float(np.sqrt(np.mean(err ** 2))),
                            "error_ms_max": float(np.max(np.abs(err))),
                            "within_3ms": float(np.mean(np.abs(err) <= OFFSET_TOLERANCE_MS)),
                            "error_within_2_sigma": float(np.mean(np.abs(err) <= 2 * est[:, 1])),
                            "runs": len(finals), "final_ms": est[:, 0].tolist(), "sigma_ms": est[:, 1].tolist()}
        drift = fault.drift
        times = [tr.flags.get(rsu, []) for tr in traces]
        entry = {"injected": drift is not None, "runs_flagged": int(sum(bool(t) for t in times)),
                 "runs": len(traces), "flag_times_s": [t[0] if t else None for t in times]}
        if drift is not None:
            delays = []
            for t, inp in zip(times, inputs):
                view = _in_view_s(inp, rsu, drift.at_s)
                if view is None:
                    delays.append(None)
                    continue
                start = max(drift.at_s, view)
                later = [x for x in t if x >= drift.at_s - 1e-9]
                delays.append(later[0] - start if later else None)
            seen = [d for d in delays if d is not None]
            entry.update({"delay_after_in_view_s": delays,
                          "delay_s_median": float(np.median(seen)) if seen else None,
                          "delay_s_max": float(np.max(seen)) if seen else None,
                          "flagged_within_10s": float(np.mean([d is not None and d <= FLAG_WITHIN_S
                                                              for d, inp in zip(delays, inputs)]))})
        else:
            false_flags += int(sum(len(t) for t in times))
            false_flag_runs += int(sum(bool(t) for t in times))
        flagged[rsu] = entry
        used[rsu] = {"fused": _applied_fraction([tr.counters for tr in traces], rsu)}
        if traces and traces[0].plain_counters is not None:
            used[rsu]["plain"] = _applied_fraction([tr.plain_counters for tr in traces], rsu)
    if hours is None:
        hours = sum(inp.traj.duration for inp in inputs) / 3600.0
    return {"offset_estimate_ms": offsets, "drift_flagged": flagged, "fixes_applied_fraction": used,
            "false_flags": false_flags,
            "false_flag_runs": false_flag_runs, "false_flags_per_hour": false_flags / hours if hours else None,
            "hours_of_data": hours}


def _applied_fraction(counters: list[dict], rsu: str) -> float | None:
    """Share of an RSU's fixes a filter applied (accepted, re-acquired or started from), over runs."""
    applied = total = 0
    for c in counters:
        per = c.get("per_source", {}).get(rsu, {})
        total += sum(per.values())
        applied += applied_count(per)
    return applied / total if total else None


def _verdicts(results: dict, faults: dict[str, RsuFault]) -> dict:
    """The issue's figures per latency: RMS ratio, offsets within 3 ms, drift flagged within 10 s."""
    out = {}
    offset_rsus = [r for r, f in faults.items() if f.time_offset_ns]
    drift_rsus = [r for r, f in faults.items() if f.drift is not None]
    for k, fr in results["faulted"]["latency_ms"].items():
        v = {"fused_over_fault_free": fr["fused_over_fault_free"],
             "plain_over_fault_free": fr["plain_over_fault_free"], "false_flags": fr["false_flags"]}
        if offset_rsus:
            v["offsets_within_3ms_every_run"] = all(fr["offset_estimate_ms"].get(r, {}).get("within_3ms", 0) == 1.0
                                                    for r in fr["offset_estimate_ms"])
            v["fused_le_1p2x_fault_free"] = bool(fr["fused_over_fault_free"] <= 1.2)
        if drift_rsus:
            v["drift_flagged_within_10s_every_run"] = all(
                fr["drift_flagged"][r].get("flagged_within_10s", 0) == 1.0 for r in drift_rsus)
            v["fused_le_1p3x_fault_free"] = bool(fr["fused_over_fault_free"] <= 1.3)
        out[k] = v
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag eval fusion", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--latency-ms", default=",".join(str(l) for l in DEFAULT_LATENCIES_MS),
                   help="comma-separated mean latencies (default %(default)s)")
    p.add_argument("--jitter-ms", type=float, default=30.0, help="delay standard deviation (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", type=int, default=16, help="Monte Carlo runs per latency (default 16)")
    p.add_argument("--rsus", type=int, default=4, choices=(1, 2, 3, 4), help="number of corner RSUs (default 4)")
    p.add_argument("--route", default="left",
                   help=f"route, or routes separated by commas that the runs drive in turn ({', '.join(ROUTES)}; "
                        "default left)")
    p.add_argument("--clock-offset-ms", default=None, metavar="RSU=MS[,RSU=MS]",
                   help="RSU clocks that are off (and undisciplined), e.g. rsu-se=30")
    p.add_argument("--capture-latency-ms", default=None, metavar="RSU=MS[,RSU=MS]",
                   help="unmodelled capture latencies (frames stamped on arrival), e.g. rsu-ne=40")
    p.add_argument("--drift-deg", default=None, metavar="RSU=DEG[@T[/RAMP]]",
                   help="camera turns: DEG about the vertical at T s (a step) or over RAMP s from T, e.g. rsu-se=0.2@3")
    p.add_argument("--flagged", choices=("downweight", "refuse"), default=None,
                   help="what the filter does with a flagged RSU's fixes (default: the filter's, downweight)")
    p.add_argument("--calib-deg", type=float, default=0.0, metavar="DEG",
                   help="each RSU camera's calibration error per axis, deg (drawn once per RSU and run; "
                        "its fixes state it); default 0")
    p.add_argument("--calib-cm", type=float, default=0.0, metavar="CM",
                   help="each RSU camera centre's calibration error per axis, cm; default 0")
    p.add_argument("--calib-as-noise", action="store_true",
                   help="the drift detector counts a fix's calibration share as noise, as it did before weighing it "
                        "as each RSU's constant bias (for comparison)")
    p.add_argument("--calib-bias", choices=("estimate", "consider", "noise"), default=None,
                   help="how the bus filter takes a fix's calibration share: a bias state per RSU (estimate), "
                        "carried but not updated (consider), or white noise (noise, as before); default: the filter's")
    p.add_argument("--calib-bias-corr-m", type=float, default=None, metavar="M",
                   help="distance over which the filter lets an RSU's calibration bias decorrelate; default: the filter's")
    p.add_argument("--bus-config", default=None, metavar="BUS.toml",
                   help="a bus settings file (toptag bus --config): the keys of its [filter] table override the study's "
                        "(e.g. drift_baseline_window_s = 0, the change test off as in the bus's defaults)")
    p.add_argument("--passes", type=int, default=1, metavar="N",
                   help="passes per run: the same bus and cameras, each pass's filter starting from what the last "
                        "learnt (the drift detector's change test needs earlier passes); default 1")
    p.add_argument("--pass-gap-s", type=float, default=60.0, metavar="S", help="time between passes (default 60)")
    p.add_argument("--fix-errors", choices=("view", "white"), default="view",
                   help="the study's fix errors: view-dependent as the live pipeline's (view, default: "
                        f"{LIVE_VIEW_ERROR['view_share']:g} of each fix's variance shared over "
                        f"{LIVE_VIEW_ERROR['view_corr_m']:g} m driven, sigmas by range as the live pipeline's, the "
                        "bus filter's own drift settings) or independent between fixes (white: 3-5 cm, 0.1-0.2 deg, "
                        "the study's model before, with the study's former drift thresholds)")
    p.add_argument("--view-share", type=float, default=None, metavar="SHARE",
                   help="with --fix-errors view: the view-dependent share of each fix's variance (default "
                        f"{LIVE_VIEW_ERROR['view_share']:g})")
    p.add_argument("--view-corr-m", type=float, default=None, metavar="M",
                   help=f"with --fix-errors view: its correlation length, m driven (default {LIVE_VIEW_ERROR['view_corr_m']:g})")
    p.add_argument("--fixes", default="study", choices=("study", "live"),
                   help="fix error model: the study's (default) or the live pipeline")
    p.add_argument("--plots", choices=("all", "trust", "none"), default="all",
                   help="figures to write: all (default), trust (with faults: the offset and drift figures only), none")
    p.add_argument("--no-plots", action="store_true", help="the same as --plots none")
    return p


def _filter_table(path: str | None) -> dict:
    """The [filter] table of a bus settings file (only the keys it sets; {} without a file)."""
    if path is None:
        return {}
    from toptag.settings import describe_settings_error, read_settings

    table = read_settings(path).get("filter", {})
    try:
        FilterConfig(**table)
    except ValidationError as e:
        raise InputError(f"settings {path}: {describe_settings_error(e)}") from None
    return table


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    try:
        require_plotting()
    except SetupError as e:
        return report("eval fusion", e)
    if a.fixes == "live":
        return report("eval fusion", InputError("--fixes live needs the RSU image pipeline; pass "
                                                "run(fix_source=...) from Python until it is wired in"))
    try:
        lats = [float(s) for s in a.latency_ms.split(",") if s.strip()]
    except ValueError:
        return report("eval fusion", InputError(f"--latency-ms must be comma-separated numbers, "
                                                f"got {a.latency_ms!r}"))
    if not lats or min(lats) < 0:
        return report("eval fusion", InputError("latencies must be >= 0"))
    bad = [r for r in a.route.split(",") if r.strip() not in ROUTES]
    if bad or not a.route.strip():
        return report("eval fusion", InputError(f"--route: unknown route(s) {', '.join(bad) or '(none)'} "
                                                f"(one or more of {', '.join(ROUTES)})"))
    try:
        faults = faults_from_options(a.clock_offset_ms, a.capture_latency_ms, a.drift_deg)
        if a.calib_deg < 0 or a.calib_cm < 0:
            raise InputError("--calib-deg and --calib-cm must be >= 0")
        opts = {"flagged_policy": a.flagged, "calib_bias": a.calib_bias, "calib_bias_corr_m": a.calib_bias_corr_m}
        if a.calib_as_noise:
            opts["drift_calibration_is_bias"] = False
        view = {} if a.fix_errors == "white" else LIVE_VIEW_ERROR | {
            k: v for k, v in (("view_share", a.view_share), ("view_corr_m", a.view_corr_m)) if v is not None}
        if view and not (0 < view["view_share"] <= 1 and view["view_corr_m"] > 0):
            raise InputError("--view-share must be in (0, 1] and --view-corr-m > 0")
        fix_model = FixErrorModel(calib_rot_sigma_deg=a.calib_deg, calib_trans_sigma=a.calib_cm / 100, **view)
        cfg = study_config(fix_model, _filter_table(a.bus_config) | {k: v for k, v in opts.items() if v is not None})
        if a.passes < 1 or a.pass_gap_s < 0:
            raise InputError("--passes must be >= 1 and --pass-gap-s >= 0")
        plots = False if a.no_plots or a.plots == "none" else ("trust" if a.plots == "trust" and faults else True)
        if a.passes > 1:
            plots = False  # the figures draw one pass per run
        res = run(a.out, lats, a.jitter_ms, a.seed, runs=a.runs, n_rsu=a.rsus, route=a.route, plots=plots,
                  faults=faults, config=cfg, fix_model=fix_model, passes=a.passes, pass_gap_s=a.pass_gap_s)
    except InputError as e:
        return report("eval fusion", e)
    print()
    print(f"{'latency':>8} {'fused cm':>9} {'naive cm':>9} {'DR cm':>8} {'fused/0':>8} {'naive/fused':>11}"
          f" {'NEES':>6} {'band':>12} {'rejected':>8}")
    for k, r in res["latency_ms"].items():
        print(f"{k:>6}ms {r['fused_pos_rms_m'] * 100:9.2f} {r['naive_pos_rms_m'] * 100:9.2f}"
              f" {r['dead_reckoning_pos_rms_m'] * 100:8.2f} {r['fused_ratio_to_min_latency']:8.2f}"
              f" {r['naive_over_fused']:11.1f} {r['nees_mean']:6.2f}"
              f" {r['nees_band_95'][0]:5.2f}-{r['nees_band_95'][1]:5.2f} {r['fixes']['rejected_gate']:8d}")
    if "200" in res["latency_ms"]:
        r, z = res["latency_ms"]["200"], res["latency_ms"][next(iter(res["latency_ms"]))]
        ok = r["fused_pos_rms_m"] <= 1.2 * z["fused_pos_rms_m"]
        print(f"\n200 ms: fused {r['fused_pos_rms_m'] * 100:.2f} cm vs lowest-latency fused "
              f"{z['fused_pos_rms_m'] * 100:.2f} cm (ratio {r['fused_ratio_to_min_latency']:.2f}, target <= 1.2: "
              f"{'met' if ok else 'NOT met'}); naive {r['naive_pos_rms_m'] * 100:.1f} cm "
              f"({r['naive_over_fused']:.0f}x fused)")
    fault_free_flags = sum(r["false_flags"] for r in res["latency_ms"].values())
    hours = sum(r["hours_of_data"] for r in res["latency_ms"].values())
    print(f"\nfix errors: {res['setup']['fix_error_model']}")
    print(f"fault-free: {fault_free_flags} drift flags in {hours * 60:.1f} min of data")
    if faults:
        _print_faulted(res)
    print(f"wrote {Path(a.out) / 'results.json'} and {', '.join(res.get('figures', []))}; "
          f"runtime {res['runtime_s']:.1f} s")
    return 0


def _print_faulted(res: dict) -> None:
    f = res["faulted"]
    print(f"faulted: {f['description']}")
    for k, r in f["latency_ms"].items():
        print(f"  {k:>4} ms: fused {r['fused_pos_rms_m'] * 100:.2f} cm = {r['fused_over_fault_free']:.2f}x fault-free "
              f"(offsets not estimated: {r['plain_over_fault_free']:.2f}x); false flags {r['false_flags']}")
        for rsu, o in r["offset_estimate_ms"].items():
            u = r["fixes_applied_fraction"].get(rsu, {})
            share = "" if u.get("plain") is None else (f"; its fixes applied {100 * u['fused']:.0f} % "
                                                      f"(offsets not estimated: {100 * u['plain']:.0f} %)")
            print(f"     {rsu}: offset {o['final_ms_mean']:6.1f} ± {o['sigma_ms_mean']:.1f} ms (injected "
                  f"{o['injected_ms']:g}; |error| max {o['error_ms_max']:.1f} ms, within 3 ms in "
                  f"{100 * o['within_3ms']:.0f} % of runs{share})")
        for rsu, d in r["drift_flagged"].items():
            if d["injected"] or d["runs_flagged"]:
                when = "" if not d["injected"] else (f"; after the bus came into view: median "
                                                     f"{_fmt(d['delay_s_median'])} s, max {_fmt(d['delay_s_max'])} s")
                print(f"     {rsu}: drift {'injected' if d['injected'] else 'NOT injected'}, flagged in "
                      f"{d['runs_flagged']}/{d['runs']} runs{when}")
    for k, v in res["time_and_trust"].items():
        print(f"  {k} ms verdicts: {v}")


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"


if __name__ == "__main__":
    raise SystemExit(main())
