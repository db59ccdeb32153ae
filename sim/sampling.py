"""Random scenes for studies, examples and tests: bus poses in the RSU's sector, a second tagged bus,
a truck hiding part of the roof. Pure: numpy in, scene objects out."""
from __future__ import annotations

import numpy as np

from sim.render import Occluder, PlacedVehicle
from sim.scene import ROAD_HALF_WIDTH
from toptag.camera import Camera
from toptag.geometry import vehicle_to_world
from toptag.rsu.regions import thinnest_cell_px_many
from toptag.vehicle import Vehicle

SECTOR_HALF_ANGLE = np.deg2rad(30.0)  # around the RSU heading: the intersection quarter nearest to it


def horizontal_distance(camera: Camera, x: float, y: float) -> float:
    c = camera.center
    return float(np.hypot(x - c[0], y - c[1]))


def camera_heading(camera: Camera) -> float:
    fwd = camera.R[2]
    return float(np.arctan2(fwd[1], fwd[0]))


# A tag is decodable when its thinnest cell in the image (toptag.rsu.regions.thinnest_cell_px) is at least
# this many px. Measured with the demo's renderer, image model and RSU pipeline at 960x720
# (`python -m sim.studies.acquire_range`, docs/site.md "Decodable tags"): tracking crops decoded few tags
# with cells under 1.25 px, about two thirds at 1.5-1.625 px and nearly all from 1.75 px on; the shortest
# side does not separate them (a grazing tag turned 45 degrees keeps long sides).
DECODABLE_CELL_PX = 1.75
# A plate counts as whole in the image when all its corners are at least this far (px) inside the image's
# edge; a single constant, so that the sampling, the site check and the monitor's "in view" say the same.
PLATE_MARGIN_PX = 2.0


def tags_seen(camera: Camera, plates: np.ndarray, tags: np.ndarray, margin_px: float = PLATE_MARGIN_PX,
              min_cell_px: float = DECODABLE_CELL_PX) -> np.ndarray:
    """The rule of a tag seen, for any number of tags at once: plates and tags (..., 4, 3) are the world
    corners of each tag's printed plate (with its white border) and of its black square; True (...) where
    the whole plate is in front of the camera and inside its image by margin_px, and the tag's cells are at
    least min_cell_px tall in it (0: not asked). Occlusion not considered. visible_tags (one pose) and
    in_some_view_many (many) both ask this, so that they cannot drift apart."""
    corners = plates.reshape(-1, 3)
    whole = (camera.to_camera(corners)[:, 2] > 0) & camera.in_image(camera.project(corners), margin_px)
    ok = whole.reshape(plates.shape[:-1]).all(axis=-1)
    if min_cell_px > 0 and ok.any():  # one pose's tags are often all out of view: skip their cells then
        ok &= thinnest_cell_px_many(camera.project(tags.reshape(-1, 3))).reshape(ok.shape) >= min_cell_px
    return ok


