"""`toptag eval fusion`: the bus filter against latency, on the simulator's truth.

A bus turns left through the SPEC intersection at 30 km/h (sim.motion). Its IMU / wheel odometry is
synthesised at 100 Hz (sim.motion.ImuModel). Corner RSUs at (±9, ±9, 8) send pose fixes at 10 Hz each
while the bus is within `range_m` of them, with the error model below, and every fix reaches the bus
`latency + jitter` later (delay = max(0, latency + N(0, jitter)), so fixes also arrive out of order).

Three estimators see the same data:
  fused           toptag.fusion.filter.BusFilter: each fix applied at its capture time, buffer re-propagated
  naive           the same EKF, each fix applied on arrival as if it were current (no gate)
  dead reckoning  the same EKF from the true initial pose, IMU / odometry only

Fix error model ("study"): per RSU, position noise sigma = 3 cm at the RSU growing linearly to 5 cm
at `range_m` (horizontal distance), 1.3x larger along the line of sight; yaw sigma 0.1° -> 0.2°;
independent between fixes; the reported covariance is exactly the covariance of the noise.
(A live image pipeline can be plugged in with `run(..., fix_source=callable)`.)

Writes DIR/results.json, DIR/fusion_error_vs_latency.png, DIR/fusion_trajectory_error.png and
DIR/fusion_nees.png. Run: `python -m sim.studies.fusion --out DIR` (or `toptag eval fusion`).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sim.motion import ImuModel, Trajectory, bus_trajectory
from sim.scene import rsu_mounts
from sim.studies import require_plotting
from toptag.errors import InputError, SetupError, report
from toptag.fix import Fix
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.geometry import wrap_angle
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.progress import Progress
from toptag.units import kmh_from_mps, ns_from_ms, ns_from_s, s_from_ns

DEFAULT_LATENCIES_MS = (0, 50, 100, 200, 300)


@dataclass(frozen=True)
class FixErrorModel:
    """Noise of RSU pose fixes (see the module docstring)."""
    rate_hz: float = 10.0
    range_m: float = 22.0
    pos_sigma_near: float = 0.03
    pos_sigma_far: float = 0.05
    yaw_sigma_near_deg: float = 0.1
    yaw_sigma_far_deg: float = 0.2
    along_sight: float = 1.3  # sigma multiplier along the RSU's line of sight

    def covariance(self, bus_xy: np.ndarray, rsu_xy: np.ndarray) -> np.ndarray:
        d_vec = bus_xy - rsu_xy
        d = float(np.hypot(*d_vec))
        r = min(d / self.range_m, 1.0)
        s = self.pos_sigma_near + (self.pos_sigma_far - self.pos_sigma_near) * r
        sy = math.radians(self.yaw_sigma_near_deg + (self.yaw_sigma_far_deg - self.yaw_sigma_near_deg) * r)
        e = d_vec / d if d > 1e-9 else np.array([1.0, 0.0])
        C2 = s * s * (np.eye(2) + (self.along_sight ** 2 - 1) * np.outer(e, e))
        C = np.zeros((3, 3))
        C[:2, :2] = C2
        C[2, 2] = sy * sy
        return C


def simulate_fixes(traj: Trajectory, model: FixErrorModel, n_rsu: int, rng: np.random.Generator,
                   fix_source=None) -> list[Fix]:
    """Capture-stamped fixes from the first n_rsu corner RSUs (no arrival time yet)."""
    mounts = rsu_mounts()[:n_rsu]
    fixes = []
    period = 1.0 / model.rate_hz
    for m in mounts:
        phase = rng.uniform(0.0, period)
        t = np.arange(phase, traj.duration, period)
        st = traj.state_at(t)
        seq = 0
        for i in range(len(t)):
            bus = np.array([st.x[i], st.y[i]])
            if np.hypot(*(bus - m.position[:2])) > model.range_m:
                continue
            if fix_source is not None:
                out = fix_source(traj, float(t[i]), m, rng)
                if out is None:
                    continue
                pose, C = out
            else:
                C = model.covariance(bus, m.position[:2])
                n = np.linalg.cholesky(C) @ rng.standard_normal(3)
                pose = (st.x[i] + n[0], st.y[i] + n[1], wrap_angle(st.yaw[i] + n[2]))
            fixes.append(Fix(traj.t_ns(t[i]), pose[0], pose[1], pose[2], C, m.id, seq))
            seq += 1
    fixes.sort(key=lambda f: f.t_ns)
    return fixes


@dataclass
class RunTrace:
    t: np.ndarray  # output times, s
    truth: np.ndarray  # (n, 3) x, y, yaw
    fused: np.ndarray  # (n, 3)
    fused_cov: np.ndarray  # (n, 3, 3)
    naive: np.ndarray
    dead: np.ndarray
    counters: dict
    delays_ms: np.ndarray


def _feed(filters, imu_rows, arrivals, out_every: int, t_out_ns: list):
    """Drive filters with IMU rows and fix arrivals in time order; collect estimates every
    `out_every` IMU samples. `arrivals`: list per filter of (arrival_ns, fix) sorted by arrival."""
    outs = [[] for _ in filters]
    ptr = [0] * len(filters)
    for k, (t_ns, g, ax, ay, w) in enumerate(imu_rows):
        for j, f in enumerate(filters):
            arr = arrivals[j]
            while ptr[j] < len(arr) and arr[ptr[j]][0] < t_ns:
                f.add_fix(arr[ptr[j]][1], arrival_ns=arr[ptr[j]][0])
                ptr[j] += 1
            f.add_imu(t_ns, g, ax, ay, w)
        if k % out_every == 0:
            if len(outs[0]) == len(t_out_ns):
                t_out_ns.append(t_ns)
            for j, f in enumerate(filters):
                outs[j].append(f.estimate(t_ns))
    return outs


def _pose_array(ests) -> tuple[np.ndarray, np.ndarray]:
    xs = np.full((len(ests), 3), np.nan)
    covs = np.full((len(ests), 3, 3), np.nan)
    for i, e in enumerate(ests):
        if e is not None:
            xs[i] = (e.x, e.y, e.yaw)
            covs[i] = e.cov
    return xs, covs


def run_once(traj: Trajectory, imu, fixes: list[Fix], latency_ms: float, jitter_ms: float,
             rng: np.random.Generator, cfg: FilterConfig, dead: np.ndarray | None, out_hz: float = 50.0):
    delays = np.maximum(0.0, latency_ms + jitter_ms * rng.standard_normal(len(fixes)))
    arrivals = sorted(((f.t_ns + ns_from_ms(d), f) for f, d in zip(fixes, delays)), key=lambda a: a[0])
    naive_arr = [(a, f.replace(t_ns=a)) for a, f in arrivals]
    fused = BusFilter(cfg)
    naive = BusFilter(cfg.model_copy(update={"gate_probability": None}))
    filters, arr = [fused, naive], [arrivals, naive_arr]
    st0 = traj.state_at(0.0)
    dr = None
    if dead is None:
        dr = BusFilter(cfg)
        dr.initialize(traj.t0_ns, st0.x, st0.y, st0.yaw, pos_sigma=0.01, yaw_sigma=math.radians(0.1),
                      speed=imu.wheel_speed[0], speed_sigma=0.1, trusted=True)
        filters.append(dr)
        arr.append([])
    every = max(1, int(round(100.0 / out_hz)))
    t_out: list[int] = []
    outs = _feed(filters, imu.rows(), arr, every, t_out)
    t = traj.seconds(np.array(t_out))
    st = traj.state_at(t)
    truth = np.stack([st.x, st.y, st.yaw], axis=1)
    fx, fc = _pose_array(outs[0])
    nx, _ = _pose_array(outs[1])
    dx = _pose_array(outs[2])[0] if dr is not None else dead
    return RunTrace(t, truth, fx, fc, nx, dx, fused.counters(), delays)


def _errors(est: np.ndarray, truth: np.ndarray):
    e = est - truth
    e[:, 2] = wrap_arr(e[:, 2])
    return e


def wrap_arr(a):
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


def _rms(v):
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if len(v) else float("nan")


def run(out_dir, latencies_ms=DEFAULT_LATENCIES_MS, jitter_ms: float = 30.0, seed: int = 0, runs: int = 16,
        n_rsu: int = 4, route: str = "left", speed: float = BUS_MAX_SPEED_MPS, settle_s: float = 1.5,
        imu_model: ImuModel | None = None, fix_model: FixErrorModel | None = None,
        config: FilterConfig | None = None, fix_source=None, plots: bool = True, log=print,
        progress: bool = True) -> dict:
    """The study. Returns the results dict also written to out_dir/results.json."""
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    imu_model = imu_model or ImuModel()
    fix_model = fix_model or FixErrorModel()
    cfg = config or FilterConfig()
    traj = bus_trajectory(route, "w", speed=speed, seed=seed)
    latencies = [float(l) for l in latencies_ms]
    ss = np.random.SeedSequence(seed)
    run_seeds = ss.spawn(runs)
    per_lat: dict[float, list[RunTrace]] = {l: [] for l in latencies}
    # Common random numbers: each run's IMU and fixes are shared by every latency.
    inputs = []
    for r in range(runs):
        g_imu, g_fix, g_lat = [np.random.default_rng(s) for s in run_seeds[r].spawn(3)]
        imu = imu_model.synthesize(traj, 0.0, traj.duration, g_imu)
        fixes = simulate_fixes(traj, fix_model, n_rsu, g_fix, fix_source)
        inputs.append((imu, fixes, g_lat))
    dead_cache: list[np.ndarray | None] = [None] * runs
    results: dict = {"latency_ms": {}}
    bar = Progress(len(latencies) * runs, "toptag eval fusion") if progress else None
    for lat in latencies:
        t0 = time.perf_counter()
        for r, (imu, fixes, g_lat) in enumerate(inputs):
            rng = np.random.default_rng([seed, r, int(lat * 1000)])
            tr = run_once(traj, imu, fixes, lat, jitter_ms, rng, cfg, dead_cache[r])
            dead_cache[r] = tr.dead
            per_lat[lat].append(tr)
            if bar:
                bar.update(note=f"{lat:g} ms")
        res = _summarise(per_lat[lat], inputs, settle_s)
        results["latency_ms"][_key(lat)] = res
        log(f"latency {lat:5.0f} ms  jitter {jitter_ms:.0f} ms  runs {runs}: "
            f"fused {res['fused_pos_rms_m'] * 100:6.2f} cm  naive {res['naive_pos_rms_m'] * 100:7.2f} cm  "
            f"dead-reckoning {res['dead_reckoning_pos_rms_m'] * 100:7.2f} cm"
            f"  NEES {res['nees_mean']:.2f} (band {res['nees_band_95'][0]:.2f}-{res['nees_band_95'][1]:.2f})"
            f"  [{time.perf_counter() - t0:.1f} s]")
    if bar:
        bar.close()
    zero = results["latency_ms"].get(_key(min(latencies)))
    for k, res in results["latency_ms"].items():
        res["fused_ratio_to_min_latency"] = res["fused_pos_rms_m"] / zero["fused_pos_rms_m"]
        res["naive_over_fused"] = res["naive_pos_rms_m"] / res["fused_pos_rms_m"]
    if "200" in results["latency_ms"] and min(latencies) == 0:
        r = results["latency_ms"]["200"]
        results["target"] = {
            "fused_200_over_fused_0": r["fused_ratio_to_min_latency"],
            "fused_200_le_1p2x_fused_0": bool(r["fused_ratio_to_min_latency"] <= 1.2),
            "naive_200_over_fused_200": r["naive_over_fused"],
            "nees_mean_in_band_all_latencies": all(
                v["nees_band_95"][0] <= v["nees_mean"] <= v["nees_band_95"][1] for v in results["latency_ms"].values()),
        }
    results["setup"] = {
        "route": traj.name, "speed_mps": speed, "duration_s": traj.duration, "runs": runs, "seed": seed,
        "jitter_ms": jitter_ms, "delay_model": "max(0, latency + N(0, jitter))", "n_rsu": n_rsu,
        "rsus": [m.id for m in rsu_mounts()[:n_rsu]], "settle_s": settle_s, "output_hz": 50,
        "fix_model": "live (fix_source)" if fix_source else asdict(fix_model), "imu_model": asdict(imu_model),
        "filter": cfg.model_dump(),
        "naive": "same EKF, each fix applied at its arrival time as if current, no gate",
        "dead_reckoning": "same EKF from the true initial pose, IMU/odometry only",
        "nees": "3-dof (x, y, yaw); band = 95% chi-square band of the run-averaged NEES at one time",
    }
    results["runtime_s"] = time.perf_counter() - t_start
    if plots:
        results["figures"] = _plots(out, traj, per_lat, results, settle_s, inputs)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=_json_default))
    results["runtime_s"] = time.perf_counter() - t_start
    return results


def _key(lat: float) -> str:
    return str(int(lat)) if float(lat).is_integer() else str(lat)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _eval_mask(tr: RunTrace, fixes: list[Fix], t0_ns: int, settle_s: float) -> np.ndarray:
    first = s_from_ns(fixes[0].t_ns - t0_ns) if fixes else 0.0
    return tr.t >= first + settle_s


def _nees(tr: RunTrace) -> np.ndarray:
    e = _errors(tr.fused, tr.truth)
    out = np.full(len(e), np.nan)
    for i in range(len(e)):
        if np.all(np.isfinite(e[i])):
            out[i] = float(e[i] @ np.linalg.solve(tr.fused_cov[i], e[i]))
    return out


def _summarise(traces: list[RunTrace], inputs, settle_s: float) -> dict:
    from scipy.stats import chi2

    t0_ns = None
    fpos, npos, dpos, fyaw, nyaw, nees_rows = [], [], [], [], [], []
    counters: dict[str, int] = {}
    delays = []
    for tr, (imu, fixes, _) in zip(traces, inputs):
        t0_ns = int(imu.t_ns[0]) - ns_from_s(imu.t[0])
        m = _eval_mask(tr, fixes, t0_ns, settle_s)
        ef, en, ed = (_errors(a, tr.truth)[m] for a in (tr.fused, tr.naive, tr.dead))
        fpos.append(np.hypot(ef[:, 0], ef[:, 1]))
        npos.append(np.hypot(en[:, 0], en[:, 1]))
        dpos.append(np.hypot(ed[:, 0], ed[:, 1]))
        fyaw.append(ef[:, 2])
        nyaw.append(en[:, 2])
        nees_rows.append(_nees(tr)[m])
        delays.append(tr.delays_ms)
        for k, v in tr.counters.items():
            if isinstance(v, int):
                counters[k] = counters.get(k, 0) + v
    n = min(len(r) for r in nees_rows)
    N = np.array([r[:n] for r in nees_rows])
    M = N.shape[0]
    avg = np.nanmean(N, axis=0)
    band = (float(chi2.ppf(0.025, 3 * M) / M), float(chi2.ppf(0.975, 3 * M) / M))
    fp = np.concatenate(fpos)
    return {
        "fused_pos_rms_m": _rms(fp),
        "naive_pos_rms_m": _rms(np.concatenate(npos)),
        "dead_reckoning_pos_rms_m": _rms(np.concatenate(dpos)),
        "fused_pos_max_m": float(np.nanmax(fp)),
        "fused_yaw_rms_deg": math.degrees(_rms(np.concatenate(fyaw))),
        "naive_yaw_rms_deg": math.degrees(_rms(np.concatenate(nyaw))),
        "nees_mean": float(np.nanmean(N)),
        "nees_band_95": band,
        "nees_frac_times_in_band": float(np.mean((avg >= band[0]) & (avg <= band[1]))),
        "nees_dof": 3,
        "n_samples": int(np.isfinite(fp).sum()),
        "delay_ms_mean": float(np.mean(np.concatenate(delays))),
        "fixes": {k: counters.get(k, 0) for k in ("fixes", "accepted", "rejected_gate", "reacquired", "initialized",
                                                  "before_start", "too_old", "duplicate", "pending")},
    }


def _plots(out: Path, traj: Trajectory, per_lat, results, settle_s, inputs) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from sim.scene import ROAD_HALF_WIDTH

    files = []
    lats = sorted(per_lat)
    R = results["latency_ms"]
    # 1. error against latency
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for key, lab, mk in (("fused_pos_rms_m", "fused (applied at capture time)", "o-"),
                         ("naive_pos_rms_m", "naive (applied on arrival)", "s-"),
                         ("dead_reckoning_pos_rms_m", "dead reckoning", "^--")):
        ax.plot(lats, [R[_key(l)][key] * 100 for l in lats], mk, label=lab)
    z = R[_key(lats[0])]["fused_pos_rms_m"] * 100
    ax.axhline(1.2 * z, color="gray", ls=":", label=f"1.2 x fused at {lats[0]:.0f} ms")
    ax.set_yscale("log")
    ax.set_xlabel("mean fix latency [ms]")
    ax.set_ylabel("position RMS error [cm]")
    setup = results["setup"]
    ax.set_title(f"{setup['route']} at {kmh_from_mps(setup['speed_mps']):.0f} km/h, {setup['n_rsu']} RSUs x 10 Hz, "
                 f"jitter {setup['jitter_ms']:.0f} ms, {setup['runs']} runs", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = out / "fusion_error_vs_latency.png"
    fig.savefig(p, dpi=120)
    plt.close(fig)
    files.append(p.name)
    # 2. trajectory coloured by error (first run, latency 200 ms or the largest)
    lat = 200.0 if 200.0 in per_lat else lats[-1]
    tr = per_lat[lat][0]
    imu0, fixes0, _ = inputs[0]
    win = _eval_mask(tr, fixes0, int(imu0.t_ns[0]) - ns_from_s(imu0.t[0]), settle_s)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5), sharex=True, sharey=True)
    errs = {name: np.hypot(*(_errors(arr, tr.truth)[:, :2].T))
            for name, arr in (("fused", tr.fused), ("naive", tr.naive))}
    vmax = max(np.nanpercentile(errs["naive"], 99), 0.05) * 100
    for axx, (name, arr) in zip(axes, (("fused", tr.fused), ("naive", tr.naive))):
        e = errs[name] * 100
        pts = arr[:, :2]
        ok = np.all(np.isfinite(pts), axis=1)
        segs = np.stack([pts[:-1], pts[1:]], axis=1)[ok[:-1] & ok[1:]]
        lc = LineCollection(segs, cmap="viridis", norm=matplotlib.colors.LogNorm(vmin=0.3, vmax=max(vmax, 1.0)))
        lc.set_array(e[:-1][ok[:-1] & ok[1:]])
        lc.set_linewidth(3)
        axx.add_collection(lc)
        axx.plot(tr.truth[:, 0], tr.truth[:, 1], "k--", lw=0.6, label="truth")
        for m in rsu_mounts()[:setup["n_rsu"]]:
            axx.plot(*m.position[:2], "r^")
            axx.add_patch(plt.Circle(m.position[:2], 22.0, fill=False, ls=":", color="r", alpha=0.3))
        h = ROAD_HALF_WIDTH
        for s in (-1, 1):
            axx.plot([-45, -h], [s * h, s * h], "gray", lw=0.5)
            axx.plot([h, 45], [s * h, s * h], "gray", lw=0.5)
            axx.plot([s * h, s * h], [-45, -h], "gray", lw=0.5)
            axx.plot([s * h, s * h], [h, 45], "gray", lw=0.5)
        axx.set_aspect("equal")
        axx.set_xlim(-45, 45)
        axx.set_ylim(-45, 45)
        i0 = int(np.argmax(win))
        axx.plot(*arr[i0, :2], "ko", ms=5, mfc="none", label="evaluation starts")
        axx.set_title(f"{name}, latency {lat:.0f} ms (run 1): RMS {_rms(errs[name][win]) * 100:.1f} cm "
                      f"(evaluated), {_rms(errs[name]) * 100:.1f} cm incl. start-up", fontsize=9)
        axx.legend(loc="lower right", fontsize=7)
        axx.set_xlabel("x east [m]")
        fig.colorbar(lc, ax=axx, label="position error [cm]", shrink=0.8)
    axes[0].set_ylabel("y north [m]")
    fig.tight_layout()
    p = out / "fusion_trajectory_error.png"
    fig.savefig(p, dpi=120)
    plt.close(fig)
    files.append(p.name)
    # 3. NEES consistency
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    for l in lats:
        rows = []
        for tr, (imu, fixes, _) in zip(per_lat[l], inputs):
            t0_ns = int(imu.t_ns[0]) - ns_from_s(imu.t[0])
            m = _eval_mask(tr, fixes, t0_ns, settle_s)
            rows.append((tr.t[m], _nees(tr)[m]))
        n = min(len(r[1]) for r in rows)
        a1.plot(rows[0][0][:n], np.nanmean([r[1][:n] for r in rows], axis=0), lw=0.8, label=f"{l:.0f} ms")
    band = R[_key(lats[0])]["nees_band_95"]
    a1.axhspan(*band, color="green", alpha=0.15, label="95% band (run average)")
    a1.axhline(3.0, color="k", lw=0.8)
    a1.set_xlabel("time [s]")
    a1.set_ylabel(f"NEES (x, y, yaw), mean over {setup['runs']} runs")
    a1.set_yscale("log")
    a1.legend(fontsize=7, ncol=3)
    means = [R[_key(l)]["nees_mean"] for l in lats]
    a2.axhspan(*band, color="green", alpha=0.15, label="95% chi-square band")
    a2.axhline(3.0, color="k", lw=0.8, label="expected (3 dof)")
    a2.plot(lats, means, "o-", color="C0", label="mean NEES (all runs, all times)")
    for l, m in zip(lats, means):
        a2.annotate(f"{m:.2f}", (l, m), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
    a2.set_ylim(0, max(band[1] * 1.15, max(means) * 1.2))
    a2.set_xlabel("latency [ms]")
    a2.set_ylabel("mean NEES")
    a2.legend(fontsize=7, loc="lower right")
    fig.suptitle("filter consistency: NEES of the fused pose against its covariance", fontsize=10)
    fig.tight_layout()
    p = out / "fusion_nees.png"
    fig.savefig(p, dpi=120)
    plt.close(fig)
    files.append(p.name)
    return files


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag eval fusion", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--latency-ms", default=",".join(str(l) for l in DEFAULT_LATENCIES_MS),
                   help="comma-separated mean latencies (default %(default)s)")
    p.add_argument("--jitter-ms", type=float, default=30.0, help="delay standard deviation (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", type=int, default=16, help="Monte Carlo runs per latency (default 16)")
    p.add_argument("--rsus", type=int, default=4, choices=(1, 2, 3, 4), help="number of corner RSUs (default 4)")
    p.add_argument("--route", default="left", choices=("left", "right", "straight", "stop"))
    p.add_argument("--fixes", default="study", choices=("study", "live"),
                   help="fix error model: the study's (default) or the live pipeline")
    p.add_argument("--no-plots", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    try:
        require_plotting()
    except SetupError as e:
        return report("eval fusion", e)
    if a.fixes == "live":
        return report("eval fusion", InputError("--fixes live needs the RSU image pipeline; pass "
                                                "run(fix_source=...) from Python until it is wired in"))
    try:
        lats = [float(s) for s in a.latency_ms.split(",") if s.strip()]
    except ValueError:
        return report("eval fusion", InputError(f"--latency-ms must be comma-separated numbers, "
                                                f"got {a.latency_ms!r}"))
    if not lats or min(lats) < 0:
        return report("eval fusion", InputError("latencies must be >= 0"))
    res = run(a.out, lats, a.jitter_ms, a.seed, runs=a.runs, n_rsu=a.rsus, route=a.route, plots=not a.no_plots)
    print()
    print(f"{'latency':>8} {'fused cm':>9} {'naive cm':>9} {'DR cm':>8} {'fused/0':>8} {'naive/fused':>11}"
          f" {'NEES':>6} {'band':>12} {'rejected':>8}")
    for k, r in res["latency_ms"].items():
        print(f"{k:>6}ms {r['fused_pos_rms_m'] * 100:9.2f} {r['naive_pos_rms_m'] * 100:9.2f}"
              f" {r['dead_reckoning_pos_rms_m'] * 100:8.2f} {r['fused_ratio_to_min_latency']:8.2f}"
              f" {r['naive_over_fused']:11.1f} {r['nees_mean']:6.2f}"
              f" {r['nees_band_95'][0]:5.2f}-{r['nees_band_95'][1]:5.2f} {r['fixes']['rejected_gate']:8d}")
    if "200" in res["latency_ms"]:
        r, z = res["latency_ms"]["200"], res["latency_ms"][next(iter(res["latency_ms"]))]
        ok = r["fused_pos_rms_m"] <= 1.2 * z["fused_pos_rms_m"]
        print(f"\n200 ms: fused {r['fused_pos_rms_m'] * 100:.2f} cm vs lowest-latency fused "
              f"{z['fused_pos_rms_m'] * 100:.2f} cm (ratio {r['fused_ratio_to_min_latency']:.2f}, target <= 1.2: "
              f"{'met' if ok else 'NOT met'}); naive {r['naive_pos_rms_m'] * 100:.1f} cm "
              f"({r['naive_over_fused']:.0f}x fused)")
    print(f"wrote {Path(a.out) / 'results.json'} and {', '.join(res.get('figures', []))}; "
          f"runtime {res['runtime_s']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
