"""The fusion study's figures (sim.studies.fusion): error against latency, the first run's trajectory
coloured by error, NEES; with injected faults, the RSUs' time-offset estimates and the drift detector."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.faults import describe
from sim.scene import ROAD_HALF_WIDTH, rsu_mounts
from sim.studies.fusion import _errors, _key, _rms, eval_mask, nees_series
from toptag.units import NS_PER_MS, kmh_from_mps


def _save(fig, out: Path, name: str, files: list[str]) -> None:
    import matplotlib.pyplot as plt

    p = out / name
    fig.savefig(p, dpi=120)
    plt.close(fig)
    files.append(p.name)


def plots(out: Path, per_case, results, settle_s, inputs, faults, trust_only: bool = False) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    files: list[str] = []
    per_lat = per_case["fault_free"]
    if not trust_only:
        _error_vs_latency(out, per_lat, results, files)
        _trajectory(out, per_lat, results, settle_s, inputs, files)
        _nees(out, per_lat, results, settle_s, inputs, files)
    if faults:
        _offsets(out, per_case, results, faults, files)
        _drift(out, per_case, results, faults, files)
    return files


def _title(results) -> str:
    s = results["setup"]
    return (f"{'/'.join(s['routes'])} at {kmh_from_mps(s['speed_mps']):.0f} km/h, {s['n_rsu']} RSUs x 10 Hz, "
            f"jitter {s['jitter_ms']:.0f} ms, {s['runs']} runs")


def _error_vs_latency(out, per_lat, results, files):
    import matplotlib.pyplot as plt

    lats = sorted(per_lat)
    R = results["latency_ms"]
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
    ax.set_title(_title(results), fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, out, "fusion_error_vs_latency.png", files)


def _trajectory(out, per_lat, results, settle_s, inputs, files):
    import matplotlib
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    lats = sorted(per_lat)
    lat = 200.0 if 200.0 in per_lat else lats[-1]
    tr = per_lat[lat][0]
    win = eval_mask(tr, inputs[0], settle_s)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5), sharex=True, sharey=True)
    errs = {name: np.hypot(*(_errors(arr, tr.truth)[:, :2].T)) for name, arr in (("fused", tr.fused), ("naive", tr.naive))}
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
        _intersection(axx, results["setup"]["n_rsu"])
        i0 = int(np.argmax(win))
        axx.plot(*arr[i0, :2], "ko", ms=5, mfc="none", label="evaluation starts")
        axx.set_title(f"{name}, latency {lat:.0f} ms (run 1): RMS {_rms(errs[name][win]) * 100:.1f} cm "
                      f"(evaluated), {_rms(errs[name]) * 100:.1f} cm incl. start-up", fontsize=9)
        axx.legend(loc="lower right", fontsize=7)
        axx.set_xlabel("x east [m]")
        fig.colorbar(lc, ax=axx, label="position error [cm]", shrink=0.8)
    axes[0].set_ylabel("y north [m]")
    fig.tight_layout()
    _save(fig, out, "fusion_trajectory_error.png", files)


def _intersection(ax, n_rsu: int) -> None:
    import matplotlib.pyplot as plt

    for m in rsu_mounts()[:n_rsu]:
        ax.plot(*m.position[:2], "r^")
        ax.add_patch(plt.Circle(m.position[:2], 22.0, fill=False, ls=":", color="r", alpha=0.3))
    h = ROAD_HALF_WIDTH
    for s in (-1, 1):
        ax.plot([-45, -h], [s * h, s * h], "gray", lw=0.5)
        ax.plot([h, 45], [s * h, s * h], "gray", lw=0.5)
        ax.plot([s * h, s * h], [-45, -h], "gray", lw=0.5)
        ax.plot([s * h, s * h], [h, 45], "gray", lw=0.5)
    ax.set_aspect("equal")
    ax.set_xlim(-45, 45)
    ax.set_ylim(-45, 45)


def _nees(out, per_lat, results, settle_s, inputs, files):
    import matplotlib.pyplot as plt

    lats = sorted(per_lat)
    R = results["latency_ms"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    for l in lats:
        rows = []
        for tr, inp in zip(per_lat[l], inputs):
            m = eval_mask(tr, inp, settle_s)
            rows.append((tr.t[m], nees_series(tr)[m]))
        n = min(len(r[1]) for r in rows)
        a1.plot(rows[0][0][:n], np.nanmean([r[1][:n] for r in rows], axis=0), lw=0.8, label=f"{l:.0f} ms")
    band = R[_key(lats[0])]["nees_band_95"]
    a1.axhspan(*band, color="green", alpha=0.15, label="95% band (run average)")
    a1.axhline(3.0, color="k", lw=0.8)
    a1.set_xlabel("time [s]")
    a1.set_ylabel(f"NEES (x, y, yaw), mean over {results['setup']['runs']} runs")
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
    _save(fig, out, "fusion_nees.png", files)


def _pick_latency(per_lat) -> float:
    lats = sorted(per_lat)
    return 100.0 if 100.0 in per_lat else lats[len(lats) // 2]


def _offsets(out, per_case, results, faults, files):
    """Each RSU's time-offset estimate over time (all runs, faulted case), with the injected value."""
    import matplotlib.pyplot as plt

    lat = _pick_latency(per_case["faulted"])
    traces = per_case["faulted"][lat]
    rsus = sorted({r for tr in traces for r in tr.offsets})
    fig, axes = plt.subplots(1, len(rsus), figsize=(3.6 * len(rsus), 3.8), sharey=True, squeeze=False)
    for ax, rsu in zip(axes[0], rsus):
        inj = faults[rsu].time_offset_ns / NS_PER_MS if rsu in faults else 0.0
        for i, tr in enumerate(traces):
            o = tr.offsets.get(rsu)
            if o is None:
                continue
            ax.plot(tr.trust_t, 1e3 * o[:, 0], color="C0", lw=0.6, alpha=0.5, label="estimate (each run)" if i == 0 else None)
            if i == 0:
                ax.fill_between(tr.trust_t, 1e3 * (o[:, 0] - o[:, 1]), 1e3 * (o[:, 0] + o[:, 1]), color="C0", alpha=0.15,
                                label="± sigma (run 1)")
        ax.axhline(inj, color="r", ls="--", lw=1, label=f"injected {inj:g} ms")
        ax.axhspan(inj - 3, inj + 3, color="r", alpha=0.08, label="± 3 ms")
        ax.set_title(rsu, fontsize=9)
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="lower right")
    axes[0][0].set_ylabel("time offset estimate [ms]")
    fig.suptitle(f"RSU time offsets estimated by the bus filter ({describe(faults)}; fixes {lat:.0f} ms late)\n"
                 + _title(results), fontsize=9)
    fig.tight_layout()
    _save(fig, out, "fusion_offsets.png", files)


