"""The RSU's per-frame work, pure and testable: acquire announced buses, track them, detect only in
predicted regions at full resolution, solve each bus's pose.

Full-frame AprilTag detection costs ~0.1 s at 960×720 and >1 s at 3200×2400; the pipeline instead
(1) acquires a bus with a row-banded pyramid search (coarse where tags are big, fine or enlarged where
they are small), confirmed at full resolution, then (2) tracks it, cropping each tag's predicted region."""
from __future__ import annotations

import functools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from toptag.camera import Camera
from toptag.detection import (
    DetectorSettings,
    RawDetection,
    TagDetector,
    assign_to_vehicles,
)
from toptag.fix import Fix
from toptag.geometry import vehicle_to_world
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.rsu.regions import (
    Band,
    Box,
    acquisition_bands,
    merge_boxes,
    projected_side_px,
    tag_region,
)
from toptag.rsu.tracking import SPEED_MARGIN, TrackSettings, VehicleTrack
from toptag.rsu.whereabouts import ReportedPosition, ViewGrid, Whereabouts, tile_boxes
from toptag.solvers import PoseSolution, canonical_method, solve
from toptag.solvers.calibrated import with_calibration
from toptag.solvers.level import TURN_RATIO
from toptag.units import s_from_ns
from toptag.vehicle import Vehicle


class PipelineSettings(BaseModel):
    """The RSU's per-frame work (the [pipeline] table of `toptag rsu --config`)."""

    model_config = ConfigDict(extra="forbid")

    method: str = "level"  # toptag.solvers: bas | hopt | sopt | level (level roof, edge-noise weighting)
    weighting: Literal["paper", "principled"] = "principled"
    # The level solver's corner-noise model for this camera's images: sigma of a tag edge's turn over its
    # offset's (toptag.solvers.level). Default: real photographs' (TURN_RATIO, docs/real-data.md). Yaw
    # rests on the turns: a camera whose edges turn more than this gets yaw covariances too small (the
    # simulator's renderer measures 2: `toptag eval livefix --turn-ratio`, docs/time-and-trust.md).
    turn_ratio: float = Field(default=TURN_RATIO, gt=0)
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    tracking: bool = True
    # Acquisition: "pyramid" searches each row band at the coarsest level that still resolves a tag at
    # least acquire_min_side_px long; "full" searches the whole frame at detector.quad_decimate.
    acquire_mode: Literal["pyramid", "full"] = "pyramid"
    acquire_min_side_px: float = 24.0
    acquire_max_decimate: int = 8
    # The detector's second decode pass (DetectorSettings.unrefined_pass) in acquisition's bands: it
    # doubles a search's cost (most of it in the far, enlarged band) and, on the demo's frames, found no
    # bus the first pass missed (`toptag bench rsu --scenario`: same fixes, 0.76 -> 0.56 cores).
    acquire_unrefined_pass: bool = False
    # In acquisition's decimated bands (whose finds are re-detected at full resolution), the quad search
    # leaves out regions whose brightest and darkest pixels differ by less than this fraction of the
    # frame's mean grey level (AprilTag's min_white_black_diff, kept within its default 5 and
    # ACQUIRE_MAX_CONTRAST): flat road under sensor noise is most of a search's cost, and a tag differs
    # from its white border by about the scene's mean level (1.15x in the simulator's default lighting; a
    # roof in a shadow that takes 80 % of the light still passes). 0: the library's floor everywhere.
    acquire_min_contrast: float = Field(default=0.2, ge=0.0, le=1.0)
    # Tags whose shortest side is below this many pixels are detected in a 2x enlarged image: at 20-25 m
    # on 960x720 a cell is 1-2 px tall and decoding fails without it.
    upsample_below_px: float = 24.0
    # Tracking crops of tags whose shortest side is at least k times this many pixels (k >= 2) run the
    # quad search decimated k times (at most track_max_decimate), edges refined and bits decoded at full
    # resolution: a bus near the camera made crops of up to the whole frame, 50-100 ms of CPU per frame
    # and the demo's slowest tracked frames (docs/architecture.md). 0: tracking crops are never decimated.
    track_decimate_side_px: float = Field(default=32.0, ge=0.0)
    track_max_decimate: int = Field(default=4, ge=1)
    # acquire_min_contrast's floor in tracking (and hinted) crops too: a velocity-less track's crops (the
    # first frames after an acquisition) grow by the top speed over the frames since, to the whole frame
    # after a slow search, and their flat road costs what a search's does: at full resolution on the
    # simulator's frames, 25-28 ms against 10-11 ms of CPU for the same corners (the contrast floor only
    # leaves regions out of the quad search; edges are refined on the image). 0: the library's floor.
    track_min_contrast: float = Field(default=0.2, ge=0.0, le=1.0)
    # ... in acquisition's search (None: upsample_below_px). A find is confirmed at full resolution, enlarged
    # by upsample_below_px, so this changes what a search finds, not the fix. On the demo's renderer and
    # image model (`python -m sim.studies.acquire_range`, 313 tags at 960x720), 16 decoded 226 tags where
    # 24 decoded 227, for 23 % less search work (12: 205 tags).
    acquire_upsample_below_px: float | None = Field(default=16.0, gt=0)
    # While other buses are tracked, an unfound one is searched at most this often: acquisition is the
    # expensive step and tracked buses must keep their frame rate.
    acquire_period_s: float = 0.5
    # With nothing tracked, the search runs at most this often (0: every frame): at 960x720 one costs
    # ~35 ms of CPU, 7x a tracked frame, and every RSU of the intersection searches until a bus is found
    # (a bus entering the view is found at most this much later). Only when tracking (tracking=False
    # means a search on every frame).
    acquire_idle_period_s: float = Field(default=0.25, ge=0.0)
    # Another RSU's fix of a bus this camera has not found tells where to look (or that the bus is out
    # of view and nothing needs searching); it is tracked from for this long, with this extra margin for
    # the two cameras' calibration differences. Older, it still bounds where acquisition searches (at the
    # distance the bus may have driven since).
    hint_max_age_s: float = 1.0
    hint_margin_m: float = 0.3
    # The bus's own fused pose (its Approach's whereabouts, with heading and velocity), when it is this
    # sure at the frame's time (position margin, heading margin), is tracked from like another RSU's fix:
    # crops where its tags must be, or nothing when none is in view. After report_hint_misses frames of
    # crops that found nothing, it only bounds the search again (until this camera fixes the bus).
    report_hint_max_radius_m: float = 1.5
    report_hint_max_yaw_rad: float = 0.4
    report_hint_misses: int = 3
    # The bus's own coarse position (its Approach's: GNSS, or its fused pose with velocity) bounds where
    # it can be, so that acquisition searches only there (or waits while that is out of view); trusted
    # for this long, at 3 sigma, moved on at its velocity (ReportedPosition.disc_at).
    coarse_max_age_s: float = 2.5
    # Acquisition searches only where an unfound bus can be (toptag.rsu.whereabouts): after a search in
    # vain, only where it can have come since. False: the whole frame every time.
    search_where_possible: bool = True
    # ... and only where some tag of the bus can project with a minor extent (its extent across its most
    # foreshortened direction, toptag.rsu.regions.tag_minor_px) of at least this many px: where all are
    # smaller the detector cannot decode them and a search is in vain (the bus is left to the RSUs that see
    # it larger, whose fixes hint this one). On the demo's renderer and image model at 960x720, acquisition
    # decoded no tag below 6.8 px, 0 of 28 below 6 px, 2 of 26 at 6-8 px, 6 of 25 at 8-9 px (`python -m
    # sim.studies.acquire_range`); this is the smallest decoded with a margin, and the grid takes each
    # cell's best case (the bus anywhere in the cell, at any yaw). 0: wherever its footprint is in the image.
    acquire_min_tag_px: float = Field(default=6.0, ge=0.0)
    crop_pad_px: float = 6.0
    workers: int = Field(default=2, ge=1)
    # The RSU service's acquisition search (on its own thread, niced) runs its costly jobs on the detector's
    # own threads (as many as workers): on a host of its own, an RSU finds a bus sooner. Where several RSUs
    # share a host's cores and search the same frame at once (a bus's Approach reaches them together), those
    # threads cost CPU and gain no time: the demo's four RSUs on two cores, three runs each alternately,
    # searches single-threaded took 0.85x the CPU and gave the bus's first fixes p50 98-108 ms against
    # 113-156 (docs/real-time.md). False: every search job on the search thread alone.
    search_threaded: bool = True
    # An acquisition search ends after the job (largest first) by which every bus it seeks has this many of
    # its tags found (all of them if it has fewer): that bus's first fix needs no more, and its tracking crops
    # find the rest on the next frame. In the demo the bus entering a view was found whole in a search's
    # first job, 40-55 % of its cost (`toptag bench rsu --scenario`, docs/real-time.md). 0: every job runs.
    acquire_enough_tags: int = Field(default=2, ge=0)
    # An RSU that sees little of where an unfound bus probably is holds its search for that bus back, for at
    # most acquire_defer_frames frames in a row on which it is due, unless that grows: a bus's Approach
    # reaches every RSU of the intersection at once and each would search the same frame, on the same cores in
    # the demo, while usually one sees the bus; its fix comes as a hint within a frame or two, by which the
    # others crop cheaply instead (or know the bus is out of their view). "Probably" is the bus's reported
    # position as a Gaussian (sigma a third of ReportedPosition.disc_at's radius); "sees" is its share over
    # the cells where the bus is likely found (ViewGrid.likely: its centre in the image, its tags decodable).
    # In the demo the RSU that found a bus had 0.96-1.0 of it, the three that searched in vain 0.00-0.03 (a
    # probe of the sixteen searches of a `toptag bench demo --duration 60`); held back, they crop from the
    # finder's fix a frame or two later, and the demo runs four searches instead of sixteen: the buses' first
    # fixes p99 54-83 ms against 71-130 (docs/real-time.md). 0 frames: never held back.
    acquire_defer_below_share: float = Field(default=0.5, ge=0.0, le=1.0)
    acquire_defer_frames: int = Field(default=3, ge=0)

    @field_validator("method")
    @classmethod
    def _known_method(cls, v: str) -> str:
        return canonical_method(v)


