"""Gray-level RSU images of vehicles with roof tags at SPEC's intersection.

`render(camera, vehicles, occluders, model, rng)` paints, per camera:
- the static background (sim.raster: ground texture, lane marks; cached per camera, already blurred);
- every vehicle / occluder as a box layer (sides and roof flat-shaded by a fixed sun, roof tags with the
  official pattern and white border exactly where `Vehicle.tag_corners` puts them), in occlusion order
  (pairwise separating planes of the ground footprints, which is exact for disjoint upright boxes);
- each layer is evaluated per pixel by inverse mapping (pixel -> exact undistorted ray -> face / tag
  plane -> cell), and re-evaluated with `model.supersample`² samples only at pixels whose footprint
  crosses an edge (box filter: exact coverage up to the sample count; those samples in compiled code,
  sim.render_kernels);
- moving layers are blurred along their image-space motion during the exposure (symmetric kernel: the
  rendered pose is the mid-exposure pose), then composited over what is behind them;
- then the image model: Gaussian blur, gain, sensor noise, JPEG (sim.image_model).
Only the image region that vehicles touch is recomputed per frame.
"""
from __future__ import annotations

import re
import threading
import weakref
from dataclasses import dataclass, field

import cv2
import numpy as np

from sim import render_kernels
from sim.image_model import ImageModel
from sim.patterns import grid_size, tag_cells
from sim.raster import NOISE_BANK_EXTRA, CameraRaster, optics_reach, raster_for
from toptag.camera import Camera
from toptag.geometry import rot_z, vehicle_to_world
from toptag.vehicle import Vehicle

SUN = np.array([np.cos(np.deg2rad(50)) * np.cos(np.deg2rad(200)),
                np.cos(np.deg2rad(50)) * np.sin(np.deg2rad(200)), np.sin(np.deg2rad(50))])
AMBIENT = 0.45
ROOF, FRONT, REAR, LEFT, RIGHT = 5, 1, 2, 3, 4  # layer labels (0 = empty)


# ---- scene description --------------------------------------------------------------------------
@dataclass
class PlacedVehicle:
    """A vehicle with roof tags in the scene. `z` is the actual roof (tag plane) height, default
    vehicle.height (differs when the body bounces); speed (m/s, along vehicle +x) and yaw_rate (rad/s)
    drive the motion blur; colour is the body paint grey level."""

    vehicle: Vehicle
    x: float
    y: float
    yaw: float
    z: float | None = None
    speed: float = 0.0
    yaw_rate: float = 0.0
    color: float = 170.0

    @property
    def roof_z(self) -> float:
        return float(self.vehicle.height if self.z is None else self.z)

    @property
    def length(self) -> float:
        return self.vehicle.length

    @property
    def width(self) -> float:
        return self.vehicle.width

    def tag_corners_world(self, tag_id: int) -> np.ndarray:
        """(4, 3) world corners of one tag, detector order."""
        return vehicle_to_world(self.vehicle.tag_corners(tag_id), self.x, self.y, self.yaw, self.roof_z)


@dataclass
class Occluder:
    """A tagless box standing on the ground (truck, van, another bus without tags)."""

    length: float
    width: float
    height: float
    x: float
    y: float
    yaw: float = 0.0
    speed: float = 0.0
    yaw_rate: float = 0.0
    color: float = 120.0

    @property
    def roof_z(self) -> float:
        return float(self.height)


# ---- layers -------------------------------------------------------------------------------------
@dataclass
class _Tag:
    H: np.ndarray  # (3, 3): normalized image coords -> homogeneous (row, col) in cells
    levels: np.ndarray  # (N, N) float32 grey levels
    n: int
    plate_world: np.ndarray  # (4, 3)
    # (xn0, xn1, yn0, yn1): normalized coords outside which no ray meets the printed grid (None: unknown).
    bounds: tuple[float, float, float, float] | None = None


def _grid_bounds(H: np.ndarray, n: int) -> tuple[float, float, float, float] | None:
    """The normalized-coordinate box of the tag's n x n grid seen from the camera. H's third row is the
    world z of the ray (xn, yn, 1): a grid corner lies ahead of the camera iff that is negative (the roof
    is below it). With all four ahead, the grid (convex) projects inside the box of its corners; a
    margin far above rounding keeps it conservative."""
    corners = np.linalg.solve(H, np.array([[0.0, 0, n, n], [0, n, 0, n], [1, 1, 1, 1]]))
    if not np.all(corners[2] < 0):
        return None
    xn, yn = corners[0] / corners[2], corners[1] / corners[2]
    m = 1e-7
    return float(xn.min()) - m, float(xn.max()) + m, float(yn.min()) - m, float(yn.max()) + m


