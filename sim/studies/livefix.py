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
- `view_correlation` (all RSUs): how much of a fix's error it shares with the same RSU's fixes taken
  nearby. The correlation of two fixes' errors (as z-scores: error / stated sigma, per axis x, y, yaw;
  pairs of one RSU under `PAIR_MAX_S` apart) by the distance the bus drove between them (`VIEW_BINS_M`),
  and its fit rho(d) = share * exp(-d / corr_m) (least squares over the pairs): `share` is the share of a
  fix's variance that is view-dependent, `corr_m` the distance over which it decorrelates. The fusion study
  draws its fixes' errors so (sim.studies.fusion.FixErrorModel.view_share / view_corr_m) and the bus's drift
  detector weighs them so (`[filter] drift_view_bias_share` = sqrt(share), `drift_view_corr_m`).
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
from toptag.rsu.regions import thinnest_cell_px
from toptag.settings import read_settings
from toptag.solvers.level import TURN_RATIO
from toptag.units import NS_PER_MS, NS_PER_S

# Bins of the thinnest tag cell (px along the view) and of the bus's yaw rate (rad/s) in the results.
CELL_BINS_PX = (0.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, math.inf)
TURNING_RAD_S = 0.05
# Pairs of one RSU's fixes at most this far apart in time, binned by the distance driven between them (m).
PAIR_MAX_S = 4.0
VIEW_BINS_M = (0.0, 0.05, 0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, math.inf)
VIEW_FIT_CORR_M = tuple(float(x) for x in np.round(np.geomspace(0.25, 64.0, 97), 3))


