"""`toptag locate`: bus pose from still RSU images, one JSON line per image, in input order."""
from __future__ import annotations

import argparse
import json

from toptag.camera import Camera
from toptag.detection import DetectorSettings
from toptag.errors import InputError, report
from toptag.images import read_gray
from toptag.solvers import METHODS
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
    p.add_argument("images", nargs="+", metavar="IMAGE")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        camera = Camera.load(args.camera)
        vehicle = Vehicle.load(args.vehicle)
        settings = DetectorSettings(max_hamming=args.max_hamming, quad_decimate=args.quad_decimate,
                                    quad_sigma=args.quad_sigma, decode_sharpening=args.sharpening,
                                    nthreads=args.threads if args.search == "full" else 1)
    except InputError as e:
        return report("locate", e)
    except ValueError as e:
        return report("locate", InputError(str(e)))

    from toptag.rsu.pipeline import PipelineSettings, RsuPipeline

    # The RSU's own acquisition (row-banded pyramid, confirmed at full resolution) on each still image:
    # one pipeline, one set of detectors for all images.
    pipeline = RsuPipeline(camera, PipelineSettings(method=args.method, weighting=args.weighting,
                                                    detector=settings, tracking=False, acquire_mode=args.search,
                                                    workers=args.threads))
    pipeline.add_vehicle(vehicle)
    code = 0
    for path in args.images:
        try:
            gray = read_gray(path, (camera.width, camera.height))
        except InputError as e:
            code = report("locate", e)  # the other images are still answered
            print(json.dumps({"image": path, "ok": False, "error": str(e)}), flush=True)
            continue
        found = pipeline.process(gray, 0).vehicles[vehicle.id].solution
        if found is None:
            line = {"image": path, "ok": False, "error": f"no tag of code bag {vehicle.id} found"}
        elif not found.ok:
            line = {"image": path, "ok": False, "error": found.error, "method": found.method,
                    "tags": found.tags, "dropped_tags": found.to_dict()["dropped_tags"]}
        else:
            line = {"image": path, **{k: v for k, v in found.to_dict().items() if k != "error"}}
        print(json.dumps(line), flush=True)
    return code
