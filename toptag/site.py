"""Deployment files shared by the bus agent, the simulator and the demo: the map of intersections.

An intersection has a centre and an approach radius: a bus inside the radius announces itself to the
intersection's RSUs; leaving it (plus a hysteresis) ends the session."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from toptag.inputs import InputError, describe_validation_error, read_json


class IntersectionSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    id: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    center: tuple[float, float]
    radius: float = Field(default=45.0, gt=0, description="approach radius, m")
    leave_margin: float = Field(default=5.0, ge=0, description="hysteresis beyond the radius, m")
    gnss_shadow_radius: float = Field(default=30.0, ge=0, description="no satellite fix inside this radius, m")


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
        try:
            return cls.model_validate(read_json(path, "map file"))
        except ValidationError as e:
            raise InputError(f"map file {path}: {describe_validation_error(e)}") from None

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
