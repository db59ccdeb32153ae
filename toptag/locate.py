"""`toptag locate`: bus pose from RSU images, video files or camera streams, one JSON line per image or
video frame, in input order.

An INPUT is an image file, a video file (mp4, mkv, ts, ...) or a stream URL (rtsp://, http://, ...). A
video's lines carry "source", "frame" (index from 0) and "capture_time_ns" (a file's own timestamps
from --start-ns; a stream's receive time minus --capture-latency-ms: toptag.sources). The frames of a
video are processed in order with the RSU's tracking (--no-tracking: every frame searched afresh, as
images are)."""
from __future__ import annotations

import argparse
import json

from toptag.camera import Camera
from toptag.detection import DetectorSettings
from toptag.errors import InputError, report
from toptag.images import read_gray
from toptag.solvers import METHODS
from toptag.sources import SourceEnded, SourceError, SourceSpec, VideoSource, is_stream_url, is_video_path
from toptag.vehicle import Vehicle


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag locate", description=__doc__)
    p.add_argument("--camera", required=True, help="camera calibration JSON (SPEC.md)")
    p.add_argument("--vehicle", required=True, help="vehicle / code bag JSON (SPEC.md)")
    p.add_argument("--method", choices=METHODS, default="level",
                   help="level: level roof with height prior (default, the most accurate); sopt: the paper's "
                        "S.Opt.; hopt: H.Opt.; bas: Bas.")
    p.add_argument("--weighting", choices=("paper", "principled"), default="principled",
                   help="S.Opt. residual weighting (paper: mu = 1; principled: sigma_px / sigma_h)")
    p.add_argument("--max-hamming", type=int, default=None,
                   help="accepted bit errors per tag (default: the family's gate: 1 for tag36h11 and tag25h9, "
                        "0 for tag16h5)")
    p.add_argument("--search", choices=("pyramid", "full"), default="pyramid",
                   help="pyramid: row bands at the coarsest level that resolves a tag, confirmed at full "
                        "resolution (default); full: the whole frame at --quad-decimate")
    p.add_argument("--quad-decimate", type=float, default=DetectorSettings().quad_decimate,
                   help="quad search decimation of --search full (default 1)")
    p.add_argument("--quad-sigma", type=float, default=DetectorSettings().quad_sigma)
    p.add_argument("--sharpening", type=float, default=DetectorSettings().decode_sharpening)
    p.add_argument("--threads", type=int, default=2, help="detection threads (default 2)")
    p.add_argument("--no-tracking", action="store_true", help="videos: search every frame afresh")
    p.add_argument("--start-ns", type=int, default=0, help="video files: capture time of the file's time 0 (ns)")
    p.add_argument("--capture-latency-ms", type=float, default=0.0,
                   help="streams: camera-to-receiver latency subtracted from the receive time (default 0)")
    p.add_argument("--max-frames", type=int, default=None, help="videos and streams: stop after N frames")
    p.add_argument("images", nargs="+", metavar="INPUT", help="image file, video file or stream URL")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        camera = Camera.load(args.camera).require_extrinsics(f"camera file {args.camera}:")
        vehicle = Vehicle.load(args.vehicle)
        settings = DetectorSettings(max_hamming=args.max_hamming, quad_decimate=args.quad_decimate,
                                    quad_sigma=args.quad_sigma, decode_sharpening=args.sharpening,
                                    nthreads=args.threads if args.search == "full" else 1)
    except InputError as e:
        return report("locate", e)
    except ValueError as e:
        return report("locate", InputError(str(e)))

    from toptag.rsu.pipeline import PipelineSettings, RsuPipeline

    def pipeline_for(tracking: bool) -> RsuPipeline:
        # The RSU's own acquisition (row-banded pyramid, confirmed at full resolution): one pipeline, one
        # set of detectors for all inputs of a kind.
        pl = RsuPipeline(camera, PipelineSettings(method=args.method, weighting=args.weighting, detector=settings,
                                                  tracking=tracking, acquire_mode=args.search,
                                                  workers=args.threads))
        pl.add_vehicle(vehicle)
        return pl

    stills = pipeline_for(False)
    code = 0
    for path in args.images:
        if is_stream_url(path) or is_video_path(path):
            code = max(code, _locate_video(path, args, camera, vehicle, pipeline_for(not args.no_tracking)))
            continue
        try:
            gray = read_gray(path, (camera.width, camera.height))
        except InputError as e:
            code = report("locate", e)  # the other images are still answered
            print(json.dumps({"image": path, "ok": False, "error": str(e)}), flush=True)
            continue
        print(json.dumps({"image": path, **_result_line(stills.process(gray, 0), vehicle.id)}), flush=True)
    return code


def _result_line(result, vehicle_id: str) -> dict:
    found = result.vehicles[vehicle_id].solution
    if found is None:
        return {"ok": False, "error": f"no tag of code bag {vehicle_id} found"}
    if not found.ok:
        return {"ok": False, "error": found.error, "method": found.method, "tags": found.tags,
                "dropped_tags": found.to_dict()["dropped_tags"]}
    return {k: v for k, v in found.to_dict().items() if k != "error"}


def _locate_video(path: str, args, camera: Camera, vehicle: Vehicle, pipeline) -> int:
    """One line per frame of a video file or stream; 2 if it cannot be opened (one line on stderr)."""
    spec = SourceSpec("stream", path) if is_stream_url(path) else SourceSpec("file", path)
    source = VideoSource(spec, capture_latency_ns=int(round(args.capture_latency_ms * 1e6)), start_ns=args.start_ns)
    try:
        source.open()
        if source.size is not None and source.size != (camera.width, camera.height):
            raise SourceError(f"source {path}: frames are {source.size[0]}x{source.size[1]}, the camera "
                              f"{camera.id} is {camera.width}x{camera.height}")
    except SourceError as e:
        source.close()
        code = report("locate", e)
        print(json.dumps({"source": path, "ok": False, "error": str(e)}), flush=True)
        return code
    code = 0
    try:
        while args.max_frames is None or source.frames_read < args.max_frames:
            try:
                frame = source.read()
            except SourceEnded:
                break
            except SourceError as e:
                if spec.kind == "file":
                    break
                code = report("locate", e)
                break
            head = {"source": path, "frame": frame.index, "capture_time_ns": frame.capture_time_ns}
            if frame.gray.shape != (camera.height, camera.width):
                err = (f"frame {frame.index}: {frame.gray.shape[1]}x{frame.gray.shape[0]}, the camera is "
                       f"{camera.width}x{camera.height}")
                print(json.dumps({**head, "ok": False, "error": err}), flush=True)
                continue
            print(json.dumps({**head, **_result_line(pipeline.process(frame.gray, frame.capture_time_ns, frame.index),
                                                     vehicle.id)}), flush=True)
    finally:
        source.close()
    return code
