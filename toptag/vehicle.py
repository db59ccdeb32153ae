"""Vehicle / code bag (SPEC.md: vehicle file): the tags on a bus roof and where their corners are."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from toptag.inputs import read_json, validate_model

# Families whose printed layout is the classic one (black square, one-cell white border) and whose
# patterns both pupil-apriltags and OpenCV know; value = data bits per side.
FAMILY_BITS = {"tag36h11": 6, "tag25h9": 5, "tag16h5": 4}
# m: the roof-height uncertainty of a bus that declares none: a uniform ±10 cm bounce (suspension, load,
# tyres). The solvers' default prior on the roof height (toptag.solvers.SIGMA_H_DEFAULT).
HEIGHT_SIGMA_DEFAULT = 0.2 / math.sqrt(12.0)


class TagSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    id: int = Field(ge=0)
    size: float = Field(gt=0, description="edge of the black square (m), across the printed tag")
    length: float | None = Field(default=None, gt=0,
                                 description="extent along the printed up axis for a long (stretched) tag; default size")
    center: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0

    @property
    def extent_up(self) -> float:
        return self.length if self.length is not None else self.size


class VehicleFile(BaseModel):
    """The vehicle JSON: what a bus announces about itself."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(min_length=1)
    height: float = Field(gt=0, description="roof (tag plane) height above ground, m")
    # Optional (added in protocol v1; absent means HEIGHT_SIGMA_DEFAULT). Left out of the JSON when not
    # declared, so that a bag which declares none reads exactly as before, to old receivers too.
    height_sigma: float | None = Field(default=None, gt=0, exclude_if=lambda v: v is None,
                                       description="standard deviation of the true roof height about `height`, m "
                                                   "(a bouncing bus: the default; a rigid or measured roof: less)")
    family: str = "tag36h11"
    length: float = Field(gt=0)
    width: float = Field(gt=0)
    tags: list[TagSpec] = Field(min_length=1)

    @field_validator("family")
    @classmethod
    def _known_family(cls, v: str) -> str:
        if v not in FAMILY_BITS:
            raise ValueError(f"unknown tag family {v!r} (known: {', '.join(FAMILY_BITS)})")
        return v

    @model_validator(mode="after")
    def _unique_ids(self) -> "VehicleFile":
        ids = [t.id for t in self.tags]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"tags: duplicate tag id(s) {dup}")
        return self


class Vehicle:
    """A bus and its roof tags. Corner coordinates are in the vehicle-top frame (z = 0 on the roof)."""

    def __init__(self, spec: VehicleFile):
        self.spec = spec
        self.id = spec.id
        self.height = spec.height
        self.height_sigma = spec.height_sigma if spec.height_sigma is not None else HEIGHT_SIGMA_DEFAULT
        self.family = spec.family
        self.length = spec.length
        self.width = spec.width
        self.tags = {t.id: t for t in spec.tags}
        self._corners = {t.id: _tag_corners(t) for t in spec.tags}

    @classmethod
    def from_dict(cls, data: dict, source: str = "vehicle") -> "Vehicle":
        return cls(validate_model(VehicleFile, data, source))

    @classmethod
    def load(cls, path: str | Path) -> "Vehicle":
        return cls.from_dict(read_json(path, "vehicle file"), source=f"vehicle file {path}")

    def to_dict(self) -> dict:
        return self.spec.model_dump(mode="json", exclude_none=True)

    @property
    def tag_ids(self) -> list[int]:
        return list(self.tags)

    def tag_corners(self, tag_id: int) -> np.ndarray:
        """(4,3) corners in the vehicle-top frame, detector order (bottom-left, bottom-right, top-right,
        top-left of the printed tag)."""
        return self._corners[tag_id]

    def plate_corners(self, tag_id: int) -> np.ndarray:
        """(4,3) corners of the printed plate (black square plus its one-cell white border), same order."""
        corners = self._corners[tag_id]
        centre = corners.mean(axis=0)
        cells = FAMILY_BITS[self.family] + 2
        return centre + (corners - centre) * (cells + 2) / cells

    def corners(self, tag_ids) -> np.ndarray:
        """Stacked (4·n, 3) corners of several tags, in the given order."""
        return np.vstack([self._corners[i] for i in tag_ids])

    def footprint(self) -> np.ndarray:
        """(4,2) roof outline corners in the vehicle frame (front-left, front-right, rear-right, rear-left)."""
        L, W = self.length / 2, self.width / 2
        return np.array([[L, W], [L, -W], [-L, -W], [-L, W]])


def _tag_corners(t: TagSpec) -> np.ndarray:
    h_up, h_side = t.extent_up / 2, t.size / 2
    # At yaw 0 the printed top faces vehicle +x and the printed left faces vehicle +y.
    local = np.array([[-h_up, h_side], [-h_up, -h_side], [h_up, -h_side], [h_up, h_side]])
    c, s = np.cos(t.yaw), np.sin(t.yaw)
    xy = local @ np.array([[c, s], [-s, c]]) + np.asarray(t.center)
    return np.column_stack([xy, np.zeros(4)])