def _drift(out, per_case, results, faults, files):
    """Fused error over time (fault-free, faulted, faulted without offset estimation and drift detection)
    and the drift detector's statistic per RSU (run 1)."""
    import matplotlib.pyplot as plt

    from toptag.fusion.filter import FilterConfig, chi2_3dof

    lat = _pick_latency(per_case["faulted"])
    free, bad = per_case["fault_free"][lat], per_case["faulted"][lat]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.5))
    n = min(len(tr.t) for tr in free + bad)
    t = free[0].t[:n]
    for label, traces, attr, color in (("fault-free", free, "fused", "k"), ("faulted", bad, "fused", "C0"),
                                       ("faulted, offsets not estimated, no drift detection", bad, "plain", "C3")):
        e = np.array([np.hypot(*(_errors(getattr(tr, attr)[:n], tr.truth[:n])[:, :2].T)) for tr in traces])
        a1.plot(t, 100 * np.sqrt(np.nanmean(e ** 2, axis=0)), color=color, lw=1, label=label)
    a1.set_yscale("log")
    a1.set_xlabel("time [s]")
    a1.set_ylabel(f"fused position error, RMS over {len(free)} runs [cm]")
    a1.grid(alpha=0.3, which="both")
    a1.legend(fontsize=7)
    a1.set_title(f"{describe(faults)}; fixes {lat:.0f} ms late", fontsize=8)
    tr = bad[0]
    for i, (rsu, stat) in enumerate(sorted(tr.stats.items())):
        a2.plot(tr.trust_t, np.maximum(stat, 0.1), color=f"C{i}", lw=1, label=rsu + (" (drift injected)" if rsu in faults and
                                                                      faults[rsu].drift is not None else ""))
        for ft in tr.flags.get(rsu, []):
            a2.axvline(ft, color=f"C{i}", ls="--", lw=1)
    cfg = FilterConfig()
    a2.axhline(chi2_3dof(1 - cfg.drift_false_alarm), color="k", ls=":", lw=1,
               label=f"flag threshold (false alarm {cfg.drift_false_alarm:g} per test)")
    for rsu, f in faults.items():
        if f.drift is not None:
            a2.axvspan(f.drift.at_s, f.drift.at_s + max(f.drift.ramp_s, 0.05), color="r", alpha=0.1)
    a2.set_yscale("log")
    a2.set_ylim(bottom=0.1)
    a2.set_xlabel("time [s]")
    a2.set_ylabel("drift statistic T (chi-square, 3 dof)")
    a2.set_title("drift detector, run 1 (dashed: flagged)", fontsize=8)
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, out, "fusion_drift.png", files)


__all__ = ["plots"]
