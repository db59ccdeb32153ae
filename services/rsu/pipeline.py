"""The RSU's per-frame work, pure and testable: acquire announced buses, track them, detect only in
predicted regions at full resolution, solve each bus's pose.

Full-frame AprilTag detection costs ~0.1 s at 960×720 and >1 s at 3200×2400; the pipeline instead
(1) acquires a bus with a row-banded pyramid search (coarse where tags are big, fine where they are
small) confirmed at full resolution, then (2) tracks it, cropping each tag's predicted region."""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.rsu.regions import Band, Box, acquisition_bands, merge_boxes, tag_region
from services.rsu.tracking import TrackSettings, VehicleTrack
from toptag.camera import Camera
from toptag.detection import DetectorSettings, RawDetection, TagDetector, assign_to_vehicles
from toptag.solvers import PoseSolution, solve
from toptag.vehicle import Vehicle


class PipelineSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    method: str = "sopt"
    weighting: str = "principled"
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    tracking: bool = True
    # Acquisition pyramid: a band is searched at decimation d when its smallest tag is still this long.
    acquire_min_side_px: float = 24.0
    acquire_max_decimate: int = 8
    # While other buses are tracked, an unfound one is searched at most this often (acquisition is the
    # expensive step; tracked buses must keep their frame rate).
    acquire_period_s: float = 0.5
    crop_pad_px: float = 6.0
    workers: int = 2


@dataclass
class VehicleResult:
    vehicle_id: str
    solution: PoseSolution | None
    mode: str  # "tracked" | "acquired" | "searching" | "skipped"
    regions: int = 0


@dataclass
class FrameResult:
    t_ns: int
    vehicles: dict[str, VehicleResult] = field(default_factory=dict)
    detect_ms: float = 0.0
    solve_ms: float = 0.0
    pixels_searched: int = 0


class _DetectorPool:
    """One detector per thread and decimation: pupil-apriltags detectors are not thread-safe, and the
    ctypes calls release the GIL so crops really run on both cores."""

    def __init__(self, families, settings: DetectorSettings, workers: int):
        self.families, self.settings = families, settings
        self._local = threading.local()
        self.executor = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None

    def get(self, decimate: float = 1.0) -> TagDetector:
        cache = self._local.__dict__.setdefault("detectors", {})
        if decimate not in cache:
            s = self.settings.model_copy(update={"quad_decimate": float(decimate), "nthreads": 1})
            cache[decimate] = TagDetector(self.families, s)
        return cache[decimate]

    def detect_boxes(self, gray: np.ndarray, jobs: list[tuple[Box, float]]) -> list[list[RawDetection]]:
        """Detections per job (box, decimation), in job order."""

        def run(job):
            box, dec = job
            return self.get(dec).detect_raw(gray[box.y0:box.y1, box.x0:box.x1], offset=(box.x0, box.y0))

        if self.executor is None or len(jobs) < 2:
            return [run(j) for j in jobs]
        # Largest first so that the workers finish together.
        order = sorted(range(len(jobs)), key=lambda i: -jobs[i][0].area / jobs[i][1] ** 2)
        results = dict(zip(order, self.executor.map(run, [jobs[i] for i in order])))
        return [results[i] for i in range(len(jobs))]


