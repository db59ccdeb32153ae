"""`toptag eval calibration`: the on-site calibration procedure on rendered images, against its targets
and its Cramér–Rao bounds.

    toptag eval calibration --out DIR [--intrinsic-trials 10] [--views 20] [--board BOARD.json]
        [--board-distance 0.6 1.0] [--max-tilt 45] [--frames snapshot|stream] [--extrinsic-trials 16] [--seed 0]

Camera: the demo's south-west RSU (960×720, 70° HFOV, the mild barrel lens of the demo site), image
model: the default ImageModel() (stated in results.json and under the figures). The board frames are
lossless snapshots (the model without its codec step), as README asks a site to grab them, or with
`--frames stream` the RSU's stream (the model's H.264 at QP 36); the plates' frame is the stream's.

Intrinsics (per trial): `--views` views of the board README recommends (toptag/data/
board_charuco_a0.json: ChArUco 24 × 17 squares of 48 mm, 36 mm DICT_4X4_250 markers, 1.15 × 0.82 m: A0
on a rigid plate) 0.6-1.0 m from the camera, tilted up to 45°, aimed over the whole image and into its
corners (sim.targets.board_poses), detected and calibrated as `toptag calibrate intrinsics` does.
Measured: the focal length's relative error, and the undistortion error (the camera model's undistortion
with the estimate vs the truth, each in its own camera matrix) over the image area the views covered. Bound: the
Cramér–Rao bound of the same problem (the detected corners' views at their true poses, corner noise
measured as detected minus projected truth), for fx and for the undistortion at every covered pixel.
Targets: |focal error| ≤ 0.05 %, undistortion ≤ 0.3 px over the covered area, in every trial.

Extrinsics (per trial): 8 AprilTag ground plates (1.0 m tags, 7-19 m from the camera, sim.targets.
plate_layout), their four corners surveyed with 5 mm noise per axis, found in one rendered image and
solved as `toptag calibrate extrinsics` does (default pixel sigma), with the true intrinsics. Measured:
the roof-height (z = 3 m) mapping error over the camera's 8-25 m footprint (RMS per trial). Bound: the
Cramér–Rao bound of the pose (survey and measured corner noise), mapped the same way. Target: RMS over
the trials ≤ 1.2 × the bound. Beside it: 8 single surveyed points (one corner per plate) with plain
cv2.solvePnP, and the whole chain (extrinsics on the intrinsics calibrated in the intrinsic trials).

Writes DIR/results.json, DIR/calibration_intrinsics.png, DIR/calibration_extrinsics.png.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sim.image_model import ImageModel
from sim.render import render
from sim.studies import require_plotting, write_results
from sim.targets import board_poses, plate_corners_world, plate_layout, render_board, surveyed_points
from toptag.calibration.boards import Board, recommended_board_path
from toptag.calibration.extrinsics import (
    DEFAULT_SIGMA_PX,
    footprint_points,
    mapping_error,
    mapping_sigma,
    pose_information,
    solve_extrinsics,
)
from toptag.calibration.intrinsics import (
    CalibrationError,
    calibrate_intrinsics,
    covered_pixels,
    intrinsics_information,
    undistort_points,
    undistortion_sigma,
)
from toptag.calibration.points import ControlPoints
from toptag.camera import Camera
from toptag.errors import InputError, SetupError, report

BOARD = json.loads(recommended_board_path().read_text())
# The views README asks a site for: the board 0.6-1.0 m from the camera (it then fills half to all of the
# 960x720 image: 37-41 px squares, which keep the markers readable through the H.264 stream), tilted by
# up to 45°, into every image corner. Issue 12's first board (16 × 12 × 45 mm at 0.7-1.1 m) left the
# focal length's bound at 0.067 %, above the 0.05 % target (README "Calibration accuracy").
VIEW_POSES = {"distance": (0.6, 1.0), "max_tilt_deg": 45.0}
# How the board frames are grabbed: lossless snapshots (the camera's PNG/BMP snapshot, a GigE/USB
# camera's raw frame), as README asks; through the stream's H.264 (QP 36 in the calibrated image model)
# the corners are 1.7 times as noisy and the focal target holds only just (1 of 10 trials at 0.052 %).
FRAMES = "snapshot"
FRAME_SOURCES = {"snapshot": "lossless snapshots", "stream": "the H.264 stream"}
SURVEY_SIGMA = 0.005
FOCAL_TARGET = 0.0005  # relative
UNDISTORTION_TARGET_PX = 0.3
MAPPING_RATIO_TARGET = 1.2


def board_frames_model(model: ImageModel, frames: str = FRAMES) -> ImageModel:
    """The image model of the board frames: `model` without its codec step for a lossless snapshot."""
    if frames not in FRAME_SOURCES:
        raise ValueError(f"frames: {frames!r} is not one of {', '.join(FRAME_SOURCES)}")
    return model.model_copy(update={"codec": "jpeg", "jpeg_quality": 0}) if frames == "snapshot" else model


def study_camera() -> Camera:
    from sim.scenario import bundled_scenario_path

    return Camera.load(bundled_scenario_path().parent / "rsu-sw.json")


# ---- intrinsics ---------------------------------------------------------------------------------
@dataclass
class IntrinsicsTrial:
    focal_rel_error: float  # (fx, fy) mean relative error, signed
    fx_error_px: float
    fx_bound_px: float
    undistortion_rms_px: float
    undistortion_max_px: float
    undistortion_bound_rms_px: float
    corner_sigma_px: float
    rms_px: float
    coverage: float
    uncovered_corners: list
    views: int
    K: list
    dist: list
    corners: int  # used by the calibration
    outliers: int  # corners it left out


def intrinsics_trial(camera: Camera, n_views: int, model: ImageModel, rng: np.random.Generator,
                     board: Board | None = None, view_poses: dict | None = None):
    """One calibration from n_views rendered board views: (IntrinsicsTrial, the calibration result).
    view_poses: board_poses' keyword arguments (default VIEW_POSES)."""
    board = board or Board.from_dict(BOARD)
    view_poses = VIEW_POSES if view_poses is None else view_poses
    pattern, texel, margin = board.pattern()
    levels = np.where(pattern > 127, model.tag_white, model.tag_black).astype(np.float32)
    size = (board.spec.squares_x * board.spec.square_size, board.spec.squares_y * board.spec.square_size)
    views, truth_poses = [], {}
    for i, (R, t) in enumerate(board_poses(camera, size, n_views, rng, **view_poses)):
        gray = render_board(camera, levels, texel, R, t, (margin, margin), model, rng)
        v = board.detect(gray, f"view-{i:02d}")
        if v is not None:
            views.append(v)
            truth_poses[v.name] = (cv2.Rodrigues(np.asarray(R))[0].ravel(), np.asarray(t, float))
    res = calibrate_intrinsics(views, (camera.width, camera.height))
    true_rv = [truth_poses[v.name][0] for v in res.views]
    true_tv = [truth_poses[v.name][1] for v in res.views]
    # corner noise of the corners the calibration used (detected minus projected truth)
    errors = [v.image_points - cv2.projectPoints(v.object_points, rv, tv, camera.K, camera.dist)[0].reshape(-1, 2)
              for v, rv, tv in zip(res.views, true_rv, true_tv)]
    sigma = float(np.sqrt(np.mean(np.vstack(errors) ** 2)))
    bound = np.linalg.inv(intrinsics_information(camera.K, camera.dist, res.views, true_rv, true_tv)) * sigma ** 2
    px = covered_pixels(res.coverage, (camera.width, camera.height))
    d = np.linalg.norm(undistort_points(res.K, res.dist, px) - undistort_points(camera.K, camera.dist, px), axis=1)
    sb = undistortion_sigma(camera.K, camera.dist, bound, px)
    rel = float(np.mean([(res.K[0, 0] - camera.K[0, 0]) / camera.K[0, 0], (res.K[1, 1] - camera.K[1, 1]) / camera.K[1, 1]]))
    trial = IntrinsicsTrial(rel, float(res.K[0, 0] - camera.K[0, 0]), float(np.sqrt(bound[0, 0])),
                            float(np.sqrt(np.mean(d ** 2))), float(d.max()), float(np.sqrt(np.mean(sb ** 2))), sigma,
                            res.rms_px, res.coverage.fraction, res.coverage.uncovered_corners, len(res.views),
                            res.K.tolist(), res.dist.tolist(), sum(len(v.ids) for v in res.views), res.outliers)
    return trial, res


