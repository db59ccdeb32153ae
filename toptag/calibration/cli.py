"""`toptag calibrate`: calibrate an RSU camera on site.

    toptag calibrate board --board BOARD.json --out BOARD.png [--dpi 200]
    toptag calibrate intrinsics --board BOARD.json --id ID IMAGE... --out CAM.json
    toptag calibrate extrinsics --camera CAM.json --points POINTS.json [IMAGE] --out CAM.json
    toptag calibrate check --camera CAM.json --points POINTS.json IMAGE

board: the board file's pattern as a PNG to print at 100 % scale (its print scale is in the file; a whole
number of pixels per square, 1 cm of white around the squares). The recommended board is
toptag/data/board_charuco_a0.json (README, "Installing at a site").

intrinsics: ChArUco or chessboard views (toptag.calibration.boards); prints the reprojection RMS, the
error of every image, each parameter with its standard deviation and the image coverage; refuses too
few views or views that leave part of the image empty, naming what is missing; warns when the image
corners are uncovered. Writes a camera file with the intrinsics and their covariance (no extrinsics
yet: services refuse it until `calibrate extrinsics`).

extrinsics: the camera pose in the site frame from surveyed control points (toptag.calibration.points:
given pixels, or AprilTag plates found in IMAGE); prints every point's residual, the pose and its
standard deviations, and the roof-height (z = 3 m) mapping sigma over the 8-25 m footprint; refuses
collinear or too few points. Writes the camera file with the pose and its covariance, which every fix
of this camera then carries.

check: the calibrated camera against a new image (after maintenance, wind, a knock): residuals of the
control points, and the camera pose re-estimated from them: how far it moved in rotation and in where
roof pixels land. Exit 0 when consistent with the calibration, 1 when the camera moved beyond it.

Bad input (missing file, a field missing or NaN, an unreadable image, a board not found) is one line
on stderr, exit 2.
"""
from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

import numpy as np

from toptag.calibration.boards import Board, write_png
from toptag.calibration.extrinsics import (
    DEFAULT_SIGMA_PX,
    FOOTPRINT,
    ROOF_Z,
    footprint_points,
    mapping_error,
    mapping_sigma,
    point_covariances,
    solve_extrinsics,
    project_jacobians,
)
from toptag.calibration.intrinsics import PARAMS, calibrate_intrinsics
from toptag.calibration.points import ControlPoints
from toptag.camera import CalibrationRecord, Camera, ExtrinsicsRecord, IntrinsicsRecord
from toptag.images import read_gray
from toptag.errors import InputError, report


def _today() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _write_camera(camera: Camera, out: Path) -> None:
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(camera.to_json() + "\n")
    except OSError as e:
        raise InputError(f"camera file {out}: cannot write ({e.strerror or e})") from None


# ---- the board to print ---------------------------------------------------------------------------
def run_board(args) -> int:
    board = Board.load(args.board)
    img, ppm = board.printable(args.dpi)
    try:
        write_png(args.out, img, ppm)
    except OSError as e:
        raise InputError(f"board image {args.out}: cannot write ({getattr(e, 'strerror', None) or e})") from None
    h, w = img.shape
    s = board.spec
    print(f"wrote {args.out}: {w}x{h} px, print at 100 % scale: {1000 * w / ppm:.1f} x {1000 * h / ppm:.1f} mm "
          f"({ppm * 0.0254:.1f} dpi), squares {1000 * s.square_size:g} mm"
          + (f", markers {1000 * s.marker_size:g} mm" if s.marker_size else "")
          + "; measure the printed squares and put their size in the board file")
    return 0


