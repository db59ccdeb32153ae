"""`toptag site check DIR`: validate a site folder (docs/site.md) and draw its top view.

    toptag site check DIR [--out PNG]

Checks every file the folder's site.json names (map, one camera file per RSU, vehicles, the optional
simulator scenario) and how they fit together: every RSU's intersection is on the map, camera ids are
unique, every camera's extrinsics are calibrated, no two vehicles share a tag. Prints one line per
problem (errors: exit 2; warnings: exit 0) and per intersection what its cameras cover: the share of
the junction box (where the roads cross) that one and two cameras see at roof height (3 m), and warns
of an intersection no camera covers; and the share of its roads within the approach radius that a
camera sees, with the distance from the centre up to which 90 % of them are seen: a bus in session
(inside the approach radius) beyond that is not fixed by an RSU, so its fused pose is not "ok" there.
"Seen" means decodable: a roof tag of the site's smallest size there, heading along the road, would show
cells at least sim.sampling.DECODABLE_CELL_PX tall (measured with the renderer and the RSU pipeline,
docs/site.md), not merely be inside the image.
With a scenario, its drive (the buses' true poses over one pass of its legs, 10 Hz): per bus, the share
of its session (presence as the bus computes it) with two of its tags decodable in some camera's image
(whole in it, cells DECODABLE_CELL_PX tall), at the approach radius and at smaller ones (the ceiling of
"fused ok while in session" for each radius),
and its longest stretch out of every image within the distance the cameras cover (a blind spot on its
route). Draws the top view (default DIR/site-check.png): roads, approach radius, RSU positions, each
camera's footprint on the ground and where at roof height it sees tags decodably.

Lives in sim/ because it validates the simulator's scenario too; it draws nothing the RSUs compute.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from sim.sampling import DECODABLE_CELL_PX
from sim.studies import require_plotting
from toptag.camera import Camera
from toptag.errors import InputError, SetupError
from toptag.rsu.regions import plane_scale_px
from toptag.site import IntersectionSpec, MapFile, load_site_file
from toptag.vehicle import Vehicle

ROOF_Z = 3.0
BAND_RANGE = 30.0  # the decodable roof band is drawn within this horizontal distance of the camera, m
DRIVE_RADII = (35.0, 25.0, 20.0, 15.0)  # approach radii below the site's at which the drive is also scored
GROUND_RANGE = 60.0  # ground footprints are drawn to this distance from the camera


def _ground_hits(camera: Camera, z: float, max_range: float, n: int = 40) -> np.ndarray:
    """Where the image border's rays meet the plane z (clipped at max_range horizontally): (M, 2)."""
    w, h = camera.width, camera.height
    t = np.linspace(0, 1, n)
    border = np.vstack([np.column_stack([t * (w - 1), np.zeros(n)]), np.column_stack([np.full(n, w - 1), t * (h - 1)]),
                        np.column_stack([(1 - t) * (w - 1), np.full(n, h - 1)]), np.column_stack([np.zeros(n), (1 - t) * (h - 1)])])
    c = camera.center
    d = camera.rays(border)
    pts = []
    for ray in d:
        if ray[2] < -1e-6 and c[2] > z:
            s = (z - c[2]) / ray[2]
            p = c[:2] + s * ray[:2]
        else:  # at or above the horizon: out to the range limit
            p = c[:2] + ray[:2] / max(1e-9, np.hypot(*ray[:2])) * max_range
        v = p - c[:2]
        r = np.hypot(*v)
        pts.append(c[:2] + v * min(1.0, max_range / r) if r > 0 else p)
    return np.array(pts)


def sees(camera: Camera, xy: np.ndarray, z: float = ROOF_Z, near: float = 0.0, far: float = np.inf,
         min_scale: float = 0.0, heading_deg: float | None = None) -> np.ndarray:
    """(N,) whether points (N,2) at height z are in the image and near..far (horizontal) from the camera,
    where a square of 1 m on the plane z, its sides along heading_deg (None: at its worst heading), is at
    least min_scale px across its narrowest direction in the image (8 cells of sampling.thinnest_cell_px's)."""
    P = np.column_stack([xy, np.full(len(xy), z)])
    front = camera.to_camera(P)[:, 2] > 0.5
    d = np.hypot(*(xy - camera.center[:2]).T)
    ok = front & (d >= near) & (d <= far)
    px = np.full((len(xy), 2), -1e9)
    px[ok] = camera.project(P[ok])
    ok &= camera.in_image(px)
    if min_scale > 0 and ok.any():
        ok[ok] = _square_width_px(camera, P[ok], heading_deg) >= min_scale
    return ok


