"""Calibration targets in the simulator: boards held in front of a camera and AprilTag plates laid on
the ground, rendered with the same image model as the RSU frames, so that tests and `toptag eval
calibration` recover known intrinsics and extrinsics.

- A board (ChArUco or chessboard, toptag.calibration.boards) is a flat printed texture at any pose in
  the camera frame. Every pixel's exact undistorted ray (sim.raster) meets the board plane; the texel it
  hits gives its grey level; pixels whose footprint crosses a texel edge or the board's outline are
  supersampled (model.supersample² samples, box filter), as sim.render does for tags. The board is
  composited over the camera's background, then goes through the image model's camera steps as an RSU
  frame does (optics in linear light, vignetting, gain, sensor noise, the stream's codec).
- A ground plate is a tag plate lying on the road: rendered by sim.render as a tagged box a few
  millimetres thick (`ground_plate`), so plates get exactly the tag pattern, corner order and image
  model of the bus roofs. Its surveyed points are the four outer corners of the tag's black square.
"""
from __future__ import annotations

import cv2
import numpy as np

from sim.image_model import ImageModel
from sim.raster import raster_for
from sim.render import PlacedVehicle, sample_offsets, sensor_and_stream
from toptag.camera import Camera
from toptag.geometry import vehicle_to_world
from toptag.vehicle import FAMILY_BITS, Vehicle, VehicleFile

PLATE_THICKNESS = 0.004  # m: the plate's top (its tag plane) above the road


def _board_homography(R_cb, t_cb, texel: float, origin_texels) -> np.ndarray:
    """Normalized camera coords (x/z, y/z, 1) -> homogeneous texel coords (col, row, 1) of a board whose
    point X_board maps to the camera as R_cb X + t_cb; texel (0, 0) is at board coords -origin_texels·texel."""
    R = np.asarray(R_cb, float)
    M = np.column_stack([R[:, 0], R[:, 1], np.asarray(t_cb, float)])  # (a, b, 1) -> ray direction
    H = np.linalg.inv(M)
    S = np.array([[1.0 / texel, 0.0, origin_texels[0]], [0.0, 1.0 / texel, origin_texels[1]], [0.0, 0.0, 1.0]])
    return S @ H


def _texel_lookup(levels: np.ndarray, H: np.ndarray, xn, yn):
    """(value, inside) of the texture along normalized rays; a ray meets the plane at depth 1/w, so
    w <= 0 means behind the camera (outside)."""
    w = H[2, 0] * xn + H[2, 1] * yn + H[2, 2]
    c = (H[0, 0] * xn + H[0, 1] * yn + H[0, 2]) / w
    r = (H[1, 0] * xn + H[1, 1] * yn + H[1, 2]) / w
    h, wdt = levels.shape
    inside = (c >= 0) & (c < wdt) & (r >= 0) & (r < h) & (w > 0)
    ci = np.clip(c, 0, wdt - 1).astype(np.intp)
    ri = np.clip(r, 0, h - 1).astype(np.intp)
    return np.where(inside, levels[ri, ci], 0.0).astype(np.float32), inside