@dataclass
class _Box:
    length: float
    width: float
    height: float
    x: float
    y: float
    yaw: float
    speed: float
    yaw_rate: float
    color: float
    tags: list = field(default_factory=list)
    family: str = ""
    tag_ids: tuple = ()

    def footprint(self) -> np.ndarray:
        L, W = self.length / 2, self.width / 2
        local = np.array([[L, W], [L, -W], [-L, -W], [-L, W]])
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return local @ np.array([[c, s], [-s, c]]) + [self.x, self.y]


def _as_box(obj) -> tuple[_Box, PlacedVehicle | None]:
    if isinstance(obj, PlacedVehicle):
        v = obj.vehicle
        return _Box(v.length, v.width, obj.roof_z, obj.x, obj.y, obj.yaw, obj.speed, obj.yaw_rate, obj.color,
                    family=v.family, tag_ids=tuple(v.tag_ids)), obj
    if isinstance(obj, Occluder):
        return _Box(obj.length, obj.width, obj.height, obj.x, obj.y, obj.yaw, obj.speed, obj.yaw_rate,
                    obj.color), None
    raise TypeError(f"not a scene object: {type(obj).__name__}")


def _tag_layers(pv: PlacedVehicle, camera: Camera, model: ImageModel) -> list[_Tag]:
    v = pv.vehicle
    n = grid_size(v.family)
    Rt = camera.R.T
    C = camera.center
    zr = pv.roof_z
    # Normalized (xn, yn, 1) -> homogeneous world (X, Y, 1) on the roof plane.
    Hp = np.vstack([C[0] * Rt[2] + (zr - C[2]) * Rt[0], C[1] * Rt[2] + (zr - C[2]) * Rt[1], Rt[2]])
    out = []
    for tid, spec in v.tags.items():
        cell_side = spec.size / (n - 2)
        cell_up = spec.extent_up / (n - 2)
        half_side, half_up = n / 2 * cell_side, n / 2 * cell_up
        # world XY -> vehicle -> tag frame (up, left) -> (row, col) of the printed grid.
        to_vehicle = np.eye(3)
        to_vehicle[:2, :2] = rot_z(-pv.yaw)[:2, :2]
        to_vehicle[:2, 2] = -to_vehicle[:2, :2] @ [pv.x, pv.y]
        to_tag = np.eye(3)
        to_tag[:2, :2] = rot_z(-spec.yaw)[:2, :2]
        to_tag[:2, 2] = -to_tag[:2, :2] @ np.asarray(spec.center)
        to_grid = np.array([[-1.0 / cell_up, 0.0, half_up / cell_up],
                            [0.0, -1.0 / cell_side, half_side / cell_side],
                            [0.0, 0.0, 1.0]])
        H = to_grid @ to_tag @ to_vehicle @ Hp
        cells = tag_cells(v.family, tid)
        levels = np.where(cells > 127, model.tag_white, model.tag_black).astype(np.float32)
        plate = vehicle_to_world(v.plate_corners(tid), pv.x, pv.y, pv.yaw, zr)
        out.append(_Tag(H, levels, n, plate, _grid_bounds(H, n)))
    return out


def _face_polygons(box: _Box, cam_center: np.ndarray):
    """Visible faces: list of (label, world polygon (4,3), world normal)."""
    L, W, Hh = box.length / 2, box.width / 2, box.height
    Rz = rot_z(box.yaw)
    o = Rz.T @ (cam_center - [box.x, box.y, 0.0])
    faces = []
    if o[2] > Hh:
        faces.append((ROOF, [[L, W, Hh], [L, -W, Hh], [-L, -W, Hh], [-L, W, Hh]], [0, 0, 1]))
    if o[0] > L:
        faces.append((FRONT, [[L, W, 0], [L, -W, 0], [L, -W, Hh], [L, W, Hh]], [1, 0, 0]))
    if o[0] < -L:
        faces.append((REAR, [[-L, W, 0], [-L, -W, 0], [-L, -W, Hh], [-L, W, Hh]], [-1, 0, 0]))
    if o[1] > W:
        faces.append((LEFT, [[L, W, 0], [-L, W, 0], [-L, W, Hh], [L, W, Hh]], [0, 1, 0]))
    if o[1] < -W:
        faces.append((RIGHT, [[L, -W, 0], [-L, -W, 0], [-L, -W, Hh], [L, -W, Hh]], [0, -1, 0]))
    out = []
    for label, poly, normal in faces:
        out.append((label, np.asarray(poly, float) @ Rz.T + [box.x, box.y, 0.0], Rz @ np.asarray(normal, float)))
    return out