# ---- extrinsics ---------------------------------------------------------------------------------
@dataclass
class ExtrinsicsTrial:
    mapping_rms_m: float
    bound_rms_m: float
    reported_sigma_m: float  # what the tool's covariance says
    plates_found: int
    corner_sigma_px: float
    single_points_pnp_rms_m: float | None
    chained_rms_m: float | None  # with the intrinsics of an intrinsic trial
    rotation_error_deg: float
    centre_error_m: float


def extrinsics_trial(camera: Camera, model: ImageModel, rng: np.random.Generator, intrinsics: Camera | None = None,
                     plates=None, survey_sigma: float = SURVEY_SIGMA, sigma_px: float = DEFAULT_SIGMA_PX):
    """One extrinsic calibration from a rendered plate image: (ExtrinsicsTrial, the calibrated camera)."""
    plates = plates if plates is not None else plate_layout(camera)
    gray = render(camera, plates, (), model, rng)
    spec = surveyed_points(plates, survey_sigma, rng)
    points, missing = ControlPoints.from_dict(spec).find_plates(gray)
    truth = {f"P{k + 1}.{j}": plate_corners_world(p)[j] for k, p in enumerate(plates) for j in range(4)}
    W_true = np.array([truth[p.id] for p in points])
    err = np.array([p.pixel for p in points]) - camera.project(W_true)
    corner_sigma = float(np.sqrt(np.mean(err ** 2)))
    result = solve_extrinsics(camera, points, sigma_px=sigma_px)
    fp = footprint_points(camera)
    e = mapping_error(camera, result.camera, fp)
    bound_cov = np.linalg.inv(pose_information(camera, W_true, np.full((len(points), 3), survey_sigma), corner_sigma))
    bound = float(np.sqrt(np.mean(mapping_sigma(camera, bound_cov, fp) ** 2)))
    # 8 single surveyed points (each plate's first corner), plain solvePnP.
    single = [p for p in points if p.id.endswith(".0")]
    pnp = None
    if len(single) >= 4:
        ok, rv, tv = cv2.solvePnP(np.array([p.world for p in single]), np.array([p.pixel for p in single]),
                                  camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            pnp_cam = camera.with_extrinsics(cv2.Rodrigues(rv)[0], tv.ravel())
            pnp = float(np.sqrt(np.mean(mapping_error(camera, pnp_cam, fp) ** 2)))
    chained = None
    if intrinsics is not None:
        cal = Camera(camera.id, camera.width, camera.height, intrinsics.K, intrinsics.dist, camera.R, camera.t)
        chained_cam = solve_extrinsics(cal, points, sigma_px=sigma_px).camera
        chained = float(np.sqrt(np.mean(mapping_error(camera, chained_cam, fp) ** 2)))
    dR = result.camera.R @ camera.R.T
    trial = ExtrinsicsTrial(float(np.sqrt(np.mean(e ** 2))), bound, result.roof_mapping_sigma(),
                            len(plates) - len(missing), corner_sigma, pnp, chained,
                            float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
                            float(np.linalg.norm(result.camera.center - camera.center)))
    return trial, result


# ---- the study ----------------------------------------------------------------------------------
def _rms(values) -> float:
    v = np.asarray([x for x in values if x is not None], float)
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else float("nan")


def summarise(intr: list[IntrinsicsTrial], extr: list[ExtrinsicsTrial], views_rendered: int | None = None) -> dict:
    out: dict = {}
    if intr:
        f_rms = _rms([t.fx_error_px for t in intr])
        f_bound = _rms([t.fx_bound_px for t in intr])
        u_rms = _rms([t.undistortion_rms_px for t in intr])
        u_bound = _rms([t.undistortion_bound_rms_px for t in intr])
        out["intrinsics"] = {"views_rendered": views_rendered,
            "trials": len(intr), "views": intr[0].views, "views_used_min": min(t.views for t in intr),
            "focal_rel_error_max": max(abs(t.focal_rel_error) for t in intr),
            "focal_rel_error_rms": _rms([t.focal_rel_error for t in intr]),
            "focal_target": FOCAL_TARGET,
            "fx_error_rms_px": f_rms, "fx_bound_px": f_bound, "fx_ratio_to_bound": f_rms / f_bound,
            "focal_bound_rel": _rms([t.fx_bound_px / (t.K[0][0] - t.fx_error_px) for t in intr]),
            "undistortion_max_px": max(t.undistortion_max_px for t in intr),
            "undistortion_rms_px": u_rms, "undistortion_bound_rms_px": u_bound,
            "undistortion_ratio_to_bound": u_rms / u_bound, "undistortion_target_px": UNDISTORTION_TARGET_PX,
            "corner_sigma_px": float(np.mean([t.corner_sigma_px for t in intr])),
            "coverage_mean": float(np.mean([t.coverage for t in intr])),
            "focal_ok": max(abs(t.focal_rel_error) for t in intr) <= FOCAL_TARGET,
            "undistortion_ok": max(t.undistortion_max_px for t in intr) <= UNDISTORTION_TARGET_PX,
        }
    if extr:
        m = _rms([t.mapping_rms_m for t in extr])
        b = _rms([t.bound_rms_m for t in extr])
        out["extrinsics"] = {
            "trials": len(extr), "plates": 8, "survey_sigma_m": SURVEY_SIGMA,
            "mapping_rms_m": m, "bound_rms_m": b, "ratio_to_bound": m / b, "ratio_target": MAPPING_RATIO_TARGET,
            "ok": m / b <= MAPPING_RATIO_TARGET,
            "reported_sigma_rms_m": _rms([t.reported_sigma_m for t in extr]),
            "single_points_solvepnp_rms_m": _rms([t.single_points_pnp_rms_m for t in extr]),
            "chained_with_calibrated_intrinsics_rms_m": _rms([t.chained_rms_m for t in extr]),
            "rotation_error_rms_deg": _rms([t.rotation_error_deg for t in extr]),
            "centre_error_rms_m": _rms([t.centre_error_m for t in extr]),
            "corner_sigma_px": float(np.mean([t.corner_sigma_px for t in extr])),
            "plates_found_min": min(t.plates_found for t in extr),
        }
    return out


def _plots(out: Path, intr: list[IntrinsicsTrial], extr: list[ExtrinsicsTrial], example, camera: Camera,
           model: ImageModel, views: int, board_label: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    caption = f"image model: {model.describe()}"
    if intr:
        fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
        k = np.arange(len(intr))
        ax[0].bar(k, [100 * t.focal_rel_error for t in intr], color="C0", label="focal error (fx, fy mean)")
        b = np.array([100 * t.fx_bound_px / camera.K[0, 0] for t in intr])
        ax[0].plot(k, b, "k_", ms=20, label="± Cramér–Rao bound (1σ)")
        ax[0].plot(k, -b, "k_", ms=20)
        ax[0].axhline(100 * FOCAL_TARGET, color="r", ls="--", label="target ±0.05 %")
        ax[0].axhline(-100 * FOCAL_TARGET, color="r", ls="--")
        ax[0].set(xlabel="trial", ylabel="focal length error (%)", title=f"intrinsics, {views} board views per trial\n{board_label}")
        ax[0].legend(fontsize=7)
        ax[1].bar(k - 0.2, [t.undistortion_max_px for t in intr], 0.4, label="max over covered area")
        ax[1].bar(k + 0.2, [t.undistortion_rms_px for t in intr], 0.4, label="RMS")
        ax[1].plot(k + 0.2, [t.undistortion_bound_rms_px for t in intr], "k_", ms=14, label="bound (RMS)")
        ax[1].axhline(UNDISTORTION_TARGET_PX, color="r", ls="--", label="target 0.3 px")
        ax[1].set(xlabel="trial", ylabel="undistortion error (px)", title="undistortion over the covered area")
        ax[1].legend(fontsize=7)
        fig.text(0.01, 0.01, caption, fontsize=6)
        fig.tight_layout(rect=(0, 0.04, 1, 1))
        fig.savefig(out / "calibration_intrinsics.png", dpi=110)
        plt.close(fig)
    if extr:
        fig, ax = plt.subplots(1, 2, figsize=(11, 4.4))
        k = np.arange(len(extr))
        ax[0].bar(k, [100 * t.mapping_rms_m for t in extr], color="C0", label="8 plates, survey-weighted (toptag)")
        ax[0].plot(k, [100 * t.single_points_pnp_rms_m for t in extr], "C1o", ms=4,
                   label="8 single points, plain solvePnP")
        m = summarise([], extr)["extrinsics"]
        ax[0].axhline(100 * m["bound_rms_m"], color="k", label=f"Cramér–Rao bound {100 * m['bound_rms_m']:.2f} cm")
        ax[0].axhline(100 * MAPPING_RATIO_TARGET * m["bound_rms_m"], color="r", ls="--", label="target 1.2 × bound")
        ax[0].set(xlabel="trial", ylabel="roof mapping error RMS (cm)",
                  title=f"extrinsics: z = 3 m over 8–25 m, RMS {100 * m['mapping_rms_m']:.2f} cm "
                        f"({m['ratio_to_bound']:.2f} × bound)")
        ax[0].legend(fontsize=7)
        if example is not None:
            fp = footprint_points(camera)
            e = mapping_error(camera, example.camera, fp)
            sc = ax[1].scatter(fp[:, 0], fp[:, 1], c=100 * e, s=4, cmap="viridis")
            plt.colorbar(sc, ax=ax[1], label="error (cm)")
            W = np.array([p.world for p in example.points])
            ax[1].plot(W[:, 0], W[:, 1], "r.", ms=3, label="plate corners")
            c = camera.center
            ax[1].plot(c[0], c[1], "k^", label="camera")
            ax[1].set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title="one trial: roof mapping error")
            ax[1].legend(fontsize=7, loc="lower right")
        fig.text(0.01, 0.01, caption, fontsize=6)
        fig.tight_layout(rect=(0, 0.04, 1, 1))
        fig.savefig(out / "calibration_extrinsics.png", dpi=110)
        plt.close(fig)


def run(out: Path, intrinsic_trials: int = 10, views: int = 20, extrinsic_trials: int = 16, seed: int = 0,
        progress=None, board: dict | None = None, view_poses: dict | None = None, frames: str = FRAMES) -> dict:
    """frames: how the board frames are grabbed (board_frames_model); the plates' frame comes from the
    stream either way."""
    out.mkdir(parents=True, exist_ok=True)
    camera, model = study_camera(), ImageModel()
    board = BOARD if board is None else board
    view_poses = VIEW_POSES if view_poses is None else view_poses
    board_model = board_frames_model(model, frames)
    rng = np.random.default_rng(seed)
    t0 = time.monotonic()
    intr, intr_results = [], []
    for i in range(intrinsic_trials):
        trial, res = intrinsics_trial(camera, views, board_model, rng, Board.from_dict(board), view_poses)
        intr.append(trial)
        intr_results.append(Camera(camera.id, camera.width, camera.height, res.K, res.dist, camera.R, camera.t))
        if progress:
            progress(f"intrinsics {i + 1}/{intrinsic_trials}: focal {100 * trial.focal_rel_error:+.4f} %, "
                     f"undistortion max {trial.undistortion_max_px:.3f} px ({time.monotonic() - t0:.0f} s)")
    extr, example = [], None
    for i in range(extrinsic_trials):
        chain = intr_results[i % len(intr_results)] if intr_results else None
        trial, res = extrinsics_trial(camera, model, rng, chain)
        extr.append(trial)
        example = example or res
        if progress:
            progress(f"extrinsics {i + 1}/{extrinsic_trials}: roof mapping {100 * trial.mapping_rms_m:.2f} cm "
                     f"(bound {100 * trial.bound_rms_m:.2f} cm) ({time.monotonic() - t0:.0f} s)")
    summary = summarise(intr, extr, views)
    if "intrinsics" in summary:
        b = Board.from_dict(board).spec
        summary["intrinsics"]["board"] = (f"{b.type} {b.squares_x}x{b.squares_y} x {1000 * b.square_size:g} mm at "
                                          f"{view_poses['distance'][0]:g}-{view_poses['distance'][1]:g} m, tilt up to "
                                          f"{view_poses['max_tilt_deg']:g}°")
        summary["intrinsics"]["frames"] = FRAME_SOURCES[frames]
    doc = {"camera": camera.id, "image_model": model.describe(), "board": board,
           "board_views": {**view_poses, "frames": frames,
                           "board_image_model": board_model.describe()},
           "summary": summary,
           "intrinsic_trials": [vars(t) for t in intr], "extrinsic_trials": [vars(t) for t in extr],
           "extrinsic_covariance_example": example.covariance.tolist() if example else None,
           "seconds": time.monotonic() - t0}
    write_results(out, doc)
    i = summary.get("intrinsics", {})
    _plots(out, intr, extr, example, camera, model, views, f"{i.get('board', '')}, {i.get('frames', '')}")
    return doc


def report_lines(summary: dict) -> str:
    lines = []
    i = summary.get("intrinsics")
    if i:
        lines += [f"intrinsics ({i['trials']} trials, {i['views_rendered']} board views each ({i['views_used_min']}+ with the "
                  f"board found), corner noise {i['corner_sigma_px']:.3f} px):",
                  f"  board {i.get('board', '?')}, frames from {i.get('frames', '?')}",
                  f"  focal length error max {100 * i['focal_rel_error_max']:.4f} % (target 0.05 %: "
                  f"{'met' if i['focal_ok'] else 'NOT met'}); fx RMS {i['fx_error_rms_px']:.3f} px, "
                  f"{i['fx_ratio_to_bound']:.2f} × its bound {i['fx_bound_px']:.3f} px ({100 * i['focal_bound_rel']:.4f} %)",
                  f"  undistortion over the covered area max {i['undistortion_max_px']:.3f} px (target 0.3 px: "
                  f"{'met' if i['undistortion_ok'] else 'NOT met'}); RMS {i['undistortion_rms_px']:.3f} px, "
                  f"{i['undistortion_ratio_to_bound']:.2f} × its bound {i['undistortion_bound_rms_px']:.3f} px"]
    e = summary.get("extrinsics")
    if e:
        lines += [f"extrinsics ({e['trials']} trials, 8 plates, 5 mm survey, corner noise {e['corner_sigma_px']:.3f} px):",
                  f"  roof (z = 3 m) mapping error over 8-25 m: RMS {100 * e['mapping_rms_m']:.2f} cm, "
                  f"{e['ratio_to_bound']:.2f} × its bound {100 * e['bound_rms_m']:.2f} cm (target ≤ 1.2: "
                  f"{'met' if e['ok'] else 'NOT met'}); the tool reported {100 * e['reported_sigma_rms_m']:.2f} cm",
                  f"  8 single points, plain solvePnP: {100 * e['single_points_solvepnp_rms_m']:.2f} cm; with the "
                  f"calibrated intrinsics (whole chain): {100 * e['chained_with_calibrated_intrinsics_rms_m']:.2f} cm",
                  f"  camera pose error RMS: rotation {e['rotation_error_rms_deg']:.4f}°, centre "
                  f"{100 * e['centre_error_rms_m']:.2f} cm"]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag eval calibration", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--intrinsic-trials", type=int, default=10)
    p.add_argument("--views", type=int, default=20)
    p.add_argument("--board", type=Path, help="board file (default: the recommended toptag/data/board_charuco_a0.json)")
    p.add_argument("--board-distance", type=float, nargs=2, metavar=("MIN", "MAX"),
                   default=VIEW_POSES["distance"], help="board distance from the camera, m (default 0.6 1.0)")
    p.add_argument("--max-tilt", type=float, default=VIEW_POSES["max_tilt_deg"], help="board tilt up to, degrees (default 45)")
    p.add_argument("--frames", choices=sorted(FRAME_SOURCES), default=FRAMES,
                   help="board frames from a lossless snapshot (default) or from the H.264 stream")
    p.add_argument("--extrinsic-trials", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    try:
        require_plotting()
        board = Board.load(args.board).spec.model_dump(exclude_none=True) if args.board else None
        doc = run(args.out, args.intrinsic_trials, args.views, args.extrinsic_trials, args.seed,
                  progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True), board=board,
                  view_poses={"distance": tuple(args.board_distance), "max_tilt_deg": args.max_tilt},
                  frames=args.frames)
    except (CalibrationError, SetupError, InputError) as e:
        return report("eval calibration", e)
    print(report_lines(doc["summary"]))
    print(f"image model: {doc['image_model']}")
    print(f"wrote {args.out / 'results.json'} and the figures ({doc['seconds']:.0f} s)")
    return 0


