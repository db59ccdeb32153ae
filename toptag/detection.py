"""AprilTag detection restricted to announced code bags.

pupil-apriltags reports corners with (0, 0) at the top-left *corner* of the first pixel; toptag uses
OpenCV's convention ((0, 0) at its centre) and the camera's ideal (undistorted) pixels.
"""
from __future__ import annotations

import atexit
import ctypes
from collections.abc import Collection
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.camera import Camera
from toptag.vehicle import FAMILY_BITS, Vehicle

PUPIL_TO_OPENCV = -0.5
# The default Hamming gate per family, from `toptag eval hamming` (docs/real-data.md): one bit error
# recovers 2 of AprilTag's 46 reference tags on its test photos, and no false decode of tag36h11 or
# tag25h9 with 0 or 1 bit errors showed up in 45 real and rendered cluttered frames (2 bit errors: 1 and
# 6); tag16h5 (minimum distance 5) decoded falsely 64 times with 1 bit error in the same frames.
FAMILY_MAX_HAMMING = {"tag36h11": 1, "tag25h9": 1, "tag16h5": 0}


class DetectorSettings(BaseModel):
    """pupil-apriltags knobs. Defaults find a 1.6 m tag at 20+ m from an 8 m, 40° RSU at 960×720."""

    model_config = ConfigDict(extra="forbid")

    quad_decimate: float = Field(default=1.0, ge=1.0)
    quad_sigma: float = Field(default=0.0, ge=0.0)
    refine_edges: bool = True
    decode_sharpening: float = Field(default=0.25, ge=0.0)
    nthreads: int = Field(default=1, ge=1)
    # Bit errors admitted per tag; None: the family's gate (FAMILY_MAX_HAMMING).
    max_hamming: int | None = Field(default=None, ge=0, le=2)
    # Cells of black border around the data bits: 1 for the official families (and toptag's roofs),
    # 2 for Kalibr-style calibration grids (aprilgrid), whose corners are those of the wider border.
    black_border: int = Field(default=1, ge=1, le=3)
    # AprilTag's edge refinement places a tag's edges inside the true black square on real cameras
    # (gamma-encoded, blurred edges: the gradient peaks on the dark side). Measured on real photographs
    # against saddle-point truth (docs/real-data.md): corners 0.19-0.25 px inward along the diagonal,
    # i.e. edges 0.13-0.18 px. Each edge line is moved outward by this much (0: as detected).
    edge_shift_px: float = Field(default=0.15, ge=-1.0, le=1.0)
    # Edge refinement makes corners more precise but loses some small, oblique tags that decode without
    # it (2 of the 46 that AprilTag's reference finds on its test photos): a second decode pass without
    # it (at full resolution) adds the tags the first pass did not find.
    unrefined_pass: bool = True


class _QuadThresholds(ctypes.Structure):
    """AprilTag 3's apriltag_quad_thresh_params."""

    _fields_ = [("min_cluster_pixels", ctypes.c_int), ("max_nmaxima", ctypes.c_int),
                ("critical_rad", ctypes.c_float), ("cos_critical_rad", ctypes.c_float),
                ("max_line_fit_mse", ctypes.c_float), ("min_white_black_diff", ctypes.c_int),
                ("deglitch", ctypes.c_int)]


class _DetectorHead(ctypes.Structure):
    """The C detector struct up to its quad thresholds (pupil-apriltags' _ApriltagDetector stops before)."""

    _fields_ = [("nthreads", ctypes.c_int), ("quad_decimate", ctypes.c_float), ("quad_sigma", ctypes.c_float),
                ("refine_edges", ctypes.c_int), ("decode_sharpening", ctypes.c_double), ("debug", ctypes.c_int),
                ("qtp", _QuadThresholds)]


@dataclass
class TagObservation:
    """One detected tag of a known vehicle in one camera."""

    tag_id: int
    corners: np.ndarray  # (4,2) ideal pixels (OpenCV convention, distortion removed), detector order
    camera: Camera
    raw_corners: np.ndarray = field(repr=False, default=None)  # (4,2) observed pixels, OpenCV convention
    hamming: int = 0
    decision_margin: float = 0.0


