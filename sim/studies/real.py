"""`toptag eval real --data DIR`: toptag's detection path and every solver on real photographs with truth.

    toptag eval real --data DIR [--out OUT] [--max-hamming N]
    toptag eval real --data DIR --make-truth      # (re)write DIR/dataset.json's truth from saddle points

DIR holds dataset.json (toptag.dataset; docs/real-data.md): images, their intrinsics, the tag layout,
corner truth and/or pose truth. Per image and in total it prints tags found / missed / false (against
the truth's tags wholly in view), the corner error median / p95 / max (px, detected against truth), and,
where pose truth exists, every solver's pose error on "vehicles" made of the board's tags, scaled to bus
size: the board is blown up so that its tags are 1.6 m (pixels do not change when the whole scene and
the camera's position scale together) and lies level at 3 m; each single tag, and each pair of
neighbouring tags in a row (a bus's two roof tags), is one vehicle with a known pose. Errors are in bus
metres; NEES is the normalised error of each fix against its own covariance (3 on average when honest).
Writes OUT/results.json and OUT/real.png.

--make-truth: corner truth without any tag detector's corners. The detector only says roughly where
the tags are (2 bit errors admitted); the grid's saddle points (each tag corner touches a small black
square) are located by cv2.cornerSubPix. With intrinsics, the board's pose from them predicts every
tag of the board (also those the detector misses), whose saddles are refined again, and the pose is
refitted from every saddle: the pose truth, a whole-board fit over ~140 points against the 4-8 corners
a solver gets. Without intrinsics the truth holds the tags the detector found.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.studies import require_plotting, write_results
from toptag.errors import SetupError, report

from toptag.dataset import (
    Dataset,
    ImageEntry,
    TagTruth,
    board_corners,
    fit_board_pose,
    ideal_pixels,
    pinhole,
    project,
    refine_saddles,
)
from toptag.detection import FAMILY_MAX_HAMMING, DetectorSettings, RawDetection, TagDetector, TagObservation
from toptag.geometry import wrap_angle
from toptag.inputs import InputError
from toptag.solvers import SIGMA_H_DEFAULT, solve
from toptag.vehicle import Vehicle

BUS_TAG_SIZE = 1.6  # m: the board is scaled so that its tags are the bus's
ROOF_HEIGHT = 3.0  # m: the scaled board lies level at this height
# Every solver as the paper study names it: (method, solve() keywords). Every solver takes the roof-height
# sigma from the vehicle's bag, which declares the board's (the dataset's target.height_sigma, scaled; a
# rigid board's is a few mm at bus scale, where H.Opt. assumes it exact). The level solver once more as
# an RSU would run it for a bag that declares nothing: the prior of a bouncing bus (SIGMA_H_DEFAULT).
SOLVERS = {"bas": ("bas", {}), "hopt": ("hopt", {}), "sopt": ("sopt", {}),
           "sopt_principled": ("sopt", {"weighting": "principled"}), "level": ("level", {}),
           "level_bounce_prior": ("level", {"sigma_h": SIGMA_H_DEFAULT})}
LABELS = {"bas": "Bas.", "hopt": "H.Opt.", "sopt": "S.Opt.", "sopt_principled": "S.Opt. principled",
          "level": "level (default)", "level_bounce_prior": "level, bounce prior"}
GOOD_TAG_PX = 1.0  # a detected tag whose corners are all within this of the truth is a good tag


def match_radius(corners: np.ndarray) -> float:
    side = float(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1).mean())
    return max(3.0, 0.25 * side)


@dataclass
class ImageResult:
    file: str
    found: int = 0
    missed: int = 0
    false: int = 0
    corner_errors: list = field(default_factory=list)  # px, every corner of every found tag
    missed_ids: list = field(default_factory=list)
    false_ids: list = field(default_factory=list)
    tags: list = field(default_factory=list)  # (TagTruth, RawDetection) of the found ones
    poses: dict = field(default_factory=dict)  # solver -> list of per-vehicle dicts


def match(truth: list[TagTruth], raw: list[RawDetection]):
    """(found pairs, missed truths, false detections): same id, corners within match_radius."""
    free = list(raw)
    found, missed = [], []
    for t in truth:
        tc = np.asarray(t.corners, float)
        best, best_d = None, math.inf
        for k, d in enumerate(free):
            if d.tag_id != t.id:
                continue
            dist = float(np.linalg.norm(d.corners - tc, axis=1).mean())
            if dist < best_d:
                best, best_d = k, dist
        if best is not None and best_d < match_radius(tc):
            found.append((t, free.pop(best)))
        else:
            missed.append(t)
    return found, missed, free


# ---- pose: the board as a bus roof ---------------------------------------------------------------
def scaled_world(ds: Dataset, entry: ImageEntry):
    """(scale, Camera in the scaled world): X_world = scale · X_board + (0, 0, ROOF_HEIGHT)."""
    cam = ds.spec.cameras[entry.camera]
    scale = BUS_TAG_SIZE / ds.spec.target.tag_size
    R = np.asarray(entry.pose.R, float)
    t = scale * np.asarray(entry.pose.t, float) - R @ np.array([0.0, 0.0, ROOF_HEIGHT])
    camera = pinhole(cam, entry.camera, R, t)
    if camera.center[2] <= ROOF_HEIGHT:
        raise InputError(f"{entry.file}: the camera is behind the board (board z must face the camera)")
    return scale, camera


def board_vehicles(ds: Dataset, ids: list[int], scale: float):
    """Single tags and pairs of row neighbours as vehicles: (Vehicle, true (x, y, yaw)). The vehicle's x
    is the board's y (a tag's printed up, SPEC: yaw 0), its y the board's -x. Each bag declares the
    board's height sigma, scaled with the board (none declared: the default of a bouncing bus)."""
    target = ds.spec.target
    present = set(ids)
    groups = [(i,) for i in sorted(present)]
    if target.grid is not None:
        cols = target.grid.cols
        groups += [(i, i + 1) for i in sorted(present) if i + 1 in present and (i % cols) + 1 < cols]
    out = []
    for g in groups:
        centres = {i: scale * board_corners(target, i)[:, :2].mean(axis=0) for i in g}
        mid = np.mean(list(centres.values()), axis=0)
        tags = [{"id": int(i), "size": BUS_TAG_SIZE, "center": [float(c[1] - mid[1]), float(-(c[0] - mid[0]))]}
                for i, c in centres.items()]
        reach = max(2.0, 2 * max(abs(v) for t in tags for v in t["center"]) + 2 * BUS_TAG_SIZE)
        bag = {"id": "tags-" + "-".join(map(str, g)), "height": ROOF_HEIGHT,
               "family": target.family, "length": reach, "width": reach, "tags": tags}
        if target.height_sigma is not None:
            bag["height_sigma"] = scale * target.height_sigma
        v = Vehicle.from_dict(bag)
        out.append((v, (float(mid[0]), float(mid[1]), math.pi / 2)))
    return out


