"""Deployment files shared by the bus agent, the simulator and the demo: the map of intersections, and
the site folder that holds a whole installation (docs/site.md).

An intersection has a centre and an approach radius: a bus inside the radius announces itself to the
intersection's RSUs; leaving it (plus a hysteresis) ends the session. Its roads (optional; default
SPEC's cross of two 4-lane roads along x and y) are what `toptag site check` draws.

A site folder: site.json names the map, one camera file per RSU with the intersection it serves, the
vehicle files, and optionally a simulator scenario; every path relative to the folder."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toptag.inputs import InputError, read_model


class RoadSpec(BaseModel):
    """A straight road through the intersection centre (for drawing and coverage checks)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    heading_deg: float = Field(description="direction of the road, degrees from world +x, counter-clockwise")
    lanes: int = Field(default=4, ge=1, le=12)
    lane_width: float = Field(default=3.7, gt=0)
    length: float = Field(default=60.0, gt=0, description="drawn this far each side of the centre, m")

    @property
    def half_width(self) -> float:
        return self.lanes * self.lane_width / 2


def _spec_cross() -> list[RoadSpec]:
    return [RoadSpec(heading_deg=0.0), RoadSpec(heading_deg=90.0)]


class IntersectionSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    center: tuple[float, float]
    radius: float = Field(default=45.0, gt=0, description="approach radius, m")
    leave_margin: float = Field(default=5.0, ge=0, description="hysteresis beyond the radius, m")
    gnss_shadow_radius: float = Field(default=30.0, ge=0, description="no satellite fix inside this radius, m")
    roads: list[RoadSpec] = Field(default_factory=_spec_cross, min_length=1)


class MapFile(BaseModel):
    model_config = ConfigDict(extra="forbid")

    intersections: list[IntersectionSpec] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique(self) -> "MapFile":
        ids = [i.id for i in self.intersections]
        if len(set(ids)) != len(ids):
            raise ValueError("intersections: duplicate id")
        return self

    @classmethod
    def load(cls, path: str | Path) -> "MapFile":
        return read_model(cls, path, "map file")

    def nearest(self, x: float, y: float) -> tuple[IntersectionSpec, float]:
        """The closest intersection and the distance to its centre."""
        d = [float(np.hypot(x - i.center[0], y - i.center[1])) for i in self.intersections]
        k = int(np.argmin(d))
        return self.intersections[k], d[k]

    def get(self, intersection_id: str) -> IntersectionSpec:
        for i in self.intersections:
            if i.id == intersection_id:
                return i
        raise InputError(f"map: no intersection {intersection_id!r}")


# ---- the site folder -------------------------------------------------------------------------------
SITE_FILE = "site.json"


class RsuEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: str = Field(min_length=1, description="camera file, relative to the site folder; its id is the RSU id")
    intersection: str = Field(min_length=1, description="the intersection (map id) the RSU serves")


class SiteFile(BaseModel):
    """site.json: what makes up one installation."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(default="site", min_length=1)
    map: str = Field(default="map.json", min_length=1)
    rsus: list[RsuEntry] = Field(min_length=1)
    vehicles: list[str] = Field(default_factory=list)
    scenario: str | None = Field(default=None, description="simulator scenario (toptag sim run), optional")


def load_site_file(folder: str | Path) -> SiteFile:
    """The folder's site.json, validated (InputError naming the file and field)."""
    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"site {d}: not a folder")
    path = d / SITE_FILE
    return read_model(SiteFile, path, "site file")
