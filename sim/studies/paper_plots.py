"""Figures of `toptag eval paper` (sim.studies.paper), drawn from its results.json dictionary.

paper_<case>.png: the paper's form (position RMS and orientation RMS against distance, one line per
solver) plus the maximum position error and every solver's ratio to the Cramér–Rao bound, with the
paper's quoted bounds drawn for comparison and the image model in the footer.
paper_calibration.png: the S.Opt. variants with known and with miscalibrated extrinsics.
"""
from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

STYLE = {
    "bas": dict(color="tab:orange", marker="s"),
    "hopt": dict(color="tab:green", marker="^"),
    "sopt": dict(color="tab:blue", marker="o"),
    "sopt_principled": dict(color="tab:purple", marker="D"),
    "sopt_level": dict(color="tab:brown", marker="P"),
    "sopt_2cam": dict(color="tab:red", marker="v"),
    "sopt_level_2cam": dict(color="black", marker="X"),
}
CASE_TITLES = {"low_flat": "960×720, no height disturbance", "low_bounce": "960×720, roof height ±10 cm",
               "high_bounce": "3200×2400, roof height ±10 cm"}


def _series(sec: dict, field: str):
    xs, ys = [], []
    for d, r in sec.items():
        if r.get(field) is not None:
            xs.append(int(d))
            ys.append(r[field])
    return xs, ys


def _footer(results: dict, extra: str = "") -> str:
    im = results["image_model"]["describe"]
    text = (f"Image model: {im}. {results['sampling']}. {results['samples_per_case']} samples per case, "
            f"seed {results['seed']}. {extra}Command: {results['command']}")
    return "\n".join(textwrap.wrap(text, 190))


def _claims_for(results: dict, case: str):
    """(panel field, value, label) of the paper's quoted bounds to draw on this case's figure."""
    out = []
    for c in results["paper_claims"].values():
        if c["case"] == case or (case == "high_bounce" and c["case"] == "low_bounce"):
            who = "S.Opt." if c["solver"] == "sopt" else "Bas."
            res = "" if c["case"] == case else " (960×720)"
            for field, unit, scale in (("pos_rms_m", "cm", 100), ("pos_max_m", "cm", 100), ("yaw_rms_deg", "°", 1)):
                if field in c:
                    v = c[field]
                    out.append((field, v, f"paper{res}: {who} < {v * scale:g} {unit} at {c['distance']} m"))
    return out