def pose_errors(ds: Dataset, entry: ImageEntry, found) -> dict:
    """Per solver, per vehicle: position error (bus m), yaw error (deg), NEES, dropped good tags."""
    scale, camera = scaled_world(ds, entry)
    cam = ds.spec.cameras[entry.camera]
    obs, good = {}, set()
    for t, d in found:
        ideal = ideal_pixels(cam, d.corners) if cam.model == "equidistant" else camera.undistort(d.corners)
        obs[t.id] = TagObservation(t.id, ideal, camera, d.corners, d.hamming, d.decision_margin)
        if np.max(np.linalg.norm(d.corners - np.asarray(t.corners), axis=1)) < GOOD_TAG_PX:
            good.add(t.id)
    out = {k: [] for k in SOLVERS}
    for vehicle, truth in board_vehicles(ds, sorted(obs), scale):
        o = [obs[i] for i in vehicle.tag_ids]
        for key, (method, kw) in SOLVERS.items():
            s = solve(vehicle, o, method, **kw)
            rec = {"vehicle": vehicle.id, "tags": len(o), "ok": bool(s.ok), "error": s.error,
                   "dropped_good": sorted({int(d["tag"]) for d in s.dropped_tags if d["tag"] in good}),
                   "ambiguous": bool(getattr(s, "ambiguous", False))}
            if s.ok:
                e = np.array([s.x - truth[0], s.y - truth[1], wrap_angle(s.yaw - truth[2])])
                rec.update(pos_m=float(math.hypot(e[0], e[1])), yaw_deg=float(math.degrees(abs(e[2]))),
                           sigma_px=float(s.sigma_px), nees=_nees(e, s.covariance))
            out[key].append(rec)
    return out