def render_board(camera: Camera, levels: np.ndarray, texel: float, R_cb, t_cb, origin_texels=(0.0, 0.0),
                 model: ImageModel | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
    """Gray uint8 frame of `camera` seeing a flat texture (`levels`, grey levels per texel of `texel`
    metres; row 0 at the top) posed by X_cam = R_cb · X_board + t_cb, where board x runs along the
    texture's columns and y along its rows. origin_texels: texel coordinates of the board origin."""
    model = ImageModel() if model is None else model
    rng = np.random.default_rng() if rng is None else rng
    levels = np.asarray(levels, np.float32)
    rast = raster_for(camera)
    H = _board_homography(R_cb, t_cb, texel, origin_texels)
    value, inside = _texel_lookup(levels, H, rast.xn.astype(np.float64), rast.yn.astype(np.float64))
    if not inside.any():
        raise ValueError("the board is not in view")
    ys, xs = np.nonzero(inside)
    y0, y1 = max(0, ys.min() - 2), min(rast.height, ys.max() + 3)
    x0, x1 = max(0, xs.min() - 2), min(rast.width, xs.max() + 3)
    val, ins = value[y0:y1, x0:x1], inside[y0:y1, x0:x1]
    alpha = ins.astype(np.float32)
    premult = val * alpha
    if model.supersample > 1:
        key = np.where(ins, val, -1.0)
        edge = np.zeros(key.shape, bool)
        dh, dv = key[:, 1:] != key[:, :-1], key[1:, :] != key[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        ey, ex = np.nonzero(edge)
        if len(ey):
            offs = sample_offsets(model.supersample)
            # Sub-pixel rays first order in the exact per-pixel map (as sim.render does).
            gy, gx = ey + y0, ex + x0
            xm, xp = np.maximum(gx - 1, 0), np.minimum(gx + 1, rast.width - 1)
            ym, yp = np.maximum(gy - 1, 0), np.minimum(gy + 1, rast.height - 1)
            X, Y = rast.xn, rast.yn
            xu = (X[gy, xp] - X[gy, xm]) / (xp - xm)
            yu = (Y[gy, xp] - Y[gy, xm]) / (xp - xm)
            xv = (X[yp, gx] - X[ym, gx]) / (yp - ym)
            yv = (Y[yp, gx] - Y[ym, gx]) / (yp - ym)
            sx = X[gy, gx][:, None] + xu[:, None] * offs[None, :, 0] + xv[:, None] * offs[None, :, 1]
            sy = Y[gy, gx][:, None] + yu[:, None] * offs[None, :, 0] + yv[:, None] * offs[None, :, 1]
            v, i = _texel_lookup(levels, H, sx.astype(np.float64), sy.astype(np.float64))
            alpha[ey, ex] = i.mean(axis=1)
            premult[ey, ex] = (v * i).mean(axis=1)
    F = rast.radiance.copy()
    F[y0:y1, x0:x1] = F[y0:y1, x0:x1] * (1.0 - alpha) + premult
    return finish(rast, F, model, rng)


def finish(rast, radiance: np.ndarray, model: ImageModel, rng: np.random.Generator) -> np.ndarray:
    """The image model's camera steps on a whole-frame radiance image, exactly as sim.render takes them:
    optics, vignetting and gain (CameraRaster.develop), then sensor noise and the stream's codec."""
    return sensor_and_stream(rast, rast.develop(radiance, model), model, rng)


# ---- ground plates ------------------------------------------------------------------------------
def plate_vehicle(tag_id: int, size: float, family: str = "tag36h11") -> Vehicle:
    """A tag plate as a thin tagged box: `size` is the tag's black square, the plate adds its white border."""
    cells = FAMILY_BITS[family] + 2
    side = size * (cells + 2) / cells
    return Vehicle(VehicleFile(id=f"plate-{family}-{tag_id}", height=PLATE_THICKNESS, family=family, length=side,
                               width=side, tags=[{"id": int(tag_id), "size": float(size)}]))


def ground_plate(tag_id: int, size: float, x: float, y: float, yaw: float = 0.0,
                 family: str = "tag36h11") -> PlacedVehicle:
    """A plate lying on the road at (x, y), its printed top toward `yaw`; white like paper."""
    return PlacedVehicle(plate_vehicle(tag_id, size, family), x, y, yaw, color=200.0)


def plate_corners_world(plate: PlacedVehicle) -> np.ndarray:
    """(4, 3) world corners of the plate's tag (the surveyed points), detector order."""
    v = plate.vehicle
    tid = v.tag_ids[0]
    return vehicle_to_world(v.tag_corners(tid), plate.x, plate.y, plate.yaw, plate.roof_z)


# ---- board views --------------------------------------------------------------------------------
def board_poses(camera: Camera, board_size: tuple[float, float], n: int, rng: np.random.Generator,
                distance: tuple[float, float] = (0.7, 1.1), max_tilt_deg: float = 45.0,
                grid: tuple[int, int] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """n board poses (R_cb, t_cb) as a careful operator takes them: the board centre aimed in turn at the
    four image corners (where only the part of the board that covers the corner is in view: ChArUco
    corners are found on a partly visible board), the middles of the four edges and a 4 x 3 grid inside
    (whole board in view, the views that fix the focal length), in random order; at a random distance,
    tilted by up to max_tilt_deg about a random axis in the board plane. grid=(gx, gy): aim at the
    centres of a gx x gy grid instead."""
    from toptag.geometry import rodrigues

    if grid is not None:
        gx, gy = grid
        cells = [((i + 0.5) / gx, (j + 0.5) / gy) for j in range(gy) for i in range(gx)]
    else:
        cells = ([(x, y) for y in (0.05, 0.95) for x in (0.04, 0.96)] + [(0.5, 0.05), (0.5, 0.95), (0.04, 0.5), (0.96, 0.5)]
                 + [(float(x), float(y)) for y in np.linspace(0.25, 0.75, 3) for x in np.linspace(0.2, 0.8, 4)])
    cells = [cells[k] for k in rng.permutation(len(cells))]
    out = []
    for k in range(n):
        fx, fy = cells[k % len(cells)]
        px = np.array([[np.clip(fx + rng.uniform(-0.03, 0.03), 0, 1) * camera.width - 0.5,
                        np.clip(fy + rng.uniform(-0.03, 0.03), 0, 1) * camera.height - 0.5]])
        ray = np.append(camera.normalized(px)[0], 1.0)
        centre = ray / np.linalg.norm(ray) * rng.uniform(*distance)
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(rng.uniform(0.35, 1.0) * max_tilt_deg)
        spin = rng.uniform(-0.3, 0.3)
        R = rodrigues(np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]) * tilt) @ rodrigues([0.0, 0.0, spin])
        t = centre - R @ np.array([board_size[0] / 2, board_size[1] / 2, 0.0])
        out.append((R, t))
    return out


def plate_layout(camera: Camera, n: int = 8, size: float = 1.0, distance: tuple[float, float] = (7.0, 19.0),
                 half_angle_deg: float = 24.0, family: str = "tag36h11", first_id: int = 0) -> list[PlacedVehicle]:
    """n ground plates spread over a camera's view: in pairs left and right of its heading, from near to
    far (zig-zag in azimuth), each facing the camera."""
    from sim.sampling import camera_heading

    c = camera.center
    heading = camera_heading(camera)
    rows = (n + 1) // 2
    out = []
    for i in range(n):
        row = i // 2
        d = distance[0] + (distance[1] - distance[0]) * (row / max(1, rows - 1))
        side = -1.0 if i % 2 == 0 else 1.0
        az = side * half_angle_deg * (1.0 if row % 2 == 0 else 0.45)
        a = heading + np.radians(az)
        out.append(ground_plate(first_id + i, size, c[0] + d * np.cos(a), c[1] + d * np.sin(a), a + np.pi, family))
    return out


def surveyed_points(plates: list[PlacedVehicle], survey_sigma: float, rng: np.random.Generator) -> dict:
    """A points file (toptag.calibration.points) for plates, their corners surveyed with N(0, sigma) per axis."""
    out = {"survey_sigma": survey_sigma, "plates": []}
    for k, p in enumerate(plates):
        C = plate_corners_world(p)
        out["plates"].append({"id": f"P{k + 1}", "family": p.vehicle.family, "tag_id": p.vehicle.tag_ids[0],
                              "corners": (C + rng.normal(0.0, survey_sigma, C.shape)).tolist()})
    return out
