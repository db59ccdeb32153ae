"""Where an announced bus that this camera has not found can be, so that acquisition searches only
there.

A set of possible positions of the bus's centre on a grid of the roof plane around what the camera
sees. It starts as "anywhere" and is cut to what is known of the bus (its own coarse position, another
RSU's fix: each a disc that grows with its age at the bus's top speed); it grows at that speed as time
passes; and it loses the positions that this camera has just searched in vain (every pixel a bus there
could cover lay inside the searched part of the image). Beyond the grid the bus is possible unless a
disc within the grid says otherwise; from there it can drive in.

Acquisition then searches only the image tiles where a bus at a still possible position would appear,
and nothing when none would: after one search of the whole view finds nothing, the next ones cover the
strip along the edge of the view that a bus can have entered since (or, with a coarse position, the
part of that strip near it), not the whole frame. A bus missed once (occluded, a bad frame) is searched
for again where it was once the possible set has grown back over it: within a few frames at bus speed."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from toptag.camera import Camera
from toptag.limits import BUS_MAX_DECEL_MPS2, BUS_MAX_SPEED_MPS, BUS_MAX_YAW_RATE
from toptag.rsu.regions import Box, plane_scale_px, tag_minor_px
from toptag.rsu.tracking import PosePrediction
from toptag.units import s_from_ns

CELL_M = 1.0  # grid spacing; every disc and footprint is widened by a cell's half diagonal
TILES = (16, 12)  # the image is searched by tiles: this many across and down
MAX_RANGE_M = 80.0  # no grid beyond this distance from the camera's nadir (tags there are sub-pixel)


# How far a bus's path can bend away from a constant-velocity prediction: braking or speeding up, and
# the lateral acceleration of its tightest turn at top speed, in any direction.
MAX_ACCEL_MPS2 = float(np.hypot(BUS_MAX_DECEL_MPS2, BUS_MAX_SPEED_MPS * BUS_MAX_YAW_RATE))
REPORT_Z_MARGIN_M = 0.3  # a report has no roof height: the vehicle's, give or take bounce and load
# A GNSS position is never trusted below this sigma: near buildings and big vehicles multipath puts a
# receiver metres off while it may state a sub-metre sigma, and a disc at 3 sigma that misses the bus
# would keep every RSU from searching where it is. 2 m is an ordinary receiver's open-sky accuracy. A
# wider floor costs searches on every approach: at 4 m the 60 s demo (whose GNSS states 2 m) took 1.45
# cores against 1.31, skipped 5-6 % of frames against 2-3 %, fix latency p99 464-673 ms against 393
# (`toptag bench demo --duration 60`, README "Real time on two cores"). A fused pose (its filter fixed by
# RSUs) keeps its own sigma.
GNSS_SIGMA_FLOOR_M = 2.0


@dataclass(frozen=True)
class ReportedPosition:
    """A bus's own report of where it is (the coarse position of its Approach): at t_ns, (x, y) with
    sigma_m, and, when it knows them, its velocity (with the sigma of each component) or its speed.
    gnss: the position is a satellite fix, whose sigma is raised to GNSS_SIGMA_FLOOR_M."""

    t_ns: int
    x: float
    y: float
    sigma_m: float
    velocity: tuple[float, float] | None = None
    velocity_sigma: float = 0.0
    speed: float | None = None
    yaw: float | None = None  # heading, with its sigma (a fused pose's)
    yaw_sigma: float = 0.0
    z: float = 0.0  # the roof's height (the vehicle's), for predict
    gnss: bool = False

    def __post_init__(self):
        if self.gnss and not self.sigma_m >= GNSS_SIGMA_FLOOR_M:
            object.__setattr__(self, "sigma_m", GNSS_SIGMA_FLOOR_M)

    def disc_at(self, t_ns: int, top_speed: float) -> tuple[float, float, float]:
        """(x, y, radius): where the bus's centre is at t_ns, surely. The position at 3 sigma, moved on
        at the reported velocity; the radius grows with the age by the velocity's 3 sigma and by the
        largest acceleration away from it (or, with a speed only, by how far it drives at that speed
        plus acceleration). Never wider than the top speed allows."""
        age = abs(s_from_ns(t_ns - self.t_ns))
        widest = 3 * self.sigma_m + top_speed * age
        if self.velocity is not None:
            x, y, r = self._moved_on(t_ns)
            if r < widest:
                return x, y, r
        elif self.speed is not None:
            widest = min(widest, 3 * self.sigma_m + (self.speed + 0.5 * MAX_ACCEL_MPS2 * age) * age)
        return self.x, self.y, widest


    def _moved_on(self, t_ns: int) -> tuple[float, float, float]:
        dt = s_from_ns(t_ns - self.t_ns)
        r = 3 * float(np.hypot(self.sigma_m, self.velocity_sigma * dt)) + 0.5 * MAX_ACCEL_MPS2 * dt * dt
        return self.x + self.velocity[0] * dt, self.y + self.velocity[1] * dt, r

    def predict(self, t_ns: int, extra_radius: float = 0.0) -> PosePrediction:
        """The pose at t_ns with margins that hold it (as VehicleTrack.predict, for tag crops): needs
        a velocity and a heading."""
        x, y, r = self._moved_on(t_ns)
        age = abs(s_from_ns(t_ns - self.t_ns))
        return PosePrediction(x, y, float(self.yaw), self.z, r + extra_radius,
                              3 * self.yaw_sigma + BUS_MAX_YAW_RATE * age, REPORT_Z_MARGIN_M)


@dataclass(frozen=True)
class ViewGrid:
    """The roof-plane grid of one camera for one kind of vehicle: for each cell, the image tiles a
    vehicle centred there can cover (any yaw, roof within +-dz)."""

    x0: float
    y0: float
    nx: int
    ny: int
    # (ny*nx,) bool: the vehicle's image footprint there overlaps the image (and, when the grid was built
    # for a decodable size, some tag of it there can project at least that large)
    in_view: np.ndarray
    tiles: np.ndarray  # (ny*nx, 4) int: tile columns [tx0, tx1) and rows [ty0, ty1) of that footprint
    # (ny*nx,) bool: where a vehicle is likely found, not only possibly: in view, its centre's image in the
    # frame and (built for a decodable size) some tag of it centred there at least that large at its best
    # yaw. in_view takes each cell's best case (any part of the footprint in the image, the tag anywhere in
    # the footprint's reach), so a bus beside the view or behind the camera is "in view" too.
    likely: np.ndarray

    @classmethod
    def build(cls, camera: Camera, roof_z: float, radius_m: float, dz: float = 0.3, pad_px: float = 4.0,
              cell_m: float = CELL_M, max_range_m: float = MAX_RANGE_M, tags_m: tuple = (),
              min_tag_px: float = 0.0) -> "ViewGrid":
        """tags_m: the vehicle's tags as (side, extent along its up axis) in metres; with min_tag_px > 0, a
        cell is in view only where one of them, on a roof centred anywhere in the cell, at any yaw, could
        project with a minor extent (regions.tag_minor_px) of at least min_tag_px: a search for a bus
        that can only be farther is in vain, the detector cannot decode its tags."""
        w, h = camera.width, camera.height
        border = np.concatenate([
            np.column_stack([np.linspace(0, w - 1, 64), np.zeros(64)]),
            np.column_stack([np.linspace(0, w - 1, 64), np.full(64, h - 1.0)]),
            np.column_stack([np.zeros(48), np.linspace(0, h - 1, 48)]),
            np.column_stack([np.full(48, w - 1.0), np.linspace(0, h - 1, 48)])])
        nadir = camera.center[:2]
        seen = camera.backproject_to_plane(border, roof_z)[:, :2]
        lo, hi = nadir - max_range_m, nadir + max_range_m
        if np.all(np.isfinite(seen)):  # the horizon is not in view: the grid needs only the footprint
            lo, hi = np.maximum(lo, seen.min(axis=0)), np.minimum(hi, seen.max(axis=0))
        margin = radius_m + 2 * cell_m
        lo, hi = lo - margin, hi + margin
        nx, ny = (np.ceil((hi - lo) / cell_m).astype(int) + 1)
        gx, gy = np.meshgrid(lo[0] + cell_m * np.arange(nx), lo[1] + cell_m * np.arange(ny))
        centres = np.column_stack([gx.ravel(), gy.ravel()])
        # A vehicle centred anywhere in the cell, at any yaw: a circle of its half diagonal plus the
        # cell's half diagonal, at the lowest and highest roof.
        r = radius_m + cell_m * np.sqrt(0.5)
        ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        ring = np.vstack([[0.0, 0.0], np.column_stack([r * np.cos(ang), r * np.sin(ang)])])  # and the centre
        pts = (centres[:, None, None, :] + ring[None, None, :, :]).repeat(2, axis=1)  # (n, 2, 13, 2)
        z = np.broadcast_to(np.array([roof_z - dz, roof_z + dz])[None, :, None, None], pts.shape[:3] + (1,))
        world = np.concatenate([pts, z], axis=-1).reshape(-1, 3)
        front = camera.to_camera(world)[:, 2] > 0.1
        uv = np.full((world.shape[0], 2), np.nan)
        uv[front] = camera.project(world[front])
        uv = uv.reshape(len(centres), -1, 2)
        all_front = front.reshape(len(centres), -1).all(axis=1)
        seen = np.isfinite(uv)
        u0, v0 = (np.where(seen, uv, np.inf).min(axis=1) - pad_px).T
        u1, v1 = (np.where(seen, uv, -np.inf).max(axis=1) + pad_px).T
        any_front = np.isfinite(u0)
        # Part of the circle behind the camera: its image can reach any edge, so the whole frame.
        partial = any_front & ~all_front
        u0[partial], v0[partial], u1[partial], v1[partial] = 0, 0, w, h
        inside = np.zeros(len(world), bool)
        inside[front] = camera.in_image(uv.reshape(-1, 2)[front], margin=-pad_px)
        in_view = partial | inside.reshape(len(centres), -1).any(axis=1)
        if min_tag_px > 0 and tags_m:
            in_view &= _best_tag_px(camera, centres, roof_z + dz, r, cell_m, (ny, nx), tags_m) >= min_tag_px
        likely = in_view.copy()
        centre = np.column_stack([centres, np.full(len(centres), roof_z)])
        ahead = camera.to_camera(centre)[:, 2] > 0.1
        shown = np.zeros(len(centres), bool)
        shown[ahead] = camera.in_image(camera.project(centre[ahead]))
        likely &= shown
        if min_tag_px > 0 and tags_m:
            smin, smax = plane_scale_px(camera, centre)
            likely &= np.max([tag_minor_px(side, up, smin, smax) for side, up in tags_m], axis=0) >= min_tag_px
        tile_w, tile_h = w / TILES[0], h / TILES[1]
        tiles = np.zeros((len(centres), 4), int)
        tiles[in_view, 0] = np.clip(np.floor(u0[in_view] / tile_w), 0, TILES[0] - 1)
        tiles[in_view, 1] = np.clip(np.ceil(u1[in_view] / tile_w), 1, TILES[0])
        tiles[in_view, 2] = np.clip(np.floor(v0[in_view] / tile_h), 0, TILES[1] - 1)
        tiles[in_view, 3] = np.clip(np.ceil(v1[in_view] / tile_h), 1, TILES[1])
        return cls(float(lo[0]), float(lo[1]), int(nx), int(ny), in_view, tiles, likely)

    def likely_share(self, x: float, y: float, sigma_m: float) -> float:
        """How much of a position known to sigma_m (a Gaussian about (x, y)) lies where the vehicle is
        likely found (likely): ~1 well inside the view, ~0 beside it, behind the camera or far off."""
        sigma = max(sigma_m, 0.25 * CELL_M)
        gx = self.x0 + CELL_M * np.arange(self.nx) - x
        gy = self.y0 + CELL_M * np.arange(self.ny) - y
        density = np.exp(-(gy[:, None] ** 2 + gx[None, :] ** 2) / (2 * sigma * sigma)).ravel()
        return min(1.0, float(density[self.likely].sum() * CELL_M * CELL_M / (2 * np.pi * sigma * sigma)))

    def disc(self, x: float, y: float, radius: float) -> np.ndarray:
        """(ny, nx) bool: the cells whose centre may lie within radius of (x, y)."""
        gx = self.x0 + CELL_M * np.arange(self.nx) - x
        gy = self.y0 + CELL_M * np.arange(self.ny) - y
        r = radius + CELL_M * np.sqrt(0.5)
        return gy[:, None] ** 2 + gx[None, :] ** 2 <= r * r



def _best_tag_px(camera: Camera, centres: np.ndarray, z: float, reach_m: float, cell_m: float, shape, tags_m) -> np.ndarray:
    """(n,) the largest minor extent (px) any of the tags can have on a roof at height z whose tag lies
    within reach_m of a cell centre: the tags' extents at each centre, at its best yaw, maximised over the
    disc (a grey dilation of the grid)."""
    smin, smax = plane_scale_px(camera, np.column_stack([centres, np.full(len(centres), z)]))
    px = np.max([tag_minor_px(side, up, smin, smax) for side, up in tags_m], axis=0)
    k = int(np.ceil(reach_m / cell_m))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    return cv2.dilate(px.reshape(shape).astype(np.float32), kernel).ravel()


class Whereabouts:
    """The possible positions of one unfound vehicle for one camera (see the module docstring)."""

    def __init__(self, grid: ViewGrid, speed_mps: float):
        self.grid, self.speed = grid, speed_mps
        self.possible = np.ones((grid.ny, grid.nx), bool)
        self.beyond = True  # may the vehicle be beyond the grid?
        self.t_ns: int | None = None
        self._growth_m = 0.0

    def advance(self, t_ns: int) -> None:
        """Let time pass to t_ns: every position reachable at the top speed becomes possible (also from
        outside the grid). A clock that goes back: anywhere again."""
        if self.t_ns is not None and t_ns < self.t_ns:
            self.possible[:] = True
            self.beyond = True
            self._growth_m = 0.0
        elif self.t_ns is not None:
            self._growth_m += self.speed * (t_ns - self.t_ns) * 1e-9
            k = int(self._growth_m // CELL_M)
            self._grow(k)
            self._growth_m -= k * CELL_M
        self.t_ns = t_ns

    def _grow(self, k: int) -> None:
        """Every position within k cells of a possible one becomes possible (also from beyond the grid)."""
        if k > 0 and not self.possible.all():
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
            grown = cv2.dilate(self.possible.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT,
                               borderValue=int(self.beyond))
            self.possible = grown.astype(bool)
            p = self.possible
            self.beyond |= bool(p[0].any() or p[-1].any() or p[:, 0].any() or p[:, -1].any())

    def limit(self, x: float, y: float, radius: float) -> None:
        """The vehicle is within radius of (x, y). When that leaves no position, neither in the grid nor
        beyond it, although the disc has some in the grid, what was believed is wrong (a coarse position
        beyond its sigma, a bus missed by every search of the disc): the disc is taken as it is. A disc
        that reaches beyond the grid while the vehicle may be there contradicts nothing: the vehicle is
        beyond (e.g. a bus leaving, whose own tight position is past the view, and an older, wider hint)."""
        disc = self.grid.disc(x, y, radius)
        g = self.grid
        within = (x - radius > g.x0 and y - radius > g.y0 and x + radius < g.x0 + CELL_M * (g.nx - 1)
                  and y + radius < g.y0 + CELL_M * (g.ny - 1))
        narrowed = self.possible & disc
        consistent = narrowed.any() or not disc.any() or (self.beyond and not within)
        self.possible = narrowed if consistent else disc
        self.beyond &= not within

    def _candidates(self) -> np.ndarray:
        return np.flatnonzero(self.possible.ravel() & self.grid.in_view)

    @property
    def in_view(self) -> bool:
        """Could the vehicle show in the image at all?"""
        return bool(self._candidates().size)

    def tile_mask(self) -> np.ndarray:
        """(rows, cols) bool: the image tiles a vehicle at a possible position could cover."""
        t = self.grid.tiles[self._candidates()]
        diff = np.zeros((TILES[1] + 1, TILES[0] + 1), int)
        np.add.at(diff, (t[:, 2], t[:, 0]), 1)
        np.add.at(diff, (t[:, 2], t[:, 1]), -1)
        np.add.at(diff, (t[:, 3], t[:, 0]), -1)
        np.add.at(diff, (t[:, 3], t[:, 1]), 1)
        return diff.cumsum(axis=0).cumsum(axis=1)[:TILES[1], :TILES[0]] > 0

    def searched(self, tiles: np.ndarray, regrow_m: float = 0.0) -> None:
        """The vehicle was not found in these image tiles: it is at none of the positions whose whole
        image footprint lies inside them. regrow_m: that was so as far back as the vehicle can drive
        this far: it may have come back into what was ruled out, that far from what was not."""
        s = np.zeros((TILES[1] + 1, TILES[0] + 1), int)
        s[1:, 1:] = tiles.astype(int).cumsum(axis=0).cumsum(axis=1)
        idx = self._candidates()
        t = self.grid.tiles[idx]
        covered = s[t[:, 3], t[:, 1]] - s[t[:, 2], t[:, 1]] - s[t[:, 3], t[:, 0]] + s[t[:, 2], t[:, 0]]
        area = (t[:, 1] - t[:, 0]) * (t[:, 3] - t[:, 2])
        flat = self.possible.ravel()  # a view: clears self.possible
        flat[idx[covered == area]] = False
        self._grow(int(np.ceil(regrow_m / CELL_M)))


def tile_boxes(width: int, height: int, tiles: np.ndarray) -> list[Box]:
    """Disjoint pixel rectangles covering the marked tiles of a width x height image: runs of each tile
    row, joined with the run below when they span the same columns."""
    tw, th = width / TILES[0], height / TILES[1]

    def box(tx0: int, ty0: int, tx1: int, ty1: int) -> Box:
        return Box(int(np.floor(tx0 * tw)), int(np.floor(ty0 * th)),
                   min(width, int(np.ceil(tx1 * tw))), min(height, int(np.ceil(ty1 * th))))

    open_runs: dict[tuple[int, int], int] = {}  # (tx0, tx1) -> first row
    out: list[Box] = []
    for ty in range(tiles.shape[0] + 1):
        runs = set()
        if ty < tiles.shape[0]:
            row = np.concatenate([[False], tiles[ty], [False]]).astype(int)
            edges = np.flatnonzero(np.diff(row))
            runs = {(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])}
        for run in list(open_runs):
            if run not in runs:
                out.append(box(run[0], open_runs.pop(run), run[1], ty))
        for run in runs:
            open_runs.setdefault(run, ty)
    return out