def _nees(e: np.ndarray, cov: np.ndarray) -> float | None:
    try:
        return float(e @ np.linalg.solve(cov, e))
    except np.linalg.LinAlgError:
        return None


# ---- running ------------------------------------------------------------------------------------
def detector_for(ds: Dataset, max_hamming: int | None) -> TagDetector:
    t = ds.spec.target
    return TagDetector((t.family,), DetectorSettings(max_hamming=max_hamming, black_border=t.black_border))


def evaluate(ds: Dataset, max_hamming: int | None = None) -> list[ImageResult]:
    det = detector_for(ds, max_hamming)
    results = []
    try:
        for entry in ds.spec.images:
            gray = ds.read_gray(entry)
            raw = det.detect_raw(gray)
            found, missed, false = match(entry.tags, raw)
            r = ImageResult(entry.file, len(found), len(missed), len(false),
                            missed_ids=[t.id for t in missed], false_ids=[d.tag_id for d in false], tags=found)
            for t, d in found:
                r.corner_errors += np.linalg.norm(d.corners - np.asarray(t.corners), axis=1).tolist()
            if entry.pose is not None and ds.spec.target.tag_size is not None and found:
                r.poses = pose_errors(ds, entry, found)
            results.append(r)
    finally:
        det.close()
    return results


def _stats(values) -> dict:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], float)
    if not len(v):
        return {"n": 0, "median": None, "p95": None, "max": None, "mean": None}
    return {"n": int(len(v)), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(v.max()), "mean": float(v.mean())}


def summarise(ds: Dataset, results: list[ImageResult], max_hamming: int | None) -> dict:
    images = []
    for r in results:
        images.append({"file": r.file, "found": r.found, "missed": r.missed, "false": r.false,
                       "missed_ids": r.missed_ids, "false_ids": r.false_ids,
                       "corner_error_px": _stats(r.corner_errors)})
    solvers = {}
    for key in SOLVERS:
        recs = [rec for r in results for rec in r.poses.get(key, [])]
        if not recs:
            continue
        by_kind = {}
        for kind, n in (("single", 1), ("pair", 2)):
            sub = [x for x in recs if x["tags"] == n]
            if not sub:
                continue
            by_kind[kind] = {
                "vehicles": len(sub), "poses": sum(x["ok"] for x in sub),
                "position_cm": {k: (None if v is None else (v * 100 if k != "n" else v))
                                for k, v in _stats([x.get("pos_m") for x in sub]).items()},
                "yaw_deg": _stats([x.get("yaw_deg") for x in sub]),
                "nees": _stats([x.get("nees") for x in sub]),
                "sigma_px": _stats([x.get("sigma_px") for x in sub]),
                "good_tags_dropped": sum(len(x["dropped_good"]) for x in sub),
                "ambiguous": sum(x["ambiguous"] for x in sub),
                "refused": sorted({x["error"] for x in sub if not x["ok"] and x["error"]})[:5],
            }
        solvers[key] = by_kind
    return {
        "dataset": ds.spec.name, "source": ds.spec.source, "licence": ds.spec.licence,
        "detector": {"family": ds.spec.target.family, "black_border": ds.spec.target.black_border,
                     "max_hamming": max_hamming if max_hamming is not None
                     else FAMILY_MAX_HAMMING[ds.spec.target.family]},
        "corner_truth": sorted({e.corner_truth for e in ds.spec.images}),
        "total": {"found": sum(r.found for r in results), "missed": sum(r.missed for r in results),
                  "false": sum(r.false for r in results),
                  "corner_error_px": _stats([e for r in results for e in r.corner_errors])},
        "images": images, "solvers": solvers,
        "scale": {"bus_tag_size_m": BUS_TAG_SIZE, "roof_height_m": ROOF_HEIGHT},
    }