# ---- intrinsics ---------------------------------------------------------------------------------
def run_intrinsics(args) -> int:
    board = Board.load(args.board)
    views, no_board, size = [], [], None
    for path in args.images:
        try:
            gray = read_gray(path)
        except InputError as e:
            print(f"toptag calibrate: {e} (left out)", file=sys.stderr)
            continue
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif (gray.shape[1], gray.shape[0]) != size:
            print(f"toptag calibrate: image {path}: {gray.shape[1]}x{gray.shape[0]}, the others are "
                  f"{size[0]}x{size[1]} (left out)", file=sys.stderr)
            continue
        v = board.detect(gray, Path(path).name)
        if v is None:
            no_board.append(Path(path).name)
        else:
            views.append(v)
    if size is None:
        raise InputError("no readable image")
    print(f"board found in {len(views)} of {len(views) + len(no_board)} images"
          + (f" (not in: {', '.join(no_board)})" if no_board else ""))
    r = calibrate_intrinsics(views, size, min_views=args.min_views, names_without_board=no_board)
    print(f"reprojection RMS {r.rms_px:.3f} px per corner; corner noise {r.sigma_px:.3f} px per coordinate"
          + (f"; {r.outliers} outlying corners left out" if r.outliers else ""))
    print("per image: " + ", ".join(f"{n} {e:.3f}" for n, e in r.per_view_rms))
    std = r.std
    vals = dict(zip(PARAMS, [r.K[0, 0], r.K[1, 1], r.K[0, 2], r.K[1, 2], *r.dist]))
    print("parameters: " + ", ".join(f"{k} {vals[k]:.6g} ± {std[k]:.2g}" for k in PARAMS))
    print(f"views cover {100 * r.coverage.fraction:.0f} % of the image")
    for w in r.warnings:
        print(f"warning: {w}", file=sys.stderr)
    s = board.spec
    rec = IntrinsicsRecord(**{k: v for k, v in r.summary().items() if k in IntrinsicsRecord.model_fields},
                           board=f"{s.type} {s.squares_x}x{s.squares_y}, square {s.square_size * 1000:g} mm")
    cam = Camera(args.id, size[0], size[1], r.K, r.dist, np.eye(3), np.zeros(3),
                 CalibrationRecord(intrinsics=rec, extrinsics=None, date=_today()))
    _write_camera(cam, args.out)
    print(f"wrote {args.out} (intrinsics; place it in the site with: toptag calibrate extrinsics)")
    return 0


# ---- extrinsics ---------------------------------------------------------------------------------
def _observe(args, camera: Camera):
    points = ControlPoints.load(args.points)
    gray = None
    if args.image is not None:
        gray = read_gray(args.image, (camera.width, camera.height))
    pts, missing = points.observed(gray)
    if missing:
        print(f"warning: not found in the image: {', '.join(missing)}", file=sys.stderr)
    return pts, missing


def _print_residuals(result) -> None:
    print(f"{'point':<14} {'du px':>7} {'dv px':>7} {'sigmas':>7}")
    for p, r, m in zip(result.points, result.residuals_px, result.normalized):
        print(f"{p.id:<14} {r[0]:7.3f} {r[1]:7.3f} {m:7.2f}")


def run_extrinsics(args) -> int:
    camera = Camera.load(args.camera)
    pts, missing = _observe(args, camera)
    r = solve_extrinsics(camera, pts, sigma_px=args.sigma_px)
    _print_residuals(r)
    s = r.summary()
    c = r.camera.center
    print(f"residual RMS {r.rms_px:.3f} px over {len(pts)} points (chi2/dof {r.chi2_dof:.2f})")
    print(f"camera centre ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) m ± ({', '.join(f'{100 * v:.2f}' for v in s['centre_std_m'])}) cm; "
          f"rotation ± ({', '.join(f'{v:.4f}' for v in s['rotation_std_deg'])})° about the camera axes")
    print(f"roof (z = {ROOF_Z:g} m) mapping sigma over {FOOTPRINT[0]:g}-{FOOTPRINT[1]:g} m: "
          f"{100 * s['roof_mapping_sigma_m']['rms']:.2f} cm RMS")
    for w in r.warnings:
        print(f"warning: {w}", file=sys.stderr)
    old = camera.calibration or CalibrationRecord()
    rec = ExtrinsicsRecord(**{k: v for k, v in s.items() if k in ExtrinsicsRecord.model_fields})
    out = r.camera.with_calibration(CalibrationRecord(intrinsics=old.intrinsics, extrinsics=rec, date=_today()))
    _write_camera(out, args.out)
    print(f"wrote {args.out}")
    return 0


