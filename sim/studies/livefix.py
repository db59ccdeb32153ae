"""`toptag eval livefix`: the live RSU pipeline's fix errors per RSU on the simulator's frames, fault-free.

    toptag eval livefix [--scenario FILE] [--bus BUS] [--seconds S] [--every-ms MS] [--turn-ratio R]
                        [--full-frame] [--out DIR]

Plays the scenario (default: the bundled demo) from its start; every `--every-ms` while the bus has a tag
in an RSU's view, renders that RSU's frame (the scenario's image model) and runs it through
`toptag.rsu.pipeline.RsuPipeline` as the RSU service does (tracking from its own previous fixes;
`--full-frame`: a full-frame search on every frame), then compares the fix with the truth at the frame's
time. Per RSU:
- `weighted_mean_cm_deg` and its standard error `weighted_se_cm_deg`: the errors' mean weighted by the
  fixes' stated variances, i.e. the constant bias a filter or a drift detector (which weigh fixes so)
  sees; `mean_cm_deg` is the plain mean, which the few far, imprecise fixes dominate;
- `z_rms`: the RMS of error / stated sigma per axis (x, y, yaw): 1 for an honest covariance;
- the spread (`std_cm_deg`) and the mean stated sigma (`reported_sigma_cm_deg`);
- `by_cell_px` (all RSUs): the same by the thinnest tag cell of the fix, in pixels along the view (a far
  tag seen at a grazing angle has cells 1-2 px tall), and `by_motion` by the bus's turning (a capture time
  off by dt shows as a yaw error yaw_rate x dt, of opposite signs in left and right turns).
Use it to choose the bus filter's drift thresholds (`[filter] drift_bias_sigma_m` / `_deg`,
docs/time-and-trust.md) and the pipeline's corner-noise model (`--turn-ratio`, PipelineSettings.turn_ratio).
Writes DIR/results.json when --out is given.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from sim.scenario import bundled_scenario_path, load_scenario
from sim.studies import write_results
from sim.world import World
from toptag.errors import InputError, report
from toptag.inputs import validate_model
from toptag.progress import Progress
from toptag.rsu.pipeline import PipelineSettings, RsuPipeline
from toptag.settings import read_settings
from toptag.solvers.level import TURN_RATIO
from toptag.units import NS_PER_MS, NS_PER_S

# Bins of the thinnest tag cell (px along the view) and of the bus's yaw rate (rad/s) in the results.
CELL_BINS_PX = (0.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, math.inf)
TURNING_RAD_S = 0.05


def thinnest_cell_px(quad: np.ndarray) -> float:
    """The smallest height of a tag cell in the image (px): each edge's distance to the opposite edge's
    midpoint over the 8 cells of a tag's black square, the least of the four."""
    out = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        e = b - a
        n = np.array([e[1], -e[0]]) / (np.linalg.norm(e) or 1.0)
        opposite = 0.5 * (quad[(k + 2) % 4] + quad[(k + 3) % 4])
        out.append(abs(float((opposite - a) @ n)) / 8.0)
    return min(out)


def error_stats(rows: np.ndarray) -> dict:
    """rows (N, 7+): error x, y (cm), yaw (deg), stated sigma x, y (cm), yaw (deg), NEES."""
    e, s = rows[:, :3], rows[:, 3:6]
    w = 1.0 / s ** 2
    return {"fixes": len(rows), "mean_cm_deg": e.mean(0).round(4).tolist(),
            "weighted_mean_cm_deg": ((w * e).sum(0) / w.sum(0)).round(4).tolist(),
            "weighted_se_cm_deg": (1.0 / np.sqrt(w.sum(0))).round(4).tolist(),
            "std_cm_deg": e.std(0).round(4).tolist(), "reported_sigma_cm_deg": s.mean(0).round(4).tolist(),
            "z_rms": np.sqrt(((e / s) ** 2).mean(0)).round(3).tolist(), "nees": round(float(rows[:, 6].mean()), 3)}


def scenario_pipeline(scenario) -> PipelineSettings:
    """The pipeline settings the scenario's RSUs run with: its rsu_config's [pipeline] table, else the
    defaults."""
    if scenario.rsu_config is None:
        return PipelineSettings()
    table = read_settings(scenario.rsu_config).get("pipeline", {})
    return validate_model(PipelineSettings, table, f"settings {scenario.rsu_config} [pipeline]")