@dataclass(frozen=True)
class DetectJob:
    box: Box
    decimate: float = 1.0
    upsample: int = 1
    thorough: bool = True  # no tag known there: decode with the second pass (DetectorSettings.unrefined_pass)
    expect: frozenset[tuple[str, int]] | None = None  # tags found there coarsely: the second pass only if one is missed
    min_contrast: int | None = None  # grey levels a region must span to be searched (None: the detector's floor)

    @property
    def cost(self) -> float:
        return self.box.area * (self.upsample / self.decimate) ** 2


@dataclass
class VehicleResult:
    vehicle_id: str
    solution: PoseSolution | None
    mode: str  # "tracked" | "hinted" | "out_of_view" | "acquired" | "searching" | "waiting"
    regions: int = 0
    observations: list = field(default_factory=list)  # the TagObservations the solution was made from
    fix: Fix | None = None  # the solution as a fix of this camera (set when the solution is ok)


@dataclass
class FrameResult:
    t_ns: int
    vehicles: dict[str, VehicleResult] = field(default_factory=dict)
    detect_ms: float = 0.0
    solve_ms: float = 0.0
    pixels_searched: int = 0
    search_cost_px: float = 0.0  # the acquisition search's detection work (DetectJob.cost), 0 without one
    acquired: bool = False
    search_deferred: bool = False  # a search for the unfound buses was begun, to go on in continue_search