def _square_width_px(camera: Camera, points: np.ndarray, heading_deg: float | None, step_m: float = 0.05) -> np.ndarray:
    """The narrowest width (px) of a 1 m square on the horizontal plane at each point, sides along
    heading_deg: the parallelogram's area over its longer side; at the worst heading (None), the plane's
    smallest scale there."""
    if heading_deg is None:
        return plane_scale_px(camera, points, step_m)[0]
    a = np.radians(heading_deg)
    u, n = np.array([np.cos(a), np.sin(a), 0.0]), np.array([-np.sin(a), np.cos(a), 0.0])
    uv = camera.project(points)
    ju, jn = (camera.project(points + step_m * u) - uv) / step_m, (camera.project(points + step_m * n) - uv) / step_m
    area = np.abs(ju[:, 0] * jn[:, 1] - ju[:, 1] * jn[:, 0])
    return area / np.maximum(np.hypot(*ju.T), np.hypot(*jn.T))


def _grid(half: float, step: float) -> np.ndarray:
    xs = np.arange(-half, half + step / 2, step)
    X, Y = np.meshgrid(xs, xs)
    return np.column_stack([X.ravel(), Y.ravel()])


def _on_road(pts: np.ndarray, road) -> np.ndarray:
    return np.abs(pts @ _normal(road.heading_deg)) <= road.half_width


def junction_box(inter: IntersectionSpec, step: float = 0.5) -> np.ndarray:
    """Grid points (N,2) where the intersection's roads overlap (inside every road's width)."""
    pts = _grid(max(r.half_width for r in inter.roads), step)
    inside = np.zeros(len(pts), bool)
    for i, a in enumerate(inter.roads):
        for b in inter.roads[i + 1:]:
            inside |= _on_road(pts, a) & _on_road(pts, b)
    if len(inter.roads) == 1:
        inside = _on_road(pts, inter.roads[0])
    return pts[inside] + np.asarray(inter.center)


def approach_roads(inter: IntersectionSpec, step: float = 0.5) -> np.ndarray:
    """Grid points (N,2) on any of the intersection's roads within its approach radius: where a bus in
    session drives."""
    pts = _grid(inter.radius, step)
    inside = np.hypot(*pts.T) <= inter.radius
    inside &= np.any([_on_road(pts, r) for r in inter.roads], axis=0)
    return pts[inside] + np.asarray(inter.center)


def covered_radius(distance: np.ndarray, seen: np.ndarray, share: float = 0.9, step: float = 1.0) -> float:
    """The largest distance r from the centre (in steps) such that at least ``share`` of the points
    within r are seen; 0 when not even the nearest are."""
    best = 0.0
    for r in np.arange(step, distance.max() + step, step):
        within = distance <= r
        if within.any() and seen[within].mean() >= share:
            best = float(r)
    return best


def _normal(heading_deg: float) -> np.ndarray:
    a = np.radians(heading_deg)
    return np.array([-np.sin(a), np.cos(a)])