@dataclass
class RawDetection:
    """A tag as the detector saw it in image pixels (OpenCV convention), before bag filtering."""

    family: str
    tag_id: int
    corners: np.ndarray
    hamming: int
    decision_margin: float


class TagDetector:
    """One AprilTag detector for a set of families: one quad search, each quad decoded against every
    family.

    pupil-apriltags 1.0.4 adds only the first family of `families` it recognises (an if/elif chain):
    built for {tag25h9, tag36h11} it silently never finds a tag36h11. The other families are therefore
    added here through the C library's own `apriltag_detector_add_family_bits`, as pupil adds its first
    one (up to 2 bit errors in the decode table; `max_hamming` then filters).

    pupil-apriltags 1.0.4's `Detector.__del__` frees the tag families before the detector that still
    reads them (pupil-labs/apriltags PR #65): a use-after-free that aborts the interpreter at exit now
    and then. Every TagDetector is therefore kept alive and released in the right order by `close()`,
    which an atexit hook calls for those still open."""

    _alive: list["TagDetector"] = []

    def __init__(self, families=("tag36h11",), settings: DetectorSettings | None = None):
        from pupil_apriltags import Detector  # heavy import; only where detection happens
        from pupil_apriltags.bindings import _ApriltagDetection, _ApriltagFamily, _ImageU8, _ZArray

        self.settings = settings or DetectorSettings()
        self.families = tuple(sorted(set(families)))
        if not self.families:
            raise ValueError("a detector needs at least one tag family")
        unknown = [f for f in self.families if f not in FAMILY_BITS]
        if unknown:
            raise ValueError(f"unknown tag family {unknown[0]!r} (known: {', '.join(FAMILY_BITS)})")
        s = self.settings
        first, *others = self.families
        d = Detector(families=first, nthreads=s.nthreads, quad_decimate=s.quad_decimate, quad_sigma=s.quad_sigma,
                     refine_edges=int(s.refine_edges), decode_sharpening=s.decode_sharpening)
        self._detector = d
        TagDetector._alive.append(self)
        self._image_type = _ImageU8
        # One view of the C detector for every field set here (pupil's own struct stops before the quad
        # thresholds).
        self._head = ctypes.cast(d.tag_detector_ptr, ctypes.POINTER(_DetectorHead)).contents
        self._thresholds = self._head.qtp
        if (self._thresholds.max_nmaxima, self._thresholds.max_line_fit_mse) != (10, 10.0):
            self.close()  # not AprilTag 3's defaults where they should be: another struct layout
            raise RuntimeError("pupil-apriltags' C detector is not laid out as AprilTag 3's")
        self._min_contrast = int(self._thresholds.min_white_black_diff)
        self._detection_list = ctypes.POINTER(ctypes.POINTER(_ApriltagDetection))
        d.libc.apriltag_detector_detect.restype = ctypes.POINTER(_ZArray)
        d.libc.apriltag_detector_detect.argtypes = [ctypes.c_void_p, ctypes.POINTER(_ImageU8)]
        d.libc.apriltag_detections_destroy.restype = None
        # pupil-apriltags 1.0.4 passes decode_sharpening through int(), turning 0.25 into 0: set it as the
        # C library expects (a double).
        self._head.decode_sharpening = float(s.decode_sharpening)
        for family in others:
            create = getattr(d.libc, f"{family}_create")
            create.restype = ctypes.POINTER(_ApriltagFamily)
            d.tag_families[family] = create()
            d.libc.apriltag_detector_add_family_bits(d.tag_detector_ptr, d.tag_families[family], 2)
        if s.black_border != 1:
            # The family structs are this detector's own (each *_create allocates one); decoding reads
            # the border width and bit positions from them at every detection.
            extra = s.black_border - 1
            for tf in d.tag_families.values():
                f = tf.contents
                f.width_at_border += 2 * extra
                f.total_width += 2 * extra
                for i in range(f.nbits):
                    f.bit_x[i] += extra
                    f.bit_y[i] += extra

    def close(self) -> None:
        """Free the C detector, then its families; afterwards pupil's __del__ has nothing to free."""
        d = self._detector
        if getattr(d, "tag_detector_ptr", None) is None:
            return
        d.libc.apriltag_detector_destroy.restype = None
        d.libc.apriltag_detector_destroy(d.tag_detector_ptr)
        for family, tf in d.tag_families.items():
            destroy = getattr(d.libc, f"{family}_destroy")
            destroy.restype = None
            destroy(tf)
        d.tag_detector_ptr = None
        d.tag_families = {}
        if self in TagDetector._alive:
            TagDetector._alive.remove(self)

    @classmethod
    def close_all(cls) -> None:
        for det in list(cls._alive):
            det.close()

    def detect_raw(self, gray: np.ndarray, offset=(0, 0), upsample: int = 1,
                   unrefined_pass: bool | None = None, expected: Collection[tuple[str, int]] | None = None,
                   min_contrast: int | None = None, decimate: float | None = None) -> list[RawDetection]:
        """Every tag of the detector's families in `gray` (uint8, 2-D); `offset` is the (x, y) of
        gray's first pixel in the full frame when gray is a crop. `upsample` > 1 enlarges the image
        (bicubic) before detection: far tags with cells of 1-2 px are decoded far more reliably and
        their corners are more precise. unrefined_pass: the second decode pass without edge refinement
        (default: the settings'; the RSU's tracking crops, where the tag is expected and small ones
        are enlarged, skip it). expected: the (family, id) of tags known to be in gray (found there at
        a coarser level): the second pass, there to find what the first misses, runs only if the first
        missed one of them. min_contrast: the grey levels by which a region's brightest pixels must
        exceed its darkest for the quad search to binarise it (AprilTag's min_white_black_diff; default
        the library's 5): a higher floor leaves flat, noisy regions out, and tags of less contrast.
        decimate: the quad search's decimation for this call (default the settings' quad_decimate): the
        C library reads it at every detection, so one detector serves every pyramid level, and its decode
        table (tens of milliseconds to build) is built once."""
        if gray.dtype != np.uint8 or gray.ndim != 2:
            raise ValueError("detector input must be a 2-D uint8 image")
        if self._detector.tag_detector_ptr is None:
            raise RuntimeError("detector was closed")
        img = gray if gray.strides[1] == 1 else np.ascontiguousarray(gray)
        if upsample > 1:
            img = cv2.resize(img, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
        # pupil's corner (0, 0) is the first pixel's corner; in the enlarged image that is the same
        # point as in the original, so scale first, then move to OpenCV's pixel-centre convention.
        shift = np.array([offset[0] + PUPIL_TO_OPENCV, offset[1] + PUPIL_TO_OPENCV])
        s = self.settings
        self._thresholds.min_white_black_diff = self._min_contrast if min_contrast is None else int(min_contrast)
        self._head.quad_decimate = s.quad_decimate if decimate is None else float(decimate)
        try:
            out = self._decoded(img, upsample, shift)
            second = s.unrefined_pass if unrefined_pass is None else unrefined_pass
            if second and expected is not None:
                second = not set(expected) <= {(d.family, d.tag_id) for d in out}
            if s.refine_edges and second and self._head.quad_decimate == 1.0:
                self._head.refine_edges = 0
                try:
                    extra = self._decoded(img, upsample, shift)
                finally:
                    self._head.refine_edges = 1
                out += [d for d in extra if not any(_same_tag(d, o) for o in out)]
        finally:
            self._thresholds.min_white_black_diff = self._min_contrast
            self._head.quad_decimate = s.quad_decimate
        return out

    def gate(self, family: str) -> int:
        """Bit errors admitted for a family's tags."""
        m = self.settings.max_hamming
        return FAMILY_MAX_HAMMING.get(family, 0) if m is None else m

    def _decoded(self, img: np.ndarray, upsample: int, shift: np.ndarray) -> list[RawDetection]:
        out = []
        for fam, tag_id, hamming, margin, quad in self._detect(img):
            if hamming > self.gate(fam):
                continue
            corners = shift_edges(quad / upsample, self.settings.edge_shift_px)
            out.append(RawDetection(fam, tag_id, corners + shift, hamming, margin))
        return out

    def _detect(self, img: np.ndarray) -> list[tuple[str, int, int, float, np.ndarray]]:
        """(family, id, bit errors, decision margin, corners in pupil's convention) of each tag the C
        detector finds in img (uint8, rows of contiguous pixels, any row stride).

        The C library reads the pixels where they are (a crop of a frame is passed with the frame's
        stride): pupil's `Detector.detect` would allocate a zeroed C image and copy the pixels first, on
        an acquisition band of a 3200x2400 frame megabytes per call. The library writes into its input
        only when it blurs or sharpens the undecimated quad image (quad_sigma != 0, quad_decimate <= 1):
        then it gets a copy, as pupil would give it."""
        d, s = self._detector, self.settings
        if s.quad_sigma != 0 and self._head.quad_decimate <= 1:
            img = img.copy()
        h, w = img.shape
        c_img = self._image_type(w, h, img.strides[0], img.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)))
        found = d.libc.apriltag_detector_detect(d.tag_detector_ptr, ctypes.byref(c_img))
        try:
            za = found.contents
            tags = ctypes.cast(za.data, self._detection_list)
            out = []
            for i in range(za.size):
                t = tags[i].contents
                out.append((ctypes.string_at(t.family.contents.name).decode(), int(t.id), int(t.hamming),
                            float(t.decision_margin), np.ctypeslib.as_array(t.p).copy()))
            return out
        finally:
            d.libc.apriltag_detections_destroy(found)


