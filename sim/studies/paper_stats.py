"""The paper study's statistics: per case, solver and distance the position and yaw errors, detection
rates, ratios to the bound, the paper's claims and the targets checked, and the plain-text table."""
from __future__ import annotations

import math

import numpy as np

from sim.image_model import ImageModel
from sim.studies.paper_bounds import case_noise, sample_bounds
from sim.studies.paper_setup import CASES, DISTANCES, SOLVERS, TARGETS

def _f(v: float | None, nd: int = 6) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), nd)


def _stats(samples: list[dict], which: str, key: str, bound_key: str) -> dict:
    res = [(s[which][key], s["bounds"].get(bound_key)) for s in samples]
    solved = [(r, b) for r, b in res if r is not None]
    out = {"n": len(samples), "detected": len(solved),
           "detection_rate": _f(len(solved) / len(samples) if samples else math.nan, 4)}
    if not solved:
        return out | {"pos_rms_m": None, "pos_max_m": None, "yaw_rms_deg": None, "crlb_pos_rms_m": None,
                      "crlb_ratio": None, "yaw_crlb_ratio": None}
    e = np.array([r[0] for r, _ in solved])
    ey = np.array([r[1] for r, _ in solved])
    bounds = [b for _, b in solved if b is not None]
    bpos = math.sqrt(np.mean([b[0] ** 2 for b in bounds])) if bounds else math.nan
    byaw = math.degrees(math.sqrt(np.mean([b[1] ** 2 for b in bounds]))) if bounds else math.nan
    rms, yrms = math.sqrt(np.mean(e ** 2)), math.sqrt(np.mean(ey ** 2))
    return out | {"pos_rms_m": _f(rms), "pos_max_m": _f(float(e.max())), "yaw_rms_deg": _f(yrms, 5),
                  "crlb_pos_rms_m": _f(bpos), "crlb_ratio": _f(rms / bpos if bpos > 0 else math.nan, 3),
                  "yaw_crlb_ratio": _f(yrms / byaw if byaw > 0 else math.nan, 3)}


def _bound_key(solver: str, known_extrinsics: bool) -> str:
    return ("2cam" if SOLVERS[solver].two_cameras else "1cam") + ("" if known_extrinsics else "_calib")


def _best(sec: dict, d: str, two_cameras: bool) -> tuple[str | None, float | None]:
    """The solver with the lowest position RMS at bin d among the one- or two-camera ones, and its
    ratio to its bound."""
    rows = {k: r[d] for k, r in sec.items() if SOLVERS[k].two_cameras == two_cameras and r[d]["pos_rms_m"] is not None}
    if not rows:
        return None, None
    k = min(rows, key=lambda k: rows[k]["pos_rms_m"])
    return k, rows[k]["crlb_ratio"]


def _rms_bound(bs: list, i: int, deg: bool = False) -> float | None:
    if not bs:
        return None
    v = math.sqrt(np.mean([b[i] ** 2 for b in bs]))
    return _f(math.degrees(v) if deg else v, 5 if deg else 6)


def summarise(samples: list[dict], model: ImageModel) -> dict:
    """results.json's "cases", "calibration", "detection", "crlb" and "noise" sections."""
    cases, calibration, detection, crlb, noise_out = {}, {}, {}, {}, {}
    for name in CASES:
        mine = [s for s in samples if s["case"] == name]
        if not mine:
            continue
        case = CASES[name]
        noise = case_noise(mine)
        noise_out[name] = {str(b): v.to_dict() for b, v in noise.items()}
        for s in mine:
            s["bounds"] = sample_bounds(s, case, noise, model)
        bins = {d: [s for s in mine if s["bin"] == d] for d in DISTANCES}
        bins = {d: v for d, v in bins.items() if v}
        cases[name] = {k: {str(d): _stats(v, "known", k, _bound_key(k, True)) for d, v in bins.items()}
                       for k in SOLVERS}
        calibration[name] = {k: {str(d): _stats(v, "miscalibrated", k, _bound_key(k, False))
                                 for d, v in bins.items()} for k in SOLVERS}
        detection[name] = {}
        crlb[name] = {}
        for d, v in bins.items():
            n = len(v)
            found = sum(bool(s["tags1"]) for s in v)
            detection[name][str(d)] = {"n": n, "found": found, "rate": _f(found / n, 4),
                                       "both_tags": sum(len(s["tags1"]) == 2 for s in v),
                                       "second_rsu_views": sum(s["second"] is not None for s in v),
                                       "second_rsu_found": sum(bool(s["tags2"]) for s in v),
                                       "garbled_tags": sum(len(s["outlier_tags"]) for s in v)}
            entry = dict(noise[d].to_dict()) if d in noise else {}
            for bk, label in (("1cam", ""), ("2cam", "_2cam"), ("1cam_calib", "_calib"),
                              ("2cam_calib", "_2cam_calib"), ("1cam_iid", "_iid")):
                bs = [s["bounds"][bk] for s in v if bk in s["bounds"]]
                entry[f"pos_rms{label}_m"] = _rms_bound(bs, 0)
                entry[f"yaw_rms{label}_deg"] = _rms_bound(bs, 1, deg=True)
            for prefix, sec in (("", cases[name]), ("calib_", calibration[name])):
                for two, tag in ((False, ""), (True, "_2cam")):
                    k, ratio = _best(sec, str(d), two)
                    entry[f"{prefix}best{tag}_solver"] = k
                    entry[f"{prefix}best{tag}_ratio"] = ratio
            crlb[name][str(d)] = entry
    return {"cases": cases, "calibration": calibration, "detection": detection, "crlb": crlb, "noise": noise_out}