def view_pairs(rows: np.ndarray, max_s: float = PAIR_MAX_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of one RSU's fixes under max_s apart: (distance driven between them (m), z_i (n, 3), z_j (n, 3)).
    rows: (N, 12) as run() collects them (time s and distance driven m in columns 9 and 10)."""
    if len(rows) < 2:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    z = rows[:, :3] / rows[:, 3:6]
    i, j = np.triu_indices(len(rows), k=1)
    keep = np.abs(rows[j, 9] - rows[i, 9]) <= max_s
    i, j = i[keep], j[keep]
    return np.abs(rows[j, 10] - rows[i, 10]), z[i], z[j]


def fit_view_correlation(dist: np.ndarray, rho: np.ndarray, weight: np.ndarray) -> tuple[float, float, float]:
    """(share, corr_m, weighted rms residual): rho ~ share * exp(-dist / corr_m) by weighted least squares over
    the bins (dist their mean distance, rho their correlation, weight their pairs), corr_m on a grid, share in
    closed form (clipped to [0, 1])."""
    best = (0.0, VIEW_FIT_CORR_M[0], math.inf)
    for L in VIEW_FIT_CORR_M:
        g = np.exp(-dist / L)
        gg = float(weight @ (g * g))
        a = min(1.0, max(0.0, float(weight @ (g * rho)) / gg)) if gg > 0 else 0.0
        r = math.sqrt(float(weight @ (rho - a * g) ** 2) / float(weight.sum())) if weight.sum() else math.inf
        if r < best[2]:
            best = (a, L, r)
    return best


RANGE_BINS_M = (0.0, 8.0, 12.0, 16.0, 20.0, 24.0, math.inf)


def size_by_range(rows: np.ndarray) -> list[dict]:
    """The fixes' error RMS (x, y cm, yaw deg) and mean stated sigma by the bus's horizontal range from the
    RSU's camera (m): the size of the errors the fusion study draws (FixErrorModel's sigmas by range)."""
    out = []
    for lo, hi in zip(RANGE_BINS_M[:-1], RANGE_BINS_M[1:]):
        m = (rows[:, 11] >= lo) & (rows[:, 11] < hi)
        if m.sum() < 5:
            continue
        out.append({"range_m": [lo, None if math.isinf(hi) else hi], "fixes": int(m.sum()),
                    "rms_cm_deg": np.sqrt((rows[m, :3] ** 2).mean(0)).round(3).tolist(),
                    "median_abs_cm_deg": np.median(np.abs(rows[m, :3]), 0).round(3).tolist(),
                    "reported_sigma_cm_deg": rows[m, 3:6].mean(0).round(3).tolist()})
    return out


def view_correlation(per_rsu: list[np.ndarray]) -> dict:
    """The fixes' error correlation by distance driven (pairs within each RSU), binned and fitted per axis
    (x, y, yaw) and over all three (the fit the study and the detector take)."""
    parts = [view_pairs(r) for r in per_rsu if len(r) > 1]
    if not parts:
        return {"pairs": 0}
    d = np.concatenate([p[0] for p in parts])
    zi = np.vstack([p[1] for p in parts])
    zj = np.vstack([p[2] for p in parts])
    bins, mid, rho, n = [], [], [], []
    for lo, hi in zip(VIEW_BINS_M[:-1], VIEW_BINS_M[1:]):
        m = (d >= lo) & (d < hi)
        if m.sum() < 10:
            continue
        a, b = zi[m], zj[m]
        r = [float(np.corrcoef(a[:, k], b[:, k])[0, 1]) for k in range(3)]
        bins.append({"m": [lo, None if math.isinf(hi) else hi], "mean_m": round(float(d[m].mean()), 3),
                     "pairs": int(m.sum()), "rho_x_y_yaw": [round(x, 3) for x in r]})
        mid.append(float(d[m].mean()))
        rho.append(r)
        n.append(float(m.sum()))
    mid, rho, n = np.array(mid), np.array(rho).reshape(-1, 3), np.array(n)
    fits = {}
    for name, k in (("x", [0]), ("y", [1]), ("yaw", [2]), ("all", [0, 1, 2])):
        share, L, res = fit_view_correlation(np.repeat(mid, len(k)), rho[:, k].ravel(), np.repeat(n, len(k)))
        fits[name] = {"share": round(share, 3), "corr_m": L, "rms_residual": round(res, 3)}
    return {"pairs": int(len(d)), "pair_max_s": PAIR_MAX_S, "bins": bins, "fit": fits}


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
    # the distance the bus has driven at each tick (for the view-dependent error's correlation)
    driven, last = {}, None
    total = 0.0
    for t in ticks:
        st = world.state(bus, t)
        if st is not None and last is not None:
            total += math.hypot(st.x - last.x, st.y - last.y)
        last = st if st is not None else last
        driven[t] = total
    out, everything = {}, []
    bar = Progress(len(rsus) * len(ticks), "toptag eval livefix")
    for rsu in rsus:
        pole = world.camera(rsu).center[:2]
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
                         min(thinnest_cell_px(o.raw_corners) for o in r.observations), t / NS_PER_S, driven[t],
                         math.hypot(st.x - pole[0], st.y - pole[1])])
        e = np.asarray(rows).reshape(-1, 12)
        everything.append(e)
        out[rsu] = {"fixes": 0} if not rows else error_stats(e)
        if rows:
            out[rsu]["bias_cm"] = round(float(math.hypot(*out[rsu]["weighted_mean_cm_deg"][:2])), 3)
    bar.close()
    e = np.vstack(everything) if everything else np.zeros((0, 12))
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
            "rsus": out, "by_cell_px": by_cell, "by_motion": by_motion, "view_correlation": view_correlation(everything),
            "_per_rsu_rows": everything}


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
    p.add_argument("--bus", default="bus-17", help="bus, or buses separated by commas (default bus-17); the "
                   "view-dependent error is fitted over all of them")
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
        runs = [run(a.scenario or bundled_scenario_path(), bus.strip(), a.seconds, a.every_ms, a.turn_ratio,
                    a.full_frame, a.rsus.split(",") if a.rsus else None) for bus in a.bus.split(",") if bus.strip()]
    except InputError as e:
        return report("eval livefix", e)
    if not runs:
        return report("eval livefix", InputError("--bus: no bus given"))
    res = runs[0] if len(runs) == 1 else {"buses": [r["bus"] for r in runs], "per_bus": runs,
                                          **{k: runs[0][k] for k in ("image_model", "image_model_text", "turn_ratio")}}
    # the view-dependent error's fit over every bus's pairs (pairs stay within one bus and RSU)
    rows = [e for r in runs for e in r.pop("_per_rsu_rows")]
    res["view_correlation"] = view_correlation(rows)
    res["size_by_range"] = size_by_range(np.vstack(rows) if rows else np.zeros((0, 12)))
    res["command"] = " ".join(["toptag eval livefix"] + list(sys.argv[1:] if argv is None else argv))
    print(f"image model: {res['image_model_text']}; turn ratio {res['turn_ratio']:g}")
    for one in res.get("per_bus", [res]):
        if "per_bus" in res:
            print(f"{one['bus']}:")
        for rsu, r in one["rsus"].items():
            print(f"{rsu}: no fixes" if r["fixes"] == 0 else _line(rsu, r))
        for b in one["by_cell_px"]:
            lo, hi = b["cell_px"]
            print(_line(f"  cells {lo:g}-{'' if hi is None else f'{hi:g}'} px", b))
        for k, b in one["by_motion"].items():
            print(_line(f"  {k}", b))
    vc = res["view_correlation"]
    if vc.get("pairs"):
        print(f"view-dependent error ({vc['pairs']} pairs of one RSU's fixes under {vc['pair_max_s']:g} s apart), "
              "correlation of x, y, yaw z-scores by distance driven:")
        for b in vc["bins"]:
            lo, hi = b["m"]
            print(f"  {lo:g}-{'' if hi is None else f'{hi:g}'} m: {b['pairs']} pairs, rho "
                  + " / ".join(f"{r:+.2f}" for r in b["rho_x_y_yaw"]))
        print("  fit rho = share * exp(-d / corr_m): " + "; ".join(
            f"{k} share {f['share']:.2f} corr {f['corr_m']:g} m" for k, f in vc["fit"].items()))
    print("error size by range from the camera (RMS x, y cm, yaw deg; median |error|; stated sigma):")
    for b in res["size_by_range"]:
        lo, hi = b["range_m"]
        print(f"  {lo:g}-{'' if hi is None else f'{hi:g}'} m: {b['fixes']} fixes, RMS "
              + " / ".join(f"{v:.2f}" for v in b["rms_cm_deg"]) + ", median "
              + " / ".join(f"{v:.2f}" for v in b["median_abs_cm_deg"]) + ", stated "
              + " / ".join(f"{v:.2f}" for v in b["reported_sigma_cm_deg"]))
    if a.out:
        print(f"wrote {write_results(a.out, res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
