"""`toptag bench rsu`: the tracked RSU pipeline against full-frame detection, side by side on the same
simulated bus pass, with detection rate and position error against the truth. Each frame is what the RSU
receives from the simulator: a JPEG (the image model's quality) of a camera with a real lens's distortion
(sim.examples.EXAMPLE_DIST), decoded in the frame's processing as the RSU decodes it (only when a region of
it is searched). The figures without "with_decode" are the pipeline's on the decoded frame (the decode's
time taken out: a camera stream's frames are decoded by its reader, toptag.sources); those with it, the
frame as the RSU receives it from the simulator."""
from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial

import cv2
import numpy as np

from sim.image_model import ImageModel
from sim.motion import bus_trajectory
from sim.examples import EXAMPLE_DIST
from sim.render import PlacedVehicle, render, render_jpeg
from sim.sampling import DECODABLE_CELL_PX, visible_tags
from sim.scene import bundled_vehicle, rsu_camera
from toptag.detection import DetectorSettings
from toptag.images import decode_gray
from toptag.progress import Progress
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline


def tags_in_view(camera, pv: PlacedVehicle) -> bool:
    """At least one of the bus's tags is decodable in the image: its plate fully inside, its cells at least
    DECODABLE_CELL_PX tall (the project's rule of a tag seen, docs/site.md)."""
    return bool(visible_tags(camera, pv, min_cell_px=DECODABLE_CELL_PX))


def simulated_pass(width: int, height: int, frames: int, fps: float, seed: int = 0, dist=None,
                   as_jpeg: bool = False):
    """Frames of the south-west RSU watching a bus come from the north and turn left across its view at
    30 km/h, starting one second before its tags enter the image (so acquisition is measured too), with
    the truth (x, y, yaw, z) and whether any tag plate is fully in view. Each frame a gray image, or with
    `as_jpeg` the JPEG bytes the simulator would send."""
    camera = rsu_camera("sw", width, height, dist=dist)
    bus = bundled_vehicle("bus_double")
    traj = bus_trajectory("left", "n", seed=seed)
    rng = np.random.default_rng(seed)
    model = ImageModel()

    def placed(t):
        st = traj.state_at(t)
        return PlacedVehicle(bus, float(st.x), float(st.y), float(st.yaw), bus.height + float(st.roof_dz),
                             speed=float(st.speed), yaw_rate=float(st.yaw_rate))

    first_seen = next(t for t in np.arange(0.0, traj.duration, 0.05) if tags_in_view(camera, placed(t)))
    out = []
    for i in range(frames):
        t = max(0.0, first_seen - 1.0) + i / fps
        pv = placed(t)
        img = (render_jpeg if as_jpeg else render)(camera, [pv], model=model, rng=rng)
        out.append((int(traj.t_ns(t)), img, (pv.x, pv.y, pv.yaw, pv.roof_z), tags_in_view(camera, pv)))
    return camera, bus, out


def _run(pipeline: RsuPipeline, vehicle_id: str, frames, label: str, show: bool) -> dict:
    """Each frame through the pipeline: wall and process CPU ms with the frame's JPEG decode and without it
    (ms, cpu_ms: the pipeline on the decoded frame), by kind of frame (tracked, or acquired)."""
    out = {k: [] for k in ("ms", "acquire_ms", "cpu_ms", "acquire_cpu_ms", "with_decode_ms",
                           "acquire_with_decode_ms", "decode_ms", "solve_ms")}
    errors, found, visible = [], 0, 0
    bar = Progress(len(frames), label) if show else None
    for t_ns, img, truth, vis in frames:
        if bar:
            bar.update()
        decode = [0.0, 0.0]  # wall, CPU ms of this frame's decode (none when the pipeline needs no pixels)

        def decoded(jpeg=img):
            w0, c0 = time.perf_counter(), time.thread_time()
            gray = decode_gray(jpeg, "frame")
            decode[:] = (time.perf_counter() - w0) * 1e3, (time.thread_time() - c0) * 1e3
            return gray

        t0, c0 = time.perf_counter(), time.process_time()  # process CPU: the pipeline's worker threads too
        res = pipeline.process(decoded if isinstance(img, bytes) else img, t_ns)
        ms, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        kind = "acquire_" if res.acquired else ""
        out[kind + "with_decode_ms"].append(ms)
        out[kind + "ms"].append(ms - decode[0])
        out[kind + "cpu_ms"].append(cpu - decode[1])
        if decode[0] > 0:
            out["decode_ms"].append(decode[0])
        if res.solve_ms > 0:
            out["solve_ms"].append(res.solve_ms)
        sol = res.vehicles[vehicle_id].solution
        visible += vis
        if vis and sol is not None and sol.ok:
            found += 1
            errors.append(np.hypot(sol.x - truth[0], sol.y - truth[1]))
    if bar:
        bar.close()
    return out | {"rate": found / max(1, visible), "visible": visible,
                  "pos_rms": float(np.sqrt(np.mean(np.square(errors)))) if errors else None}


