"""Where a vehicle's tags can appear in an image: predicted tag regions and acquisition bands.

Pure geometry on a calibrated camera; the RSU pipeline detects only inside these regions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toptag.camera import Camera
from toptag.geometry import rot_z, vehicle_to_world
from toptag.vehicle import Vehicle


@dataclass(frozen=True)
class Box:
    """Pixel rectangle [x0, x1) × [y0, y1) of a frame."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def area(self) -> int:
        return max(0, self.x1 - self.x0) * max(0, self.y1 - self.y0)

    def overlaps(self, o: "Box", gap: int = 0) -> bool:
        return not (self.x1 + gap <= o.x0 or o.x1 + gap <= self.x0 or self.y1 + gap <= o.y0 or o.y1 + gap <= self.y0)

    def union(self, o: "Box") -> "Box":
        return Box(min(self.x0, o.x0), min(self.y0, o.y0), max(self.x1, o.x1), max(self.y1, o.y1))


def bounding_box(camera: Camera, points_world: np.ndarray, pad_px: float) -> Box | None:
    """Padded pixel bounding box of world points, clipped to the frame; None if none is in front or in view."""
    in_front = camera.to_camera(points_world)[:, 2] > 0.1
    if not np.any(in_front):
        return None
    uv = camera.project(points_world[in_front])
    x0, y0 = np.floor(uv.min(axis=0) - pad_px).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0) + pad_px).astype(int) + 1
    box = Box(max(0, x0), max(0, y0), min(camera.width, x1), min(camera.height, y1))
    return box if box.x1 - box.x0 >= 8 and box.y1 - box.y0 >= 8 else None


def projected_side_px(camera: Camera, corners_world: np.ndarray) -> float:
    """Shortest side (px) of a tag whose corners are given in world coordinates."""
    uv = camera.project(corners_world)
    return float(np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).min())


def thinnest_cell_px(quad: np.ndarray) -> float:
    """The smallest height of a tag cell in the image (px), from the tag's four corners (px): each edge's
    distance to the opposite edge's midpoint over the 8 cells of a tag's black square, the least of the
    four. A grazing tag turned 45 degrees keeps long sides while its cells are a pixel tall: decoding
    needs this, not the shortest side."""
    return float(thinnest_cell_px_many(quad)[0])


def thinnest_cell_px_many(quads) -> np.ndarray:
    """thinnest_cell_px of each of many tags' corners (M, 4, 2)."""
    q = np.asarray(quads, dtype=float).reshape(-1, 4, 2)
    out = np.full(len(q), np.inf)
    for k in range(4):
        a, e = q[:, k], q[:, (k + 1) % 4] - q[:, k]
        length = np.hypot(e[:, 0], e[:, 1])
        length[length == 0] = 1.0
        opposite = 0.5 * (q[:, (k + 2) % 4] + q[:, (k + 3) % 4]) - a
        out = np.minimum(out, np.abs(opposite[:, 0] * e[:, 1] - opposite[:, 1] * e[:, 0]) / length / 8.0)
    return out


def tag_region(camera: Camera, vehicle: Vehicle, tag_id: int, x: float, y: float, yaw: float, z: float,
               pos_radius: float, yaw_margin: float, z_margin: float, pad_px: float = 4.0) -> Box | None:
    """Every pixel the tag's plate can cover for a pose within the given margins."""
    # the 24 extreme poses (yaw, z, corner of the position square) at once: to the bit what one at a time gives
    dyaw, dz, dx, dy = (a.ravel() for a in np.meshgrid((-yaw_margin, 0.0, yaw_margin), (-z_margin, z_margin),
                                                         (-1.0, 1.0), (-1.0, 1.0), indexing="ij"))
    pts = vehicle_to_world(vehicle.plate_corners(tag_id), x + dx * pos_radius, y + dy * pos_radius, yaw + dyaw,
                           z + dz)
    return bounding_box(camera, pts.reshape(-1, 3), pad_px)


def merge_boxes(boxes: list[Box], gap: int = 0) -> list[Box]:
    """Union overlapping boxes until the rest are disjoint (a tag inside one input box stays inside one output)."""
    out = [b for b in boxes if b is not None]
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                if out[i].overlaps(out[j], gap):
                    out[i] = out[i].union(out.pop(j))
                    merged = True
                    break
            if merged:
                break
    return out


@dataclass(frozen=True)
class Band:
    """Rows of the frame searched at one pyramid level during acquisition: quad search decimated by
    `decimate`, or the image enlarged `upsample` times (far rows, where cells are 1-2 px)."""

    box: Box
    decimate: float = 1.0
    upsample: int = 1
    tag_px: float = 0.0  # the largest extent (either axis, px) of a tag centred on the band's rows


def tag_extent_by_row(camera: Camera, roof_z: float, tag_size: float) -> tuple[np.ndarray, np.ndarray]:
    """For each image row, (shortest side, vertical extent) in px of a tag of `tag_size` lying flat at
    `roof_z` whose centre appears on that row, worst cases over yaw; zeros where the plane is not seen."""
    side, extent, _ = _tag_sizes_by_row(camera, roof_z, tag_size)
    return side, extent