def _same_tag(a: RawDetection, b: RawDetection) -> bool:
    size = float(np.ptp(b.corners, axis=0).max())
    return (a.family == b.family and a.tag_id == b.tag_id
            and float(np.linalg.norm(a.corners.mean(axis=0) - b.corners.mean(axis=0))) < 0.5 * size)


def shift_edges(quad: np.ndarray, distance: float) -> np.ndarray:
    """The quad (4, 2) with each edge line moved `distance` px outward (negative: inward): each corner
    goes to the intersection of its two moved edges."""
    if distance == 0.0:
        return quad
    centre = quad.mean(axis=0)
    out = np.empty_like(quad)
    lines = []
    for a in range(4):
        p, q = quad[a], quad[(a + 1) % 4]
        n = np.array([q[1] - p[1], p[0] - q[0]])
        n /= np.linalg.norm(n) or 1.0
        if n @ (p - centre) < 0:
            n = -n
        lines.append((n, n @ p + distance))  # n · x = c
    for a in range(4):
        (n1, c1), (n2, c2) = lines[a - 1], lines[a]  # the edges ending and starting at corner a
        A = np.array([n1, n2])
        if abs(np.linalg.det(A)) < 1e-9:
            out[a] = quad[a]
        else:
            out[a] = np.linalg.solve(A, [c1, c2])
    return out