def run(width: int = 3200, height: int = 2400, frames: int = 60, fps: float = 10.0, seed: int = 0,
        progress=None) -> dict:
    cv2.setNumThreads(1)
    say = progress or (lambda msg: None)
    say(f"rendering {frames} frames at {width}x{height} ...")
    camera, bus, pass_frames = simulated_pass(width, height, frames, fps, seed, EXAMPLE_DIST, as_jpeg=True)

    full = RsuPipeline(camera, PipelineSettings(tracking=False, acquire_mode="full",
                                                detector=DetectorSettings(quad_decimate=1.0, nthreads=2), workers=1))
    tracked = RsuPipeline(camera, PipelineSettings())
    acquire = RsuPipeline(camera, PipelineSettings(tracking=False))
    for p in (full, tracked, acquire):
        p.add_vehicle(bus)
    show = progress is not None
    f = _run(full, bus.id, pass_frames, "full-frame detection (quad_decimate 1, 2 threads)", show)
    t = _run(tracked, bus.id, pass_frames, "tracked pipeline", show)
    a = _run(acquire, bus.id, pass_frames, "acquisition only (pyramid search on every frame)", show)
    pct = lambda xs, q: float(np.percentile(xs, q)) if xs else None  # noqa: E731
    return {
        "width": width, "height": height, "frames": frames, "frames_with_tags_in_view": t["visible"],
        "frame": f"JPEG q{ImageModel().jpeg_quality} (its decode timed apart: *_with_decode_ms); lens {EXAMPLE_DIST}",
        "decode_ms_p50": pct(t["decode_ms"], 50),
        "full_frame_ms_p50": pct(f["acquire_ms"], 50),
        "tracked_ms_p50": pct(t["ms"], 50),
        "tracked_ms_p99": pct(t["ms"], 99),
        "tracked_with_decode_ms_p50": pct(t["with_decode_ms"], 50),
        "acquire_ms_p50": pct(a["acquire_ms"], 50),
        "acquire_with_decode_ms_p50": pct(a["acquire_with_decode_ms"], 50),
        "solve_ms_p50": pct(t["solve_ms"], 50),
        "cpu_ms_p50": {"full_frame": pct(f["acquire_cpu_ms"], 50), "tracked": pct(t["cpu_ms"], 50),
                       "acquire": pct(a["acquire_cpu_ms"], 50)},
        "detect_rate_full": f["rate"],
        "detect_rate_tracked": t["rate"],
        "detect_rate_acquire": a["rate"],
        "pos_rms_full_m": f["pos_rms"],
        "pos_rms_tracked_m": t["pos_rms"],
        "speedup_tracked_vs_full": (pct(f["acquire_ms"], 50) / pct(t["ms"], 50)) if t["ms"] else None,
    }


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag bench rsu", description=__doc__)
    p.add_argument("--width", type=int, default=3200)
    p.add_argument("--height", type=int, default=2400)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--fps", type=float, default=10.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenario", nargs="?", const="", default=None, metavar="FILE",
                   help="instead: every RSU of a scenario (default: the bundled demo) on every frame of its first "
                        "--duration s, offline, with sessions, coarse positions and hints as in the demo; CPU per "
                        "frame by kind of work, searches, fix rate (services/rsu/scenario_bench.py)")
    p.add_argument("--duration", type=float, default=60.0, help="with --scenario: seconds of scenario (default 60)")
    args = p.parse_args(argv)
    if args.scenario is not None:
        from services.rsu.scenario_bench import run_scenario

        result = run_scenario(args.scenario or None, args.duration,
                              progress=lambda m: print(m, file=sys.stderr, flush=True))
        print(json.dumps(result, indent=1))
        return 0
    result = run(args.width, args.height, args.frames, args.fps, args.seed,
                 progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(json.dumps(result, indent=1))
    return 0
