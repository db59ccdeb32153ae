"""`toptag bench rsu --scenario`: the demo's RSUs, offline, on every frame of a scenario.

The live demo's figures depend on the machine's load (a busy RSU skips frames, which changes what it
does next). This plays the scenario's cameras frame by frame in simulated time instead and feeds each
RSU pipeline what its service would get: a bus's code bag while the bus is inside the intersection's
approach radius (toptag.fusion.presence on the true position), the bus's whereabouts every 0.2 s as its
Approach carries them (services.bus.agent.announced_position: the pose of a bus filter fed with the
bus's IMU/odometry and with the RSUs' fixes, once a fix has started it, with its velocity; else the
latest GNSS fix, at most 5 s old, with the odometry's speed; none inside the GNSS shadow before a fix),
and every other RSU's fixes as hints. Fixes reach the filter and the hints at once (no network delay). Each frame's processing (decode, search or track, solve) is timed in process CPU
time, so the figures say how much work the RSUs do, not how busy the machine was. Rendering is not
counted."""
from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.bus.agent import ANNOUNCE_PERIOD_S, IMU_GAP_RESET_S, announced_position
from protocol.convert import reported_position
from protocol.messages import GnssFix
from services.monitor import frame_kind
from sim.sampling import in_some_view
from sim.scenario import bundled_scenario_path, load_scenario
from sim.world import World
from toptag.fusion.filter import BusFilter
from toptag.fusion.presence import IntersectionPresence
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.units import NS_PER_S, s_from_ns

FIX_FRESH_S = 1.0  # the bus filter's health is "degraded" after this long without a fix (FilterConfig)
T0_NS = 1_800_000_000 * NS_PER_S  # the scenario's start (any fixed instant: the run repeats exactly)


@dataclass
class RsuTally:
    frames: int = 0  # frames while a bus was in session
    cpu_ms: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))  # by kind of work
    # wall ms of the pipeline's two steps (detection, with decoding; solving), by kind of work
    steps_ms: dict[str, list[tuple[float, float]]] = field(default_factory=lambda: defaultdict(list))
    in_view: int = 0  # (frame, bus) pairs with at least two tags of the bus fully in view
    fixed_in_view: int = 0  # ... of which the RSU made an ok fix
    fixes: int = 0
    searches_ms: list[float] = field(default_factory=list)  # frames with an acquisition search
    searches_in_vain: int = 0  # ... while none of the buses searched for had two tags in view
    # A bus entering this camera's view (two tags in view, after a frame without): the time from there to
    # this RSU's next fix of it, or a miss when it left the view first.
    entering: dict[str, int] = field(default_factory=dict)  # bus -> capture time of the entry, until fixed
    acquire_delays_ms: list[float] = field(default_factory=list)
    entries_missed: int = 0

    def figures(self, duration_s: float) -> dict:
        every = [ms for v in self.cpu_ms.values() for ms in v]
        return {"frames_in_session": self.frames, "cpu_s": round(sum(every) / 1e3, 3),
                "cores": round(sum(every) / 1e3 / duration_s, 4),
                "cpu_ms_p50": round(float(np.percentile(every, 50)), 3) if every else None,
                "by_kind": {k: {"frames": len(v), "cpu_ms_mean": round(float(np.mean(v)), 3),
                                "cpu_ms_p50": round(float(np.percentile(v, 50)), 3),
                                "detect_ms_p50": round(float(np.percentile([d for d, _ in self.steps_ms[k]], 50)), 3),
                                "solve_ms_p50": round(float(np.percentile([s for _, s in self.steps_ms[k]], 50)), 3)}
                            for k, v in sorted(self.cpu_ms.items())},
                "searches": len(self.searches_ms),
                "search_cpu_ms_p50": round(float(np.percentile(self.searches_ms, 50)), 3) if self.searches_ms else None,
                "searches_with_no_bus_in_view": self.searches_in_vain,
                "fixes": self.fixes,
                "view_entries": len(self.acquire_delays_ms) + self.entries_missed,
                "view_entries_missed": self.entries_missed,
                "acquire_delay_ms": _spread(self.acquire_delays_ms),
                "fix_rate_in_view": round(self.fixed_in_view / self.in_view, 4) if self.in_view else None}


def _spread(ms: list[float]) -> dict | None:
    if not ms:
        return None
    return {"mean": round(float(np.mean(ms)), 1), "p90": round(float(np.percentile(ms, 90)), 1),
            "max": round(float(np.max(ms)), 1)}