def run(scenario_path: Path, bus: str, seconds: float, every_ms: float, turn_ratio: float | None = None,
        full_frame: bool = False, rsus: list[str] | None = None) -> dict:
    """turn_ratio: the pipeline's corner-noise model (None: the scenario's RSU settings')."""
    scenario = load_scenario(scenario_path)
    world = World(scenario)
    world.start(0)
    if bus not in {b.vehicle.id for b in world.buses}:
        raise InputError(f"--bus {bus}: not in the scenario (buses: {', '.join(b.vehicle.id for b in world.buses)})")
    rsus = rsus or world.rsu_ids
    unknown = sorted(set(rsus) - set(world.rsu_ids))
    if unknown:
        raise InputError(f"RSU {unknown[0]}: not in the scenario (RSUs: {', '.join(world.rsu_ids)})")
    settings = scenario_pipeline(scenario)
    change = {"turn_ratio": turn_ratio} if turn_ratio is not None else {}
    if full_frame:
        change.update(tracking=False, acquire_mode="full")
    settings = settings.model_copy(update=change)
    ticks = range(0, int(min(world.legs_end_ns, seconds * NS_PER_S)), int(every_ms * NS_PER_MS))
    out, everything = {}, []
    bar = Progress(len(rsus) * len(ticks), "toptag eval livefix")
    for rsu in rsus:
        pipe = RsuPipeline(world.camera(rsu), settings)
        pipe.add_vehicle(world.vehicle(bus))
        rows = []
        for k, t in enumerate(ticks):
            bar.update(note=rsu)
            if not world.tags_in_view(rsu, t).get(bus):
                continue
            jpeg, stamp = world.capture(rsu, t)
            gray = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
            r = pipe.process(gray, stamp, k).vehicles.get(bus)
            if r is None or r.fix is None:
                continue
            st, f = world.state(bus, t), r.fix
            err = np.array([f.x - st.x, f.y - st.y, math.remainder(f.yaw - st.yaw, 2 * math.pi)])
            sd = np.sqrt(np.diag(f.cov))
            rows.append([100 * err[0], 100 * err[1], math.degrees(err[2]), 100 * sd[0], 100 * sd[1], math.degrees(sd[2]),
                         float(err @ np.linalg.solve(f.cov, err)), st.yaw_rate,
                         min(thinnest_cell_px(o.raw_corners) for o in r.observations)])
        e = np.asarray(rows).reshape(-1, 9)
        everything.append(e)
        out[rsu] = {"fixes": 0} if not rows else error_stats(e)
        if rows:
            out[rsu]["bias_cm"] = round(float(math.hypot(*out[rsu]["weighted_mean_cm_deg"][:2])), 3)
    bar.close()
    e = np.vstack(everything) if everything else np.zeros((0, 9))
    by_cell = []
    for lo, hi in zip(CELL_BINS_PX[:-1], CELL_BINS_PX[1:]):
        m = (e[:, 8] >= lo) & (e[:, 8] < hi)
        if m.any():
            by_cell.append({"cell_px": [lo, None if math.isinf(hi) else hi], **error_stats(e[m])})
    turning = {"left": e[:, 7] > TURNING_RAD_S, "right": e[:, 7] < -TURNING_RAD_S,
               "straight": np.abs(e[:, 7]) <= TURNING_RAD_S}
    by_motion = {k: error_stats(e[m]) for k, m in turning.items() if m.any()}
    return {"scenario": str(scenario_path), "bus": bus, "seconds": seconds, "every_ms": every_ms,
            "turn_ratio": settings.turn_ratio, "full_frame": full_frame,
            "image_model": world.model.model_dump() if hasattr(world.model, "model_dump") else str(world.model),
            "image_model_text": world.model.describe() if hasattr(world.model, "describe") else str(world.model),
            "rsus": out, "by_cell_px": by_cell, "by_motion": by_motion}


def _line(name: str, r: dict) -> str:
    m, wm, se, s, q, z = (r[k] for k in ("mean_cm_deg", "weighted_mean_cm_deg", "weighted_se_cm_deg", "std_cm_deg",
                                          "reported_sigma_cm_deg", "z_rms"))
    return (f"{name}: {r['fixes']} fixes; weighted mean error x {wm[0]:+.2f} ± {se[0]:.2f} cm, y {wm[1]:+.2f} ± {se[1]:.2f} cm, "
            f"yaw {wm[2]:+.3f} ± {se[2]:.3f} deg (plain mean {m[0]:+.1f} cm {m[1]:+.1f} cm {m[2]:+.2f} deg); "
            f"spread {s[0]:.1f} / {s[1]:.1f} cm, {s[2]:.2f} deg; stated sigma {q[0]:.1f} / {q[1]:.1f} cm, {q[2]:.2f} deg; "
            f"z-RMS {z[0]:.2f} {z[1]:.2f} {z[2]:.2f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="toptag eval livefix", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", type=Path, default=None, help="scenario file (default: the bundled demo)")
    p.add_argument("--bus", default="bus-17")
    p.add_argument("--rsus", default=None, help="comma-separated RSU ids (default: all)")
    p.add_argument("--seconds", type=float, default=60.0, help="scenario seconds to play (default 60)")
    p.add_argument("--every-ms", type=float, default=100.0, help="one frame per RSU this often (default 100)")
    p.add_argument("--turn-ratio", type=float, default=None,
                   help="the pipeline's corner-noise model, PipelineSettings.turn_ratio (default: the scenario's "
                        f"rsu_config, else {TURN_RATIO:g}, real photographs')")
    p.add_argument("--full-frame", action="store_true", help="search the full frame every frame (no tracking)")
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    if a.turn_ratio is not None and not a.turn_ratio > 0:
        return report("eval livefix", InputError(f"--turn-ratio {a.turn_ratio}: must be positive"))
    try:
        res = run(a.scenario or bundled_scenario_path(), a.bus, a.seconds, a.every_ms, a.turn_ratio, a.full_frame,
                  a.rsus.split(",") if a.rsus else None)
    except InputError as e:
        return report("eval livefix", e)
    res["command"] = " ".join(["toptag eval livefix"] + list(sys.argv[1:] if argv is None else argv))
    print(f"image model: {res['image_model_text']}; turn ratio {res['turn_ratio']:g}")
    for rsu, r in res["rsus"].items():
        print(f"{rsu}: no fixes" if r["fixes"] == 0 else _line(rsu, r))
    for b in res["by_cell_px"]:
        lo, hi = b["cell_px"]
        print(_line(f"  cells {lo:g}-{'' if hi is None else f'{hi:g}'} px", b))
    for k, b in res["by_motion"].items():
        print(_line(f"  {k}", b))
    if a.out:
        print(f"wrote {write_results(a.out, res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
