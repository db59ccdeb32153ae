"""The live simulator's world, without Zenoh: a scenario (sim.scenario) on a clock.

    world = World(load_scenario(bundled_scenario_path()))
    world.warm_up()                      # per-camera background caches (~0.2-0.3 s per 960x720 camera)
    world.start(time.time_ns())          # t0: the scenario starts now
    world.vehicles_at(t_ns)              # -> [PlacedVehicle]: the tagged buses on the road at t_ns
    world.truth_at(t_ns)                 # -> {bus_id: BusState}
    world.render_jpeg("rsu-sw", t_ns)    # the RSU frame of the scene at t_ns (JPEG bytes)
    world.capture("rsu-sw", tick_ns)     # the frame published at a tick: (JPEG, capture stamp), faults applied
    world.imu_between("bus-17", a, b)    # IMU samples on the imu_hz grid in (a, b]

Time. Every time is integer nanoseconds on the simulator's clock; `start(t0_ns)` says when the
scenario starts (default 0). A leg of a vehicle runs from t0 + start_s (+ k * period when the scenario
loops) for its trajectory's duration; its state at t is `bus_trajectory(**leg kwargs).state_at(t -
leg start)` translated to the intersection centre of the map. Sensor samples lie on fixed grids
t0 + round(k * 1e9 / rate) (IMU, truth, GNSS; frames of RSU r at t0 + r/n_rsu * period + k * period).

Presence. A bus exists only during its legs: it is rendered, and it has IMU, truth and GNSS samples,
only then. Between legs it is "parked away" (nothing at all), so a consumer knows a bus is on the road
by its samples, and where by its GNSS fixes (a leg starts 55 m out by default, outside the GNSS shadow).

Faults (the scenario's `faults`, sim.faults). The frame an RSU gets at tick t shows the scene at
t - capture latency, taken by its camera turned by its drift at that time (the angle kept to
DRIFT_STEP_DEG steps, so a ramp rebuilds a camera's raster cache a bounded number of times), and is
stamped t + clock offset. The RSU's camera file stays the surveyed one.

IMU. Per bus, one sensor for the whole run with sim.motion.ImuModel's noise model (the scenario's
imu_model at imu_hz): a turn-on gyro bias that random-walks through time (also while parked), a
constant accelerometer bias and wheel-scale error, white noise per sample. `imu_between` is therefore
stateful: each sample is produced once, windows must move forward (a window reaching back before the
previous one is clipped). GNSS noise is drawn per call from a per-bus generator likewise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.faults import RsuFault, turned
from sim.image_model import ImageModel
from sim.motion import Trajectory, bus_trajectory
from sim.raster import raster_for
from sim.render import Occluder, PlacedVehicle, render_jpeg
from sim.sampling import PLATE_MARGIN_PX, footprints_overlap, visible_tags
from sim.scenario import BusEntry, Leg, Scenario, TruckEntry, leg_seed
from toptag.camera import Camera
from toptag.inputs import InputError
from toptag.site import MapFile
from toptag.units import NS_PER_MS, NS_PER_S, ns_from_s, s_from_ns
from toptag.vehicle import Vehicle

DRIFT_STEP_DEG = 0.005



@dataclass(frozen=True)
class LegRun:
    """One leg of one vehicle, with its trajectory (t0_ns = 0: times relative to the leg start)."""

    actor_id: str
    index: int  # position in the vehicle's `legs` list of the scenario file
    leg: Leg
    kwargs: dict  # sim.motion.bus_trajectory keyword arguments (t0_ns excluded)
    trajectory: Trajectory
    start_ns: int  # offset from the scenario (cycle) start
    duration_ns: int

    @property
    def end_ns(self) -> int:
        return self.start_ns + self.duration_ns


@dataclass
class Actor:
    """A vehicle of the scenario: a tagged bus (vehicle set) or a tagless truck (box only)."""

    id: str
    kind: str  # "bus" | "truck"
    entry: BusEntry | TruckEntry
    vehicle: Vehicle | None
    legs: list[LegRun] = field(default_factory=list)


@dataclass(frozen=True)
class BusState:
    """True state of a vehicle at t_ns (world frame). z is the roof (tag plane) height."""

    bus_id: str
    t_ns: int
    x: float
    y: float
    z: float
    yaw: float
    speed: float
    yaw_rate: float
    accel_long: float
    accel_lat: float
    roof_dz: float
    leg: int  # index of the leg in the scenario file
    cycle: int  # loop repeat (0 for the first pass)


@dataclass(frozen=True)
class ImuBatch:
    """IMU / wheel-odometry samples of one bus (arrays of equal length, vehicle frame).
    gyro_bias, accel_bias and wheel_scale are the sensor's true errors (diagnostics, tests)."""

    bus_id: str
    t_ns: np.ndarray  # int64
    seq: np.ndarray  # int64, per bus, +1 per sample over the whole run
    gyro_z: np.ndarray
    accel_x: np.ndarray
    accel_y: np.ndarray
    wheel_speed: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: tuple[float, float]
    wheel_scale: float

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(frozen=True)
class GnssSample:
    bus_id: str
    t_ns: int
    x: float
    y: float
    sigma_m: float