class SiteCheck:
    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.errors: list[str] = []
        self.warnings: list[str] = []
        self.notes: list[str] = []
        self.map: MapFile | None = None
        self.cameras: list[tuple[Camera, str]] = []  # (camera, intersection id)
        self.vehicles: list[Vehicle] = []
        self.coverage: dict[str, dict] = {}
        self.scenario = None
        self.min_scale = 0.0  # px per metre at roof height where the site's tags are decodable (0: no vehicles)

    def _load(self, what, loader):
        try:
            return loader()
        except InputError as e:
            self.errors.append(str(e))
        except ValueError as e:
            self.errors.append(f"{what}: {e}")
        return None

    def run(self) -> "SiteCheck":
        site = self._load("site.json", lambda: load_site_file(self.folder))
        if site is None:
            return self
        d = self.folder
        self.map = self._load(site.map, lambda: MapFile.load(d / site.map))
        ids: dict[str, str] = {}
        for entry in site.rsus:
            cam = self._load(entry.camera, lambda e=entry: Camera.load(d / e.camera))
            if cam is None:
                continue
            if cam.id in ids:
                self.errors.append(f"camera file {entry.camera}: id {cam.id!r} already used by {ids[cam.id]}")
                continue
            ids[cam.id] = entry.camera
            if self._load(entry.camera, lambda c=cam, e=entry: c.require_extrinsics(f"camera file {e.camera}:")) is None:
                continue
            if self.map is not None and entry.intersection not in {i.id for i in self.map.intersections}:
                self.errors.append(f"site file: RSU {cam.id} serves intersection {entry.intersection!r}, which the map "
                                   f"does not have")
                continue
            if cam.extrinsic_covariance is None:
                self.notes.append(f"camera {cam.id}: no calibration covariance, its extrinsics count as exact "
                                  "(toptag calibrate extrinsics records one)")
            self.cameras.append((cam, entry.intersection))
        owners: dict[tuple[str, int], str] = {}
        files: dict[str, str] = {}
        for vf in site.vehicles:
            v = self._load(vf, lambda vf=vf: Vehicle.load(d / vf))
            if v is None:
                continue
            if v.id in files:
                self.errors.append(f"vehicle file {vf}: vehicle id {v.id!r} already in {files[v.id]}")
                continue
            files[v.id] = vf
            for t in v.tag_ids:
                other = owners.setdefault((v.family, t), v.id)
                if other != v.id:
                    self.errors.append(f"vehicle file {vf}: tag {v.family} {t} is also on {other} (ambiguous for both)")
            self.vehicles.append(v)
        if site.scenario is not None:
            from sim.scenario import load_scenario

            self.scenario = self._load(site.scenario, lambda: load_scenario(d / site.scenario))
        if self.vehicles:  # the 8 cells across the smallest tag's black square span its size * this scale
            self.min_scale = 8 * DECODABLE_CELL_PX / min(t.size for v in self.vehicles for t in v.spec.tags)
        if self.map is not None:
            self._cover()
            if self.scenario is not None and not self.errors:
                self._drive()
        return self

    def _drive(self, step_s: float = 0.1) -> None:
        """The scenario's buses on their true poses: how much of each one's session some camera sees."""
        from sim.render import PlacedVehicle
        from sim.sampling import in_some_view
        from sim.world import World
        from toptag.fusion.presence import IntersectionPresence

        world = World(self.scenario)
        world.start(0)
        times = np.arange(0, world.legs_end_ns, int(step_s * 1e9))
        for inter in self.map.intersections:
            cams = [c for c, i in self.cameras if i == inter.id]
            if not cams:
                continue
            radii = [inter.radius] + [r for r in DRIVE_RADII if r < inter.radius]
            reach = self.coverage[inter.id]["covered_radius_m"]
            buses = {}
            for bus in world.bus_ids:
                vehicle = world.vehicle(bus)
                track = []  # (t s, x, y, distance from the centre, in view)
                for t in times:
                    s = world.state(bus, int(t))
                    if s is not None:
                        seen = in_some_view(cams, PlacedVehicle(vehicle, s.x, s.y, s.yaw, s.z))
                        track.append((t / 1e9, s.x, s.y, float(np.hypot(s.x - inter.center[0], s.y - inter.center[1])), seen))
                shares = {}
                for r in radii:
                    presence = IntersectionPresence(MapFile(intersections=[inter.model_copy(update={"radius": r})]))
                    inside = []
                    for t, x, y, _, seen in track:
                        presence.update(x, y)
                        if presence.current is not None:
                            inside.append(seen)
                    if inside:
                        shares[r] = float(np.mean(inside))
                blind, run = (0.0, None), None  # longest stretch out of view within reach: (s, (from, to))
                for t, x, y, dist, seen in track:
                    if dist <= reach and not seen:
                        run = (run[0], (t, x, y)) if run else ((t, x, y), (t, x, y))
                        if run[1][0] - run[0][0] + step_s > blind[0]:
                            blind = (run[1][0] - run[0][0] + step_s, run)
                    else:
                        run = None
                buses[bus] = {"in_view_in_session": shares, "longest_unseen_within_reach_s": round(blind[0], 1),
                              "unseen_from_to": None if blind[1] is None else
                              [[round(v, 1) for v in blind[1][0][1:]], [round(v, 1) for v in blind[1][1][1:]]]}
            self.coverage[inter.id]["drive"] = {"duration_s": round(world.legs_end_ns / 1e9, 1), "buses": buses}
            worst = min((b["in_view_in_session"].get(inter.radius, 1.0) for b in buses.values()), default=1.0)
            if worst < 0.95:
                self.notes.append(f"intersection {inter.id}: in the scenario's drive a bus has two tags decodable in "
                                  f"some camera's image during only {100 * worst:.0f} % of its session: its fused pose "
                                  f"is \"ok\" (a fix less than 1 s old) for little more of it; the shares at smaller "
                                  "approach radii follow")

    def _cover(self) -> None:
        for inter in self.map.intersections:
            cams = [c for c, i in self.cameras if i == inter.id]
            box = junction_box(inter)
            n = np.zeros(len(box), int)
            for c in cams:  # a bus in the box heads along one of the roads
                n += np.any([sees(c, box, ROOF_Z, min_scale=self.min_scale, heading_deg=r.heading_deg)
                             for r in inter.roads], axis=0)
            one, two = float(np.mean(n >= 1)), float(np.mean(n >= 2))
            roads = approach_roads(inter)
            seen = np.zeros(len(roads), bool)
            for c in cams:
                for r in inter.roads:
                    on = _on_road(roads - np.asarray(inter.center), r)
                    seen[on] |= sees(c, roads[on], ROOF_Z, min_scale=self.min_scale, heading_deg=r.heading_deg)
            approach = float(np.mean(seen)) if len(roads) else 0.0
            reach = covered_radius(np.hypot(*(roads - np.asarray(inter.center)).T), seen) if len(roads) else 0.0
            self.coverage[inter.id] = {"cameras": [c.id for c in cams], "one": one, "two": two,
                                       "approach": approach, "covered_radius_m": reach}
            if cams and approach < 0.9:
                self.notes.append(f"intersection {inter.id}: cameras see {100 * approach:.0f} % of its roads within the "
                                  f"approach radius ({inter.radius:g} m), 90 % of them up to {reach:g} m from the centre: "
                                  f"beyond, a bus in session gets no RSU fix (its fused pose is degraded there)")
            if not cams or one == 0.0:
                self.warnings.append(f"intersection {inter.id}: no camera covers it")
            elif one < 0.9:
                self.warnings.append(f"intersection {inter.id}: only {100 * one:.0f} % of the junction box is seen by a "
                                     "camera where its tags are decodable at roof height")

    def draw(self, out: Path) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.patches import Circle, Polygon

        fig, ax = plt.subplots(figsize=(8, 8))
        colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for inter in self.map.intersections if self.map else []:
            c = np.asarray(inter.center)
            for r in inter.roads:
                a = np.radians(r.heading_deg)
                u, n = np.array([np.cos(a), np.sin(a)]), _normal(r.heading_deg)
                L, W = r.length, r.half_width
                ax.add_patch(Polygon([c + L * u + W * n, c - L * u + W * n, c - L * u - W * n, c + L * u - W * n],
                                     closed=True, fc="0.85", ec="0.6", lw=0.5, zorder=0))
            ax.add_patch(Circle(c, inter.radius, fill=False, ls="--", ec="0.3", lw=1))
            cov = self.coverage.get(inter.id, {})
            ax.annotate(f"{inter.id}\njunction box seen: {100 * cov.get('one', 0):.0f} % by one, "
                        f"{100 * cov.get('two', 0):.0f} % by two cameras\nroads within the approach radius: "
                        f"{100 * cov.get('approach', 0):.0f} % (90 % up to {cov.get('covered_radius_m', 0):g} m)",
                        c + [0, inter.radius + 2], ha="center", fontsize=8)
            for bus, b in cov.get("drive", {}).get("buses", {}).items():
                if b["unseen_from_to"]:  # the bus's longest blind stretch within the covered distance
                    (xa, ya), (xb, yb) = b["unseen_from_to"]
                    ax.plot([xa, xb], [ya, yb], "-", color="red", lw=3, zorder=4)
                    ax.annotate(f"{bus} unseen {b['longest_unseen_within_reach_s']:g} s", ((xa + xb) / 2, (ya + yb) / 2 + 1),
                                color="red", fontsize=7, ha="center", zorder=4)
        for k, (cam, _) in enumerate(self.cameras):
            col = colours[k % len(colours)]
            ground = _ground_hits(cam, 0.0, GROUND_RANGE)
            ax.add_patch(Polygon(ground, closed=True, fc=col, alpha=0.08, ec=col, lw=0.8, zorder=1))
            grid = self._band(cam)
            if len(grid):
                ax.plot(grid[:, 0], grid[:, 1], ".", color=col, ms=1.2, alpha=0.5, zorder=2)
            c = cam.center
            ax.plot(c[0], c[1], "^", color=col, ms=9, zorder=3)
            ax.annotate(cam.id, c[:2] + [1, 1], fontsize=8, color=col)
        ax.set(aspect="equal", xlabel="x east (m)", ylabel="y north (m)",
               title=f"site {self.folder.name}: ground footprints (shaded), roof height where tags are decodable "
                     "(dots), "
                     "approach radius (dashed)")
        ax.title.set_fontsize(8)
        ax.autoscale_view()
        fig.tight_layout()
        fig.savefig(out, dpi=110)
        plt.close(fig)

    def _band(self, cam: Camera, step: float = 1.5) -> np.ndarray:
        c = cam.center[:2]
        xs = np.arange(-BAND_RANGE, BAND_RANGE + step, step)
        X, Y = np.meshgrid(xs + c[0], xs + c[1])
        pts = np.column_stack([X.ravel(), Y.ravel()])
        return pts[sees(cam, pts, ROOF_Z, far=BAND_RANGE, min_scale=self.min_scale)]


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag site check", description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path, metavar="DIR")
    p.add_argument("--out", type=Path, default=None, help="top view PNG (default DIR/site-check.png)")
    args = p.parse_args(argv)
    check = SiteCheck(args.folder).run()
    for e in check.errors:
        print(f"error: {e}", file=sys.stderr)
    for w in check.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for n in check.notes:
        print(f"note: {n}")
    if check.map is not None:
        print(f"site {args.folder}: {len(check.cameras)} RSU cameras, {len(check.vehicles)} vehicles, "
              f"{len(check.map.intersections)} intersections")
        for iid, cov in check.coverage.items():
            print(f"  {iid}: cameras {', '.join(cov['cameras']) or 'none'}; junction box seen at roof height by one camera "
                  f"{100 * cov['one']:.0f} %, by two {100 * cov['two']:.0f} %; roads within the approach radius by one "
                  f"{100 * cov['approach']:.0f} % (90 % up to {cov['covered_radius_m']:g} m from the centre)")
            drive = cov.get("drive")
            if drive:
                print(f"  {iid}: the scenario's drive ({drive['duration_s']:g} s, true poses): two tags of the bus "
                      "decodable in some camera's image during its session")
                for bus, b in drive["buses"].items():
                    shares = ", ".join(f"{r:g} m {100 * v:.0f} %" for r, v in b["in_view_in_session"].items())
                    blind = (f"; longest unseen within {cov['covered_radius_m']:g} m: {b['longest_unseen_within_reach_s']:g} s, "
                             f"({b['unseen_from_to'][0][0]:g}, {b['unseen_from_to'][0][1]:g}) to "
                             f"({b['unseen_from_to'][1][0]:g}, {b['unseen_from_to'][1][1]:g})") if b["unseen_from_to"] else ""
                    print(f"    {bus}: with an approach radius of {shares}{blind}")
        out = args.out or args.folder / "site-check.png"
        try:
            require_plotting()
            check.draw(out)
            print(f"top view: {out}")
        except SetupError as e:  # a plain install has no matplotlib: the check itself still holds
            print(f"warning: top view not drawn: {e}", file=sys.stderr)
        except OSError as e:
            print(f"error: top view {out}: cannot write ({e.strerror or e})", file=sys.stderr)
            return 2
    if check.errors:
        print(f"site {args.folder}: {len(check.errors)} error(s)", file=sys.stderr)
        return 2
    print(f"site {args.folder}: valid" + (f", {len(check.warnings)} warning(s)" if check.warnings else ""))
    return 0
