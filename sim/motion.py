"""Bus motion through the SPEC intersection: routes, speed profiles, roof bounce, truth states and a
synthetic IMU / wheel-odometry sensor.

Everything here is pure and vectorised over time. Times are seconds since the trajectory start
(`Trajectory.t0_ns` maps them to SPEC's integer nanoseconds). World frame as in SPEC.md: x east,
y north, yaw counter-clockwise from +x, wrapped to (-pi, pi]. Right-hand traffic.

Geometry
    A `Path` is a chain of segments whose curvature varies linearly with arc length (straights,
    clothoids, arcs), so curvature, heading and position are continuous. Beyond its ends a path
    continues straight, so a trajectory can be queried slightly outside its duration.
Speed
    A `SpeedProfile` is a chain of phases, each blending speed with a raised cosine: speed and
    acceleration are continuous (acceleration is zero at every phase boundary).
Roof
    `RoofBounce` is a sum of a few low-frequency sinusoids with seeded phases, |dz| <= amplitude.

Routes (`bus_trajectory(kind, approach)`): "straight", "left", "right", each optionally with a stop
at the stop line (`stop=True`) or slowed for the turn (`turn_speed`), and "stop" (straight with a
stop). `approach` is the side the bus
comes from ("w" = coming from the west, heading east; "s", "e", "n" by 90° rotations).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.scene import LANE_WIDTH, ROAD_HALF_WIDTH
from toptag.geometry import wrap_angle
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.units import NS_PER_S, s_from_ns

INNER_LANE = LANE_WIDTH / 2  # lateral offset of the inner lane centre from the road centre line
OUTER_LANE = 1.5 * LANE_WIDTH
STOP_LINE = ROAD_HALF_WIDTH + 2.0  # distance from the intersection centre of the stop line
APPROACH_YAW = {"w": 0.0, "s": np.pi / 2, "e": np.pi, "n": -np.pi / 2}  # heading when entering


_wrap = wrap_angle


def _out(a, scalar: bool):
    return float(np.asarray(a).reshape(-1)[0]) if scalar else a


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """A piece of path of `length` metres whose curvature goes linearly from k0 to k1 (1/m)."""
    length: float
    k0: float = 0.0
    k1: float | None = None  # None: constant curvature k0

    @property
    def k_end(self) -> float:
        return self.k0 if self.k1 is None else self.k1


class Path:
    """A planar curve from a start pose and a chain of linear-curvature segments.

    `pose_at(s)` -> (x, y, yaw, curvature), vectorised over arc length s. Heading and curvature are
    exact; x, y are integrated with 3-point Gauss-Legendre on a fine grid and interpolated with
    cubic Hermite (error well below a micrometre)."""

    def __init__(self, x0: float, y0: float, yaw0: float, segments: list[Segment], ds: float = 0.05):
        if not segments or any(s.length <= 0 for s in segments):
            raise ValueError("a path needs segments of positive length")
        self.x0, self.y0, self.yaw0 = float(x0), float(y0), float(yaw0)
        self.segments = list(segments)
        lengths = np.array([s.length for s in segments])
        self._s0 = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self._len = lengths
        self._k0 = np.array([s.k0 for s in segments])
        self._dk = np.array([(s.k_end - s.k0) / s.length for s in segments])
        th0 = [0.0]
        for i in range(len(segments) - 1):
            L = lengths[i]
            th0.append(th0[-1] + self._k0[i] * L + 0.5 * self._dk[i] * L * L)
        self._th0 = np.array(th0)
        self.length = float(lengths.sum())
        n = max(2, int(np.ceil(self.length / ds)) + 1)
        self._grid = np.linspace(0.0, self.length, n)
        h = self._grid[1] - self._grid[0]
        # Gauss-Legendre 3 points on each interval.
        gl_x = np.array([-np.sqrt(3 / 5), 0.0, np.sqrt(3 / 5)])
        gl_w = np.array([5 / 9, 8 / 9, 5 / 9])
        mids = (self._grid[:-1] + self._grid[1:]) / 2
        sq = mids[:, None] + gl_x[None, :] * h / 2
        th = self._heading_local(sq)
        dx = (np.cos(th) * gl_w).sum(axis=1) * h / 2
        dy = (np.sin(th) * gl_w).sum(axis=1) * h / 2
        self._gx = np.concatenate([[0.0], np.cumsum(dx)])
        self._gy = np.concatenate([[0.0], np.cumsum(dy)])
        self._gh = h
        c, s = np.cos(self.yaw0), np.sin(self.yaw0)
        self._rot = np.array([[c, -s], [s, c]])

    # heading relative to yaw0, and curvature, for s inside [0, length]
    def _seg_index(self, s):
        return np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self._len) - 1)

    def _heading_local(self, s):
        s = np.clip(s, 0.0, self.length)
        i = self._seg_index(s)
        u = s - self._s0[i]
        return self._th0[i] + self._k0[i] * u + 0.5 * self._dk[i] * u * u

    def curvature(self, s):
        s = np.asarray(s, dtype=float)
        inside = (s >= 0) & (s <= self.length)
        sc = np.clip(s, 0.0, self.length)
        i = self._seg_index(sc)
        k = self._k0[i] + self._dk[i] * (sc - self._s0[i])
        return np.where(inside, k, 0.0)

    def curvature_rate(self, s):
        """d curvature / ds."""
        s = np.asarray(s, dtype=float)
        inside = (s >= 0) & (s <= self.length)
        return np.where(inside, self._dk[self._seg_index(np.clip(s, 0.0, self.length))], 0.0)

    def pose_at(self, s):
        """World (x, y, yaw, curvature) at arc length s (scalar or array)."""
        scalar = np.ndim(s) == 0
        s = np.atleast_1d(np.asarray(s, dtype=float))
        sc = np.clip(s, 0.0, self.length)
        th = self._heading_local(sc)
        # cubic Hermite on the grid with exact derivatives (cos th, sin th)
        j = np.clip(np.floor(sc / self._gh).astype(int), 0, len(self._grid) - 2)
        h = self._gh
        u = (sc - self._grid[j]) / h
        tha, thb = self._heading_local(self._grid[j]), self._heading_local(self._grid[j + 1])
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        lx = h00 * self._gx[j] + h10 * h * np.cos(tha) + h01 * self._gx[j + 1] + h11 * h * np.cos(thb)
        ly = h00 * self._gy[j] + h10 * h * np.sin(tha) + h01 * self._gy[j + 1] + h11 * h * np.sin(thb)
        # straight continuation outside [0, length]
        extra = s - sc
        lx = lx + extra * np.cos(th)
        ly = ly + extra * np.sin(th)
        wx = self.x0 + self._rot[0, 0] * lx + self._rot[0, 1] * ly
        wy = self.y0 + self._rot[1, 0] * lx + self._rot[1, 1] * ly
        yaw = _wrap(self.yaw0 + th)
        k = self.curvature(s)
        return _out(wx, scalar), _out(wy, scalar), _out(yaw, scalar), _out(k, scalar)

    @property
    def end_pose(self) -> tuple[float, float, float]:
        x, y, yaw, _ = self.pose_at(self.length)
        return x, y, yaw

    def rotated(self, angle: float) -> "Path":
        """The same path turned by `angle` about the world origin."""
        c, s = np.cos(angle), np.sin(angle)
        return Path(c * self.x0 - s * self.y0, s * self.x0 + c * self.y0, float(_wrap(self.yaw0 + angle)),
                    self.segments, ds=self._gh)


def turn_segments(angle: float, radius: float, transition: float) -> list[Segment]:
    """Clothoid in, arc, clothoid out turning by `angle` (rad, + = left) at minimum `radius` with
    clothoids of length `transition` (continuous curvature)."""
    k = np.sign(angle) / radius
    arc = abs(angle) * radius - transition  # the two clothoids turn transition / radius in total
    if arc < -1e-9:
        raise ValueError("transition too long for this turn: need transition <= |angle| * radius")
    segs = [Segment(transition, 0.0, k)] if transition > 0 else []
    if arc > 1e-9:
        segs.append(Segment(arc, k))
    if transition > 0:
        segs.append(Segment(transition, k, 0.0))
    return segs


def _turn_offset(angle: float, radius: float, transition: float) -> tuple[float, float]:
    """End point of a turn that starts at the origin heading +x."""
    p = Path(0.0, 0.0, 0.0, turn_segments(angle, radius, transition), ds=0.01)
    x, y, _ = p.end_pose
    return x, y


def route_path(kind: str, approach: str = "w", start_dist: float = 40.0, end_dist: float = 40.0,
               left_radius: float = 11.0, right_radius: float = 7.0, transition: float | None = None,
               lane: str | None = None, exit_lane: str | None = None) -> Path:
    """The centre-line path of a bus route through the intersection (right-hand traffic).

    kind: "straight" (inner lane unless lane="outer"), "left" (inner lane -> inner lane), "right"
    (outer lane -> inner lane: a 6 m bus cannot turn from the outer lane into the outer lane around
    SPEC's sharp kerb corner; the default keeps the centre line >= 1.5 m from the corner).
    Turns are clothoid-arc-clothoid (transition 5 m for left, 3 m for right by default). The bus starts
    `start_dist` metres before the intersection centre on its approach road and ends `end_dist`
    metres past it on the exit road. The first segment of a turn route is the straight lead-in
    (`path.segments[0].length` is where the turn starts)."""
    if approach not in APPROACH_YAW:
        raise ValueError(f"approach must be one of {sorted(APPROACH_YAW)}, got {approach!r}")
    kind = "straight" if kind == "stop" else kind
    offset = {"inner": INNER_LANE, "outer": OUTER_LANE}
    for name, v in (("lane", lane), ("exit_lane", exit_lane)):
        if v is not None and v not in offset:
            raise ValueError(f"{name} must be 'inner' or 'outer', got {v!r}")
    # Build for approach "w" (heading east on the south half of the x road), then rotate.
    if kind == "straight":
        p = Path(-start_dist, -offset[lane or "inner"], 0.0, [Segment(start_dist + end_dist)])
    elif kind in ("left", "right"):
        left = kind == "left"
        y_in = -offset[lane or ("inner" if left else "outer")]
        lat_out = offset[exit_lane or "inner"]
        # exit: left turn -> heading north on x > 0; right turn -> heading south on x < 0
        x_out = lat_out if left else -lat_out
        angle = np.pi / 2 if left else -np.pi / 2
        radius = left_radius if left else right_radius
        trans = (5.0 if left else 3.0) if transition is None else transition
        trans = min(trans, abs(angle) * radius)
        ex, ey = _turn_offset(angle, radius, trans)
        x_turn = x_out - ex
        lead = x_turn + start_dist
        tail = end_dist - abs(y_in + ey)
        if lead <= 0 or tail <= 0:
            raise ValueError("start_dist/end_dist too short for this turn")
        segs = [Segment(lead)] + turn_segments(angle, radius, trans) + [Segment(tail)]
        p = Path(-start_dist, y_in, 0.0, segs)
    else:
        raise ValueError(f"unknown route kind {kind!r} (straight, left, right, stop)")
    return p.rotated(APPROACH_YAW[approach]) if APPROACH_YAW[approach] else p


# --------------------------------------------------------------------------------------------
# Speed
# --------------------------------------------------------------------------------------------
class SpeedProfile:
    """Speed against time: starts at `v0`, then each phase (duration_s, v_end) blends to v_end with
    a raised cosine. Constant before t = 0 and after the last phase."""

    def __init__(self, v0: float, phases: list[tuple[float, float]] = (), max_speed: float = BUS_MAX_SPEED_MPS):
        self.v0 = float(v0)
        self.phases = [(float(d), float(v)) for d, v in phases]
        speeds = [self.v0] + [v for _, v in self.phases]
        if min(speeds) < 0 or max(speeds) > max_speed + 1e-9:
            raise ValueError(f"speeds must lie in [0, {max_speed:.3f}] m/s, got {speeds}")
        if any(d <= 0 for d, _ in self.phases):
            raise ValueError("phase durations must be positive")
        self._t0 = np.concatenate([[0.0], np.cumsum([d for d, _ in self.phases])])
        self._va = np.array(speeds[:-1] + [speeds[-1]])
        self._vb = np.array(speeds[1:] + [speeds[-1]])
        self._T = np.array([d for d, _ in self.phases] + [np.inf])
        # distance at each phase start
        s0 = [0.0]
        for (d, _), va, vb in zip(self.phases, self._va, self._vb):
            s0.append(s0[-1] + 0.5 * (va + vb) * d)
        self._s0 = np.array(s0)

    @property
    def end_time(self) -> float:
        return float(self._t0[-1])

    @classmethod
    def constant(cls, v: float) -> "SpeedProfile":
        return cls(v)

    @classmethod
    def stop_at(cls, v: float, s_stop: float, decel_s: float = 6.0, wait_s: float = 3.0,
                accel_s: float = 7.0) -> "SpeedProfile":
        """Cruise at v, come to rest exactly at arc length s_stop, wait, accelerate back to v."""
        d_decel = 0.5 * v * decel_s
        cruise = (s_stop - d_decel) / v if v > 0 else 0.0
        if cruise < 0:
            raise ValueError("stop too close to the start for this deceleration")
        phases = ([(cruise, v)] if cruise > 0 else []) + [(decel_s, 0.0), (wait_s, 0.0), (accel_s, v)]
        return cls(v, phases)

    def _phase(self, t):
        i = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, len(self._T) - 1)
        tau = t - self._t0[i]
        return i, tau

    def evaluate(self, t):
        """(distance, speed, acceleration) at times t (array); before t=0 speed is v0."""
        t = np.asarray(t, dtype=float)
        neg = t < 0
        tc = np.where(neg, 0.0, t)
        i, tau = self._phase(tc)
        T = self._T[i]
        va, vb = self._va[i], self._vb[i]
        fin = np.isfinite(T)
        Tf = np.where(fin, T, 1.0)
        r = np.where(fin, np.minimum(tau / Tf, 1.0), 1.0)
        dv = np.where(fin, vb - va, 0.0)
        v = va + dv * (1 - np.cos(np.pi * r)) / 2
        a = np.where(fin & (r < 1), dv * np.pi / (2 * Tf) * np.sin(np.pi * r), 0.0)
        s_in = np.where(fin, va * tau + dv * (tau / 2 - Tf * np.sin(np.pi * r) / (2 * np.pi)), vb * tau)
        s = self._s0[i] + s_in
        s = np.where(neg, self.v0 * t, s)
        v = np.where(neg, self.v0, v)
        a = np.where(neg, 0.0, a)
        return s, v, a

    def time_at_distance(self, s_target: float) -> float:
        """First time the travelled distance reaches s_target (bisection on the monotone s(t))."""
        hi = max(self.end_time, 1.0)
        while self.evaluate(hi)[0] < s_target:
            if self.evaluate(hi)[1] <= 0:
                raise ValueError("the profile ends at rest before reaching that distance")
            hi *= 2
        lo = 0.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if self.evaluate(mid)[0] < s_target:
                lo = mid
            else:
                hi = mid
        return hi


# --------------------------------------------------------------------------------------------
# Roof bounce
# --------------------------------------------------------------------------------------------
class RoofBounce:
    """Roof-height oscillation: sum of sinusoids at `freqs_hz` with seeded phases and weights
    normalised so that |dz| <= amplitude (band-limited, smooth)."""

    def __init__(self, amplitude: float = 0.10, freqs_hz=(0.8, 1.3, 2.1), seed: int = 0):
        rng = np.random.default_rng(seed)
        self.amplitude = float(amplitude)
        self.freqs = np.asarray(freqs_hz, dtype=float)
        w = rng.uniform(0.5, 1.0, size=len(self.freqs))
        self.weights = self.amplitude * w / w.sum()
        self.phases = rng.uniform(0, 2 * np.pi, size=len(self.freqs))

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        arg = 2 * np.pi * self.freqs * t[..., None] + self.phases
        return (self.weights * np.sin(arg)).sum(axis=-1)


# --------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TruthState:
    """True bus state; every field is a float, or an array when state_at got an array of times.
    accel_long = dv/dt, accel_lat = v * yaw_rate (vehicle frame, y left); roof_dz = roof height
    offset from nominal (m)."""
    t: float | np.ndarray
    x: float | np.ndarray
    y: float | np.ndarray
    yaw: float | np.ndarray
    speed: float | np.ndarray
    yaw_rate: float | np.ndarray
    accel_long: float | np.ndarray
    accel_lat: float | np.ndarray
    roof_dz: float | np.ndarray


DEFAULT_T0_NS = 1_700_000_000_000_000_000


@dataclass
class Trajectory:
    """A path travelled with a speed profile. `duration` is the time to reach the path's end."""
    path: Path
    speed: SpeedProfile
    bounce: RoofBounce | None = None
    t0_ns: int = DEFAULT_T0_NS
    name: str = "route"
    duration: float = field(init=False)

    def __post_init__(self):
        self.duration = self.speed.time_at_distance(self.path.length)

    def state_at(self, t) -> TruthState:
        """Truth at t seconds since the start (scalar or array)."""
        scalar = np.ndim(t) == 0
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s, v, a = self.speed.evaluate(t)
        x, y, yaw, k = self.path.pose_at(s)
        w = k * v
        dz = self.bounce(t) if self.bounce is not None else np.zeros_like(t)
        vals = [t, x, y, yaw, v, w, a, v * w, dz]
        return TruthState(*[_out(np.asarray(q, dtype=float), scalar) for q in vals])

    def yaw_accel_at(self, t):
        """d(yaw_rate)/dt = dk/ds v^2 + k a."""
        s, v, a = self.speed.evaluate(np.asarray(t, dtype=float))
        return self.path.curvature_rate(s) * v * v + self.path.curvature(s) * a

    def t_ns(self, t) -> np.ndarray | int:
        t = np.asarray(t, dtype=float)
        out = self.t0_ns + np.round(t * NS_PER_S).astype(np.int64)
        return int(out) if out.ndim == 0 else out

    def seconds(self, t_ns) -> np.ndarray | float:
        d = s_from_ns(np.asarray(t_ns, dtype=np.int64) - self.t0_ns)
        return float(d) if np.ndim(d) == 0 else d

    def state_at_ns(self, t_ns) -> TruthState:
        return self.state_at(self.seconds(t_ns))


def bus_trajectory(kind: str = "left", approach: str = "w", speed: float = BUS_MAX_SPEED_MPS,
                   stop: bool | None = None, stop_wait_s: float = 3.0, decel_s: float = 6.0,
                   accel_s: float = 7.0, turn_speed: float | None = None, bounce_amplitude: float = 0.10,
                   seed: int = 0, t0_ns: int = DEFAULT_T0_NS, **path_kw) -> Trajectory:
    """A bus route through the SPEC intersection (see route_path for kinds and geometry).

    speed: cruise speed (<= 30 km/h). stop=True (default for kind "stop") comes to rest at the stop
    line, waits `stop_wait_s` and goes again. turn_speed: slow down to this speed for the turn of a
    "left"/"right" route (default: keep `speed` through the turn). roof bounce: `bounce_amplitude`
    (m, 0 = none), phases seeded by `seed`."""
    path = route_path(kind, approach, **path_kw)
    do_stop = (kind == "stop") if stop is None else stop
    if do_stop and turn_speed is not None:
        raise ValueError("choose either a stop or a turn speed")
    if do_stop:
        s_stop = path_kw.get("start_dist", 40.0) - STOP_LINE
        prof = SpeedProfile.stop_at(speed, s_stop, decel_s, stop_wait_s, accel_s)
    elif turn_speed is not None and kind in ("left", "right"):
        s_in = path.segments[0].length
        s_turn = sum(sg.length for sg in path.segments[1:-1])
        v, vt = speed, float(turn_speed)
        t_dec = min(decel_s, 0.95 * 2 * s_in / (v + vt))
        cruise = (s_in - 0.5 * (v + vt) * t_dec) / v
        phases = ([(cruise, v)] if cruise > 0 else []) + [(t_dec, vt), (s_turn / vt, vt), (accel_s, v)]
        prof = SpeedProfile(v, phases)
    else:
        prof = SpeedProfile.constant(speed)
    bounce = RoofBounce(bounce_amplitude, seed=seed) if bounce_amplitude > 0 else None
    suffix = "-stop" if do_stop and kind != "stop" else ""
    return Trajectory(path, prof, bounce, t0_ns, name=f"{kind}-{approach}{suffix}")


# --------------------------------------------------------------------------------------------
# IMU / odometry
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ImuSamples:
    """Synthetic IMU + wheel odometry at a fixed rate. Arrays of equal length; `gyro_bias` and
    `wheel_scale` are the truth the sensor used (for tests and diagnostics)."""
    t: np.ndarray  # seconds since trajectory start
    t_ns: np.ndarray  # int64 ns
    gyro_z: np.ndarray  # rad/s
    accel_x: np.ndarray  # m/s^2, vehicle forward (gravity-free, flat road)
    accel_y: np.ndarray  # m/s^2, vehicle left
    wheel_speed: np.ndarray  # m/s
    gyro_bias: np.ndarray
    wheel_scale: float

    def __len__(self) -> int:
        return len(self.t)

    def rows(self):
        """(t_ns, gyro_z, accel_x, accel_y, wheel_speed) per sample, as Python scalars."""
        return zip(self.t_ns.tolist(), self.gyro_z.tolist(), self.accel_x.tolist(), self.accel_y.tolist(),
                   self.wheel_speed.tolist())


@dataclass(frozen=True)
class ImuModel:
    """Noise model of the bus IMU (z gyro, x/y accelerometer) and wheel-speed odometry.

    Densities are continuous-time; a sample's white-noise sigma is density * sqrt(rate).
    Defaults: a decent automotive MEMS IMU and a wheel-speed sensor with a 1 % scale error."""
    rate_hz: float = 100.0
    gyro_noise_density: float = 5e-4  # rad/s/sqrt(Hz)  (~0.03 deg/s/sqrt(Hz))
    gyro_bias_sigma: float = 0.005  # rad/s, turn-on bias (~0.3 deg/s)
    gyro_bias_walk: float = 2e-5  # rad/s/sqrt(s)
    accel_noise_density: float = 0.01  # m/s^2/sqrt(Hz)
    accel_bias_sigma: float = 0.02  # m/s^2, constant per run
    wheel_speed_sigma: float = 0.03  # m/s, white per sample
    wheel_scale_sigma: float = 0.01  # relative scale error, constant per run

    @classmethod
    def perfect(cls, rate_hz: float = 100.0) -> "ImuModel":
        return cls(rate_hz, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def synthesize(self, traj: Trajectory, t_start: float = 0.0, t_end: float | None = None,
                   rng: np.random.Generator | int | None = 0) -> ImuSamples:
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        t_end = traj.duration if t_end is None else t_end
        dt = 1.0 / self.rate_hz
        n = int(np.floor((t_end - t_start) / dt + 1e-9)) + 1
        t = t_start + dt * np.arange(n)
        st = traj.state_at(t)
        sq = np.sqrt(self.rate_hz)
        b0 = rng.normal(0.0, self.gyro_bias_sigma) if self.gyro_bias_sigma > 0 else 0.0
        walk = rng.normal(0.0, self.gyro_bias_walk * np.sqrt(dt), size=n)
        walk[0] = 0.0
        bias = b0 + np.cumsum(walk)
        ab = rng.normal(0.0, self.accel_bias_sigma, size=2) if self.accel_bias_sigma > 0 else np.zeros(2)
        scale = 1.0 + (rng.normal(0.0, self.wheel_scale_sigma) if self.wheel_scale_sigma > 0 else 0.0)
        gyro = st.yaw_rate + bias + rng.normal(0.0, 1.0, n) * self.gyro_noise_density * sq
        ax = st.accel_long + ab[0] + rng.normal(0.0, 1.0, n) * self.accel_noise_density * sq
        ay = st.accel_lat + ab[1] + rng.normal(0.0, 1.0, n) * self.accel_noise_density * sq
        wheel = scale * st.speed + rng.normal(0.0, 1.0, n) * self.wheel_speed_sigma
        return ImuSamples(t, traj.t_ns(t), gyro, ax, ay, wheel, bias, float(scale))


def dead_reckon(imu: ImuSamples, x0: float, y0: float, yaw0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain integration of gyro and wheel speed (midpoint heading) from a start pose: x, y, yaw at
    every sample. A reference for tests, not an estimator."""
    dt = np.diff(imu.t)
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(0.5 * (imu.gyro_z[1:] + imu.gyro_z[:-1]) * dt)])
    v = 0.5 * (imu.wheel_speed[1:] + imu.wheel_speed[:-1])
    ym = 0.5 * (yaw[1:] + yaw[:-1])
    x = x0 + np.concatenate([[0.0], np.cumsum(v * np.cos(ym) * dt)])
    y = y0 + np.concatenate([[0.0], np.cumsum(v * np.sin(ym) * dt)])
    return x, y, _wrap(yaw)