def _face_colors(box: _Box) -> np.ndarray:
    Rz = rot_z(box.yaw)
    lut = np.zeros(6, np.float32)
    for label, n in ((ROOF, [0, 0, 1]), (FRONT, [1, 0, 0]), (REAR, [-1, 0, 0]), (LEFT, [0, 1, 0]),
                     (RIGHT, [0, -1, 0])):
        lut[label] = box.color * (AMBIENT + (1 - AMBIENT) * max(0.0, float(Rz @ np.asarray(n, float) @ SUN)))
    return lut


# Per axis of the box frame (x, y, z), the face a ray enters through when it runs toward -k, and toward +k.
_ENTERED_FACES = np.array([[FRONT, REAR], [LEFT, RIGHT], [ROOF, 0]], np.int64)


def _supersample_box(rast: CameraRaster, box: _Box, ys: np.ndarray, xs: np.ndarray, offsets: np.ndarray,
                     colors: np.ndarray, tags: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Coverage and premultiplied colour (float32) of image pixels (ys, xs) by the box, each the mean of
    exact ray casts at its sub-pixel `offsets` (box faces, and the roof's tags: render_kernels.stack_tags)."""
    Rz = rot_z(box.yaw)
    M = Rz.T @ rast.camera.R.T
    o = Rz.T @ (rast.camera.center - [box.x, box.y, 0.0])
    lo = np.array([-box.length / 2, -box.width / 2, 0.0])
    hi = np.array([box.length / 2, box.width / 2, box.height])
    return render_kernels.supersample_box(rast.xn.ravel(), rast.yn.ravel(), rast.width, rast.height, ys, xs,
                                          offsets, M, o, lo, hi, _ENTERED_FACES, colors, *tags)


def _supersample_tags(rast: CameraRaster, ys: np.ndarray, xs: np.ndarray, offsets: np.ndarray, roof_color,
                      tags: tuple) -> np.ndarray:
    """Mean grey level (float32) of roof pixels (ys, xs) over their sub-pixel `offsets`: the tags' cells
    where a sample's ray meets one, the roof's colour elsewhere."""
    return render_kernels.supersample_tags(rast.xn.ravel(), rast.yn.ravel(), rast.width, rast.height, ys, xs,
                                           offsets, np.float32(roof_color), *tags)


# ---- supersampling ------------------------------------------------------------------------------
_PATTERNS: dict[int, np.ndarray] = {}


def sample_offsets(s: int) -> np.ndarray:
    """(s², 2) sub-pixel offsets in [-0.5, 0.5): a rank-1 lattice (all x distinct, all y distinct,
    well spread), chosen for the largest minimum toroidal distance."""
    if s not in _PATTERNS:
        n = s * s
        if n == 1:
            _PATTERNS[s] = np.zeros((1, 2))
        else:
            k = np.arange(n)
            best, best_g = -1.0, 1
            for g in range(1, n):
                if np.gcd(g, n) != 1:
                    continue
                p = np.column_stack([k / n, (k * g % n) / n])
                d = np.abs(p[:, None] - p[None])
                d = np.minimum(d, 1 - d)
                dist = np.sqrt((d ** 2).sum(-1)) + np.eye(n) * 9
                if dist.min() > best + 1e-12:
                    best, best_g = dist.min(), g
            _PATTERNS[s] = np.column_stack([(k + 0.5) / n, ((k * best_g % n) + 0.5) / n]) - 0.5
    return _PATTERNS[s]


# Pixels whose centre lies within this distance of a projected edge are supersampled: the samples' half
# diagonal (0.71 px) plus a margin above the edges' rasterisation (fillPoly at 1/16 px) and the chords'
# error (edges are subdivided so that lens distortion bends them: sim.raster.project_polygon).
EDGE_REACH_PX = 1.5
_PIECE_PX = 8.0  # edges are cut into pieces this long, each tested against the pixels of its box


def _near_edges(outlines: list[np.ndarray], x0: int, y0: int, h: int, w: int, reach: float) -> np.ndarray:
    """(h, w) bool: the crop's pixels whose centre is within `reach` of an edge of any closed pixel
    outline (M, 2)."""
    a = np.vstack(outlines) - [x0, y0]
    b = np.vstack([np.roll(o, -1, axis=0) for o in outlines]) - [x0, y0]
    return render_kernels.near_edges(a, b, h, w, float(reach), _PIECE_PX)


# ---- one layer ----------------------------------------------------------------------------------
@dataclass
class _Layer:
    x0: int
    y0: int
    alpha: np.ndarray  # (h, w) float32 coverage
    premult: np.ndarray  # (h, w) float32 colour * coverage


def _motion_kernel(rast: CameraRaster, box: _Box, exposure: float) -> np.ndarray | None:
    if exposure <= 0 or (box.speed == 0 and box.yaw_rate == 0):
        return None
    pts = []
    for dt in (-exposure / 2, exposure / 2):
        mid = box.yaw + box.yaw_rate * dt / 2  # mean heading between mid-exposure and dt
        pts.append([box.x + box.speed * dt * np.cos(mid), box.y + box.speed * dt * np.sin(mid), box.height])
    p = rast.camera.project(np.array(pts))
    delta = p[1] - p[0]
    length = float(np.hypot(*delta))
    if not np.isfinite(length) or length < 0.25:
        return None
    r = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1), np.float64)
    m = max(8, int(np.ceil(length * 8)))
    s = (np.arange(m) + 0.5) / m - 0.5  # symmetric about 0: no mean shift
    px = r + s * delta[0]
    py = r + s * delta[1]
    ix, iy = np.floor(px).astype(int), np.floor(py).astype(int)
    fx, fy = px - ix, py - iy
    np.add.at(k, (iy, ix), (1 - fx) * (1 - fy))
    np.add.at(k, (iy, ix + 1), fx * (1 - fy))
    np.add.at(k, (iy + 1, ix), (1 - fx) * fy)
    np.add.at(k, (iy + 1, ix + 1), fx * fy)
    return (k / k.sum()).astype(np.float32)