def _roof_corners(vehicle: Vehicle, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world corners of every tag's plate and black square at each of poses (N, 4): two (N, T, 4, 3)."""
    shape = (len(poses), len(vehicle.tag_ids), 4, 3)
    return tuple(vehicle_to_world(np.stack([corners(t) for t in vehicle.tag_ids]), *poses.T).reshape(shape)
                 for corners in (vehicle.plate_corners, vehicle.tag_corners))


def visible_tags(camera: Camera, pv: PlacedVehicle, margin_px: float = PLATE_MARGIN_PX,
                 min_cell_px: float = 0.0) -> list[int]:
    """The tags whose whole printed plate (with its white border) projects inside the image and whose
    cells are at least min_cell_px tall in it (tags_seen; the default asks only the first)."""
    plates, tags = _roof_corners(pv.vehicle, np.array([[pv.x, pv.y, pv.yaw, pv.roof_z]]))
    ok = tags_seen(camera, plates[0], tags[0], margin_px, min_cell_px)
    return [tid for tid, seen in zip(pv.vehicle.tag_ids, ok) if seen]


def in_some_view(cameras, pv: PlacedVehicle, min_tags: int = 2, margin_px: float = PLATE_MARGIN_PX,
                 min_cell_px: float = DECODABLE_CELL_PX) -> bool:
    """At least min_tags of the vehicle's tags are decodable in one of the cameras' images (whole inside
    it, cells at least min_cell_px tall): where an RSU can fix it (occlusion not considered)."""
    return bool(in_some_view_many(cameras, pv.vehicle, [(pv.x, pv.y, pv.yaw, pv.roof_z)], min_tags, margin_px,
                                  min_cell_px)[0])


def in_some_view_many(cameras, vehicle: Vehicle, poses, min_tags: int = 2, margin_px: float = PLATE_MARGIN_PX,
                      min_cell_px: float = DECODABLE_CELL_PX) -> np.ndarray:
    """in_some_view for many poses of one vehicle at once: poses (N, 4) of x, y, yaw, roof z; (N,) bools.
    One projection per camera for all of them (a pose at a time costs ~0.3 ms of Python)."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 4)
    plates, tags = _roof_corners(vehicle, poses)
    seen = np.zeros(len(poses), dtype=bool)
    for camera in cameras:
        seen |= tags_seen(camera, plates, tags, margin_px, min_cell_px).sum(axis=1) >= min_tags
    return seen


def plates_in_view(camera: Camera, pv: PlacedVehicle, margin_px: float = PLATE_MARGIN_PX) -> bool:
    """Every tag's printed plate projects inside the image."""
    return len(visible_tags(camera, pv, margin_px)) == len(pv.vehicle.tag_ids)


def footprints_overlap(a, b, clearance: float = 0.5) -> bool:
    """Conservative test on bounding circles of two boxes on the ground."""
    ra = np.hypot(a.length, a.width) / 2
    rb = np.hypot(b.length, b.width) / 2
    return np.hypot(a.x - b.x, a.y - b.y) < ra + rb + clearance


def sector_pose(rng: np.random.Generator, camera: Camera, vehicle: Vehicle, distance: float,
                roof_dz: float = 0.0, tries: int = 200) -> PlacedVehicle | None:
    """The vehicle at `distance` (horizontal, camera to vehicle centre) within the sector in front of
    the RSU, any heading, with its tags fully in view; None if no such pose was found."""
    c = camera.center
    head = camera_heading(camera)
    for _ in range(tries):
        bearing = head + rng.uniform(-SECTOR_HALF_ANGLE, SECTOR_HALF_ANGLE)
        pv = PlacedVehicle(vehicle, c[0] + distance * np.cos(bearing), c[1] + distance * np.sin(bearing),
                           rng.uniform(-np.pi, np.pi), vehicle.height + roof_dz)
        if plates_in_view(camera, pv):
            return pv
    return None


def second_bus(rng: np.random.Generator, camera: Camera, vehicle: Vehicle, avoid: list, tries: int = 200):
    """Another tagged bus somewhere in view on the roads, not overlapping anything in `avoid`."""
    for _ in range(tries):
        d = rng.uniform(6.0, 20.0)
        pv = sector_pose(rng, camera, vehicle, d, tries=1)
        if pv is None:
            continue
        on_road = min(abs(pv.x), abs(pv.y)) <= ROAD_HALF_WIDTH
        if on_road and not any(footprints_overlap(pv, o) for o in avoid):
            return pv
    return None


def segment_hits_box(a: np.ndarray, b: np.ndarray, box) -> bool:
    """Does the segment a->b pass through the upright box (Occluder-like: x, y, yaw, length, width, height)?"""
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    to_local = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    la, lb = to_local @ (a - [box.x, box.y, 0.0]), to_local @ (b - [box.x, box.y, 0.0])
    lo = np.array([-box.length / 2, -box.width / 2, 0.0])
    hi = np.array([box.length / 2, box.width / 2, box.height])
    d = lb - la
    t0, t1 = 0.0, 1.0
    for k in range(3):  # slab test
        if abs(d[k]) < 1e-12:
            if not lo[k] <= la[k] <= hi[k]:
                return False
            continue
        u, v = sorted(((lo[k] - la[k]) / d[k], (hi[k] - la[k]) / d[k]))
        t0, t1 = max(t0, u), min(t1, v)
        if t0 > t1:
            return False
    return True


def occluding_truck(rng: np.random.Generator, camera: Camera, target: PlacedVehicle, tries: int = 300,
                    length: float = 8.0, width: float = 2.5) -> Occluder | None:
    """A truck in the next lane, on the camera's side of `target`, tall enough to hide part of its roof
    tags while at least one tag stays fully visible; None if no such placement was found."""
    c = camera.center
    plates = {tid: vehicle_to_world(target.vehicle.plate_corners(tid), target.x, target.y, target.yaw,
                                    target.roof_z) for tid in target.vehicle.tag_ids}
    left = np.array([-np.sin(target.yaw), np.cos(target.yaw)])
    fwd = np.array([np.cos(target.yaw), np.sin(target.yaw)])
    side = 1.0 if left @ (c[:2] - [target.x, target.y]) > 0 else -1.0
    for _ in range(tries):
        p = np.array([target.x, target.y]) + side * rng.uniform(3.0, 3.8) * left + rng.uniform(-4, 4) * fwd
        truck = Occluder(length, width, target.roof_z + rng.uniform(0.9, 1.5), float(p[0]), float(p[1]),
                         float(target.yaw + rng.normal(0, 0.05)))
        hidden = {tid: sum(segment_hits_box(c, q, truck) for q in pts) for tid, pts in plates.items()}
        if any(hidden.values()) and any(n == 0 for n in hidden.values()):
            return truck
    return None