# ---- check --------------------------------------------------------------------------------------
def run_check(args) -> int:
    camera = Camera.load(args.camera).require_extrinsics("camera file")
    pts, _ = _observe(args, camera)
    if not pts:
        raise InputError("check: no control point could be observed in the image")
    W = np.array([p.world for p in pts])
    P = np.array([p.pixel for p in pts])
    u, Jp, Jx = project_jacobians(camera, W)
    C = point_covariances(Jx, np.array([p.sigma for p in pts]), args.sigma_px)
    cal = camera.extrinsic_covariance
    if cal is not None:
        C = C + np.einsum("nik,kl,njl->nij", Jp, cal, Jp)
    r = P - u
    m = np.sqrt(np.einsum("ni,nij,nj->n", r, np.linalg.inv(C), r))
    print(f"{'point':<14} {'du px':>7} {'dv px':>7} {'sigmas':>7}")
    for p, ri, mi in zip(pts, r, m):
        print(f"{p.id:<14} {ri[0]:7.3f} {ri[1]:7.3f} {mi:7.2f}")
    rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    print(f"residual RMS {rms:.3f} px over {len(pts)} points; largest {m.max():.2f} sigma")
    moved = False
    if len(pts) >= 4:
        fresh = solve_extrinsics(camera, pts, sigma_px=args.sigma_px, start=camera)
        fp = footprint_points(camera)
        shift = float(np.sqrt(np.mean(mapping_error(camera, fresh.camera, fp) ** 2))) if len(fp) else float("nan")
        both = fresh.covariance + (cal if cal is not None else 0.0)
        sig = float(np.sqrt(np.mean(mapping_sigma(camera, both, fp) ** 2))) if len(fp) else float("nan")
        dR = fresh.camera.R @ camera.R.T
        angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
        moved = shift > args.tolerance * sig
        print(f"re-estimated pose: turned {angle:.4f}°, centre moved "
              f"{100 * np.linalg.norm(fresh.camera.center - camera.center):.2f} cm; roof (z = {ROOF_Z:g} m) pixels land "
              f"{100 * shift:.2f} cm RMS from before (calibration and check together allow {100 * sig:.2f} cm)")
    else:
        moved = bool(m.max() > 2 * args.tolerance)
    print("MOVED: the camera no longer matches its calibration; run toptag calibrate extrinsics" if moved
          else "OK: consistent with the calibration")
    return 1 if moved else 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag calibrate", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    b = sub.add_parser("board", help="the board file's pattern as a PNG to print at 100 %% scale")
    b.add_argument("--board", required=True, help="board file (JSON)")
    b.add_argument("--out", required=True, type=Path, help="PNG to write")
    b.add_argument("--dpi", type=float, default=200.0, help="print resolution (default 200)")
    i = sub.add_parser("intrinsics", help="intrinsics from ChArUco or chessboard views")
    i.add_argument("--board", required=True, help="board file (JSON)")
    i.add_argument("--id", required=True, help="camera id (the RSU id)")
    i.add_argument("--out", required=True, type=Path)
    i.add_argument("--min-views", type=int, default=10)
    i.add_argument("images", nargs="+", metavar="IMAGE")
    for name, help_ in (("extrinsics", "camera pose in the site frame from control points"),
                        ("check", "residuals of a calibration against a new image")):
        e = sub.add_parser(name, help=help_)
        e.add_argument("--camera", required=True, help="camera file with the intrinsics")
        e.add_argument("--points", required=True, help="control points file (JSON)")
        e.add_argument("--sigma-px", type=float, default=DEFAULT_SIGMA_PX,
                       help=f"pixel noise of a detected or clicked point, per coordinate (default {DEFAULT_SIGMA_PX})")
        e.add_argument("image", nargs="?" if name == "extrinsics" else None, default=None, metavar="IMAGE",
                       help="image in which the plates are found" + (" (needed for plates)" if name == "extrinsics" else ""))
        if name == "extrinsics":
            e.add_argument("--out", required=True, type=Path)
        else:
            e.add_argument("--tolerance", type=float, default=3.0,
                           help="moved when the roof mapping shifts by more than this many sigmas (default 3)")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    run = {"board": run_board, "intrinsics": run_intrinsics, "extrinsics": run_extrinsics, "check": run_check}[args.what]
    try:
        return run(args)
    except InputError as e:
        return report("calibrate", e)
    except ValueError as e:  # a loader's own check (e.g. pydantic)
        return report("calibrate", InputError(str(e)))