@dataclass
class _Search:
    """An acquisition search begun on one frame and run while later frames are processed: its work on
    another thread (RsuPipeline.process(defer_search=True), search_work), ended by continue_search."""

    t_ns: int
    seq: int | None
    gray: np.ndarray | None  # None: no jobs
    vehicle_ids: list[str]
    tiles: np.ndarray | None  # the image tiles searched (None: the whole frame)
    jobs: list[DetectJob]  # largest first
    pool: "_DetectorPool"
    wanted: frozenset = frozenset()  # (family, tag id) of the buses sought: the coarse finds worth confirming
    # Per bus sought, (its tags' (family, tag id), how many found end the search): PipelineSettings.acquire_enough_tags
    enough: tuple[tuple[frozenset, int], ...] = ()
    ended_early: bool = False  # its last jobs were not run (enough found): it says nothing of where buses are not
    detect_s: float = 0.0
    raw: list | None = None  # all its detections, once its work has run (RsuPipeline.search_work)
    handed_out: bool = False  # its work was given to another thread (search_work)

    @property
    def pixels(self) -> int:
        return sum(j.box.area for j in self.jobs)

    @property
    def cost_px(self) -> float:
        return sum(j.cost for j in self.jobs)


# The contrast floor of acquisition's decimated bands and of tracking's crops (PipelineSettings.
# acquire_min_contrast, track_min_contrast) in grey
# levels: at least AprilTag's own default; at most 20, a sixth of a default-lit tag's contrast (a bright
# or overexposed frame does not raise it further).
APRILTAG_MIN_CONTRAST, ACQUIRE_MAX_CONTRAST = 5, 20
# A lone job at least this costly (DetectJob.cost: pixels searched) runs on the detector's own threads
# (the C library's: its stages split the image in rows, same results): acquisition's confirmation at
# full resolution would otherwise keep one core waiting. Smaller ones (tracking crops) are not worth
# the threads' hand-offs.
_THREADED_JOB_COST = 100_000
# Peer fixes of one camera this far apart at least make a hint track's velocity (RsuPipeline.hint): the
# tracker's own frame spacing, whose velocity error TrackSettings.velocity_error_mps bounds.
HINT_MIN_SPACING_S = 0.08


class _DetectorPool:
    """One detector per thread and threading (each job sets its own decimation): pupil-apriltags detectors
    are not thread-safe, and its ctypes calls release the GIL, so crops really run on both cores."""

    def __init__(self, families, settings: DetectorSettings, workers: int):
        self.families, self.settings, self.workers = families, settings, workers
        self._local = threading.local()
        self.executor = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None

    def _detector(self, threaded: bool = False) -> TagDetector:
        cache = self._local.__dict__.setdefault("detectors", {})
        if threaded not in cache:
            nthreads = max(self.settings.nthreads, self.workers) if threaded else self.settings.nthreads
            cache[threaded] = TagDetector(self.families, self.settings.model_copy(update={"nthreads": nthreads}))
        return cache[threaded]

    def prepare_here(self, threaded: bool = True) -> None:
        """Build the calling thread's detectors now (run_here uses them; threaded: also the one on the
        detector's own threads)."""
        self._detector(False)
        if threaded and self.workers > 1:
            self._detector(True)

    def prepare_workers(self) -> None:
        """Build each worker's detector now: every worker takes one build and waits for the others, so
        that no worker builds twice while another builds none."""
        if self.executor is None:
            return
        barrier = threading.Barrier(self.workers)

        def build(_) -> None:
            self._detector(False)
            try:
                barrier.wait(timeout=30.0)
            except threading.BrokenBarrierError:
                pass  # a worker was late: it builds its detector on its first job instead

        list(self.executor.map(build, range(self.workers)))

    def _one(self, gray: np.ndarray, job: DetectJob, threaded: bool = False) -> list[RawDetection]:
        b = job.box
        return self._detector(threaded).detect_raw(
            gray[b.y0:b.y1, b.x0:b.x1], (b.x0, b.y0), job.upsample, None if job.thorough else False, job.expect,
            job.min_contrast, job.decimate)

    def run_here(self, gray: np.ndarray, jobs: list[DetectJob], threaded: bool = True) -> list[list[RawDetection]]:
        """Detections per job, in job order, each on the calling thread (a costly one on the detector's own
        threads, which the calling thread starts, unless not threaded)."""
        return [self._one(gray, j, threaded and self.workers > 1 and j.cost >= _THREADED_JOB_COST) for j in jobs]

    def run(self, gray: np.ndarray, jobs: list[DetectJob]) -> list[list[RawDetection]]:
        """Detections per job, in job order (on the workers when there are several)."""
        if self.executor is None or len(jobs) < 2:
            return self.run_here(gray, jobs)
        order = sorted(range(len(jobs)), key=lambda i: -jobs[i].cost)  # largest first: workers end together
        results = dict(zip(order, self.executor.map(lambda j: self._one(gray, j), [jobs[i] for i in order])))
        return [results[i] for i in range(len(jobs))]


