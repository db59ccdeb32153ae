"""Scenario files of the live simulator (`toptag sim run`): which RSU cameras stream, which buses drive
which routes when, tagless trucks, sensor rates, the image model, looping.

A scenario is a JSON file; every path in it is relative to the scenario file. Example (the bundled
default is toptag/data/demo/scenario.json, see `bundled_scenario_path()`):

    {"intersection_id": "x1", "map": "map.json",
     "rsus": ["rsu-sw.json", {"camera": "rsu-ne.json", "fps": 5}],
     "fps": 10,
     "buses": [{"vehicle": "bus-17.json",
                "legs": [{"route": "left", "approach": "n", "start_s": 0, "turn_speed": 4},
                         {"route": "stop", "approach": "s", "start_s": 30}]}],
     "trucks": [{"length": 8, "width": 2.5, "height": 3.6,
                 "legs": [{"route": "straight", "approach": "w", "start_s": 5}]}],
     "imu_hz": 100, "imu_per_message": 4, "truth_hz": 20, "gnss_hz": 1, "gnss_sigma_m": 2.0,
     "image_model": {"noise_sigma": 3.0}, "imu_model": {"gyro_bias_sigma": 0.005},
     "loop": true, "loop_gap_s": 3, "seed": 1,
     "faults": {"rsu-ne": {"clock_offset_ms": 40},
                "rsu-sw": {"drift": {"yaw_deg": 0.5, "at_s": 20, "ramp_s": 0}}}}

Legs (`Leg`): a route of sim.motion (`route` straight|left|right|stop, `approach` w|s|e|n: the side the
vehicle comes from) started `start_s` seconds after the scenario start (after every loop repeat, the
same offsets again). The vehicle appears `start_dist` m before the intersection centre, already at
`speed`, and vanishes `end_dist` m past it. Between its legs a bus is parked away: not rendered, and no
IMU, truth or GNSS is published for it. A bus's legs must not overlap in time.

`loop`: after the last leg of any vehicle ends, wait `loop_gap_s` and start the whole scenario again
(period = last leg end + loop_gap_s).

`faults` (sim.faults.RsuFault, keyed by RSU id = camera id): a clock offset or a capture latency shifts
that RSU's frame stamps, a drift turns the camera the simulator renders with while the RSU keeps its
surveyed camera file.

`bus_config`: a bus settings file (services.bus.agent.BusSettings, TOML) that `toptag demo` passes to
the scenario's buses (`toptag bus --config`), e.g. the drift detector's thresholds for the live pipeline.
`rsu_config`: likewise an RSU settings file for its RSUs (`toptag rsu --config`), e.g. the corner-noise
model of the simulator's images ([pipeline] turn_ratio; `toptag eval livefix` reads it too).

Errors: `load_scenario` raises toptag.inputs.InputError with one line naming the file and the field.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from sim.faults import RsuFault
from sim.image_model import ImageModel
from sim.motion import STOP_LINE, ImuModel, Trajectory, bus_trajectory
from toptag.inputs import InputError, read_json, validate_model
from toptag.limits import BUS_MAX_SPEED_MPS

SCENARIO_FILE = "scenario.json"
_IMU_DEFAULTS = ImuModel()


class RsuEntry(BaseModel):
    """One RSU camera: its camera file (id = RSU id) and an optional frame-rate override."""

    model_config = ConfigDict(extra="forbid")

    camera: str = Field(min_length=1, description="camera file (SPEC.md), relative to the scenario file")
    fps: float | None = Field(default=None, gt=0, le=60, description="frames per second; default: scenario fps")


class Leg(BaseModel):
    """One pass of a vehicle through the intersection (a sim.motion route)."""

    model_config = ConfigDict(extra="forbid")

    route: Literal["straight", "left", "right", "stop"]
    approach: Literal["w", "s", "e", "n"] = Field(description="side the vehicle comes from")
    start_s: float = Field(ge=0, description="start, seconds after the scenario (or loop repeat) start")
    speed: float = Field(default=7.0, gt=0, le=BUS_MAX_SPEED_MPS, description="cruise speed, m/s; default 7")
    stop: bool | None = Field(default=None, description="stop at the stop line (default: route == 'stop')")
    stop_wait_s: float = Field(default=3.0, ge=0, description="standstill at the stop line, s; default 3")
    turn_speed: float | None = Field(default=None, gt=0, le=BUS_MAX_SPEED_MPS,
                                     description="slow to this speed for a left/right turn, m/s")
    start_dist: float = Field(default=55.0, gt=STOP_LINE, le=500,
                              description="appears this far before the centre, m; default 55")
    end_dist: float = Field(default=55.0, ge=15.0, le=500, description="vanishes this far past the centre, m")

    def trajectory_kwargs(self, seed: int, bounce_amplitude: float) -> dict:
        """The keyword arguments of sim.motion.bus_trajectory for this leg (without t0_ns)."""
        kw = dict(kind=self.route, approach=self.approach, speed=self.speed, stop=self.stop,
                  stop_wait_s=self.stop_wait_s, turn_speed=self.turn_speed, bounce_amplitude=bounce_amplitude,
                  seed=int(seed), start_dist=self.start_dist, end_dist=self.end_dist)
        return kw


class BusEntry(BaseModel):
    """A tagged bus (vehicle file: its id is the bus id) and its legs."""

    model_config = ConfigDict(extra="forbid")

    vehicle: str = Field(min_length=1, description="vehicle file (SPEC.md), relative to the scenario file")
    legs: list[Leg] = Field(min_length=1)
    bounce_amplitude: float = Field(default=0.10, ge=0, le=0.5, description="roof bounce, m; default 0.10")
    color: float = Field(default=170.0, ge=0, le=255, description="body grey level")


class TruckEntry(BaseModel):
    """Tagless traffic: an upright box driving its legs like a bus (occludes the buses' roofs)."""

    model_config = ConfigDict(extra="forbid")

    id: str | None = Field(default=None, description="name for logs; default truck-<n>")
    length: float = Field(default=8.0, gt=0, le=25)
    width: float = Field(default=2.5, gt=0, le=3.5)
    height: float = Field(default=3.6, gt=0, le=5)
    legs: list[Leg] = Field(min_length=1)
    color: float = Field(default=120.0, ge=0, le=255)


class ImuNoise(BaseModel):
    """sim.motion.ImuModel's noise and biases (its defaults); the rate is the scenario's imu_hz."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    gyro_noise_density: float = Field(default=_IMU_DEFAULTS.gyro_noise_density, ge=0)
    gyro_bias_sigma: float = Field(default=_IMU_DEFAULTS.gyro_bias_sigma, ge=0)
    gyro_bias_walk: float = Field(default=_IMU_DEFAULTS.gyro_bias_walk, ge=0)
    accel_noise_density: float = Field(default=_IMU_DEFAULTS.accel_noise_density, ge=0)
    accel_bias_sigma: float = Field(default=_IMU_DEFAULTS.accel_bias_sigma, ge=0)
    wheel_speed_sigma: float = Field(default=_IMU_DEFAULTS.wheel_speed_sigma, ge=0)
    wheel_scale_sigma: float = Field(default=_IMU_DEFAULTS.wheel_scale_sigma, ge=0)

    def model_for(self, rate_hz: float) -> ImuModel:
        return ImuModel(rate_hz=rate_hz, **self.model_dump())


IMU_PER_MESSAGE_MAX = 100


class Scenario(BaseModel):
    """A live-simulator scenario file (see the module docstring). Paths are as written in the file
    until `load_scenario` resolves them against the file's directory."""

    model_config = ConfigDict(extra="forbid")

    intersection_id: str = Field(min_length=1)
    map: str = Field(min_length=1, description="map file (toptag.site.MapFile)")
    rsus: list[RsuEntry] = Field(min_length=1)
    fps: float = Field(default=10.0, gt=0, le=60)
    buses: list[BusEntry] = Field(default_factory=list)
    trucks: list[TruckEntry] = Field(default_factory=list)
    imu_hz: float = Field(default=100.0, gt=0, le=1000)
    # A bus's IMU samples this many to a message (ImuBatch on keys.imu_batch, sent when its newest sample's
    # time has come; 1: each sample an Imu on keys.imu as it comes). 4 at 100 Hz: one message per filter
    # cycle of the bus agent (25 Hz), which takes its inputs in once a cycle anyway; each message costs the
    # agent a wake-up of Zenoh's thread and a decode (`toptag bench bus --imu-per-message`, docs/real-time.md).
    # At most what one ImuBatch holds (protocol.messages.IMU_BATCH_MAX; the core imports no protocol, a test
    # checks that they agree).
    imu_per_message: int = Field(default=4, ge=1, le=IMU_PER_MESSAGE_MAX)
    truth_hz: float = Field(default=20.0, gt=0, le=1000)
    gnss_hz: float = Field(default=1.0, gt=0, le=100)
    gnss_sigma_m: float = Field(default=2.0, gt=0)
    # The live simulator's frames travel as JPEG (protocol Frame); its cameras' stream codec is that JPEG
    # (q90), not the calibrated model's H.264 stage, which would cost every RSU frame 16 ms more of a
    # small machine's real time. Everything else is the calibrated model; a scenario may say otherwise.
    image_model: ImageModel = Field(default_factory=lambda: ImageModel(codec="jpeg"))
    imu_model: ImuNoise = Field(default_factory=ImuNoise)
    loop: bool = False
    loop_gap_s: float = Field(default=3.0, gt=0, description="pause between the last leg end and the repeat")
    seed: int = Field(default=0, ge=0)
    faults: dict[str, RsuFault] = Field(default_factory=dict, description="per RSU id: injected faults")
    bus_config: str | None = Field(default=None, description="bus settings file (toptag bus --config) that "
                                                             "`toptag demo` gives the scenario's buses")
    rsu_config: str | None = Field(default=None, description="RSU settings file (toptag rsu --config) that "
                                                             "`toptag demo` gives the scenario's RSUs")

    @field_validator("rsus", mode="before")
    @classmethod
    def _plain_paths(cls, v):
        if isinstance(v, list):
            return [{"camera": x} if isinstance(x, str) else x for x in v]
        return v

    @model_validator(mode="after")
    def _legs_are_drivable(self) -> "Scenario":
        # Every leg must make a valid sim.motion route, and one vehicle's legs must not overlap in time.
        for group, actors in (("buses", self.buses), ("trucks", self.trucks)):
            for a, actor in enumerate(actors):
                ends = []
                for i, leg in enumerate(actor.legs):
                    try:
                        traj = bus_trajectory(**leg.trajectory_kwargs(0, 0.0))
                    except ValueError as e:
                        raise ValueError(f"{group}[{a}].legs[{i}]: {e}") from None
                    ends.append((leg.start_s, leg.start_s + traj.duration, i))
                ends.sort()
                for (_, e0, i0), (s1, _, i1) in zip(ends, ends[1:], strict=False):
                    if s1 < e0:
                        raise ValueError(f"{group}[{a}].legs[{i1}]: starts at {s1:g} s, before legs[{i0}] "
                                         f"ends (at {e0:.1f} s)")
        return self

    def rsu_fps(self, index: int) -> float:
        return float(self.rsus[index].fps or self.fps)

    def camera_paths(self) -> list[Path]:
        """The RSU camera files (absolute after load_scenario)."""
        return [Path(r.camera) for r in self.rsus]

    def vehicle_paths(self) -> list[Path]:
        """The buses' vehicle files (absolute after load_scenario)."""
        return [Path(b.vehicle) for b in self.buses]

    def map_path(self) -> Path:
        return Path(self.map)


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file; every path in it is resolved relative to the file's
    directory. Raises InputError (one line naming the file and the field) on any problem."""
    p = Path(path)
    data = read_json(p, "scenario file")
    if not isinstance(data, dict):
        raise InputError(f"scenario file {p}: must hold a JSON object")
    sc = validate_model(Scenario, data, f"scenario file {p}")
    base = p.resolve().parent

    def resolve(q: str) -> str:
        return str((base / q).resolve()) if not Path(q).is_absolute() else q

    return sc.model_copy(update={
        "map": resolve(sc.map),
        "rsus": [r.model_copy(update={"camera": resolve(r.camera)}) for r in sc.rsus],
        "buses": [b.model_copy(update={"vehicle": resolve(b.vehicle)}) for b in sc.buses],
        "bus_config": None if sc.bus_config is None else resolve(sc.bus_config),
        "rsu_config": None if sc.rsu_config is None else resolve(sc.rsu_config),
    })


def bundled_scenario_path() -> Path:
    """The default scenario shipped with toptag (toptag/data/demo/scenario.json): buses bus-17 and
    bus-42 through the four-RSU intersection x1, looping."""
    return Path(str(resources.files("toptag.data.demo").joinpath(SCENARIO_FILE)))


def leg_seed(seed: int, group: int, actor: int, leg: int) -> int:
    """The roof-bounce seed of one leg (stable for a scenario seed)."""
    return int(np.random.SeedSequence([int(seed), group, actor, leg]).generate_state(1)[0])


def leg_trajectory(leg: Leg, seed: int, bounce_amplitude: float, t0_ns: int) -> Trajectory:
    return bus_trajectory(t0_ns=int(t0_ns), **leg.trajectory_kwargs(seed, bounce_amplitude))


__all__ = ["BusEntry", "ImuNoise", "Leg", "RsuEntry", "Scenario", "TruckEntry", "bundled_scenario_path",
           "leg_seed", "leg_trajectory", "load_scenario"]