def case_figure(results: dict, case: str, path: Path) -> None:
    sec = results["cases"][case]
    cr = results["crlb"][case]
    fig, axes = plt.subplots(2, 2, figsize=(15.5, 9.4))
    panels = [(axes[0, 0], "pos_rms_m", "position RMS error (m)"),
              (axes[0, 1], "pos_max_m", "position maximum error (m)"),
              (axes[1, 0], "yaw_rms_deg", "orientation (yaw) RMS error (°)"),
              (axes[1, 1], "crlb_ratio", "position RMS / Cramér–Rao bound")]
    for ax, field, ylabel in panels:
        for key, r in sec.items():
            xs, ys = _series(r, field)
            if xs:
                # H.Opt. drawn wide: in low_flat the principled solvers, told the height, lie on it.
                ax.plot(xs, ys, label=results["solvers"][key]["label"], lw=3.2 if key == "hopt" else 1.6,
                        ms=5 if key == "hopt" else 4, **STYLE.get(key, {}))
        if field in ("pos_rms_m", "yaw_rms_deg"):
            unit = "m" if field == "pos_rms_m" else "deg"
            base = "pos_rms" if field == "pos_rms_m" else "yaw_rms"
            xs, ys = _series(cr, f"{base}_{unit}")
            ax.plot(xs, ys, color="0.15", ls="--", lw=2.2, alpha=0.8, label="Cramér–Rao bound, 1 RSU")
            xs, ys = _series(cr, f"{base}_2cam_{unit}")
            ax.plot(xs, ys, color="0.15", ls=":", lw=2.2, alpha=0.8, label="Cramér–Rao bound, 2 RSUs")
            xs, ys = _series(cr, f"{base}_iid_{unit}")
            ax.plot(xs, ys, color="0.6", ls="--", lw=1.0, label="bound with i.i.d. corner noise (1 RSU)")
        for f, v, label in _claims_for(results, case):
            if f == field:
                ax.axhline(v, color="0.35", ls="-.", lw=1.2)
                ax.plot([16], [v], marker="v", color="0.2", ms=9, ls="none", label=label)
        if field == "crlb_ratio":
            ax.axhline(1.0, color="k", lw=1.0)
            ax.axhline(1.5, color="0.4", ls="--", lw=1.0, label="1.5 × bound")
        ax.set_yscale("log")
        ax.set_xlabel("horizontal distance bus–RSU (m, whole-metre bins)")
        ax.set_ylabel(ylabel)
        ax.set_xticks(results["distances_m"])
        ax.grid(True, which="both", alpha=0.3)
    handles = {}
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, h)
    fig.legend(list(handles.values()), list(handles), loc="center right", fontsize=8.5, frameon=False)
    det = results["detection"][case]
    n = sum(v["n"] for v in det.values())
    found = sum(v["found"] for v in det.values())
    fig.suptitle(f"toptag eval paper — {case}: {CASE_TITLES.get(case, case)}; RSU extrinsics known "
                 f"(paper's setting); tags found in {found}/{n} images", fontsize=12)
    fig.text(0.01, 0.005, _footer(results, "Here the solvers know the RSU extrinsics exactly; the model's "
                                             "calibration error is studied in paper_calibration.png. "),
             fontsize=7, va="bottom", family="monospace")
    fig.tight_layout(rect=(0, 0.07, 0.8, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def calibration_figure(results: dict, path: Path) -> None:
    cases = list(results["calibration"])
    fig, axes = plt.subplots(1, len(cases), figsize=(5.0 * len(cases) + 2.6, 5.6), squeeze=False)
    for ax, case in zip(axes[0], cases):
        for key in ("sopt", "sopt_principled", "sopt_level", "sopt_2cam", "sopt_level_2cam"):
            xs, ys = _series(results["calibration"][case][key], "pos_rms_m")
            ax.plot(xs, ys, lw=1.6, ms=4, label=results["solvers"][key]["label"], **STYLE[key])
        cr = results["crlb"][case]
        xs, ys = _series(cr, "pos_rms_calib_m")
        ax.plot(xs, ys, color="0.15", ls="--", lw=2.2, alpha=0.8, label="bound incl. calibration, 1 RSU")
        xs, ys = _series(cr, "pos_rms_2cam_calib_m")
        ax.plot(xs, ys, color="0.15", ls=":", lw=2.2, alpha=0.8, label="bound incl. calibration, 2 RSUs")
        xs, ys = _series(results["cases"][case]["sopt_level"], "pos_rms_m")
        ax.plot(xs, ys, color="tab:brown", lw=1.0, alpha=0.5, label="S.Opt. level, extrinsics known")
        ax.axhline(0.03, color="0.4", ls="-.", lw=1.0, label="3 cm (target at 16 m)")
        ax.set_yscale("log")
        ax.set_title(f"{case}: {CASE_TITLES.get(case, case)}", fontsize=10)
        ax.set_xlabel("horizontal distance bus–RSU (m)")
        ax.set_ylabel("position RMS error (m)")
        ax.set_xticks(results["distances_m"][::3])
        ax.grid(True, which="both", alpha=0.3)
    h, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, labels, loc="center right", fontsize=8.5, frameon=False)
    im = results["image_model"]
    proc = results.get("calibration_procedure")
    if proc:
        maps = ", ".join(f"{k} {100 * v:.2f}" for k, v in proc["roof_mapping_rms_m"].items())
        what = (f"the extrinsics toptag calibrate leaves (8 surveyed ground plates, {proc['calibrations_per_camera']} "
                f"calibrations per RSU; roof mapping error RMS {maps} cm)")
    else:
        what = (f"RSU calibration error ({im['calib_rot_sigma_deg']:g}° rotation and "
                f"{im['calib_trans_sigma'] * 100:g} cm position per axis, one draw per RSU and sample)")
    fig.suptitle(f"With {what}: the same images, solved with the miscalibrated cameras", fontsize=10.5)
    fig.text(0.01, 0.005, _footer(results), fontsize=6.5, va="bottom", family="monospace")
    fig.tight_layout(rect=(0, 0.1, 1 - 2.5 / (5.0 * len(cases) + 2.6), 0.92))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_figures(results: dict, out: Path) -> list[str]:
    names = []
    for case in results["cases"]:
        name = f"paper_{case}.png"
        case_figure(results, case, out / name)
        names.append(name)
    calibration_figure(results, out / "paper_calibration.png")
    names.append("paper_calibration.png")
    return names


# ---- tables (Markdown) --------------------------------------------------------------------------------
def _cell(r: dict, ratio: bool = False) -> str:
    if r.get("pos_rms_m") is None:
        return "–"
    text = f"{r['pos_rms_m'] * 100:.2f} / {r['pos_max_m'] * 100:.2f} / {r['yaw_rms_deg']:.3f}"
    if ratio and r.get("crlb_ratio") is not None:
        text += f" (×{r['crlb_ratio']:.2f})"
    if r["detected"] < r["n"]:
        text += f" [{r['detected']}/{r['n']}]"
    return text


def markdown_tables(results: dict) -> str:
    """Per case and distance: every solver's position RMS / max (cm) / yaw RMS (°), the RSU's detection
    rate, the measured corner noise and the Cramér–Rao bound, the study's solvers as a ratio to it; then
    the same with calibration error for the S.Opt. variants."""
    out = []
    names = {k: v["label"] for k, v in results["solvers"].items()}
    for case, sec in results["cases"].items():
        keys = list(sec)
        out.append(f"\n#### {case}: {CASE_TITLES.get(case, case)}, extrinsics known\n")
        out.append("Cells: position RMS / max (cm) / yaw RMS (°); (×n) = RMS over the Cramér–Rao bound of the "
                   "same samples (one or two RSUs); [k/n] = poses returned when fewer than the images.\n")
        out.append("| m | tags found | corner σ (px) | bound 1 / 2 RSUs (cm) | "
                   + " | ".join(names[k] for k in keys) + " | best 1-RSU solver (×bound) |")
        out.append("|" + "---|" * (len(keys) + 5))
        for d in sec[keys[0]]:
            det = results["detection"][case][d]
            cr = results["crlb"][case][d]
            cells = [_cell(sec[k][d], ratio=k.startswith("sopt_level")) for k in keys]
            best = cr.get("best_solver")
            best_text = f"{names[best]} (×{cr['best_ratio']:.2f})" if best and cr.get("best_ratio") else "–"
            out.append(f"| {d} | {det['found']}/{det['n']} | {cr.get('sigma_px', float('nan')):.3f} | "
                       f"{cr['pos_rms_m'] * 100:.3f} / {cr['pos_rms_2cam_m'] * 100:.3f} | " + " | ".join(cells)
                       + f" | {best_text} |")
    keys = ["sopt", "sopt_principled", "sopt_level", "sopt_2cam", "sopt_level_2cam"]
    which = ("with the extrinsics toptag calibrate leaves" if results.get("calibration_procedure")
             else "with the image model's calibration error")
    for case, sec in results["calibration"].items():
        out.append(f"\n#### {case}: {CASE_TITLES.get(case, case)}, {which}\n")
        out.append("| m | bound incl. calibration 1 / 2 RSUs (cm) | " + " | ".join(names[k] for k in keys) + " |")
        out.append("|" + "---|" * (len(keys) + 2))
        for d in sec[keys[0]]:
            cr = results["crlb"][case][d]
            cells = [_cell(sec[k][d], ratio=True) for k in keys]
            out.append(f"| {d} | {cr['pos_rms_calib_m'] * 100:.2f} / {cr['pos_rms_2cam_calib_m'] * 100:.2f} | "
                       + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"