def _tag_sizes_by_row(camera: Camera, roof_z: float, tag_size: float):
    """tag_extent_by_row's two, and the largest extent along either axis."""
    step = max(1, camera.height // 240)  # the sizes vary slowly with the row: sample, then interpolate
    rows = np.arange(0, camera.height, step, dtype=float)
    centre_px = np.column_stack([np.full_like(rows, (camera.width - 1) / 2.0), rows])
    ground = camera.backproject_to_plane(centre_px, roof_z)
    side = np.zeros(rows.size)
    extent = np.zeros(rows.size)
    reach = np.zeros(rows.size)
    half = tag_size / 2
    square = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
    seen = np.flatnonzero(np.all(np.isfinite(ground), axis=1))
    if seen.size:
        yaws = np.array([0.0, np.pi / 8, np.pi / 4, 3 * np.pi / 8, np.pi / 2])
        # every seen row's square at every yaw in one projection (a row and yaw at a time cost ~80 ms)
        corners = (square @ rot_z(yaws).swapaxes(-1, -2))[None] + ground[seen][:, None, None, :]  # (rows, yaws, 4, 3)
        uv = camera.project(corners.reshape(-1, 3), distort=False).reshape(seen.size, yaws.size, 4, 2)
        sides = np.linalg.norm(np.roll(uv, -1, axis=2) - uv, axis=3).min(axis=2)  # (rows, yaws)
        side[seen] = sides.min(axis=1)
        extent[seen] = np.ptp(uv[..., 1], axis=2).max(axis=1)
        reach[seen] = np.ptp(uv, axis=2).max(axis=(1, 2))
    every_row = np.arange(camera.height)
    return (np.interp(every_row, rows, side), np.interp(every_row, rows, extent),
            np.interp(every_row, rows, reach))


def acquisition_bands(camera: Camera, roof_z: float, tag_size: float, min_side_px: float,
                      max_decimate: int = 8, upsample_below_px: float = 0.0) -> list[Band]:
    """Split the frame into row bands, each searched at the coarsest pyramid level that still leaves a
    tag at least `min_side_px` long (the paper's hierarchical processing, by image row: far rows hold
    small tags and are searched finely, near rows coarsely); rows whose tags are shorter than
    `upsample_below_px` are searched enlarged 2x. A band owns the tags centred on its rows and reaches
    half a tag (with its white border) beyond them, so no tag is cut by a band edge. Rows above the
    horizon of the roof plane are skipped."""
    side, extent, reach = _tag_sizes_by_row(camera, roof_z, tag_size)
    visible = np.flatnonzero(side > 0)
    if visible.size == 0:
        return []
    levels = np.ones(camera.height)
    d = 2
    while d <= max_decimate:
        levels[side / d >= min_side_px] = d
        d *= 2
    levels[(side > 0) & (side < upsample_below_px)] = 0.5
    bands: list[Band] = []
    start = int(visible[0])
    for r in range(start + 1, camera.height + 1):
        if r == camera.height or levels[r] != levels[start]:
            top, bottom = (int(np.ceil(0.6 * extent[i])) + 4 for i in (start, r - 1))
            box = Box(0, max(0, start - top), camera.width, min(camera.height, r + bottom))
            level = float(levels[start])
            bands.append(Band(box, max(level, 1.0), 2 if level < 1 else 1, float(reach[start:r].max())))
            start = r
    return bands


def plane_scale_px(camera: Camera, points_world: np.ndarray, step_m: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Pixels per metre of the horizontal plane through each world point, in its most and least
    foreshortened directions: the singular values (smallest, largest) of the projection's Jacobian
    there. Zeros for points not in front of the camera. A flat tag of side s at the point spans about
    s * smallest px across its most foreshortened direction, whatever its yaw."""
    p = np.asarray(points_world, float).reshape(-1, 3)
    out_min, out_max = np.zeros(len(p)), np.zeros(len(p))
    front = camera.to_camera(p)[:, 2] > 0.1
    if not front.any():
        return out_min, out_max
    q = p[front]
    uv = camera.project(q)
    ju = (camera.project(q + [step_m, 0.0, 0.0]) - uv) / step_m  # d(u, v) / dx
    jv = (camera.project(q + [0.0, step_m, 0.0]) - uv) / step_m  # d(u, v) / dy
    # singular values of the 2x2 [ju jv] in closed form
    a, b, c, d = ju[:, 0], jv[:, 0], ju[:, 1], jv[:, 1]
    s1 = a * a + b * b + c * c + d * d
    det = np.abs(a * d - b * c)
    root = np.sqrt(np.maximum(s1 * s1 - 4 * det * det, 0.0))
    out_max[front] = np.sqrt((s1 + root) / 2)
    out_min[front] = np.sqrt(np.maximum((s1 - root) / 2, 0.0))
    return out_min, out_max


def tag_minor_px(size_m: float, up_m: float, scale_min: np.ndarray, scale_max: np.ndarray) -> np.ndarray:
    """The shorter of a flat tag's two projected extents (px) at its best yaw, from plane_scale_px's
    scales: its longer edge along the most foreshortened direction, its shorter across it."""
    return np.minimum(max(size_m, up_m) * scale_min, min(size_m, up_m) * scale_max)