class RsuPipeline:
    """Per-camera pipeline. `process(gray, t_ns)` once per frame; vehicles come and go with the bags."""

    def __init__(self, camera: Camera, settings: PipelineSettings | None = None):
        self.camera = camera
        self.settings = settings or PipelineSettings()
        self.vehicles: dict[str, Vehicle] = {}
        self.tracks: dict[str, VehicleTrack] = {}
        self._pools: dict[tuple[str, ...], _DetectorPool] = {}
        self._bands: dict[tuple[float, float], list[Band]] = {}
        self._last_acquire_ns: int | None = None

    # ---- code bags ----------------------------------------------------------------------------
    def add_vehicle(self, vehicle: Vehicle) -> None:
        self.vehicles[vehicle.id] = vehicle
        self.tracks.setdefault(vehicle.id, VehicleTrack(TrackSettings()))

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.vehicles.pop(vehicle_id, None)
        self.tracks.pop(vehicle_id, None)

    def reset_tracks(self) -> None:
        for t in self.tracks.values():
            t.reset()

    def _pool(self) -> _DetectorPool:
        families = tuple(sorted({v.family for v in self.vehicles.values()}))
        if families not in self._pools:
            self._pools[families] = _DetectorPool(families, self.settings.detector, self.settings.workers)
        return self._pools[families]

    def _acquisition_bands(self, vehicles: list[Vehicle]) -> list[Band]:
        # The smallest tag at the lowest roof decides how fine each row must be searched.
        roof = min(v.height for v in vehicles)
        size = min(min(t.size, t.extent_up) for v in vehicles for t in v.tags.values())
        key = (round(roof, 2), round(size, 3))
        if key not in self._bands:
            self._bands[key] = acquisition_bands(self.camera, roof, size, self.settings.acquire_min_side_px,
                                                 self.settings.acquire_max_decimate)
        return self._bands[key]

    # ---- per frame ----------------------------------------------------------------------------
    def process(self, gray: np.ndarray, t_ns: int) -> FrameResult:
        result = FrameResult(t_ns)
        if not self.vehicles:
            return result
        if gray.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"frame is {gray.shape[1]}x{gray.shape[0]}, camera {self.camera.id} is "
                             f"{self.camera.width}x{self.camera.height}")
        pool = self._pool()
        tracked = [vid for vid, tr in self.tracks.items() if tr.found and self.settings.tracking]
        unfound = [vid for vid in self.vehicles if vid not in tracked]
        t0 = time.perf_counter()

        jobs: list[tuple[Box, float]] = []
        regions_of: dict[str, int] = {}
        for vid in tracked:
            boxes = self._predicted_boxes(self.vehicles[vid], self.tracks[vid], t_ns)
            regions_of[vid] = len(boxes)
            jobs += [(b, 1.0) for b in boxes]
        jobs = [(b, 1.0) for b in merge_boxes([b for b, _ in jobs])]

        acquiring = bool(unfound) and self._acquisition_due(t_ns, bool(tracked))
        if acquiring:
            self._last_acquire_ns = t_ns
            jobs += [(band.box, float(band.decimate)) for band in
                     self._acquisition_bands([self.vehicles[v] for v in unfound])]
        per_job = pool.detect_boxes(gray, jobs)
        raw = [d for (_, dec), found in zip(jobs, per_job) if dec == 1.0 for d in found]
        coarse = [d for (_, dec), found in zip(jobs, per_job) if dec != 1.0 for d in found]
        wanted = {(self.vehicles[v].family, tid) for v in unfound for tid in self.vehicles[v].tag_ids}
        coarse = [d for d in coarse if (d.family, d.tag_id) in wanted]
        if coarse:
            raw += self._confirm_full_resolution(gray, coarse, pool)
        result.pixels_searched = sum(b.area for b, _ in jobs)
        result.detect_ms = (time.perf_counter() - t0) * 1e3

        t1 = time.perf_counter()
        observed = assign_to_vehicles(_dedupe(raw), self.camera, list(self.vehicles.values()))
        for vid, vehicle in self.vehicles.items():
            obs = observed.get(vid, [])
            mode = "tracked" if vid in tracked else ("acquired" if acquiring else "skipped")
            if not obs:
                if vid in tracked:
                    self.tracks[vid].miss()
                result.vehicles[vid] = VehicleResult(vid, None, mode if mode == "skipped" else "searching",
                                                     regions_of.get(vid, 0))
                continue
            sol = solve(vehicle, obs, method=self.settings.method, weighting=self.settings.weighting)
            if sol.ok:
                self.tracks[vid].update(t_ns, sol.x, sol.y, sol.yaw, sol.z)
            elif vid in tracked:
                self.tracks[vid].miss()
            result.vehicles[vid] = VehicleResult(vid, sol, mode, regions_of.get(vid, 0))
        result.solve_ms = (time.perf_counter() - t1) * 1e3
        return result

    def _acquisition_due(self, t_ns: int, others_tracked: bool) -> bool:
        if not others_tracked or self._last_acquire_ns is None:
            return True
        return (t_ns - self._last_acquire_ns) * 1e-9 >= self.settings.acquire_period_s

    def _predicted_boxes(self, vehicle: Vehicle, track: VehicleTrack, t_ns: int) -> list[Box]:
        p = track.predict(t_ns)
        boxes = [tag_region(self.camera, vehicle, tid, p.x, p.y, p.yaw, p.z, p.pos_radius, p.yaw_margin,
                            p.z_margin, self.settings.crop_pad_px) for tid in vehicle.tag_ids]
        return [b for b in boxes if b is not None]

    def _confirm_full_resolution(self, gray, raw: list[RawDetection], pool) -> list[RawDetection]:
        """Re-detect each coarse find in a crop at full resolution: decimated quads lose corner accuracy.
        A coarse find that the fine pass cannot confirm is dropped: unrefined corners are never used."""
        crops = []
        for d in raw:
            lo, hi = d.corners.min(axis=0), d.corners.max(axis=0)
            pad = 0.35 * (hi - lo).max() + self.settings.crop_pad_px  # the white border and a margin
            crops.append(Box(max(0, int(lo[0] - pad)), max(0, int(lo[1] - pad)),
                             min(self.camera.width, int(hi[0] + pad) + 1),
                             min(self.camera.height, int(hi[1] + pad) + 1)))
        return [d for found in pool.detect_boxes(gray, [(b, 1.0) for b in merge_boxes(crops)]) for d in found]


def _dedupe(raw: list[RawDetection]) -> list[RawDetection]:
    """The same tag found twice (overlapping bands or crops) keeps its most confident detection; two
    finds of one id far apart stay two (assign_to_vehicles then treats that id as ambiguous)."""
    kept: list[RawDetection] = []
    for d in sorted(raw, key=lambda d: -d.decision_margin):
        c = d.corners.mean(axis=0)
        size = np.ptp(d.corners, axis=0).max()
        if not any(k.family == d.family and k.tag_id == d.tag_id
                   and np.linalg.norm(k.corners.mean(axis=0) - c) < max(4.0, 0.5 * size) for k in kept):
            kept.append(d)
    return kept
