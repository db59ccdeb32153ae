"""Control points file: surveyed ground points in the site frame, and where they are in an image.

    {"survey_sigma": 0.005,
     "points": [{"id": "lamp-base", "world": [12.31, -4.02, 0.05], "pixel": [611.2, 402.7]},
                {"id": "kerb-3", "world": [8.0, 2.1, 0.12], "sigma": [0.003, 0.003, 0.01], "pixel": [402, 388]}],
     "plates": [{"id": "P1", "family": "tag36h11", "tag_id": 0,
                 "corners": [[x, y, z], [x, y, z], [x, y, z], [x, y, z]]}]}

- `world`: metres in the site frame (SPEC: origin at the intersection centre, x east, y north, z up).
- `sigma`: the survey's standard deviation of that point, one number (every axis) or [sx, sy, sz];
  default `survey_sigma` of the file (required if a point has none).
- `pixel`: where the point is in the image (OpenCV convention: (0, 0) is the centre of the top-left
  pixel), as observed (with the lens distortion); points without a pixel are not used.
- `plates`: AprilTag plates laid on the ground in view, their four tag corners surveyed (the outer
  corners of the black square, in the detector's order: printed bottom-left, bottom-right, top-right,
  top-left). Their pixels are found automatically in the image: nothing to click.
Any missing field, NaN or unknown key is refused with one line naming it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toptag.inputs import read_model, validate_model
from toptag.vehicle import FAMILY_BITS

Vec3 = tuple[float, float, float]


class PointSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: str = Field(min_length=1)
    world: Vec3
    sigma: float | Vec3 | None = None
    pixel: tuple[float, float] | None = None


class PlateSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: str = Field(min_length=1)
    family: str = "tag36h11"
    tag_id: int = Field(ge=0)
    corners: tuple[Vec3, Vec3, Vec3, Vec3]
    sigma: float | Vec3 | None = None

    @model_validator(mode="after")
    def _family(self) -> "PlateSpec":
        if self.family not in FAMILY_BITS:
            raise ValueError(f"family: unknown tag family {self.family!r} (known: {', '.join(FAMILY_BITS)})")
        return self


class PointsFile(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    survey_sigma: float | None = Field(default=None, gt=0, description="default survey sigma, m")
    points: list[PointSpec] = Field(default_factory=list)
    plates: list[PlateSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check(self) -> "PointsFile":
        if not self.points and not self.plates:
            raise ValueError("no points and no plates")
        ids = [p.id for p in self.points] + [p.id for p in self.plates]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicate id(s) {dup}")
        tags = [(p.family, p.tag_id) for p in self.plates]
        if len(set(tags)) != len(tags):
            raise ValueError("plates: two plates with the same family and tag_id")
        for where, items in (("points", self.points), ("plates", self.plates)):
            for i, p in enumerate(items):
                s = p.sigma if p.sigma is not None else self.survey_sigma
                if s is None:
                    raise ValueError(f"{where}.{i}.sigma: missing (and no survey_sigma for the file)")
                if not np.all(np.asarray(s, float) > 0):
                    raise ValueError(f"{where}.{i}.sigma: must be positive")
        return self


@dataclass
class ControlPoint:
    """One surveyed point and its observed pixel (None until found)."""

    id: str
    world: np.ndarray  # (3,)
    sigma: np.ndarray  # (3,) survey standard deviation per axis, m
    pixel: np.ndarray | None  # (2,) observed, with lens distortion


class ControlPoints:
    def __init__(self, spec: PointsFile):
        self.spec = spec

    @classmethod
    def load(cls, path: str | Path) -> "ControlPoints":
        return cls(read_model(PointsFile, path, "points file"))

    @classmethod
    def from_dict(cls, data: dict, source: str = "points") -> "ControlPoints":
        return cls(validate_model(PointsFile, data, source))

    def _sigma(self, s) -> np.ndarray:
        s = self.spec.survey_sigma if s is None else s
        return np.broadcast_to(np.asarray(s, float), (3,)).copy()

    def given(self) -> list[ControlPoint]:
        """The points with their given pixels (those without a pixel are left out)."""
        return [ControlPoint(p.id, np.asarray(p.world, float), self._sigma(p.sigma), np.asarray(p.pixel, float))
                for p in self.spec.points if p.pixel is not None]

    def find_plates(self, gray: np.ndarray, upsample: int = 2) -> tuple[list[ControlPoint], list[str]]:
        """The plates' corners found in an image (AprilTag detection, whole frame, enlarged `upsample`×
        so that far plates decode): (control points, ids of the plates not found)."""
        if not self.spec.plates:
            return [], []
        from toptag.detection import DetectorSettings, TagDetector

        found: dict[tuple[str, int], np.ndarray] = {}
        twice: set[tuple[str, int]] = set()
        for family in sorted({p.family for p in self.spec.plates}):
            det = TagDetector((family,), DetectorSettings(nthreads=2))
            try:
                for d in det.detect_raw(gray, upsample=upsample):
                    key = (d.family, d.tag_id)
                    if key in found:
                        twice.add(key)
                    found[key] = d.corners
            finally:
                det.close()
        out, missing = [], []
        for p in self.spec.plates:
            key = (p.family, p.tag_id)
            if key not in found or key in twice:
                missing.append(p.id + (" (seen twice)" if key in twice else ""))
                continue
            for k in range(4):
                out.append(ControlPoint(f"{p.id}.{k}", np.asarray(p.corners[k], float), self._sigma(p.sigma),
                                        found[key][k]))
        return out, missing

    def observed(self, gray: np.ndarray | None) -> tuple[list[ControlPoint], list[str]]:
        """Given points plus the plates found in `gray` (if an image is given)."""
        pts = self.given()
        missing: list[str] = []
        if gray is not None:
            plates, missing = self.find_plates(gray)
            pts += plates
        elif self.spec.plates:
            missing = [p.id + " (no image given)" for p in self.spec.plates]
        return pts, missing