def render_text(summary: dict) -> str:
    lines = [f"{summary['dataset']}: corner truth {', '.join(summary['corner_truth'])}; detector "
             f"{summary['detector']['family']} border {summary['detector']['black_border']} "
             f"max_hamming {summary['detector']['max_hamming']}",
             f"{'image':<40} {'found':>5} {'missed':>6} {'false':>5} {'median px':>9} {'p95 px':>7} {'max px':>7}"]
    for im in summary["images"] + [dict(summary["total"], file="TOTAL")]:
        c = im["corner_error_px"]
        f = (lambda v: f"{v:.3f}" if v is not None else "-")
        lines.append(f"{im['file'][-40:]:<40} {im['found']:>5} {im['missed']:>6} {im['false']:>5} "
                     f"{f(c['median']):>9} {f(c['p95']):>7} {f(c['max']):>7}")
    if summary["solvers"]:
        lines.append("pose error at bus scale (tags 1.6 m): position median / p95 / max cm, yaw median deg, "
                     "mean NEES (3 if honest), good tags dropped, poses/vehicles")
        for kind in ("single", "pair"):
            for key, by in summary["solvers"].items():
                s = by.get(kind)
                if not s:
                    continue
                p = s["position_cm"]
                g = (lambda v, d=2: f"{v:.{d}f}" if v is not None else "-")
                lines.append(f"  {kind:<6} {LABELS[key]:<20} {g(p['median'])} / {g(p['p95'])} / {g(p['max'])} cm"
                             f"   yaw {g(s['yaw_deg']['median'], 3)}   NEES {g(s['nees']['mean'], 1)}"
                             f"   dropped {s['good_tags_dropped']}   {s['poses']}/{s['vehicles']}")
    return "\n".join(lines)