class _ImuSensor:
    """The stateful noise of one bus's IMU (see the module docstring)."""

    def __init__(self, model, rng: np.random.Generator):
        self.m = model
        self.rng = rng
        self.bias = rng.normal(0.0, model.gyro_bias_sigma) if model.gyro_bias_sigma > 0 else 0.0
        self.accel_bias = (tuple(float(v) for v in rng.normal(0.0, model.accel_bias_sigma, 2))
                           if model.accel_bias_sigma > 0 else (0.0, 0.0))
        self.scale = 1.0 + (rng.normal(0.0, model.wheel_scale_sigma) if model.wheel_scale_sigma > 0 else 0.0)
        self.last_ns: int | None = None
        self.cursor_ns: int | None = None  # end of the last window asked for
        self.seq = 0

    def measure(self, t_ns: np.ndarray, yaw_rate, accel_long, accel_lat, speed):
        m, rng, n = self.m, self.rng, len(t_ns)
        prev = np.concatenate([[t_ns[0] if self.last_ns is None else self.last_ns], t_ns[:-1]])
        dt = s_from_ns(np.maximum(t_ns - prev, 0))
        walk = rng.normal(0.0, 1.0, n) * m.gyro_bias_walk * np.sqrt(dt) if m.gyro_bias_walk > 0 else np.zeros(n)
        bias = self.bias + np.cumsum(walk)
        self.bias = float(bias[-1])
        self.last_ns = int(t_ns[-1])
        sq = math.sqrt(m.rate_hz)
        gyro = yaw_rate + bias + rng.normal(0.0, 1.0, n) * m.gyro_noise_density * sq
        ax = accel_long + self.accel_bias[0] + rng.normal(0.0, 1.0, n) * m.accel_noise_density * sq
        ay = accel_lat + self.accel_bias[1] + rng.normal(0.0, 1.0, n) * m.accel_noise_density * sq
        wheel = self.scale * speed + rng.normal(0.0, 1.0, n) * m.wheel_speed_sigma
        seq = self.seq + np.arange(n, dtype=np.int64)
        self.seq += n
        return seq, gyro, ax, ay, wheel, bias


def boxes_overlap(a, b, clearance: float = 0.0) -> bool:
    """Exact test of two oriented ground rectangles (x, y, yaw, length, width), each grown by
    clearance/2 on every side (separating axis theorem)."""
    def corners(o):
        L, W = o.length / 2 + clearance / 2, o.width / 2 + clearance / 2
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        local = np.array([[L, W], [L, -W], [-L, -W], [-L, W]])
        return local @ np.array([[c, s], [-s, c]]) + [o.x, o.y]

    pa, pb = corners(a), corners(b)
    for yaw in (a.yaw, b.yaw):
        for axis in ((math.cos(yaw), math.sin(yaw)), (-math.sin(yaw), math.cos(yaw))):
            qa, qb = pa @ axis, pb @ axis
            if qa.max() < qb.min() or qb.max() < qa.min():
                return False
    return True


