"""`toptag eval paper`: the paper's simulation study, reproduced and beaten (SPEC.md, "The paper's simulation").

    toptag eval paper --out DIR [--samples N] [--seed S] [--cases low_flat,low_bounce,high_bounce]

Scene (per sample). The south-west RSU of SPEC's intersection (8 m, 40° down, 70° HFOV, no lens
distortion) sees the double-tag bus (6 × 2 × 3 m, two 1.6 m tag36h11 tags) at a random pose in the
sector it faces (±30° about its heading: the intersection quarter nearest to it), any heading, both
tag plates wholly in view (sim.sampling.sector_pose). --samples N is per case, stratified evenly over
the whole-metre horizontal-distance bins 5..20 (sample i goes to bin 5 + i mod 16, its distance uniform
within ±0.5 m of it), so every bin gets N/16 samples. The bus drives at a random speed 0-30 km/h along
its heading (motion blur over the exposure). Cases:
    low_flat     960×720,   roof at the nominal 3 m
    low_bounce   960×720,   roof height uniform in 3 m ± 10 cm (the whole roof, level)
    high_bounce  3200×2400, ± 10 cm
Image model: the default ImageModel() (anti-aliasing, blur, sensor noise, JPEG, motion blur, tag
contrast, calibration error), stated in results.json and under every figure.

Detection is the RSU's: toptag.rsu.pipeline.RsuPipeline with tracking off (row-banded pyramid
acquisition, confirmed at full resolution, far tags enlarged), once per image and RSU; every solver
then solves the same observations:
    bas              Bas. (homography)                                       paper
    hopt             H.Opt. (x, y, yaw; roof at 3 m)                          paper
    sopt             S.Opt. (6-DOF, mu = 1)                                   paper
    sopt_principled  S.Opt., residuals over their sigmas, common roof offset  toptag.solvers
    sopt_level       x, y, yaw, z of a level roof, height prior, edge-noise    toptag.solvers "level"
                     weighting, garbled tags weighed down, calibration-aware   (built by this study)
    sopt_2cam        sopt_principled on two RSUs' images of the same scene: the south-west one and
                     the nearer of its neighbours (south-east, north-west) that sees both plates
    sopt_level_2cam  sopt_level on the same two RSUs
The paper's solvers are told nothing (mu = 1; toptag's default sigma_h for its outlier test). The
principled ones are told the roof-height sigma of the case (a uniform ±10 cm has 5.8 cm; low_flat:
FLAT_SIGMA_H, "known") and, in "calibration", the RSUs' calibration sigmas: that is what principled
weighting means. No pose is refused for its uncertainty (Limits(max_position_sigma_m=inf): the paper
reports Bas. far out); a pose refused for any other reason, or no tag found, counts as not detected.

Calibration. The paper's RSUs have exactly known extrinsics, and so do the solvers in "cases". In
"calibration" every solver solves the same images again with the extrinsics that toptag's on-site
procedure actually leaves (sim.studies.calibration.procedure_errors: each RSU calibrated
CALIBRATION_POOL times by `toptag calibrate extrinsics` on rendered images of 8 surveyed ground plates;
each sample draws one of those calibrations per RSU), and the calibration-aware solvers and the bound
are told those errors' RMS per axis (--calibration model: the image model's assumed
calib_rot_sigma_deg / calib_trans_sigma drawn by sim.image_model.perturb_camera instead).

Bound. The corner noise is measured per case and whole-metre distance (from the camera that saw the
tag): detected corners (ideal pixels) against the projected true corners, as the pooled sigma per
coordinate and as the edge-line model of paper_models (each edge's offset and turn; AprilTag corners
are intersections of fitted edge lines, so their errors are not independent). The Cramér–Rao bound of
every sample (unknowns x, y, yaw of the level roof and its height with the case's prior; the tags
detected correctly; the measured edge noise of its bin; the true pose) is averaged in quadrature over
the samples each solver solved: crlb_ratio = pos_rms / bound. Two-RSU solvers are compared with the
two-RSU bound; "calibration" with the bound that carries every RSU's extrinsics as unknowns with their
prior. toptag.solvers.position_crlb with the pooled sigma (i.i.d. corners) is reported beside it
("_iid"): the paper's H.Opt. beats that one by up to 2x, which is how the i.i.d. model was found wrong.

Writes DIR/results.json, DIR/paper_<case>.png, DIR/paper_calibration.png and DIR/tables.md (the
Markdown tables of docs/paper-study.md). Runs the samples on
all cores (one process each, own renderer caches, OpenCV single-threaded), with a progress bar on stderr.
Run: `toptag eval paper --out DIR` or `python -m sim.studies.paper --out DIR`.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

from sim.image_model import ImageModel
from sim.sampling import SECTOR_HALF_ANGLE
from sim.scene import bundled_vehicle
from sim.studies import require_plotting
from sim.studies.paper_sample import run_sample, worker_init
from sim.studies.paper_setup import CASES, DISTANCES, NEIGHBOURS, PAPER_CLAIMS, PRIMARY, SOLVERS, VEHICLE
from sim.studies.paper_stats import check_targets, render_table, summarise
from toptag.errors import SetupError, report
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.machine import usable_cores
from toptag.progress import Progress
from toptag.units import kmh_from_mps

CALIBRATION_POOL = 12  # procedure calibrations per RSU for the "calibration" case

def run(out: Path, samples: int = 200, seed: int = 0, cases=tuple(CASES), workers: int | None = None,
        model: ImageModel | None = None, speed_max: float = BUS_MAX_SPEED_MPS, progress: bool = True,
        command: str | None = None, figures: bool = True, calibration: str = "procedure",
        calibration_pool: int = CALIBRATION_POOL) -> dict:
    """Run the study; write out/results.json and the figures; return the results."""
    model = ImageModel() if model is None else model
    cases = list(cases)
    for c in cases:
        if c not in CASES:
            raise ValueError(f"unknown case {c!r} (known: {', '.join(CASES)})")
    if samples < 1:
        raise ValueError("--samples must be at least 1")
    workers = usable_cores() if workers is None else max(1, int(workers))
    out.mkdir(parents=True, exist_ok=True)
    # Slowest case first so that the workers finish together.
    order = sorted(cases, key=lambda c: -CASES[c].width * CASES[c].height)
    calib_errors = None
    if calibration == "procedure":
        from sim.scene import rsu_camera
        from sim.studies.calibration import procedure_errors

        calib_errors = procedure_errors([rsu_camera(n) for n in (PRIMARY, *NEIGHBOURS)], calibration_pool, model, seed,
                                        progress=(lambda m: print(f"\r{m}\033[K", end="", file=sys.stderr))
                                        if progress else None)
        if progress:
            print(file=sys.stderr)
    tasks = [(c, i, seed, model.model_dump_json(), speed_max, calib_errors) for c in order for i in range(samples)]
    t0 = time.monotonic()
    bar = Progress(len(tasks), "toptag eval paper") if progress else None
    done: list[dict] = []
    if workers == 1:
        worker_init()
        for t in tasks:
            done.append(run_sample(t))
            if bar:
                bar.update(note=done[-1]["case"])
    else:
        # Not fork: a process that already runs threads (Zenoh, OpenCV, a test runner) can hand a forked
        # child a lock held by a thread that does not exist there (seen: workers hung in cv2).
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers, initializer=worker_init, maxtasksperchild=None) as pool:
            for r in pool.imap_unordered(run_sample, tasks, chunksize=1):
                done.append(r)
                if bar:
                    bar.update(note=r["case"])
    if bar:
        bar.close()
    sample_s = time.monotonic() - t0
    done.sort(key=lambda s: (cases.index(s["case"]), s["index"]))
    summary = summarise(done, model)
    results = {
        "command": command or f"toptag eval paper --out {out} --samples {samples} --seed {seed} "
                              f"--cases {','.join(cases)}",
        "samples_per_case": samples,
        "seed": seed,
        "distances_m": list(DISTANCES),
        "sampling": (f"per case, sample i at the whole-metre bin 5 + i mod 16 (distance uniform within "
                     f"±0.5 m), uniform bearing within ±{math.degrees(SECTOR_HALF_ANGLE):.0f}° of the RSU's "
                     f"heading, any bus heading, both plates in view; speed uniform 0-{kmh_from_mps(speed_max):.0f} km/h"),
        "image_model": model.model_dump() | {"describe": model.describe()},
        "calibration_error": ("'cases': extrinsics known exactly (the paper's setting); 'calibration': the same "
                              "images solved with " + (
                                  calib_errors["describe"] + "; the calibration-aware solvers (and the bound) told their RMS per axis "
                                  f"{math.degrees(calib_errors['sigmas'][0]):.4f} deg, {calib_errors['sigmas'][1] * 100:.2f} cm "
                                  "per axis" if calib_errors else
                                  "cameras perturbed by the image model's calibration error "
                                  f"({model.calib_rot_sigma_deg:g} deg, {model.calib_trans_sigma * 100:g} cm per axis)")),
        "calibration_procedure": ({k: v for k, v in calib_errors.items() if k != "deltas"} if calib_errors else None),
        "scene": {"rsu": PRIMARY, "second_rsu": "nearer of " + "/".join(NEIGHBOURS) + " with both plates in view",
                  "vehicle": bundled_vehicle(VEHICLE).to_dict(),
                  "cases": {c: dataclasses.asdict(CASES[c]) for c in cases}},
        "solvers": {k: {"label": v.label, "method": v.method, "weighting": v.weighting,
                        "cameras": 2 if v.two_cameras else 1, "text": v.text} for k, v in SOLVERS.items()},
        "bound": ("Cramér–Rao bound of a level roof's x, y, yaw and height (Gaussian prior of the case's sigma_h; "
                  "0.1 mm in low_flat) from the correctly detected tags at the true pose, under the corner noise "
                  "measured per case and distance bin as an edge-line model (each edge's offset and turn, "
                  "'noise'); RMS over the samples each solver solved; crlb_ratio = pos_rms / bound. Two-RSU "
                  "solvers against the two-RSU bound; 'calibration' against the bound with every RSU's extrinsics "
                  "as unknowns with the model's prior. '_iid': toptag.solvers.position_crlb with the pooled sigma."),
        "sigma_h": {c: CASES[c].sigma_h for c in cases},
        "paper_claims": PAPER_CLAIMS,
        **summary,
    }
    results["targets"] = check_targets(results)
    results["runtime_s"] = {"samples": round(sample_s, 1), "total": round(time.monotonic() - t0, 1),
                            "workers": workers,
                            "per_sample_s": {c: round(float(np.mean([s["seconds"] for s in done if s["case"] == c])), 3)
                                                 for c in cases}}
    (out / "results.json").write_text(json.dumps(results, indent=1, allow_nan=False))
    from sim.studies.paper_plots import markdown_tables, write_figures

    (out / "tables.md").write_text(markdown_tables(results))
    if figures:
        results["figures"] = write_figures(results, out)
        (out / "results.json").write_text(json.dumps(results, indent=1, allow_nan=False))
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="toptag eval paper", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=Path, help="output directory (results.json, PNGs)")
    p.add_argument("--samples", type=int, default=200,
                   help="samples per case, spread evenly over the 16 whole-metre bins 5..20 m (default 200)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {','.join(CASES)}")
    p.add_argument("--workers", type=int, default=None, help="processes (default: every core)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--calibration", choices=("procedure", "model"), default="procedure",
                   help="the 'calibration' case's extrinsic errors: those toptag calibrate extrinsics leaves on rendered "
                        "plates (default), or the image model's assumed 0.05 deg / 2 cm")
    p.add_argument("--calibration-pool", type=int, default=CALIBRATION_POOL,
                   help=f"procedure calibrations per RSU (default {CALIBRATION_POOL})")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        require_plotting()
    except SetupError as e:
        return report("eval paper", e)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad or not cases:
        p.error(f"unknown case(s) {', '.join(bad) or '(none)'}; known: {', '.join(CASES)}")
    if args.samples < 1:
        p.error("--samples must be at least 1")
    argv_text = " ".join(["toptag eval paper"] + list(sys.argv[1:] if argv is None else argv))
    res = run(args.out, args.samples, args.seed, cases, args.workers, progress=not args.no_progress,
              command=argv_text, calibration=args.calibration, calibration_pool=max(1, args.calibration_pool))
    print(render_table(res))
    print(f"wrote {args.out / 'results.json'} and {', '.join(res.get('figures', []))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