def assign_to_vehicles(raw: list[RawDetection], camera: Camera,
                       vehicles: list[Vehicle]) -> dict[str, list[TagObservation]]:
    """Keep only detections whose family and id belong to a vehicle's code bag, per vehicle.

    A (family, id) claimed by two vehicles is ambiguous and goes to neither."""
    owner: dict[tuple[str, int], str | None] = {}
    for v in vehicles:
        for tid in v.tag_ids:
            key = (v.family, tid)
            owner[key] = None if key in owner else v.id
    result: dict[str, list[TagObservation]] = {v.id: [] for v in vehicles}
    seen: set[tuple[str, int]] = set()
    for d in raw:
        key = (d.family, d.tag_id)
        vid = owner.get(key)
        if vid is None:
            continue
        if key in seen:
            # The same tag twice in one frame is impossible for one vehicle: a look-alike is in view.
            result[vid] = [o for o in result[vid] if o.tag_id != d.tag_id]
            owner[key] = None
            continue
        seen.add(key)
        result[vid].append(TagObservation(d.tag_id, camera.undistort(d.corners), camera, d.corners,
                                          d.hamming, d.decision_margin))
    return result


def detect_vehicle_tags(detector: TagDetector, gray: np.ndarray, camera: Camera,
                        vehicles: list[Vehicle]) -> dict[str, list[TagObservation]]:
    """Full-frame detection of the announced vehicles' tags in one camera image."""
    return assign_to_vehicles(detector.detect_raw(gray), camera, vehicles)


atexit.register(TagDetector.close_all)