def check_targets(results: dict) -> dict:
    """The issue's acceptance targets, measured (only for the cases that ran)."""
    t = TARGETS
    out: dict = {"targets": dict(t)}
    d = str(t["distance"])
    for which in ("cases", "calibration"):
        sec = results[which].get(t["case"])
        if not sec:
            continue
        for key in ("sopt", "sopt_principled", "sopt_level", "sopt_2cam", "sopt_level_2cam"):
            r = sec[key].get(d)
            if not r or r["pos_rms_m"] is None:
                continue
            out[f"{which}.{key}@{d}m"] = {
                "pos_rms_m": r["pos_rms_m"], "pos_max_m": r["pos_max_m"], "yaw_rms_deg": r["yaw_rms_deg"],
                "met": bool(r["pos_rms_m"] <= t["pos_rms_m"] and r["pos_max_m"] <= t["pos_max_m"]
                            and r["yaw_rms_deg"] <= t["yaw_rms_deg"])}
    for name, det in results["detection"].items():
        n = sum(v["n"] for v in det.values())
        found = sum(v["found"] for v in det.values())
        out[f"detection.{name}"] = {"rate": _f(found / n, 4), "worst_bin_rate": min(v["rate"] for v in det.values()),
                                    "met": found / n >= t["detection_rate"]}
    for name, cr in results["crlb"].items():
        for prefix, what in (("", "extrinsics known"), ("calib_", "calibration error")):
            for tag in ("", "_2cam"):
                ratios = {k: v[f"{prefix}best{tag}_ratio"] for k, v in cr.items()}
                vals = [r for r in ratios.values() if r is not None]
                out[f"bound.{name}.{prefix}best{tag}"] = {
                    "what": f"best {'two' if tag else 'one'}-RSU solver / its bound, {what}",
                    "ratio_by_distance": ratios, "worst": max(vals) if vals else None,
                    "met": bool(vals) and max(vals) <= t["bound_ratio"]}
    return out


def render_table(results: dict, which: str = "cases") -> str:
    """A plain-text table per case: per distance, every solver's position RMS / max (cm) and yaw RMS (deg),
    the detection rate, the measured corner noise and the bounds for one and two RSUs (cm)."""
    lines = []
    cal = "_calib" if which == "calibration" else ""
    for name, sec in results[which].items():
        keys = list(sec)
        lines.append(f"\n{name} ({which}): position RMS/max cm, yaw RMS deg; sigma = corner noise px; "
                     f"bound = Cramér–Rao position RMS cm, 1 RSU / 2 RSUs")
        lines.append(f"{'m':>3} {'det':>5} {'sigma':>6} {'bound':>6} {'bnd2':>6} "
                     + " ".join(f"{k:>20}" for k in keys))
        for d in sec[keys[0]]:
            det = results["detection"][name][d]
            cr = results["crlb"][name][d]
            cells = []
            for k in keys:
                r = sec[k][d]
                cells.append(f"{'-':>20}" if r["pos_rms_m"] is None else
                             f"{r['pos_rms_m'] * 100:.2f}/{r['pos_max_m'] * 100:.2f}/{r['yaw_rms_deg']:.3f}".rjust(20))
            b1, b2 = cr.get(f"pos_rms{cal}_m"), cr.get(f"pos_rms_2cam{cal}_m")
            lines.append(f"{d:>3} {det['rate']:5.0%} {cr.get('sigma_px', math.nan):6.3f} "
                         f"{(b1 or math.nan) * 100:6.2f} {(b2 or math.nan) * 100:6.2f} " + " ".join(cells))
    return "\n".join(lines)