# ---- the errors the procedure leaves (for the paper study's calibration case) --------------------------
def procedure_errors(cameras: list[Camera], n: int, model: ImageModel, seed: int = 0, progress=None) -> dict:
    """Calibrate each camera's extrinsics n times by the procedure (8 rendered ground plates, 5 mm survey,
    the tool's default pixel sigma) and return what it leaves: per camera id the pose errors (6-vectors in
    the convention of toptag.calibration.extrinsics.perturbed: rotation about the camera axes, centre
    shift); `sigmas`: their RMS per axis (rotation rad, centre m) over every calibration, the prior the
    study's calibration-aware solvers and its bound are given, so that the bound describes the errors
    actually drawn; `reported_sigmas`: the same from the covariance the tool reported (what a camera file
    carries; larger, as the tool assumes 0.3 px corner noise)."""
    from toptag.geometry import rotation_vector

    rng = np.random.default_rng([seed, 7171])
    deltas: dict[str, list[list[float]]] = {}
    reported, mapping = [], {}
    for cam in cameras:
        deltas[cam.id], errs = [], []
        for k in range(n):
            trial, result = extrinsics_trial(cam, model, rng)
            est = result.camera
            w = rotation_vector(est.R @ cam.R.T)
            deltas[cam.id].append([*map(float, w), *map(float, est.center - cam.center)])
            reported.append(np.diag(result.covariance))
            errs.append(trial.mapping_rms_m)
            if progress:
                progress(f"calibrating {cam.id} {k + 1}/{n}: roof mapping {100 * trial.mapping_rms_m:.2f} cm")
        mapping[cam.id] = _rms(errs)
    d = np.mean(reported, axis=0)
    D = np.array([x for v in deltas.values() for x in v])
    return {"deltas": deltas, "sigmas": (float(np.sqrt(np.mean(D[:, :3] ** 2))), float(np.sqrt(np.mean(D[:, 3:] ** 2)))),
            "reported_sigmas": (float(np.sqrt(d[:3].mean())), float(np.sqrt(d[3:].mean()))),
            "roof_mapping_rms_m": mapping, "calibrations_per_camera": n,
            "describe": (f"each RSU's extrinsics from one of {n} calibrations by toptag calibrate extrinsics on rendered "
                         f"images (8 ground plates of 1.0 m tags, corners surveyed with {1000 * SURVEY_SIGMA:g} mm noise, "
                         f"960x720)")}