def _image_velocity(rast: CameraRaster, box: _Box) -> np.ndarray:
    """Pixels per second at which the box's roof centre moves in the image."""
    if box.speed == 0 and box.yaw_rate == 0:
        return np.zeros(2)
    dt = 0.01
    pts = [[box.x + box.speed * s * np.cos(box.yaw), box.y + box.speed * s * np.sin(box.yaw), box.height]
           for s in (-dt / 2, dt / 2)]
    p = rast.camera.project(np.array(pts))
    v = (p[1] - p[0]) / dt
    return v if np.all(np.isfinite(v)) else np.zeros(2)


def _rolling_shutter(layer: "_Layer", rast: CameraRaster, velocity: np.ndarray, readout: float) -> None:
    """Row y is exposed (y/H − 1/2)·readout after the frame's middle row: the layer moves on by
    velocity times that, row by row."""
    h, w = layer.alpha.shape
    t = ((np.arange(h, dtype=np.float32) + layer.y0) / rast.height - 0.5) * readout
    xs = np.arange(w, dtype=np.float32)[None, :] - velocity[0] * t[:, None]
    ys = np.arange(h, dtype=np.float32)[:, None] - velocity[1] * t[:, None] + 0 * xs
    for name in ("alpha", "premult"):
        setattr(layer, name, cv2.remap(getattr(layer, name), xs.astype(np.float32), ys.astype(np.float32),
                                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0))


