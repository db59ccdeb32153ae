"""Render benchmark: per-frame time of `sim.render.render` on ONE thread, one double-tag bus moving at
8 m/s at 8-16 m from the SW RSU (random pose per frame), default image model; the per-camera cache is
built before timing. Optionally, the detection rate of that bus versus distance.

    python -m sim.bench_render                    # 960x720 and 3200x2400, 100 frames each
    python -m sim.bench_render --frames 30 --detection
    python -m sim.bench_render --live             # the live simulator's frames (`toptag sim run`)

--live times what `toptag sim run` does per camera frame: every RSU of the bundled demo scenario at
0.3 s steps over its first 60 s (buses, trucks, empty roads alike), the scenario's image model, JPEG
bytes out; thread CPU ms (time.thread_time), so that other work on a shared machine inflates it less.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import cv2
import numpy as np

from sim.image_model import ImageModel
from sim.raster import raster_for
from sim.render import PlacedVehicle, render
from sim.sampling import visible_tags
from sim.scene import bundled_vehicle, rsu_camera


def _bus_on_heading(camera, vehicle, distance: float, rng: np.random.Generator, spread: float = 0.0,
                    speed: float = 0.0) -> PlacedVehicle:
    c = camera.center
    heading = float(np.arctan2(camera.R[2, 1], camera.R[2, 0]))  # optical axis projected on the ground
    a = heading + rng.uniform(-spread, spread)
    return PlacedVehicle(vehicle, c[0] + distance * np.cos(a), c[1] + distance * np.sin(a),
                         float(rng.uniform(-np.pi, np.pi)), speed=speed)


def run(width: int, height: int, frames: int, model: ImageModel | None = None, seed: int = 0) -> dict:
    """Time `frames` renders at width x height; returns p50/p90/mean ms and the cache build time."""
    cv2.setNumThreads(1)
    model = ImageModel() if model is None else model
    rng = np.random.default_rng(seed)
    cam = rsu_camera("sw", width, height)
    bus = bundled_vehicle("bus_double")
    t = time.perf_counter()
    raster_for(cam)
    cache_s = time.perf_counter() - t
    render(cam, [_bus_on_heading(cam, bus, 12.0, rng, 0.3, 8.0)], model=model, rng=rng)
    times = []
    for _ in range(frames):
        pv = _bus_on_heading(cam, bus, float(rng.uniform(8.0, 16.0)), rng, 0.3, 8.0)
        t = time.perf_counter()
        render(cam, [pv], model=model, rng=rng)
        times.append((time.perf_counter() - t) * 1e3)
    ms = np.asarray(times)
    return {"width": width, "height": height, "frames": frames, "p50_ms": round(float(np.percentile(ms, 50)), 2),
            "p90_ms": round(float(np.percentile(ms, 90)), 2), "mean_ms": round(float(ms.mean()), 2),
            "cache_build_s": round(cache_s, 3), "model": model.describe()}


def live_frames(seconds: float = 60.0, step_s: float = 0.3) -> dict:
    """Thread CPU ms per `World.render_jpeg` of the bundled scenario (see the module doc)."""
    from sim.scenario import bundled_scenario_path, load_scenario
    from sim.world import World

    cv2.setNumThreads(1)
    world = World(load_scenario(bundled_scenario_path()))
    world.warm_up()
    world.start(0)
    ms, with_vehicles = [], []
    for k in range(int(seconds / step_s)):
        t_ns = int(round(k * step_s * 1e9))
        busy = bool(world.vehicles_at(t_ns) or world.occluders_at(t_ns))
        for r in range(len(world.cameras)):
            t = time.thread_time()
            world.render_jpeg(r, t_ns)
            ms.append((time.thread_time() - t) * 1e3)
            with_vehicles.append(busy)
    a = np.asarray(ms)
    return {"frames": len(a), "cpu_p50_ms": round(float(np.percentile(a, 50)), 2),
            "cpu_p90_ms": round(float(np.percentile(a, 90)), 2), "cpu_mean_ms": round(float(a.mean()), 2),
            "frames_with_vehicles_on_the_road": int(np.sum(with_vehicles)), "model": world.model.describe()}


def detection_rates(distances=(5, 10, 15, 18, 20, 22), trials: int = 50, width: int = 960, height: int = 720,
                    model: ImageModel | None = None, settings=None, upsample: int = 1, seed: int = 0) -> list[dict]:
    """Detection rate of the double-tag bus on the camera's heading at each horizontal distance (random
    yaw). `in_view` counts tags whose whole plate projects inside the image; `rate_in_view` is the
    rate among those (what the detector is responsible for)."""
    from toptag.detection import TagDetector, assign_to_vehicles

    cv2.setNumThreads(1)
    model = ImageModel() if model is None else model
    rng = np.random.default_rng(seed)
    cam = rsu_camera("sw", width, height)
    bus = bundled_vehicle("bus_double")
    det = TagDetector(settings=settings)
    out = []
    for d in distances:
        found = in_view = found_in_view = both = 0
        err2 = []
        for _ in range(trials):
            pv = _bus_on_heading(cam, bus, float(d), rng)
            img = render(cam, [pv], model=model, rng=rng)
            if upsample > 1:
                big = cv2.resize(img, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
                raw = det.detect_raw(big)
                for r in raw:  # back to original pixels (OpenCV centre convention)
                    r.corners = (r.corners + 0.5) / upsample - 0.5
            else:
                raw = det.detect_raw(img)
            obs = {o.tag_id: o for o in assign_to_vehicles(raw, cam, [bus])[bus.id]}
            both += len(obs) == len(bus.tag_ids)
            whole = visible_tags(cam, pv, margin_px=0.0)
            for tid in bus.tag_ids:
                w = pv.tag_corners_world(tid)
                visible = tid in whole
                in_view += visible
                found += tid in obs
                found_in_view += visible and tid in obs
                if tid in obs:
                    err2.append(((obs[tid].raw_corners - cam.project(w)) ** 2).sum(axis=1))
        e = np.concatenate(err2) if err2 else np.array([np.nan])
        n = trials * len(bus.tag_ids)
        out.append({"distance_m": d, "tag_rate": round(found / n, 3), "both_tags_rate": round(both / trials, 3),
                    "tags_in_view": f"{in_view}/{n}",
                    "rate_in_view": round(found_in_view / in_view, 3) if in_view else None,
                    "corner_rms_px": round(float(np.sqrt(np.nanmean(e))), 3)})
    det.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--detection", action="store_true", help="also measure detection rate vs distance")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--live", action="store_true", help="only the live simulator's frames (see above)")
    args = ap.parse_args(argv)
    if args.live:
        print(json.dumps(live_frames(), indent=2))
        return 0
    result = {"render": [run(960, 720, args.frames), run(3200, 2400, args.frames)]}
    if args.detection:
        result["detection_960x720"] = detection_rates(trials=args.trials)
    print(json.dumps(result, indent=2))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    import os

    code = main()
    sys.stdout.flush()
    os._exit(code)  # pupil-apriltags' Detector.__del__ can crash at interpreter exit (toptag.detection)