def scenario_frames(world: World, duration_s: float, progress=None):
    """(rsu index, capture tick, JPEG) of every RSU's frames in time order over duration_s."""
    end = world.t0_ns + int(duration_s * NS_PER_S)
    n = len(world.cameras)
    ticks = sorted((world.frame_time(r, k), r) for r in range(n)
                   for k in range(world.frame_index_from(r, end)))
    for i, (t, r) in enumerate(ticks):
        if progress is not None and i % 200 == 0:
            progress(f"rendering frame {i}/{len(ticks)}")
        jpeg, _ = world.capture(r, t)
        yield r, t, jpeg


def replay(world: World, frames, duration_s: float, settings: PipelineSettings | None = None) -> dict:
    """Every RSU pipeline on `frames` (from scenario_frames), with sessions, coarse positions and hints
    as the services would give them; figures per RSU and in all."""
    cv2.setNumThreads(1)
    pipelines = [RsuPipeline(cam, settings) for cam in world.cameras]
    tallies = [RsuTally() for _ in pipelines]
    presence = {b: IntersectionPresence(world.site) for b in world.bus_ids}
    in_session: set[str] = set()
    gnss: dict[str, GnssFix] = {}
    next_approach: dict[str, int] = {}
    filters: dict[str, BusFilter] = {}  # each bus's own filter, as its agent runs it
    last_imu: dict[str, int] = {}
    wheel: dict[str, float] = {}
    seen_by: set[tuple[int, str]] = set()  # (RSU, bus): two of its tags in view in the RSU's last frame
    last_fix: dict[str, int] = {}
    covered = samples = 0
    viewed = view_samples = 0  # (first RSU's frame, bus in session): two of its tags in some RSU's view
    # per bus, over the first RSU's frames while in session: [samples, in view, fix fresh, both]
    by_bus: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0, 0])
    for r, t, jpeg in frames:
        truth = world.truth_at(t)
        for bus in world.bus_ids:
            for g in world.gnss_between(bus, t - NS_PER_S, t):
                gnss[bus] = GnssFix(bus_id=bus, t_ns=g.t_ns, x=g.x, y=g.y, sigma_m=g.sigma_m)
            s = truth.get(bus)
            imu = world.imu_between(bus, last_imu.get(bus, t - NS_PER_S), t)
            for i in range(len(imu)):
                ti = int(imu.t_ns[i])
                if bus not in filters or s_from_ns(ti - last_imu[bus]) > IMU_GAP_RESET_S:
                    filters[bus] = BusFilter()
                filters[bus].add_imu(ti, float(imu.gyro_z[i]), float(imu.accel_x[i]), float(imu.accel_y[i]),
                                     float(imu.wheel_speed[i]))
                last_imu[bus], wheel[bus] = ti, float(imu.wheel_speed[i])
            events = presence[bus].update(s.x, s.y) if s is not None else (
                [("leave", None)] if presence[bus].current is not None else [])
            if s is None:
                presence[bus].current = None
            for event, _ in events:
                if event == "enter":
                    in_session.add(bus)
                    next_approach[bus] = t
                    for p in pipelines:
                        p.add_vehicle(world.vehicle(bus))
                else:
                    in_session.discard(bus)
                    for p in pipelines:
                        p.remove_vehicle(bus)
            if bus in in_session and t >= next_approach[bus]:
                next_approach[bus] = t + int(ANNOUNCE_PERIOD_S * NS_PER_S)
                f = filters.get(bus)
                est = f.estimate(max(t, f.head_ns)) if f is not None and f.initialized else None
                c = announced_position(est, gnss.get(bus), wheel.get(bus), t)
                if c is not None:
                    for p in pipelines:
                        p.report_position(bus, reported_position(c))
        if not in_session:
            continue
        if r == 0:  # the buses with two tags decodable in some camera's image, once for this frame
            seen_now = {pv.vehicle.id for pv in world.vehicles_at(t) if in_some_view(world.cameras, pv)}
        for bus in in_session:
            samples += 1
            covered += bus in last_fix and s_from_ns(t - last_fix[bus]) <= FIX_FRESH_S
            if r == 0:
                view_samples += 1
                seen = bus in seen_now
                fresh = bus in last_fix and s_from_ns(t - last_fix[bus]) <= FIX_FRESH_S
                viewed += seen
                tally_bus = by_bus[bus]
                tally_bus[0] += 1
                tally_bus[1] += seen
                tally_bus[2] += fresh
                tally_bus[3] += seen and fresh
        pipe, tally = pipelines[r], tallies[r]
        c0 = time.process_time()
        res = pipe.process(lambda: cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE), t)
        ms = (time.process_time() - c0) * 1e3
        tally.frames += 1
        kind = frame_kind({b: v.mode for b, v in res.vehicles.items()})
        tally.cpu_ms[kind].append(ms)
        tally.steps_ms[kind].append((res.detect_ms, res.solve_ms))
        visible = world.tags_in_view(world.cameras[r].id, t)
        if res.acquired:
            tally.searches_ms.append(ms)
            sought = [b for b, v in res.vehicles.items() if v.mode in ("acquired", "searching")]
            tally.searches_in_vain += not any(len(visible.get(b, [])) >= 2 for b in sought)
        for bus, vr in res.vehicles.items():
            seen = len(visible.get(bus, [])) >= 2
            tally.in_view += seen
            if seen and (r, bus) not in seen_by:
                tally.entering[bus] = t
            elif not seen and (r, bus) in seen_by and tally.entering.pop(bus, None) is not None:
                tally.entries_missed += 1
            (seen_by.add if seen else seen_by.discard)((r, bus))
            if vr.fix is not None:
                if bus in tally.entering:
                    tally.acquire_delays_ms.append((t - tally.entering.pop(bus)) / 1e6)
                tally.fixes += 1
                tally.fixed_in_view += seen
                last_fix[bus] = t
                if bus in filters:
                    filters[bus].add_fix(dataclasses.replace(vr.fix, clock_bound_ns=0), arrival_ns=t)
                for o, p in enumerate(pipelines):
                    if o != r:
                        p.hint(bus, t, vr.fix.x, vr.fix.y, vr.fix.yaw, vr.fix.z, vr.fix.source)
    per_rsu = {cam.id: tally.figures(duration_s) for cam, tally in zip(world.cameras, tallies)}
    in_view = sum(t.in_view for t in tallies)
    return {"duration_s": duration_s, "rsus": per_rsu,
            "cores": round(sum(r["cores"] for r in per_rsu.values()), 4),
            "searches": sum(r["searches"] for r in per_rsu.values()),
            "searches_with_no_bus_in_view": sum(r["searches_with_no_bus_in_view"] for r in per_rsu.values()),
            # A bus entering an RSU's view: how long until that RSU's first fix of it (all RSUs, all entries).
            "view_entries": sum(r["view_entries"] for r in per_rsu.values()),
            "view_entries_missed": sum(r["view_entries_missed"] for r in per_rsu.values()),
            "acquire_delay_ms": _spread([d for t in tallies for d in t.acquire_delays_ms]),
            # What the bus's "ok" needs: a fix from some RSU in the last second, at every moment in session.
            "fix_fresh_in_session": round(covered / samples, 4) if samples else None,
            # ... which no RSU can give while none sees two of the bus's tags: the bound on the above.
            "tags_in_view_in_session": round(viewed / view_samples, 4) if view_samples else None,
            # Per bus: the share of its session with two tags in some RSU's view, and how often a fix was
            # fresh over its session and while in view (what "fused ok while in view" would measure).
            "buses": {b: {"session_s": round(n[0] / world.fps[0], 1), "tags_in_view_in_session": round(n[1] / n[0], 4),
                          "fix_fresh_in_session": round(n[2] / n[0], 4),
                          "fix_fresh_in_view": round(n[3] / n[1], 4) if n[1] else None}
                      for b, n in sorted(by_bus.items())},
            "fix_rate_in_view": round(sum(t.fixed_in_view for t in tallies) / in_view, 4) if in_view else None}


def run_scenario(path: str | None = None, duration_s: float = 60.0, settings: PipelineSettings | None = None,
                 progress=None) -> dict:
    """Render the scenario's frames (not timed), then replay them through the RSU pipelines."""
    cv2.setNumThreads(1)
    world = World(load_scenario(path or bundled_scenario_path()))
    world.warm_up()
    world.start(T0_NS)
    frames = list(scenario_frames(world, duration_s, progress))
    world.start(T0_NS)  # the same sensor noise (GNSS) as if rendering and replay ran together
    if progress is not None:
        progress(f"replaying {len(frames)} frames through {len(world.cameras)} RSU pipelines ...")
    return {"scenario": str(path or bundled_scenario_path()), "image_model": world.model.describe(),
            **replay(world, frames, duration_s, settings)}