class World:
    """A scenario on a clock (see the module docstring). Files named by the scenario are loaded here
    (InputError on a bad one); pass `cameras` / `vehicles` to use objects instead (tests)."""

    def __init__(self, scenario: Scenario, *, cameras: list[Camera] | None = None,
                 vehicles: list[Vehicle] | None = None, site: MapFile | None = None):
        self.scenario = sc = scenario
        self.model: ImageModel = sc.image_model
        self.site = site if site is not None else MapFile.load(sc.map)
        self.intersection = self.site.get(sc.intersection_id)
        self.center = np.asarray(self.intersection.center, float)
        self.cameras = cameras if cameras is not None else [Camera.load(r.camera) for r in sc.rsus]
        if len(self.cameras) != len(sc.rsus):
            raise ValueError("one camera per scenario RSU")
        ids = [c.id for c in self.cameras]
        if len(set(ids)) != len(ids):
            raise InputError(f"scenario: two RSU cameras share the id {_first_dup(ids)!r}")
        self.fps = [sc.rsu_fps(i) for i in range(len(self.cameras))]
        self._cam_index = {c.id: i for i, c in enumerate(self.cameras)}
        unknown = sorted(set(sc.faults) - set(ids))
        if unknown:
            raise InputError(f"scenario: faults name RSUs it does not have: {', '.join(unknown)} "
                             f"(RSUs: {', '.join(ids)})")
        self.faults = [sc.faults.get(c.id, RsuFault()) for c in self.cameras]
        vehicles = vehicles if vehicles is not None else [Vehicle.load(b.vehicle) for b in sc.buses]
        if len(vehicles) != len(sc.buses):
            raise ValueError("one vehicle per scenario bus")
        bus_ids = [v.id for v in vehicles]
        if len(set(bus_ids)) != len(bus_ids):
            raise InputError(f"scenario: two buses share the vehicle id {_first_dup(bus_ids)!r}")

        self.actors: list[Actor] = []
        for a, (entry, v) in enumerate(zip(sc.buses, vehicles, strict=True)):
            self.actors.append(self._actor(v.id, "bus", entry, v, 0, a, entry.bounce_amplitude))
        for a, entry in enumerate(sc.trucks):
            tid = entry.id or f"truck-{a + 1}"
            if tid in bus_ids or any(x.id == tid for x in self.actors):
                raise InputError(f"scenario: trucks[{a}].id {tid!r} is already used")
            self.actors.append(self._actor(tid, "truck", entry, None, 1, a, 0.0))
        self._by_id = {x.id: x for x in self.actors}
        self.buses = [x for x in self.actors if x.kind == "bus"]
        self.trucks = [x for x in self.actors if x.kind == "truck"]
        self.legs_end_ns = max((lr.end_ns for x in self.actors for lr in x.legs), default=0)
        self.period_ns: int | None = (self.legs_end_ns + ns_from_s(sc.loop_gap_s)) if sc.loop else None
        self.t0_ns = 0
        self._reset_sensors()

    def _actor(self, aid, kind, entry, vehicle, group, index, bounce) -> Actor:
        actor = Actor(aid, kind, entry, vehicle)
        for i, leg in enumerate(entry.legs):
            kw = leg.trajectory_kwargs(leg_seed(self.scenario.seed, group, index, i), bounce)
            traj = bus_trajectory(t0_ns=0, **kw)
            actor.legs.append(LegRun(aid, i, leg, kw, traj, ns_from_s(leg.start_s),
                                     int(math.floor(traj.duration * NS_PER_S))))
        actor.legs.sort(key=lambda lr: lr.start_ns)
        return actor

    def _reset_sensors(self) -> None:
        sc = self.scenario
        imu_model = sc.imu_model.model_for(sc.imu_hz)
        ss = np.random.SeedSequence([sc.seed, 7])
        kids = ss.spawn(2 * len(self.buses) + len(self.cameras))
        self._imu = {b.id: _ImuSensor(imu_model, np.random.default_rng(kids[i])) for i, b in enumerate(self.buses)}
        self._gnss_rng = {b.id: np.random.default_rng(kids[len(self.buses) + i]) for i, b in enumerate(self.buses)}
        self._gnss_cursor: dict[str, int] = {}
        self._render_rng = [np.random.default_rng(kids[2 * len(self.buses) + i]) for i in range(len(self.cameras))]

    # ---- clock -----------------------------------------------------------------------------
    def start(self, t0_ns: int) -> None:
        """The scenario starts at t0_ns (resets the sensors' noise streams)."""
        self.t0_ns = int(t0_ns)
        self._reset_sensors()

    @property
    def rsu_ids(self) -> list[str]:
        return [c.id for c in self.cameras]

    @property
    def bus_ids(self) -> list[str]:
        return [b.id for b in self.buses]

    def camera(self, rsu_id: str) -> Camera:
        return self.cameras[self._cam_index[rsu_id]]

    def vehicle(self, bus_id: str) -> Vehicle:
        return self._by_id[bus_id].vehicle

    def actor(self, actor_id: str) -> Actor:
        return self._by_id[actor_id]

    def leg_start_ns(self, actor_id: str, leg: int, cycle: int = 0) -> int:
        """Absolute start time of a leg (index in the file) in a loop repeat."""
        lr = self._leg(actor_id, leg)
        return self.t0_ns + (cycle * self.period_ns if self.period_ns else 0) + lr.start_ns

    def trajectory(self, actor_id: str, leg: int, cycle: int = 0) -> Trajectory:
        """sim.motion's trajectory of a leg with its absolute t0_ns (positions relative to the
        intersection centre, as bus_trajectory makes them)."""
        lr = self._leg(actor_id, leg)
        return bus_trajectory(t0_ns=self.leg_start_ns(actor_id, leg, cycle), **lr.kwargs)

    def _leg(self, actor_id: str, leg: int) -> LegRun:
        return next(lr for lr in self._by_id[actor_id].legs if lr.index == leg)

    def grid(self, rate_hz: float, t_from_ns: int, t_to_ns: int) -> np.ndarray:
        """Times t0 + round(k * 1e9 / rate) (k >= 0) in (t_from, t_to], int64."""
        step = NS_PER_S / rate_hz
        k0 = max(0, int(math.floor((t_from_ns - self.t0_ns) / step)) - 1)
        k1 = int(math.floor((t_to_ns - self.t0_ns) / step)) + 1
        if k1 < k0:
            return np.zeros(0, np.int64)
        t = self.t0_ns + np.round(np.arange(k0, k1 + 1) * step).astype(np.int64)
        return t[(t > t_from_ns) & (t <= t_to_ns)]

    def _index(self, rsu: int | str) -> int:
        """An RSU given by id or by index, as its index."""
        return self._cam_index[rsu] if isinstance(rsu, str) else rsu

    def frame_time(self, rsu: int | str, k: int) -> int:
        """Capture time of frame k of an RSU: RSUs are staggered by 1/n of their period."""
        r = self._index(rsu)
        step = NS_PER_S / self.fps[r]
        return self.t0_ns + int(round(r / len(self.cameras) * step)) + int(round(k * step))

    def frame_index_from(self, rsu: int | str, t_ns: int) -> int:
        """The first frame index whose capture time is >= t_ns."""
        r = self._index(rsu)
        k = max(0, int(math.floor((t_ns - self.frame_time(r, 0)) * self.fps[r] / NS_PER_S)))
        while self.frame_time(r, k) < t_ns:
            k += 1
        while k > 0 and self.frame_time(r, k - 1) >= t_ns:
            k -= 1
        return k

    # ---- states ----------------------------------------------------------------------------
    def _states(self, actor: Actor, t_ns: np.ndarray):
        """Vectorised state of an actor at times t_ns: (present mask, leg index, cycle, TruthState
        fields as arrays; NaN where absent)."""
        t_ns = np.asarray(t_ns, np.int64)
        n = len(t_ns)
        rel = t_ns - self.t0_ns
        if self.period_ns:
            cycle = np.floor_divide(rel, self.period_ns)
            within = rel - cycle * self.period_ns
        else:
            cycle = np.zeros(n, np.int64)
            within = rel
        present = np.zeros(n, bool)
        leg = np.full(n, -1, np.int64)
        names = ("x", "y", "yaw", "speed", "yaw_rate", "accel_long", "accel_lat", "roof_dz")
        out = {k: np.full(n, np.nan) for k in names}
        for lr in actor.legs:
            m = (rel >= 0) & (within >= lr.start_ns) & (within <= lr.end_ns) & ~present
            if not m.any():
                continue
            st = lr.trajectory.state_at(s_from_ns(within[m] - lr.start_ns))
            for k in names:
                out[k][m] = np.atleast_1d(getattr(st, k))
            present |= m
            leg[m] = lr.index
        out["x"] = out["x"] + self.center[0]
        out["y"] = out["y"] + self.center[1]
        return present, leg, cycle, out

    def _state_list(self, actor: Actor, t_ns: np.ndarray) -> list[BusState]:
        present, leg, cycle, s = self._states(actor, t_ns)
        height = actor.vehicle.height if actor.vehicle is not None else actor.entry.height
        res = []
        for i in np.nonzero(present)[0]:
            res.append(BusState(actor.id, int(t_ns[i]), float(s["x"][i]), float(s["y"][i]),
                                float(height + s["roof_dz"][i]), float(s["yaw"][i]), float(s["speed"][i]),
                                float(s["yaw_rate"][i]), float(s["accel_long"][i]), float(s["accel_lat"][i]),
                                float(s["roof_dz"][i]), int(leg[i]), int(cycle[i])))
        return res

    def state(self, actor_id: str, t_ns: int) -> BusState | None:
        """State of a bus or truck at t_ns, None while it is parked away."""
        r = self._state_list(self._by_id[actor_id], np.array([t_ns], np.int64))
        return r[0] if r else None

    def truth_at(self, t_ns: int) -> dict[str, BusState]:
        """The buses on the road at t_ns and their true states."""
        out = {}
        for b in self.buses:
            s = self.state(b.id, t_ns)
            if s is not None:
                out[b.id] = s
        return out

    def vehicles_at(self, t_ns: int) -> list[PlacedVehicle]:
        """The tagged buses on the road at t_ns, placed for sim.render."""
        out = []
        for b in self.buses:
            s = self.state(b.id, t_ns)
            if s is not None:
                out.append(PlacedVehicle(b.vehicle, s.x, s.y, s.yaw, s.z, s.speed, s.yaw_rate,
                                         color=b.entry.color))
        return out

    def occluders_at(self, t_ns: int) -> list[Occluder]:
        """The tagless trucks on the road at t_ns."""
        out = []
        for tr in self.trucks:
            s = self.state(tr.id, t_ns)
            if s is not None:
                e = tr.entry
                out.append(Occluder(e.length, e.width, e.height, s.x, s.y, s.yaw, s.speed, s.yaw_rate, e.color))
        return out

    def tags_in_view(self, rsu_id: str, t_ns: int, margin_px: float = PLATE_MARGIN_PX) -> dict[str, list[int]]:
        """Per bus on the road: the tags whose whole printed plate projects inside the RSU's image
        (trucks' occlusion not considered)."""
        cam = self.camera(rsu_id)
        return {pv.vehicle.id: visible_tags(cam, pv, margin_px) for pv in self.vehicles_at(t_ns)}

    # ---- sensors ---------------------------------------------------------------------------
    def imu_between(self, bus_id: str, t_from_ns: int, t_to_ns: int) -> ImuBatch:
        """The bus's IMU samples on the imu_hz grid in (t_from, t_to] while it is on the road
        (stateful: see the module docstring)."""
        sensor = self._imu[bus_id]
        if sensor.cursor_ns is not None:
            t_from_ns = max(t_from_ns, sensor.cursor_ns)
        sensor.cursor_ns = max(t_to_ns, sensor.cursor_ns or t_to_ns)
        t = self.grid(self.scenario.imu_hz, t_from_ns, t_to_ns)
        present, _, _, s = self._states(self._by_id[bus_id], t)
        t = t[present]
        if len(t) == 0:
            e = np.zeros(0)
            return ImuBatch(bus_id, t, np.zeros(0, np.int64), e, e, e, e, e, sensor.accel_bias, sensor.scale)
        seq, gyro, ax, ay, wheel, bias = sensor.measure(
            t, s["yaw_rate"][present], s["accel_long"][present], s["accel_lat"][present], s["speed"][present])
        return ImuBatch(bus_id, t, seq, gyro, ax, ay, wheel, bias, sensor.accel_bias, float(sensor.scale))

    def truth_between(self, bus_id: str, t_from_ns: int, t_to_ns: int) -> list[BusState]:
        """True states on the truth_hz grid in (t_from, t_to] while the bus is on the road."""
        return self._state_list(self._by_id[bus_id], self.grid(self.scenario.truth_hz, t_from_ns, t_to_ns))

    def in_gnss_shadow(self, x: float, y: float) -> bool:
        """Inside the gnss_shadow_radius of any intersection of the map."""
        return any(math.hypot(x - i.center[0], y - i.center[1]) < i.gnss_shadow_radius
                   for i in self.site.intersections)

    def gnss_between(self, bus_id: str, t_from_ns: int, t_to_ns: int) -> list[GnssSample]:
        """GNSS fixes on the gnss_hz grid in (t_from, t_to]: true position + N(0, gnss_sigma_m) per
        axis, none while parked away or inside a GNSS shadow (stateful noise, windows move forward)."""
        cur = self._gnss_cursor.get(bus_id)
        if cur is not None:
            t_from_ns = max(t_from_ns, cur)
        self._gnss_cursor[bus_id] = max(t_to_ns, cur if cur is not None else t_to_ns)
        sigma = self.scenario.gnss_sigma_m
        rng = self._gnss_rng[bus_id]
        out = []
        for s in self._state_list(self._by_id[bus_id], self.grid(self.scenario.gnss_hz, t_from_ns, t_to_ns)):
            if self.in_gnss_shadow(s.x, s.y):
                continue
            dx, dy = rng.normal(0.0, sigma, 2)
            out.append(GnssSample(bus_id, s.t_ns, s.x + float(dx), s.y + float(dy), sigma))
        return out

    # ---- frames ----------------------------------------------------------------------------
    def render_jpeg(self, rsu: int | str, t_ns: int, camera: Camera | None = None) -> bytes:
        """The RSU's camera frame of the scene at t_ns (JPEG, the scenario's image model), taken by
        `camera` (default: the RSU's surveyed camera)."""
        r = self._index(rsu)
        return render_jpeg(camera or self.cameras[r], self.vehicles_at(t_ns), self.occluders_at(t_ns), self.model,
                           self._render_rng[r])

    def actual_camera(self, rsu: int | str, t_ns: int) -> Camera:
        """The RSU's camera as it really is at t_ns: turned by its drift (in DRIFT_STEP_DEG steps)."""
        r = self._index(rsu)
        drift = self.faults[r].drift
        if drift is None:
            return self.cameras[r]
        yaw, pitch = drift.angles(s_from_ns(t_ns - self.t0_ns))
        step = math.radians(DRIFT_STEP_DEG)
        return turned(self.cameras[r], round(yaw / step) * step, round(pitch / step) * step)

    def capture(self, rsu: int | str, tick_ns: int) -> tuple[bytes, int]:
        """The frame the RSU gets at tick_ns and its capture stamp (see Faults in the module docstring)."""
        r = self._index(rsu)
        f = self.faults[r]
        exposure = tick_ns - int(round(f.capture_latency_ms * NS_PER_MS))
        jpeg = self.render_jpeg(r, exposure, self.actual_camera(r, exposure))
        return jpeg, tick_ns + int(round(f.clock_offset_ms * NS_PER_MS))

    def warm_up(self, rsus: list[int | str] | None = None) -> None:
        """Build the cameras' background caches and render once (call before the clock starts): every
        camera's, or those of `rsus` only (what a render process of sim.live renders)."""
        wanted = None if rsus is None else {self._index(r) for r in rsus}
        probe = []
        if self.buses:
            b = self.buses[0]
            probe = [PlacedVehicle(b.vehicle, float(self.center[0]), float(self.center[1]), 0.3, speed=5.0)]
        rng = np.random.default_rng(0)
        for r, cam in enumerate(self.cameras):
            if wanted is not None and r not in wanted:
                continue
            drift = self.faults[r].drift
            later = [self.actual_camera(r, self.t0_ns + ns_from_s(drift.at_s + drift.ramp_s))] if drift else []
            for c in [cam] + later:  # a stepped camera's cache too, so the step does not stall the loop
                raster_for(c).finished_background(self.model)
                render_jpeg(c, probe, (), self.model, rng)

    # ---- checks ----------------------------------------------------------------------------
    def conflicts(self, step_s: float = 0.1, conservative: bool = True,
                  clearance: float = 0.5) -> list[tuple[float, str, str]]:
        """(seconds after the scenario start, id, id) for every sample time (one pass of the scenario)
        at which two vehicles get too close: conservative = sim.sampling.footprints_overlap (bounding
        circles + clearance), else the exact rectangles grown by `clearance`."""
        t0 = self.t0_ns
        n = int(math.ceil(self.legs_end_ns / (step_s * NS_PER_S))) + 1
        t = t0 + np.round(np.arange(n) * step_s * NS_PER_S).astype(np.int64)
        boxes = {}
        for a in self.actors:
            present, _, _, s = self._states(a, t)
            L = a.vehicle.length if a.vehicle is not None else a.entry.length
            W = a.vehicle.width if a.vehicle is not None else a.entry.width
            boxes[a.id] = (present, s, L, W)
        out = []
        ids = [a.id for a in self.actors]
        for i in range(len(ids)):
            for j in range(i + 1, len(ids)):
                pa, sa, La, Wa = boxes[ids[i]]
                pb, sb, Lb, Wb = boxes[ids[j]]
                for k in np.nonzero(pa & pb)[0]:
                    A = _Box(sa["x"][k], sa["y"][k], sa["yaw"][k], La, Wa)
                    B = _Box(sb["x"][k], sb["y"][k], sb["yaw"][k], Lb, Wb)
                    hit = footprints_overlap(A, B, clearance) if conservative else boxes_overlap(A, B, clearance)
                    if hit:
                        out.append(((t[k] - t0) / NS_PER_S, ids[i], ids[j]))
        return out


@dataclass(frozen=True)
class _Box:
    x: float
    y: float
    yaw: float
    length: float
    width: float


def _first_dup(ids: list[str]) -> str:
    seen = set()
    for i in ids:
        if i in seen:
            return i
        seen.add(i)
    return ""