def _roof_light(rast: CameraRaster, box: _Box, x0: int, y0: int, roof: np.ndarray, model: ImageModel,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(factor, added grey levels) over the crop's roof pixels: a soft shadow edge across the roof at a
    random place and direction (a pole, a sign, the bus's own roof unit), and a specular highlight."""
    h, w = roof.shape
    xn = rast.xn[y0:y0 + h, x0:x0 + w].astype(np.float64)
    yn = rast.yn[y0:y0 + h, x0:x0 + w].astype(np.float64)
    Rt, C, z = rast.camera.R.T, rast.center, box.height
    d = np.stack([Rt[i, 0] * xn + Rt[i, 1] * yn + Rt[i, 2] for i in range(3)])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z - C[2]) / d[2]
    c, si = np.cos(box.yaw), np.sin(box.yaw)
    X, Y = C[0] + s * d[0] - box.x, C[1] + s * d[1] - box.y
    u, v = c * X + si * Y, -si * X + c * Y  # vehicle frame
    factor = np.ones((h, w), np.float32)
    added = np.zeros((h, w), np.float32)
    if model.shadow > 0:
        phi = rng.uniform(0, np.pi)
        off = rng.uniform(-0.4, 0.4) * box.length / 2
        dist = np.cos(phi) * u + np.sin(phi) * v - off
        penumbra = 0.15  # m
        dark = np.clip(0.5 + dist / penumbra, 0.0, 1.0)
        factor = np.where(roof, 1.0 - model.shadow * dark, 1.0).astype(np.float32)
    if model.glare > 0:
        gu, gv = rng.uniform(-0.4, 0.4) * box.length, rng.uniform(-0.4, 0.4) * box.width
        spot = np.exp(-((u - gu) ** 2 + (v - gv) ** 2) / (2 * 0.5 ** 2))
        added = np.where(roof, model.glare * spot, 0.0).astype(np.float32)
    return np.nan_to_num(factor, nan=1.0), np.nan_to_num(added)


def _render_layer(rast: CameraRaster, box: _Box, pv: PlacedVehicle | None, model: ImageModel,
                  rng: np.random.Generator | None = None) -> _Layer | None:
    camera = rast.camera
    faces = _face_polygons(box, rast.center)
    polys = []
    for label, poly_w, _n in faces:
        px = rast.project_polygon(poly_w)
        if px is not None:
            polys.append((label, px))
    if not polys:
        return None
    kernel = _motion_kernel(rast, box, model.exposure)
    velocity = _image_velocity(rast, box) if model.readout_s > 0 else np.zeros(2)
    shutter = int(np.ceil(np.abs(velocity).max() * model.readout_s / 2))
    pad = 3 + (kernel.shape[0] // 2 if kernel is not None else 0) + shutter
    allpts = np.vstack([p for _, p in polys])
    x0 = max(0, int(np.floor(allpts[:, 0].min())) - pad)
    y0 = max(0, int(np.floor(allpts[:, 1].min())) - pad)
    x1 = min(rast.width, int(np.ceil(allpts[:, 0].max())) + pad + 1)
    y1 = min(rast.height, int(np.ceil(allpts[:, 1].max())) + pad + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    h, w = y1 - y0, x1 - x0
    # Labels are rasterised with a 2-pixel apron beyond the crop (and beyond the image), so that an
    # edge just outside the frame still marks the border pixels it touches.
    ap = 2
    label_x = np.zeros((h + 2 * ap, w + 2 * ap), np.uint8)
    outline = np.zeros_like(label_x)
    for lab, px in polys:
        pts = np.round((px - [x0 - ap, y0 - ap]) * 16).astype(np.int32)
        cv2.fillPoly(label_x, [pts], int(lab), lineType=cv2.LINE_8, shift=4)
        # Every projected edge is marked too: faces seen edge-on may be thinner than a pixel.
        cv2.polylines(outline, [pts], True, 1, thickness=1, lineType=cv2.LINE_8, shift=4)
    label = label_x[ap:ap + h, ap:ap + w]
    colors = _face_colors(box)
    color = colors[label]
    tags = _tag_layers(pv, camera, model) if (pv is not None and any(l == ROOF for l, _ in polys)) else []

    # Pixels whose footprint may straddle a face/silhouette edge: label changes, dilated by one.
    diff = outline
    dh = label_x[:, 1:] != label_x[:, :-1]
    dv = label_x[1:, :] != label_x[:-1, :]
    diff[:, 1:] |= dh
    diff[:, :-1] |= dh
    diff[1:, :] |= dv
    diff[:-1, :] |= dv
    band = cv2.dilate(diff, np.ones((3, 3), np.uint8))[ap:ap + h, ap:ap + w].astype(bool)
    # Of those, only the pixels an edge can really cross: every sample of a pixel lies within its
    # half-diagonal of its centre, so a pixel farther than that (plus the labels' rounding) from every
    # projected edge sees one face alone, and its centre's label and colour are what its samples give.
    band &= _near_edges([px for _, px in polys], x0, y0, h, w, EDGE_REACH_PX)

    tag_edge = []  # per tag: mask of its cell-edge pixels in the crop
    for tg in tags:
        pp = rast.project_polygon(tg.plate_world)
        if pp is None:
            continue
        tx0 = max(x0, int(np.floor(pp[:, 0].min())) - 2)
        ty0 = max(y0, int(np.floor(pp[:, 1].min())) - 2)
        tx1 = min(x1, int(np.ceil(pp[:, 0].max())) + 3)
        ty1 = min(y1, int(np.ceil(pp[:, 1].max())) + 3)
        if tx1 <= tx0 or ty1 <= ty0:
            continue
        xn = rast.xn[ty0:ty1, tx0:tx1].astype(np.float64)
        yn = rast.yn[ty0:ty1, tx0:tx1].astype(np.float64)
        sl = (slice(ty0 - y0, ty1 - y0), slice(tx0 - x0, tx1 - x0))
        mask = np.zeros((h, w), bool)
        mask[sl] = render_kernels.tag_cells(xn, yn, tg.H, tg.n, tg.levels, label[sl] == ROOF, color[sl])
        tag_edge.append((tg, mask))

    alpha = (label > 0).astype(np.float32)
    premult = color * alpha
    offs = sample_offsets(model.supersample)
    if model.supersample > 1:
        # Silhouette and face edges: full ray casting (box + tags) at every sample.
        ys, xs = np.nonzero(band)
        if len(ys):
            alpha[ys, xs], premult[ys, xs] = _supersample_box(rast, box, ys + y0, xs + x0, offs, colors,
                                                              render_kernels.stack_tags(tags))
        # Tag cell edges inside the roof: the roof-plane homography of that tag suffices (of all
        # tags where plates touch).
        shared = np.sum([m for _, m in tag_edge], axis=0) > 1 if len(tag_edge) > 1 else None
        groups = [([tg], m & ~shared if shared is not None else m) for tg, m in tag_edge]
        if shared is not None:
            groups.append((tags, shared))
        for group, mask in groups:
            ys, xs = np.nonzero(mask & ~band)
            if len(ys):
                premult[ys, xs] = _supersample_tags(rast, ys + y0, xs + x0, offs, colors[ROOF],
                                                    render_kernels.stack_tags(group))
    if pv is not None and (model.shadow > 0 or model.glare > 0) and rng is not None:
        factor, added = _roof_light(rast, box, x0, y0, label == ROOF, model, rng)
        premult = premult * factor + added * alpha
    if kernel is not None:
        alpha = cv2.filter2D(alpha, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        premult = cv2.filter2D(premult, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    layer = _Layer(x0, y0, alpha, premult)
    if shutter:
        _rolling_shutter(layer, rast, velocity, model.readout_s)
    return layer


# ---- occlusion order ----------------------------------------------------------------------------
def _in_front(a: _Box, b: _Box, eye_xy: np.ndarray) -> int:
    """+1 if a may hide b (a nearer), -1 if b may hide a, 0 if unknown (footprints overlap).
    For disjoint upright boxes a separating vertical plane exists; the one on the camera's side is
    in front."""
    fa, fb = a.footprint(), b.footprint()
    for poly in (fa, fb):
        for i in range(4):
            e = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-e[1], e[0]])
            pa, pb = fa @ axis, fb @ axis
            pe = eye_xy @ axis
            if pa.max() <= pb.min():
                return 1 if pe <= pa.max() else (-1 if pe >= pb.min() else 0)
            if pb.max() <= pa.min():
                return 1 if pe >= pa.min() else (-1 if pe <= pb.max() else 0)
    return 0


def draw_order(boxes: list[_Box], eye: np.ndarray) -> list[int]:
    """Indices far-to-near (painter's order)."""
    n = len(boxes)
    eye_xy = np.asarray(eye[:2], float)
    dist = [float(np.min(np.linalg.norm(b.footprint() - eye_xy, axis=1))) for b in boxes]
    behind = {i: set() for i in range(n)}  # i must be drawn after every j in behind[i]
    for i in range(n):
        for j in range(i + 1, n):
            r = _in_front(boxes[i], boxes[j], eye_xy)
            if r > 0:
                behind[i].add(j)
            elif r < 0:
                behind[j].add(i)
    order, done = [], set()
    remaining = sorted(range(n), key=lambda i: -dist[i])
    while remaining:
        for i in remaining:
            if behind[i] <= done:
                break
        else:  # cycle: fall back to distance
            i = remaining[0]
        order.append(i)
        done.add(i)
        remaining.remove(i)
    return order


# ---- frame --------------------------------------------------------------------------------------
def render(camera: Camera, vehicles=(), occluders=(), model: ImageModel | None = None,
           rng: np.random.Generator | None = None) -> np.ndarray:
    """One gray uint8 (H, W) frame of `camera` seeing `vehicles` (PlacedVehicle) and `occluders`
    (Occluder or PlacedVehicle) under `model` (default ImageModel()). `rng` seeds the sensor noise."""
    model = ImageModel() if model is None else model
    rng = np.random.default_rng() if rng is None else rng
    rast, out, _rows = _developed(camera, vehicles, occluders, model, rng)
    return sensor_and_stream(rast, out, model, rng)


def _developed(camera: Camera, vehicles, occluders, model: ImageModel, rng: np.random.Generator):
    """(raster, the frame through the optics before sensor noise, rows (y0, y1) that differ from the
    static background or None)."""
    rast = raster_for(camera)
    out = rast.finished_background(model).copy()
    items = [_as_box(o) for o in list(vehicles) + list(occluders)]
    layers = []
    for i in draw_order([b for b, _ in items], rast.center):
        layer = _render_layer(rast, items[i][0], items[i][1], model, rng)
        if layer is not None:
            layers.append(layer)
    rows = _composite(rast, layers, model, out) if layers else None
    return rast, out, rows


def sensor_and_stream(rast: CameraRaster, out: np.ndarray, model: ImageModel, rng: np.random.Generator) -> np.ndarray:
    """The model's last steps on a developed uint8 frame (CameraRaster.develop: optics, vignetting, gain):
    sensor noise, then the stream's codec (an intra-coded H.264/H.265 frame, or JPEG). Every rendered image
    goes through here (RSU frames, calibration boards and plates)."""
    if model.noise_sigma > 0:
        cv2.add(out, rast.noise(float(model.noise_sigma), rng), dst=out, dtype=cv2.CV_8U)
    if model.codec != "jpeg":
        out = video_roundtrip(out, model.codec, model.video_qp)
    elif model.jpeg_quality > 0:
        out = cv2.imdecode(np.frombuffer(encode_jpeg(out, model.jpeg_quality), np.uint8), cv2.IMREAD_GRAYSCALE)
    return out


_CODECS = threading.local()


def video_roundtrip(image: np.ndarray, codec: str, qp: int) -> np.ndarray:
    """The frame as an RSU's video stream delivers it: encoded by x264 / x265 as an intra frame (keyint
    1, 4:2:0, as cameras stream) at the constant quantizer qp, decoded again (PyAV's FFmpeg). One encoder
    and decoder per thread and format, reused frame after frame (a constant quantizer, unlike a rate
    factor, does not depend on the frames before)."""
    h, w = image.shape
    W, H = w - w % 2, h - h % 2
    key = (codec, int(qp), W, H)
    pairs = _CODECS.__dict__.setdefault("pairs", {})
    if key not in pairs:
        import av

        enc = av.CodecContext.create({"h264": "libx264", "h265": "libx265"}[codec], "w")
        enc.width, enc.height, enc.pix_fmt = W, H, "yuv420p"
        params = "keyint=1" if codec == "h264" else "keyint=1:log-level=error"
        enc.options = {"qp": str(int(qp)), "preset": "veryfast", "tune": "zerolatency",
                       f"{'x264' if codec == 'h264' else 'x265'}-params": params}
        pairs[key] = [enc, av.CodecContext.create({"h264": "h264", "h265": "hevc"}[codec], "r"), 0]
    enc, dec, n = pairs[key]
    import av

    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image[:H, :W]), format="gray").reformat(format="yuv420p")
    frame.pts = n
    pairs[key][2] = n + 1
    frames = [f for p in enc.encode(frame) for f in dec.decode(p)]
    if not frames:
        raise RuntimeError(f"{codec} encoder returned no frame")
    out = image.copy()
    out[:H, :W] = frames[-1].to_ndarray(format="gray")
    return out


def encode_jpeg(image: np.ndarray, quality: int, params: list[int] | None = None) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, params or [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def render_jpeg(camera: Camera, vehicles=(), occluders=(), model: ImageModel | None = None,
                rng: np.random.Generator | None = None) -> bytes:
    """The frame as the RSU's camera stream delivers it: JPEG bytes at the model's quality (90 when the
    model has JPEG off), compressed once."""
    model = ImageModel() if model is None else model
    if model.codec == "jpeg":
        rng = np.random.default_rng() if rng is None else rng
        rast, out, rows = _developed(camera, vehicles, occluders, model, rng)
        return _strips_for(rast, model).jpeg(out, rows, rng)
    raw = render(camera, vehicles, occluders, model.model_copy(update={"jpeg_quality": 0}), rng)
    return encode_jpeg(raw, model.jpeg_quality or 90)


# ---- JPEG of a frame whose background is static -------------------------------------------------
STRIP_NOISE_CHOICES = 16  # noise fields per 8-row strip of the static background (see _JpegStrips)
_RST = re.compile(rb"\xff[\xd0-\xd7]")


class _JpegStrips:
    """JPEG bytes of a camera's frames in which only the rows that vehicles touch are encoded afresh.

    The frame is coded with a restart marker after every 8-row strip (one row of 8x8 blocks of the gray
    image), which makes each strip's entropy-coded data independent of the others' (the DC prediction
    restarts); every strip is coded with the same standard tables at the same quality. The sensor noise of
    strip m is rows 8m.. of one of STRIP_NOISE_CHOICES fixed fields of the camera's noise bank, drawn per
    strip and frame, so that a static strip's code is one of STRIP_NOISE_CHOICES cached ones and only the
    strips that vehicles touch are noised and encoded. Decoded, the bytes are exactly the pixels a plain
    encoding of the same noised frame gives (tests/test_render_noise.py). The noise is i.i.d. within a
    frame as before; over time a static strip's noise repeats one frame in STRIP_NOISE_CHOICES."""

    def __init__(self, rast: CameraRaster, model: ImageModel):
        self.rast, self.quality, self.sigma = rast, int(model.jpeg_quality or 90), float(model.noise_sigma)
        self.background = rast.finished_background(model)
        h, w = self.background.shape
        self.n_strips = (h + 7) // 8
        self.params = [cv2.IMWRITE_JPEG_QUALITY, self.quality, cv2.IMWRITE_JPEG_RST_INTERVAL, (w + 7) // 8]
        self.choices = STRIP_NOISE_CHOICES if self.sigma > 0 else 1
        stride = NOISE_BANK_EXTRA // self.choices
        self.noise = [rast.noise_window(self.sigma, k * stride) if self.sigma > 0 else None
                      for k in range(self.choices)]
        self.header = b""
        self.cached: list[list[bytes]] = []  # [noise choice][strip]
        for k in range(self.choices):
            header, segments = self._encode(self._noised(self.background, 0, h, [k] * self.n_strips))
            self.header = header
            self.cached.append(segments)

    def _noised(self, img: np.ndarray, y0: int, y1: int, choice) -> np.ndarray:
        """Rows y0:y1 (whole strips, or to the bottom) of img with each strip's noise field."""
        rows = img[y0:y1]
        if self.sigma <= 0:
            return rows
        noise = np.empty(rows.shape, np.int16)
        for m in range(y0 // 8, (y1 + 7) // 8):
            a, b = 8 * m, min(8 * m + 8, y1)
            noise[a - y0:b - y0] = self.noise[choice[m]][a:b]
        return cv2.add(rows, noise, dtype=cv2.CV_8U)

    def _encode(self, img: np.ndarray) -> tuple[bytes, list[bytes]]:
        """(everything up to the scan data, the entropy-coded data of each strip)."""
        data = encode_jpeg(img, self.quality, self.params)
        sos = data.index(b"\xff\xda")
        start = sos + 2 + int.from_bytes(data[sos + 2:sos + 4], "big")
        assert data.endswith(b"\xff\xd9")
        return data[:start], _RST.split(data[start:-2])

    def jpeg(self, out: np.ndarray, rows: tuple[int, int] | None, rng: np.random.Generator) -> bytes:
        choice = rng.integers(0, self.choices, self.n_strips) if self.choices > 1 else np.zeros(self.n_strips, int)
        segments = [self.cached[k][m] for m, k in enumerate(choice)]
        if rows is not None:
            m0, m1 = rows[0] // 8, (rows[1] + 7) // 8
            y1 = min(8 * m1, out.shape[0])
            _, fresh = self._encode(self._noised(out, 8 * m0, y1, choice))
            segments[m0:m1] = fresh
        parts = [self.header]
        for m, seg in enumerate(segments):
            if m:
                parts.append(bytes((0xFF, 0xD0 + (m - 1) % 8)))
            parts.append(seg)
        parts.append(b"\xff\xd9")
        return b"".join(parts)


_STRIPS: "weakref.WeakKeyDictionary[CameraRaster, dict[tuple, _JpegStrips]]" = weakref.WeakKeyDictionary()
_STRIPS_LOCK = threading.Lock()


def _strips_for(rast: CameraRaster, model: ImageModel) -> _JpegStrips:
    key = (float(model.blur_sigma), float(model.gamma), float(model.defocus_px), float(model.gain),
           float(model.vignetting), float(model.noise_sigma), int(model.jpeg_quality or 90))
    with _STRIPS_LOCK:
        per_model = _STRIPS.setdefault(rast, {})
        if key not in per_model:
            if len(per_model) >= 2:
                per_model.pop(next(iter(per_model)))
            per_model[key] = _JpegStrips(rast, model)
        return per_model[key]


def _composite(rast: CameraRaster, layers: list[_Layer], model: ImageModel, out: np.ndarray) -> tuple[int, int]:
    """Paints the layers over out (the developed background); the rows it changed."""
    x0 = min(l.x0 for l in layers)
    y0 = min(l.y0 for l in layers)
    x1 = max(l.x0 + l.alpha.shape[1] for l in layers)
    y1 = max(l.y0 + l.alpha.shape[0] for l in layers)
    mb = optics_reach(model)
    # Paste region: the layers plus the blur reach; crop: plus the blur's input context.
    px0, py0 = max(0, x0 - mb), max(0, y0 - mb)
    px1, py1 = min(rast.width, x1 + mb), min(rast.height, y1 + mb)
    cx0, cy0 = max(0, x0 - 2 * mb), max(0, y0 - 2 * mb)
    cx1, cy1 = min(rast.width, x1 + 2 * mb), min(rast.height, y1 + 2 * mb)
    F = rast.radiance[cy0:cy1, cx0:cx1].copy()
    for l in layers:
        h, w = l.alpha.shape
        sl = (slice(l.y0 - cy0, l.y0 - cy0 + h), slice(l.x0 - cx0, l.x0 - cx0 + w))
        F[sl] = F[sl] * (1.0 - l.alpha) + l.premult
    img = rast.develop(F, model, cx0, cy0)
    out[py0:py1, px0:px1] = img[py0 - cy0:py1 - cy0, px0 - cx0:px1 - cx0]
    return py0, py1