def plot(summary: dict, results: list[ImageResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    errs = np.array([e for r in results for e in r.corner_errors])
    if len(errs):
        axes[0].hist(errs, bins=40, color="tab:blue")
        axes[0].axvline(np.median(errs), color="k", ls="--", label=f"median {np.median(errs):.2f} px")
        axes[0].axvline(np.percentile(errs, 95), color="r", ls=":", label=f"p95 {np.percentile(errs, 95):.2f} px")
        axes[0].legend()
    axes[0].set_xlabel("corner error, detected vs truth (px)")
    axes[0].set_title(f"{summary['dataset']}: {summary['total']['found']} tags found, "
                      f"{summary['total']['missed']} missed, {summary['total']['false']} false", fontsize=9)
    ax = axes[1]
    for key in SOLVERS:
        v = np.sort([x["pos_m"] * 100 for r in results for x in r.poses.get(key, []) if x["ok"] and x["tags"] == 2])
        if len(v):
            ax.plot(v, np.arange(1, len(v) + 1) / len(v), label=LABELS[key])
    if ax.lines:
        ax.set_xscale("log")
        ax.legend(fontsize=8)
    ax.set_xlabel("position error, tag pairs at bus scale (cm)")
    ax.set_ylabel("fraction of vehicles")
    ax.set_title("real images, real corners; truth: whole-board fit of saddle points", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- truth --------------------------------------------------------------------------------------
def make_truth(ds: Dataset) -> None:
    """Rewrite every grid image's tags (and, with intrinsics, pose) from the grid's saddle points."""
    target = ds.spec.target
    if target.grid is None:
        raise InputError(f"{ds.root}: --make-truth needs a grid target")
    det = detector_for(ds, 2)
    board = {i: board_corners(target, i) for i in range(target.grid.rows * target.grid.cols)}
    try:
        for entry in ds.spec.images:
            gray = ds.read_gray(entry)
            raw = [d for d in det.detect_raw(gray) if d.tag_id in board]
            side = np.median([match_radius(d.corners) for d in raw]) if raw else 12.0
            window = int(np.clip(side / 4, 3, 7))
            obj = np.vstack([board[d.tag_id] for d in raw])
            px, ok = refine_saddles(gray, np.vstack([d.corners for d in raw]), window)
            if entry.camera is not None:
                # With intrinsics, the board pose from the saddles found predicts every tag of the board,
                # so that tags the detector misses are in the truth too.
                cam = ds.spec.cameras[entry.camera]
                pose = fit_board_pose(cam, obj[ok], px[ok])
                ids = range(target.grid.rows * target.grid.cols)
                guess = project(cam, pose.R, pose.t, np.vstack([board[i] for i in ids]))
            else:
                # Without them (an unknown lens), only where the detector (2 bit errors admitted) found a tag.
                ids = [d.tag_id for d in raw]
                guess = np.vstack([d.corners for d in raw])
            all_obj = np.vstack([board[i] for i in ids])
            h, w = gray.shape
            inside = np.all((guess > window + 1) & (guess < [w - window - 2, h - window - 2]), axis=1)
            sad, ok = refine_saddles(gray, guess, window)
            ok &= inside
            ok4 = ok.reshape(-1, 4).all(axis=1)
            entry.tags = [TagTruth(id=i, corners=sad[4 * k:4 * k + 4].tolist()) for k, i in enumerate(ids) if ok4[k]]
            entry.corner_truth = "saddle"
            if entry.camera is not None:
                keep = np.repeat(ok4, 4)
                entry.pose = fit_board_pose(ds.spec.cameras[entry.camera], all_obj[keep], sad[keep])
    finally:
        det.close()
    path = ds.root / "dataset.json"
    path.write_text(json.dumps(ds.spec.model_dump(mode="json", exclude_none=True), indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="toptag eval real", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, type=Path, help="folder with dataset.json (docs/real-data.md)")
    p.add_argument("--out", type=Path, default=None, help="where results.json and real.png go (default: none)")
    p.add_argument("--max-hamming", type=int, default=None,
                   help="bit errors admitted per tag (default: the RSU's gate for the family)")
    p.add_argument("--make-truth", action="store_true", help="(re)make the corner and pose truth, then stop")
    args = p.parse_args(argv)
    if getattr(args, "out", None) is not None:
        try:
            require_plotting()
        except SetupError as e:
            return report("eval real", e)
    try:
        ds = Dataset.load(args.data)
        if args.make_truth:
            make_truth(ds)
            for e in ds.spec.images:
                if e.pose is not None:
                    print(f"{e.file}: board pose from the saddle points, {e.pose.rms_px:.3f} px RMS; plane known "
                          f"to {1000 * e.pose.plane_sigma:.3f} mm along its normal (board units)")
            print(f"wrote {ds.root / 'dataset.json'}")
            return 0
        results = evaluate(ds, args.max_hamming)
    except InputError as e:
        print(f"toptag eval real: {e}", file=sys.stderr)
        return 2
    summary = summarise(ds, results, args.max_hamming)
    print(render_text(summary))
    if args.out is not None:
        path = write_results(args.out, summary)
        plot(summary, results, args.out / "real.png")
        print(f"wrote {path} and {args.out / 'real.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