class RsuPipeline:
    """Per-camera pipeline. `process(gray, t_ns, seq)` once per frame; vehicles come and go with their
    bags. Its fixes carry the camera id as their source."""

    def __init__(self, camera: Camera, settings: PipelineSettings | None = None):
        self.camera = camera
        self._calibration_id = camera.calibration_id  # every fix names it: a bus forgets a recalibrated camera's past
        self.settings = settings or PipelineSettings()
        self.vehicles: dict[str, Vehicle] = {}
        self.tracks: dict[str, VehicleTrack] = {}
        self._pools: dict[tuple[str, ...], _DetectorPool] = {}
        self._bands: dict[tuple[float, float], list[Band]] = {}
        self._hints: dict[str, dict[str, VehicleTrack]] = {}  # bus -> the peer camera whose fixes make it -> track
        self._coarse: dict[str, ReportedPosition] = {}
        self._report_misses: dict[str, int] = {}
        self._last_acquire_ns: int | None = None
        self._grids: dict[tuple, ViewGrid] = {}  # by kind of vehicle (_view_grid)
        self._whereabouts: dict[str, Whereabouts] = {}
        self._search: _Search | None = None  # a deferred search under way
        self._held: dict[str, int] = {}  # bus -> due searches held back in a row (_search_held_back)

    # ---- code bags ----------------------------------------------------------------------------
    def add_vehicle(self, vehicle: Vehicle) -> None:
        """A bus's code bag (its Approach): detected from the next frame on. Its kind's view grid (where it can
        be seen from this camera) is built now if it is new here, not on the session's first frame: ~25 ms of
        CPU that every RSU of the intersection spent at once, on the frame whose search gives the bus's first
        fix (its latency, `toptag bench demo`'s acquired fixes)."""
        self.vehicles[vehicle.id] = vehicle
        self.tracks.setdefault(vehicle.id, VehicleTrack(TrackSettings()))
        if self._bounded():
            self._view_grid(vehicle)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.vehicles.pop(vehicle_id, None)
        self.tracks.pop(vehicle_id, None)
        self._hints.pop(vehicle_id, None)
        self._coarse.pop(vehicle_id, None)
        self._report_misses.pop(vehicle_id, None)
        self._whereabouts.pop(vehicle_id, None)
        self._held.pop(vehicle_id, None)
        if self._search is not None and not any(v in self.vehicles for v in self._search.vehicle_ids):
            self._search = None

    def coarse_position(self, vehicle_id: str, t_ns: int, x: float, y: float, sigma_m: float,
                        velocity: tuple[float, float] | None = None, velocity_sigma: float = 0.0,
                        speed: float | None = None, yaw: float | None = None, yaw_sigma: float = 0.0) -> None:
        """The vehicle's own rough position (metres of error), with its velocity or speed, and heading,
        when it knows them: bounds where acquisition searches, or, when sure enough, where to crop."""
        self.report_position(vehicle_id, ReportedPosition(t_ns, x, y, sigma_m, velocity, velocity_sigma, speed, yaw,
                                                          yaw_sigma))

    def report_position(self, vehicle_id: str, report: ReportedPosition) -> None:
        """As coarse_position, the report whole (its roof height is the vehicle's)."""
        if vehicle_id in self.vehicles:
            self._coarse[vehicle_id] = replace(report, z=self.vehicles[vehicle_id].height)

    def _whereabouts_at(self, vid: str, t_ns: int) -> Whereabouts:
        """Where the unfound vehicle can be at t_ns: grown since the last frame, cut to its coarse
        position and to the latest hint, each widened by the distance the bus may have driven since."""
        wb = self._whereabouts.get(vid)
        if wb is None:
            wb = self._whereabouts[vid] = Whereabouts(self._view_grid(self.vehicles[vid]),
                                                      BUS_MAX_SPEED_MPS * SPEED_MARGIN)
        wb.advance(t_ns)
        c, h = self._coarse.get(vid), self._newest_hint(vid)
        if c is not None and s_from_ns(abs(t_ns - c.t_ns)) <= self.settings.coarse_max_age_s:
            wb.limit(*c.disc_at(t_ns, BUS_MAX_SPEED_MPS * SPEED_MARGIN))
        if h is not None:
            wb.limit(h.pose[0], h.pose[1], self.settings.hint_margin_m + self._driven(h.t_ns, t_ns))
        return wb

    def _view_grid(self, v: Vehicle) -> ViewGrid:
        """This camera's view grid for vehicles of v's kind (its roof height, footprint and tag sizes): built
        once per kind, kept for the pipeline's life."""
        tags = tuple(sorted({(round(t.size, 3), round(t.extent_up, 3)) for t in v.tags.values()}))
        key = (round(v.height, 2), round(float(np.hypot(v.length, v.width)) / 2, 2), tags)
        grid = self._grids.get(key)
        if grid is None:
            grid = self._grids[key] = ViewGrid.build(self.camera, key[0], key[1], pad_px=self.settings.crop_pad_px,
                                                     tags_m=tags, min_tag_px=self.settings.acquire_min_tag_px)
        return grid

    @staticmethod
    def _driven(since_ns: int, t_ns: int) -> float:
        """The farthest a bus can have gone between the two times."""
        return BUS_MAX_SPEED_MPS * SPEED_MARGIN * s_from_ns(abs(t_ns - since_ns))

    def hint(self, vehicle_id: str, t_ns: int, x: float, y: float, yaw: float, z: float,
             source: str | None = None) -> None:
        """A pose of an announced vehicle from elsewhere (another RSU's fix; source: that camera's id).
        The fixes of one source make a track: one at least HINT_MIN_SPACING_S after the last gives it a
        velocity, so a hinted crop is the bus's predicted motion's margin (~0.5 m at 0.1 s), not the
        top speed in any direction (2 m). Closer fixes, or fixes of two cameras (whose calibrations differ
        by up to hint_margin_m), would make a velocity of noise: a closer one is left out while the track
        has a velocity, else it restarts the track."""
        if vehicle_id not in self.vehicles:
            return
        tracks = self._hints.setdefault(vehicle_id, {})
        track = tracks.get(source)
        if track is None or not track.found or t_ns < track.t_ns \
                or s_from_ns(t_ns - track.t_ns) > self.settings.hint_max_age_s:
            track = tracks[source] = VehicleTrack(TrackSettings())
        elif s_from_ns(t_ns - track.t_ns) < HINT_MIN_SPACING_S:
            if track.velocity is not None:
                return
            track.reset()
        track.update(t_ns, x, y, yaw, z)

    def _newest_hint(self, vid: str) -> VehicleTrack | None:
        tracks = self._hints.get(vid)
        return max(tracks.values(), key=lambda tr: tr.t_ns) if tracks else None

    def _pool(self, families: tuple[str, ...] | None = None) -> _DetectorPool:
        if families is None:
            families = tuple(sorted({v.family for v in self.vehicles.values()}))
        if families not in self._pools:
            self._pools[families] = _DetectorPool(families, self.settings.detector, self.settings.workers)
        return self._pools[families]

    def prepare(self, families: Iterable[str]) -> Callable[[], None]:
        """Build now the detectors that buses of these tag families will need, on the calling thread (the
        one that processes frames) and the pool's workers; returns the same work for the thread that will
        run search_work. A detector takes tens of milliseconds to build (its decode table), a few times
        that on a loaded machine: built on a session's first frames it would hold them up."""
        pool = self._pool(tuple(sorted(set(families))))
        pool.prepare_here()
        pool.prepare_workers()
        return functools.partial(pool.prepare_here, self.settings.search_threaded)

    # ---- per frame ----------------------------------------------------------------------------
    def process(self, gray: np.ndarray | Callable[[], np.ndarray], t_ns: int, seq: int | None = None,
                on_vehicle: Callable[[VehicleResult], None] | None = None, defer_search: bool = False) -> FrameResult:
        """Detect and solve every announced vehicle in the frame captured at t_ns (frame number seq).
        gray: the image, or a function that decodes it, called only when some region is to be searched
        (a frame whose buses are all out of view, or whose search is not due, is never decoded).
        on_vehicle: called with each vehicle's result as soon as it is final; the tracked and hinted
        buses' come before the frame's acquisition search runs, so their fixes never wait for it.
        defer_search: a due acquisition search is only begun (result.search_deferred; the unfound buses
        are "waiting"), to be run by continue_search between frames, so that it never delays the next
        frame; no other search begins until it ends."""
        result = FrameResult(t_ns)
        if not self.vehicles:
            return result
        pool = self._pool()
        tracked = [vid for vid, tr in self.tracks.items() if tr.found and self.settings.tracking]
        hints = {vid: self._hint_at(vid, t_ns) for vid in self.vehicles if vid not in tracked}
        hinted = [vid for vid, h in hints.items() if h is not None]
        rest = [vid for vid in self.vehicles if vid not in tracked and vid not in hinted]
        t0 = time.perf_counter()
        where = {vid: self._whereabouts_at(vid, t_ns) for vid in rest} if self._bounded() else {}
        away = [vid for vid in rest if vid in where and not where[vid].in_view]
        unfound = [vid for vid in rest if vid not in away]
        decoded: list[np.ndarray] = []

        def image() -> np.ndarray:
            if not decoded:
                g = gray() if callable(gray) else gray
                if g.shape != (self.camera.height, self.camera.width):
                    raise ValueError(f"frame is {g.shape[1]}x{g.shape[0]}, camera {self.camera.id} is "
                                     f"{self.camera.width}x{self.camera.height}")
                decoded.append(g)
            return decoded[0]

        def done(vr: VehicleResult) -> None:
            result.vehicles[vr.vehicle_id] = vr
            if on_vehicle is not None:
                on_vehicle(vr)

        # Tracked and hinted buses: crops around where each must be. Those of buses tracked from frame to
        # frame (a velocity, no miss: crops of about their tags' size) are searched and solved first, so
        # that their fixes never wait for the wide crops of a bus found on one frame only, missed, or hinted
        # (up to the whole frame: 50-150 ms of CPU in the demo, docs/architecture.md).
        jobs_of: dict[str, list[DetectJob]] = {}
        for vid in tracked + hinted:
            track, extra = (self.tracks[vid], 0.0) if vid in tracked else hints[vid]
            jobs_of[vid] = self._tracking_jobs(self.vehicles[vid], track, t_ns, extra)
        regions_of = {vid: len(vjobs) for vid, vjobs in jobs_of.items()}
        steady = [vid for vid in tracked if self.tracks[vid].velocity is not None and self.tracks[vid].misses == 0]
        all_jobs: list[DetectJob] = []
        found: list[list[RawDetection]] = []
        raw: list[RawDetection] = []
        observed: dict = {}  # per vehicle, its tags among raw (as assigned after the last stage)
        t1 = t0  # the start of a stage's detection (the first's includes the whereabouts above)
        for stage in (steady, [vid for vid in tracked + hinted if vid not in steady]):
            if not stage:
                continue
            jobs = _merge_jobs([j for vid in stage for j in jobs_of[vid]])
            jobs = self._contrast_floor(image(), jobs, self.settings.track_min_contrast, True) if jobs else []
            if jobs:
                all_jobs += jobs
                found += pool.run(image(), jobs)
                raw = _own_crop_first(all_jobs, found)
            result.pixels_searched += sum(j.box.area for j in jobs)
            t2 = time.perf_counter()
            result.detect_ms += (t2 - t1) * 1e3
            observed = assign_to_vehicles(_dedupe(raw), self.camera, list(self.vehicles.values()))
            for vid in stage:
                mode = "tracked" if vid in tracked else ("hinted" if regions_of[vid] else "out_of_view")
                vr = self._conclude(vid, observed.get(vid, []), mode, t_ns, seq, regions_of[vid])
                if vid in hinted and isinstance(hints[vid][0], ReportedPosition):
                    if vr.fix is None and regions_of[vid] > 0:
                        self._report_misses[vid] = self._report_misses.get(vid, 0) + 1
                done(vr)
            t1 = time.perf_counter()
            result.solve_ms += (t1 - t2) * 1e3
        t2 = time.perf_counter()
        result.detect_ms += (t2 - t1) * 1e3  # without tracked or hinted buses: the whereabouts above

        # The others: searched for where they can be, if a search is due.
        due = bool(unfound) and self._search is None and self._acquisition_due(t_ns, bool(tracked))
        sought = [v for v in unfound if not self._search_held_back(v, t_ns)] if due else unfound
        for v in unfound if due else ():
            self._held[v] = 0 if v in sought else self._held.get(v, 0) + 1
        due = due and bool(sought)
        search = None
        if due:
            self._last_acquire_ns = t_ns
            tiles = np.logical_or.reduce([where[v].tile_mask() for v in sought]) if where else None
            jobs = self._acquisition_jobs([self.vehicles[v] for v in sought], tiles)
            jobs = self._contrast_floor(image(), jobs, self.settings.acquire_min_contrast) if jobs else []
            tags_of = {v: frozenset((self.vehicles[v].family, tid) for tid in self.vehicles[v].tag_ids)
                       for v in sought}
            wanted = frozenset().union(*tags_of.values())
            n = self.settings.acquire_enough_tags
            enough = tuple((tags, min(n, len(tags))) for tags in tags_of.values()) if n else ()
            search = _Search(t_ns, seq, image() if jobs else None, list(sought), tiles,
                             sorted(jobs, key=lambda j: -j.cost), pool, wanted, enough)
            result.pixels_searched += search.pixels
            result.search_cost_px = search.cost_px
            if defer_search and jobs:
                self._search, result.search_deferred = search, True
            else:
                result.acquired = True
                raw += self._run_search(search)
                observed = assign_to_vehicles(_dedupe(raw), self.camera, list(self.vehicles.values()))
        t3 = time.perf_counter()
        result.detect_ms += (t3 - t2) * 1e3
        for vid in away + unfound:
            mode = "out_of_view" if vid in away else ("acquired" if result.acquired and vid in sought else "waiting")
            obs = observed.get(vid, [])  # an "away" bus's tags may still show in another's crop
            vr = self._conclude(vid, obs, mode, t_ns, seq, 0)
            if result.acquired and search.tiles is not None and vid in sought and not obs:
                where[vid].searched(search.tiles)
            done(vr)
        result.solve_ms += (time.perf_counter() - t3) * 1e3
        result.vehicles = {vid: result.vehicles[vid] for vid in self.vehicles}
        return result

    @property
    def tracking(self) -> bool:
        """Is some bus tracked?"""
        return self.settings.tracking and any(tr.found for tr in self.tracks.values())

    @property
    def search_pending(self) -> bool:
        """Is a deferred search under way (continue_search)?"""
        return self._search is not None

    @property
    def search_ready(self) -> bool:
        """Has the deferred search's work run on another thread (search_work), so that continue_search ends it?"""
        return self._search is not None and self._search.raw is not None

    def drop_search(self) -> None:
        """Abandon the deferred search (its buses are searched for again when due)."""
        self._search = None

    def search_work(self) -> Callable[[], None] | None:
        """The deferred search's detection (its jobs, then its coarse finds confirmed at full resolution) as
        work for another thread, so that frames go on being processed meanwhile: it reads only the search's
        own frame and jobs, runs them one at a time on the calling thread (not on the pool's workers, which
        the frames' crops use), and touches nothing else of the pipeline. Once it has run, continue_search
        ends the search at once. None when no search is pending or its work was handed out already."""
        s = self._search
        if s is None or s.handed_out:
            return None
        s.handed_out = True

        def work() -> None:
            s.raw = self._run_search(s, alone=True)

        return work

    def continue_search(self, on_vehicle: Callable[[VehicleResult], None] | None = None) -> FrameResult | None:
        """End the deferred search (running its work here unless search_work handed it out): its frame's
        result for the buses it sought (mode "acquired", or "searching" when not found; a bus found
        meanwhile by other means, or gone, is left out), each also to on_vehicle. None when there is
        none, or while its work runs on another thread."""
        s = self._search
        if s is None or (s.handed_out and s.raw is None):  # none, or its work runs elsewhere
            return None
        raw = s.raw if s.raw is not None else self._run_search(s)
        self._search = None
        t0 = time.perf_counter()
        result = FrameResult(s.t_ns, acquired=True, pixels_searched=s.pixels, search_cost_px=s.cost_px)
        observed = assign_to_vehicles(_dedupe(raw), self.camera, list(self.vehicles.values()))
        for vid in s.vehicle_ids:
            if vid not in self.vehicles or self.tracks[vid].found:
                continue
            obs = observed.get(vid, [])
            vr = self._conclude(vid, obs, "acquired", s.t_ns, s.seq, 0)
            wb = self._whereabouts.get(vid)
            if s.tiles is not None and not obs and wb is not None and not s.ended_early:
                # not there at the search's frame; since then it may have driven back into some of it
                wb.searched(s.tiles, regrow_m=self._driven(s.t_ns, wb.t_ns if wb.t_ns is not None else s.t_ns))
            result.vehicles[vid] = vr
            if on_vehicle is not None:
                on_vehicle(vr)
        result.detect_ms = s.detect_s * 1e3
        result.solve_ms = (time.perf_counter() - t0) * 1e3
        return result

    def _run_search(self, s: _Search, alone: bool = False) -> list[RawDetection]:
        """The search's detections (coarse finds confirmed at full resolution), up to the job by which it found
        enough (_found_enough). alone: its jobs on the calling thread, one after the other, none after that one
        (search_work; on the detector's threads only if search_threaded); else all on the pool's workers."""
        run = functools.partial(s.pool.run_here, threaded=self.settings.search_threaded) if alone else s.pool.run
        t0 = time.perf_counter()
        try:
            # alone: each job run when the ones before have not found enough; else all at once on the pool's
            # workers, of which the same jobs' detections are used
            results = (found for job in s.jobs for found in run(s.gray, [job])) if alone else iter(run(s.gray, s.jobs))
            per_job = []
            for found in results:
                per_job.append(found)
                if _found_enough(s, per_job):
                    break
            jobs = s.jobs[:len(per_job)]
            s.ended_early = len(jobs) < len(s.jobs)
            raw = [d for job, found in zip(jobs, per_job) if job.decimate == 1.0 for d in found]
            coarse = [d for job, found in zip(jobs, per_job) if job.decimate != 1.0 for d in found
                      if (d.family, d.tag_id) in s.wanted]
            if coarse:
                raw += self._confirm_full_resolution(s.gray, coarse, run)
            return raw
        finally:
            s.detect_s += time.perf_counter() - t0

    def _conclude(self, vid: str, obs: list, mode: str, t_ns: int, seq: int | None, regions: int) -> VehicleResult:
        """Solve one vehicle from its observations in this frame and update its track."""
        vehicle = self.vehicles[vid]
        sol = solve(vehicle, obs, method=self.settings.method, weighting=self.settings.weighting,
                    turn_ratio=self.settings.turn_ratio) if obs else None
        fix = None
        if sol is not None and sol.ok:
            # never more certain than the camera's calibration, weighed as the solve weighed the corners
            calib = with_calibration(vehicle, obs, sol, self.settings.turn_ratio)
            fix = Fix.from_solution(sol, t_ns, self.camera.id, seq, calib, self._calibration_id)
            track = self.tracks[vid]
            first = not track.found
            track.update(t_ns, sol.x, sol.y, sol.yaw, sol.z)
            if first:
                self._seed_velocity(vid, track)
            self._whereabouts.pop(vid, None)
            self._report_misses.pop(vid, None)
            self._held.pop(vid, None)
        elif mode == "tracked":
            self._lost_track(vid)
        if sol is None and mode not in ("waiting", "out_of_view"):
            mode = "searching"
        return VehicleResult(vid, sol, mode, regions, obs, fix)

    def _seed_velocity(self, vid: str, track: VehicleTrack) -> None:
        """A track begun from one fix (the bus found by a hinted crop or a search) takes the velocity of a
        fresh hint track of the bus: its next crops are the predicted motion's margin, not the top speed's."""
        s = self.settings
        moving = [h for h in self._hints.get(vid, {}).values()
                  if h.velocity is not None and s_from_ns(abs(track.t_ns - h.t_ns)) <= s.hint_max_age_s]
        if moving:
            track.velocity = min(moving, key=lambda h: abs(track.t_ns - h.t_ns)).velocity.copy()

    def _bounded(self) -> bool:
        """Is acquisition limited to where the buses can be? (Not in the search-every-frame mode.)"""
        return self.settings.tracking and self.settings.search_where_possible

    def _lost_track(self, vid: str) -> None:
        """A tracked frame without the bus: after a few, the track is lost and the bus is searched for
        where it can have gone since its last fix (a widening region, not the whole frame)."""
        track = self.tracks[vid]
        last = (track.t_ns, *track.pose[:2])
        track.miss()
        if not track.found and self._bounded():
            self._whereabouts.pop(vid, None)
            wb = self._whereabouts_at(vid, last[0])
            wb.limit(last[1], last[2], self.settings.hint_margin_m)

    def _acquisition_due(self, t_ns: int, others_tracked: bool) -> bool:
        s = self.settings
        if self._last_acquire_ns is None or not s.tracking:
            return True
        period = s.acquire_period_s if others_tracked else s.acquire_idle_period_s
        return not s_from_ns(abs(t_ns - self._last_acquire_ns)) < period  # a clock jump back: due

    def _search_held_back(self, vid: str, t_ns: int) -> bool:
        """Is the unfound bus's due search held back on this frame (PipelineSettings.acquire_defer_below_share):
        its fresh reported position lies mostly where this camera is unlikely to find it, and fewer than
        acquire_defer_frames of its due searches were held back in a row?"""
        s, c = self.settings, self._coarse.get(vid)
        if (not s.acquire_defer_frames or c is None or not self._bounded()
                or self._held.get(vid, 0) >= s.acquire_defer_frames
                or s_from_ns(abs(t_ns - c.t_ns)) > s.coarse_max_age_s):
            return False
        x, y, radius = c.disc_at(t_ns, BUS_MAX_SPEED_MPS * SPEED_MARGIN)
        return self._view_grid(self.vehicles[vid]).likely_share(x, y, radius / 3) < s.acquire_defer_below_share

    def _acquisition_jobs(self, vehicles: list[Vehicle], tiles: np.ndarray | None = None) -> list[DetectJob]:
        """The search for these vehicles: the pyramid's bands, only over the marked image tiles (and
        around them by a tag's size, so that no tag is cut) when tiles are given."""
        s = self.settings
        if s.acquire_mode == "full":
            return [DetectJob(Box(0, 0, self.camera.width, self.camera.height), s.detector.quad_decimate)]
        # The smallest tag at the lowest roof decides how finely each row must be searched.
        roof = min(v.height for v in vehicles)
        size = min(min(t.size, t.extent_up) for v in vehicles for t in v.tags.values())
        key = (round(roof, 2), round(size, 3))
        if key not in self._bands:
            upsample_below = s.upsample_below_px if s.acquire_upsample_below_px is None else s.acquire_upsample_below_px
            self._bands[key] = acquisition_bands(self.camera, roof, size, s.acquire_min_side_px,
                                                 s.acquire_max_decimate, upsample_below)
        bands = self._bands[key]
        thorough = s.acquire_unrefined_pass
        if tiles is None:
            return [DetectJob(b.box, b.decimate, b.upsample, thorough) for b in bands]
        w, h = self.camera.width, self.camera.height
        regions = tile_boxes(w, h, tiles)
        jobs = []
        for b in bands:
            pad = int(np.ceil(b.tag_px + s.crop_pad_px))
            grown = [Box(max(r.x0 - pad, b.box.x0), max(r.y0 - pad, b.box.y0), min(r.x1 + pad, b.box.x1),
                         min(r.y1 + pad, b.box.y1)) for r in regions]
            for box in merge_boxes([g for g in grown if min(g.x1 - g.x0, g.y1 - g.y0) * b.upsample >= 8 * b.decimate]):
                jobs.append(DetectJob(box, b.decimate, b.upsample, thorough))
        return jobs

    def _contrast_floor(self, gray: np.ndarray, jobs: list[DetectJob], ratio: float,
                        every_job: bool = False) -> list[DetectJob]:
        """The jobs with the contrast a region needs to be searched (ratio of the frame's mean grey level on
        a sparse grid: PipelineSettings.acquire_min_contrast, track_min_contrast): acquisition's decimated
        jobs only (their finds are confirmed at full resolution without it), or every_job."""
        if not ratio or all(j.decimate == 1.0 and not every_job for j in jobs):
            return jobs
        floor = round(ratio * float(gray[::16, ::16].mean()))
        floor = int(min(ACQUIRE_MAX_CONTRAST, max(floor, APRILTAG_MIN_CONTRAST)))
        return [replace(j, min_contrast=floor) if j.decimate != 1.0 or every_job else j for j in jobs]

    def _hint_at(self, vid: str, t_ns: int):
        """(what predicts the unfound vehicle's pose, extra margin) to crop for its tags: another RSU's
        fresh fix, else its own report when sure enough; None: it is to be searched for."""
        s = self.settings
        fresh = [h for h in self._hints.get(vid, {}).values() if s_from_ns(abs(t_ns - h.t_ns)) <= s.hint_max_age_s]
        if fresh:  # the one that crops least: a track with a velocity, else the newest
            return min(fresh, key=lambda h: h.predict(t_ns).pos_radius), s.hint_margin_m
        c = self._coarse.get(vid)
        if (c is None or c.yaw is None or c.velocity is None or not self._bounded()
                or s_from_ns(abs(t_ns - c.t_ns)) > s.hint_max_age_s
                or self._report_misses.get(vid, 0) >= s.report_hint_misses):
            return None
        p = c.predict(t_ns)
        if p.pos_radius > s.report_hint_max_radius_m or p.yaw_margin > s.report_hint_max_yaw_rad:
            return None
        return c, s.hint_margin_m

    def _tracking_jobs(self, vehicle: Vehicle, track: VehicleTrack, t_ns: int, extra_radius: float = 0.0) -> list[DetectJob]:
        p = track.predict(t_ns, extra_radius)
        jobs = []
        for tid in vehicle.tag_ids:
            box = tag_region(self.camera, vehicle, tid, p.x, p.y, p.yaw, p.z, p.pos_radius, p.yaw_margin,
                             p.z_margin, self.settings.crop_pad_px)
            if box is not None:
                corners = vehicle_to_world(vehicle.tag_corners(tid), p.x, p.y, p.yaw, p.z)
                side = projected_side_px(self.camera, corners)
                jobs.append(DetectJob(box, self._decimate_for(side), self._upsample_for(side), thorough=False,
                                      expect=frozenset({(vehicle.family, tid)})))
        return jobs

    def _upsample_for(self, side_px: float) -> int:
        return 2 if side_px < self.settings.upsample_below_px else 1

    def _decimate_for(self, side_px: float) -> float:
        s = self.settings
        if not s.track_decimate_side_px:
            return 1.0
        return float(max(1, min(s.track_max_decimate, int(side_px // s.track_decimate_side_px))))

    def _confirm_full_resolution(self, gray, coarse: list[RawDetection], run) -> list[RawDetection]:
        """Re-detect each coarse find in a crop at full resolution: decimated quads lose corner accuracy.
        A coarse find that the fine pass cannot confirm is dropped: unrefined corners are never used."""
        jobs = []
        for d in coarse:
            lo, hi = d.corners.min(axis=0), d.corners.max(axis=0)
            pad = 0.35 * (hi - lo).max() + self.settings.crop_pad_px  # the white border and a margin
            box = Box(max(0, int(lo[0] - pad)), max(0, int(lo[1] - pad)),
                      min(self.camera.width, int(hi[0] + pad) + 1), min(self.camera.height, int(hi[1] + pad) + 1))
            side = float(np.linalg.norm(np.roll(d.corners, -1, axis=0) - d.corners, axis=1).min())
            jobs.append(DetectJob(box, 1.0, self._upsample_for(side), expect=frozenset({(d.family, d.tag_id)})))
        jobs = _merge_jobs(jobs)
        return _own_crop_first(jobs, run(gray, jobs))


def _found_enough(s: _Search, per_job: list[list[RawDetection]]) -> bool:
    """Has every bus the search seeks enough of its tags among these jobs' detections (_Search.enough)?"""
    if not s.enough:
        return False
    found = {(d.family, d.tag_id) for ds in per_job for d in ds}
    return all(len(found & tags) >= n for tags, n in s.enough)


def _merge_jobs(jobs: list[DetectJob]) -> list[DetectJob]:
    """Overlapping crops become one (so no tag is found twice or cut), at the finest level of its parts:
    enlarged if any needed it, decimated only as much as the least decimated. (Crops of two levels kept
    apart lost 1.8 % of the demo's fixes, `toptag bench rsu --scenario`: a tag just above
    upsample_below_px decodes more often in a neighbour's enlarged crop.)"""
    out = []
    for box in merge_boxes([j.box for j in jobs]):
        parts = [j for j in jobs if box.overlaps(j.box)]
        up = max((j.upsample for j in parts), default=1)
        decimate = min((j.decimate for j in parts), default=1.0)
        known = [j.expect for j in parts]
        expect = frozenset().union(*known) if known and None not in known else None
        out.append(DetectJob(box, decimate, up, thorough=any(j.thorough for j in parts) or not parts,
                             expect=expect))
    return out


def _own_crop_first(jobs: list[DetectJob], found: list[list[RawDetection]]) -> list[RawDetection]:
    """The detections of every job (found: per job), a tag found both in a crop made for it (its expect)
    and in another's (a steady bus's and another bus's, searched apart) keeping only the former."""
    own = {(d.family, d.tag_id) for j, ds in zip(jobs, found) if j.expect for d in ds
           if (d.family, d.tag_id) in j.expect}
    return [d for j, ds in zip(jobs, found) for d in ds
            if (d.family, d.tag_id) not in own or (j.expect is not None and (d.family, d.tag_id) in j.expect)]


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
