"""Bus filter benchmark: the cost of `BusFilter.add_fix`, `add_imu` and `estimate` on the fusion
study's data (sim.studies.fusion: a bus turning left at 30 km/h, four corner RSUs at 10 Hz, IMU at
100 Hz), each fix arriving `latency ± jitter` after its capture, so it lands inside the buffer and
the buffer is re-propagated from its capture time.

    toptag bench filter [--runs 5] [--latency-ms 100] [--jitter-ms 30] [--calib-deg 0.05 --calib-cm 2]
                        [--calib-bias estimate|consider|noise]

With `--calib-deg/--calib-cm` the cameras carry a calibration error and every fix states it, so the
filter keeps a calibration-bias block per RSU (toptag.fusion.biases; `--calib-bias noise`: none).

The filter re-propagates lazily: `add_fix` redoes the steps up to the fix, the next `add_imu` or
`estimate` the rest. So the figure to compare between two versions of the filter is the total (all
three calls) per fix, and the per-call figures say where it goes. Times are the CPU time of the
calling thread (time.thread_time_ns), so time spent waiting for a busy CPU is not counted; each figure
is the best of `--runs` runs. Quote ratios between versions measured on one machine in one sitting.
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from sim.motion import ImuModel, bus_trajectory
from sim.studies.fusion import FixErrorModel, fix_arrivals, simulate_fixes
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.limits import BUS_MAX_SPEED_MPS
from toptag.machine import cpu_model, usable_cores
from toptag.progress import Progress


def _one_run(imu, arrivals, out_every: int, cfg: FilterConfig) -> dict:
    f = BusFilter(cfg)
    t_fix = t_imu = t_est = 0
    n_fix = n_imu = n_est = 0
    j = 0
    clock = time.thread_time_ns  # CPU time of this thread: waiting for a busy CPU is not counted
    for k, (t_ns, g, ax, ay, w) in enumerate(imu.rows()):
        while j < len(arrivals) and arrivals[j][0] < t_ns:
            c0 = clock()
            f.add_fix(arrivals[j][1], arrival_ns=arrivals[j][0])
            t_fix += clock() - c0
            n_fix += 1
            j += 1
        c0 = clock()
        f.add_imu(t_ns, g, ax, ay, w)
        t_imu += clock() - c0
        n_imu += 1
        if k % out_every == 0 and f.initialized:
            c0 = clock()
            f.estimate(t_ns)
            t_est += clock() - c0
            n_est += 1
    return {"add_fix_ns": t_fix, "add_imu_ns": t_imu, "estimate_ns": t_est, "fixes": n_fix, "imu": n_imu,
            "estimates": n_est, "counters": f.counters()}


def run(runs: int = 5, latency_ms: float = 100.0, jitter_ms: float = 30.0, seed: int = 0,
        config: FilterConfig | None = None, progress: bool = True, calib_deg: float = 0.0,
        calib_cm: float = 0.0) -> dict:
    cfg = config or FilterConfig()
    traj = bus_trajectory("left", "w", speed=BUS_MAX_SPEED_MPS, seed=seed)
    rng = np.random.default_rng(seed)
    imu = ImuModel().synthesize(traj, 0.0, traj.duration, rng)
    fixes = simulate_fixes(traj, FixErrorModel(calib_rot_sigma_deg=calib_deg, calib_trans_sigma=calib_cm / 100), 4, rng)
    delays = np.maximum(0.0, latency_ms + jitter_ms * rng.standard_normal(len(fixes)))
    arrivals = fix_arrivals(fixes, delays, {})
    best: dict | None = None
    bar = Progress(runs, "toptag bench filter") if progress else None
    for _ in range(runs):
        r = _one_run(imu, arrivals, 2, cfg)
        total = r["add_fix_ns"] + r["add_imu_ns"] + r["estimate_ns"]
        if best is None or total < best["total_ns"]:
            best = dict(r, total_ns=total)
        if bar:
            bar.update()
    if bar:
        bar.close()
    b = best
    return {
        "fixes": b["fixes"], "imu_samples": b["imu"], "estimates": b["estimates"],
        "accepted": b["counters"]["accepted"], "duration_s": traj.duration,
        "add_fix_us": b["add_fix_ns"] / b["fixes"] / 1e3,
        "add_imu_us": b["add_imu_ns"] / b["imu"] / 1e3,
        "estimate_us": b["estimate_ns"] / max(b["estimates"], 1) / 1e3,
        "total_per_fix_us": b["total_ns"] / b["fixes"] / 1e3,
        "total_s_per_data_s": b["total_ns"] / 1e9 / traj.duration,
        "runs": runs, "latency_ms": latency_ms, "jitter_ms": jitter_ms, "seed": seed,
        "calib_deg": calib_deg, "calib_cm": calib_cm, "calib_bias": cfg.calib_bias,
        "machine": f"{platform.machine()}, {cpu_model(unknown='unknown CPU')}, nproc {usable_cores()}",
    }


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toptag bench filter", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=5, help="runs; the best is reported (default 5)")
    p.add_argument("--latency-ms", type=float, default=100.0, help="mean fix delay (default 100)")
    p.add_argument("--jitter-ms", type=float, default=30.0, help="fix delay standard deviation (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--calib-deg", type=float, default=0.0, help="cameras' calibration error per axis, deg (default 0)")
    p.add_argument("--calib-cm", type=float, default=0.0, help="camera centres' calibration error per axis, cm (default 0)")
    p.add_argument("--calib-bias", choices=("estimate", "consider", "noise"), default=None,
                   help="the filter's treatment of the fixes' calibration share (default: the filter's)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    cfg = FilterConfig() if a.calib_bias is None else FilterConfig(calib_bias=a.calib_bias)
    r = run(a.runs, a.latency_ms, a.jitter_ms, a.seed, config=cfg, calib_deg=a.calib_deg, calib_cm=a.calib_cm)
    if a.json:
        print(json.dumps(r, indent=1))
        return 0
    print(f"{r['fixes']} fixes ({r['accepted']} accepted), {r['imu_samples']} IMU samples, {r['estimates']} "
          f"estimates over {r['duration_s']:.1f} s of data; fix delay {r['latency_ms']:g} ± {r['jitter_ms']:g} ms; "
          f"best of {r['runs']} runs; calibration error {r['calib_deg']:g} deg / {r['calib_cm']:g} cm "
          f"({r['calib_bias']}); {r['machine']}")
    print(f"add_fix {r['add_fix_us']:.0f} µs/fix  add_imu {r['add_imu_us']:.0f} µs/sample  "
          f"estimate {r['estimate_us']:.0f} µs/call")
    print(f"total {r['total_per_fix_us']:.0f} µs per fix; {r['total_s_per_data_s'] * 1e3:.1f} ms of filter time "
          f"per second of data")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
