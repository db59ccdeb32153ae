"""The intersection of SPEC.md: roads, lanes, four corner RSUs. One home for the layout, used by the
renderer, the studies, the live simulator and the tests."""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

from toptag.camera import Camera
from toptag.vehicle import Vehicle

LANE_WIDTH = 3.7
LANES_PER_ROAD = 4  # two each way
ROAD_HALF_WIDTH = LANE_WIDTH * LANES_PER_ROAD / 2  # 7.4 m
RSU_HEIGHT = 8.0
RSU_PITCH_DOWN = np.deg2rad(40.0)
RSU_HFOV = np.deg2rad(70.0)
RSU_SETBACK = 1.6  # pole distance beyond the kerb corner, along each road
LOW_RES = (960, 720)
HIGH_RES = (3200, 2400)

# Corner name -> (sign x, sign y); each RSU faces the intersection centre.
RSU_CORNERS = {"sw": (-1, -1), "se": (1, -1), "ne": (1, 1), "nw": (-1, 1)}


@dataclass(frozen=True)
class RsuMount:
    id: str
    position: np.ndarray  # world (x, y, z) of the camera centre
    yaw: float  # heading of the optical axis projected on the ground


def rsu_mounts(height: float = RSU_HEIGHT) -> list[RsuMount]:
    d = ROAD_HALF_WIDTH + RSU_SETBACK
    out = []
    for name, (sx, sy) in RSU_CORNERS.items():
        pos = np.array([sx * d, sy * d, height])
        out.append(RsuMount(f"rsu-{name}", pos, float(np.arctan2(-pos[1], -pos[0]))))
    return out


def rsu_camera(corner: str = "sw", width: int = LOW_RES[0], height: int = LOW_RES[1],
               hfov: float = RSU_HFOV, pitch_down: float = RSU_PITCH_DOWN, dist=None) -> Camera:
    """The calibrated camera of one corner RSU (default: SPEC's 8 m, 40° down, 70° HFOV)."""
    mount = next(m for m in rsu_mounts() if m.id == f"rsu-{corner}")
    return Camera.looking_at(mount.id, mount.position, mount.yaw, pitch_down, hfov, width, height, dist)


def rsu_cameras(width: int = LOW_RES[0], height: int = LOW_RES[1], **kw) -> list[Camera]:
    return [rsu_camera(c, width, height, **kw) for c in RSU_CORNERS]


def bundled_vehicle(name: str = "bus_double") -> Vehicle:
    """A vehicle file shipped with toptag (toptag/data/<name>.json)."""
    text = resources.files("toptag.data").joinpath(f"{name}.json").read_text()
    import json

    return Vehicle.from_dict(json.loads(text), source=f"bundled vehicle {name}")
