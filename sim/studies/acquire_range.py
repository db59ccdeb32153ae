"""`python -m sim.studies.acquire_range`: how small a tag can acquisition, and tracking, still decode?

    python -m sim.studies.acquire_range --out DIR [--per-distance N] [--seed S]

The demo's buses are rendered by the demo's renderer with the demo scenario's image model, standing in
front of each of its four RSU cameras (960x720) at horizontal distances of 8-44 m, any heading, some
tag's whole plate in view (only those count), driving at 7 m/s (motion blur as in the demo); from 14 m
on, every other pose with the bus's tags 0.6x as large (the views end where the real tags are still
~8 px: smaller ones show where decoding ends). Each frame goes through a fresh
RsuPipeline (the demo's settings, acquisition over the whole frame: the pyramid's bands, far rows
enlarged 2x) exactly as a first search would run. For each tag: its minor extent in px (the tag's side
times the smallest scale of the roof plane's projection at its centre, toptag.rsu.regions.tag_minor_px:
its extent across its most foreshortened direction) and whether the pipeline decoded it. The decode rate
by minor extent gives the threshold below which a search for a bus is in vain
(PipelineSettings.acquire_min_tag_px). The same frame also goes through a tracking pipeline given the
bus's true pose as another RSU's fix (the crops a tracked bus gets, enlarged 2x below upsample_below_px):
its decode rate by each tag's thinnest cell in the image as posed (toptag.rsu.regions.thinnest_cell_px)
gives the cell height from which a tag counts as decodable (sim.sampling.DECODABLE_CELL_PX, which
`toptag site check` scores a site with).

Writes DIR/results.json and DIR/acquire_range.png.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from sim.render import PlacedVehicle, render_jpeg
from sim.sampling import DECODABLE_CELL_PX, camera_heading, visible_tags
from sim.scenario import bundled_scenario_path, load_scenario
from sim.studies import require_plotting, write_results
from sim.world import World
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.rsu.regions import plane_scale_px, tag_minor_px, thinnest_cell_px
from toptag.vehicle import Vehicle

DISTANCES = tuple(range(8, 45, 2))  # m, camera nadir to the bus centre (the image corners reach ~40 m)
BEARING_HALF_ANGLE = np.deg2rad(60.0)  # around the camera's heading
BIN_PX = 1.0
SMALL_TAGS, SMALL_TAGS_FROM_M = 0.6, 14  # every other pose from this distance: the bus with tags this much smaller
# acquisition's search enlarges 2x the rows whose tags' shortest side is below this (PipelineSettings's
# acquire_upsample_below_px): the pipeline's default (24) and smaller ones, which cost less
UPSAMPLE_BELOW = (24.0, 16.0, 12.0)


def _scaled(vehicle: Vehicle, factor: float) -> Vehicle:
    spec = vehicle.spec
    return Vehicle(spec.model_copy(update={"tags": [t.model_copy(update={"size": t.size * factor}) for t in spec.tags]}))


def _pose(rng, camera, vehicle, distance: float, tries: int = 300) -> PlacedVehicle | None:
    c, head = camera.center, camera_heading(camera)
    for _ in range(tries):
        b = head + rng.uniform(-BEARING_HALF_ANGLE, BEARING_HALF_ANGLE)
        yaw = rng.uniform(-np.pi, np.pi)
        pv = PlacedVehicle(vehicle, c[0] + distance * np.cos(b), c[1] + distance * np.sin(b), yaw, speed=7.0)
        if visible_tags(camera, pv):
            return pv
    return None


def run(per_distance: int = 4, seed: int = 0, progress=print) -> dict:
    cv2.setNumThreads(1)
    scenario = load_scenario(bundled_scenario_path())
    world = World(scenario)
    variants = {up: PipelineSettings(search_where_possible=False, acquire_upsample_below_px=up) for up in UPSAMPLE_BELOW}
    rng = np.random.default_rng(seed)
    rows = []  # (camera, distance, bus, tag, minor px, thinnest cell px, tracked, decoded by each variant)
    t_ns = 0
    cost = {up: [] for up in UPSAMPLE_BELOW}
    for camera in world.cameras:
        pipes = {up: RsuPipeline(camera, s) for up, s in variants.items()}  # per camera (detectors); fresh sessions
        tracker = RsuPipeline(camera, PipelineSettings())
        for d in DISTANCES:
            for k in range(per_distance):
                bus = world.bus_ids[k % len(world.bus_ids)]
                vehicle = world.vehicle(bus)
                if k % 2 and d >= SMALL_TAGS_FROM_M:  # the same bus with smaller tags: smaller minor extents
                    bus, vehicle = f"{bus} x{SMALL_TAGS}", _scaled(vehicle, SMALL_TAGS)
                pv = _pose(rng, camera, vehicle, float(d))
                if pv is None:
                    continue
                jpeg = render_jpeg(camera, [pv], (), world.model, rng)
                gray = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
                t_ns += 10**9  # a search is due (acquire_idle_period_s)
                found = {}
                for up, pipe in pipes.items():
                    pipe.add_vehicle(vehicle)
                    res = pipe.process(gray, t_ns)
                    pipe.remove_vehicle(vehicle.id)
                    found[up] = {int(o.tag_id) for o in res.vehicles[vehicle.id].observations}
                    cost[up].append(res.search_cost_px)
                tracker.add_vehicle(vehicle)
                tracker.hint(vehicle.id, t_ns, pv.x, pv.y, pv.yaw, pv.roof_z, source="truth")
                res = tracker.process(gray, t_ns)
                tracker.remove_vehicle(vehicle.id)
                tracked = {int(o.tag_id) for o in res.vehicles[vehicle.id].observations}
                for tid in visible_tags(camera, pv):
                    centre = pv.tag_corners_world(tid).mean(axis=0)
                    smin, smax = plane_scale_px(camera, centre[None])
                    t = vehicle.tags[tid]
                    minor = float(tag_minor_px(t.size, t.extent_up, smin, smax)[0])
                    cell = thinnest_cell_px(camera.project(pv.tag_corners_world(tid)))
                    rows.append((camera.id, d, bus, tid, minor, cell, tid in tracked,
                                 *(tid in found[up] for up in UPSAMPLE_BELOW)))
            progress(f"{camera.id}: {d} m, {len(rows)} tags so far")
    minor = np.array([r[4] for r in rows])
    by_variant = {}
    for k, up in enumerate(UPSAMPLE_BELOW):
        ok = np.array([r[7 + k] for r in rows])
        by_variant[str(up)] = {"acquire_upsample_below_px": up,
                               "search_cost_px_mean": round(float(np.mean(cost[up])), 1),
                               **_rates(minor, ok, "minor_px", BIN_PX)}
    cell, tracked = np.array([r[5] for r in rows]), np.array([r[6] for r in rows])
    usable = cell >= DECODABLE_CELL_PX
    tracking = {**_rates(cell, tracked, "cell_px", BIN_PX / 8), "decodable_cell_px": DECODABLE_CELL_PX,
                "decoded_from_decodable_cell": round(float(tracked[usable].mean()), 3) if usable.any() else None}
    return {"image_model": world.model.describe(), "scenario": str(bundled_scenario_path()),
            "cameras": [c.id for c in world.cameras], "distances_m": list(DISTANCES), "per_distance": per_distance,
            "seed": seed, "tags": len(rows), "variants": by_variant, "tracking": tracking,
            "samples": [{"camera": r[0], "distance_m": r[1], "bus": r[2], "tag": r[3], "minor_px": round(r[4], 2),
                         "cell_px": round(r[5], 3), "tracked": bool(r[6]),
                         "decoded": dict(zip(map(str, UPSAMPLE_BELOW), map(bool, r[7:])))} for r in rows]}


def _rates(size: np.ndarray, ok: np.ndarray, name: str, step: float) -> dict:
    """Decode rate in bins (step px) of a tag size measure (name: its key), and the sizes that bound it."""
    edges = np.arange(0.0, np.ceil(size.max()) + step, step)
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (size >= lo) & (size < hi)
        if m.any():
            bins.append({name: [float(lo), float(hi)], "tags": int(m.sum()), "decoded": int(ok[m].sum()),
                         "rate": round(float(ok[m].mean()), 3)})
    return {"decoded": int(ok.sum()),
            f"smallest_decoded_{name}": round(float(size[ok].min()), 2) if ok.any() else None,
            f"largest_missed_{name}": round(float(size[~ok].max()), 2) if (~ok).any() else None,
            f"by_{name}": bins}


def plot(doc: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, v in doc["variants"].items():
        mids = [(b["minor_px"][0] + b["minor_px"][1]) / 2 for b in v["by_minor_px"]]
        ax.plot(mids, [b["rate"] for b in v["by_minor_px"]], marker="o",
                label=f"enlarged below {name} px (search cost {v['search_cost_px_mean'] / 1e3:.0f} k)")
    ax.legend()
    ax.set_xlim(0, 40)
    ax.set_xlabel("tag minor extent (px)")
    ax.set_ylabel("decoded by acquisition")
    ax.set_title("Acquisition decode rate, demo image model, 960x720")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m sim.studies.acquire_range", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="directory for results.json and acquire_range.png")
    p.add_argument("--per-distance", type=int, default=4, help="poses per camera and distance (default 4)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    require_plotting()
    doc = run(args.per_distance, args.seed, progress=lambda s: print(s, file=sys.stderr))
    out = Path(args.out)
    path = write_results(out, doc)
    plot(doc, out / "acquire_range.png")
    print(f"{doc['tags']} tags; {path}")
    for name, v in doc["variants"].items():
        print(f"enlarged below {name} px: search cost {v['search_cost_px_mean']:.0f} px, decoded {v['decoded']}, "
              f"smallest decoded minor extent {v['smallest_decoded_minor_px']} px, largest missed "
              f"{v['largest_missed_minor_px']} px")
        _print_bins(v["by_minor_px"], "minor_px", 30, 0)
    tr = doc["tracking"]
    print(f"tracking crops (true pose as a hint): decoded {tr['decoded']}, thinnest cell decoded "
          f"{tr['smallest_decoded_cell_px']} px, largest missed {tr['largest_missed_cell_px']} px; from "
          f"{tr['decodable_cell_px']:g} px on {100 * tr['decoded_from_decodable_cell']:.1f} %")
    _print_bins(tr["by_cell_px"], "cell_px", 3, 3)
    return 0


def _print_bins(bins: list[dict], name: str, below: float, decimals: int) -> None:
    for b in bins:
        lo, hi = b[name]
        if lo < below:
            print(f"  {lo:.{decimals}f}-{hi:<.{decimals}f} px: {b['decoded']:3d} / {b['tags']:3d}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
