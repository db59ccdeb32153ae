"""The static map of the live view: roads, RSU positions and what each camera sees, from the site's
files (the map of intersections and the camera calibrations). Plain geometry, world frame (x east, y
north, metres)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.scene import LANE_WIDTH, ROAD_HALF_WIDTH
from toptag.camera import Camera
from toptag.site import MapFile
from toptag.vehicle import Vehicle

FOOTPRINT_RANGE_M = 45.0  # a footprint is cut at this horizontal distance from its camera
BORDER_SAMPLES = 24  # samples per image side


@dataclass
class RsuSite:
    id: str
    position: np.ndarray  # (2,) camera centre on the ground
    footprint: np.ndarray  # (N,2) closed polygon: where the camera sees the roof plane


@dataclass
class RoadLine:
    points: np.ndarray  # (N,2)
    kind: str  # "surface" (radius: half the road's width), "centre", "lane", "stop"


@dataclass
class SiteMap:
    intersections: list[tuple[str, np.ndarray, float]]  # id, centre, approach radius
    roads: list[RoadLine]
    rsus: list[RsuSite]
    roof_height: float
    vehicles: dict[str, Vehicle]

    @property
    def extent(self) -> tuple[tuple[float, float], tuple[float, float]]:
        pts = np.vstack([c for _, c, _ in self.intersections] + [r.position[None] for r in self.rsus])
        r = 0.6 * max(rad for _, _, rad in self.intersections)  # the junction and its approaches
        lo, hi = pts.min(axis=0) - r, pts.max(axis=0) + r
        return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


def camera_footprint(camera: Camera, z: float, max_range: float = FOOTPRINT_RANGE_M,
                     samples: int = BORDER_SAMPLES) -> np.ndarray:
    """Where the image border meets the plane Z = z, as a closed polygon (N,2); rays that miss the
    plane, or meet it beyond ``max_range`` (horizontally), are cut at that range."""
    w, h = camera.width - 1.0, camera.height - 1.0
    s = np.linspace(0.0, 1.0, samples, endpoint=False)
    border = np.vstack([np.column_stack([s * w, np.zeros_like(s)]), np.column_stack([np.full_like(s, w), s * h]),
                        np.column_stack([w - s * w, np.full_like(s, h)]), np.column_stack([np.zeros_like(s), h - s * h])])
    hits = camera.backproject_to_plane(border, z)[:, :2]
    c = camera.center[:2]
    rays = camera.rays(border)[:, :2]
    away = rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    far = ~np.isfinite(hits).all(axis=1) | (np.linalg.norm(hits - c, axis=1) > max_range)
    hits[far] = c + away[far] * max_range
    return np.vstack([hits, hits[:1]])


def _roads(centre: np.ndarray, reach: float) -> list[RoadLine]:
    """Two four-lane roads crossing at ``centre`` (SPEC's intersection), out to ``reach`` metres: the
    surfaces, and outside the junction box the centre lines and the lines between a side's two lanes."""
    out = []
    for axis in (np.array([1.0, 0.0]), np.array([0.0, 1.0])):
        out.append(RoadLine(np.vstack([centre - axis * reach, centre + axis * reach]), "surface"))
        side = axis[::-1]
        for lo, hi in ((-reach, -ROAD_HALF_WIDTH), (ROAD_HALF_WIDTH, reach)):
            seg = np.vstack([centre + axis * lo, centre + axis * hi])
            out.append(RoadLine(seg, "centre"))
            out += [RoadLine(seg + side * offset, "lane") for offset in (-LANE_WIDTH, LANE_WIDTH)]
    return out


def load_site(map_path: str | Path, camera_paths: list[str | Path], vehicle_paths: list[str | Path] = ()) -> SiteMap:
    """The map for the view from the site's files (InputError for a bad file)."""
    site = MapFile.load(map_path)
    cameras = [Camera.load(p) for p in camera_paths]
    vehicles = {v.id: v for v in (Vehicle.load(p) for p in vehicle_paths)}
    roof = float(np.mean([v.height for v in vehicles.values()])) if vehicles else 3.0
    roads = []
    inters = []
    for i in site.intersections:
        c = np.asarray(i.center, dtype=float)
        inters.append((i.id, c, i.radius))
        roads += _roads(c, i.radius + 5.0)
    rsus = [RsuSite(cam.id, cam.center[:2].copy(), camera_footprint(cam, roof)) for cam in cameras]
    return SiteMap(inters, roads, rsus, roof, vehicles)
