"""`toptag eval livefix`: the live RSU pipeline's fix errors per RSU on the simulator's frames, fault-free.

    toptag eval livefix [--scenario FILE] [--bus BUS] [--seconds S] [--every-ms MS] [--out DIR]

Plays the scenario (default: the bundled demo) from its start; every `--every-ms` while the bus has a tag
in an RSU's view, renders that RSU's frame (the scenario's image model) and runs it through
`toptag.rsu.pipeline.RsuPipeline` as the RSU service does (tracking from its own previous fixes), then
compares the fix with the truth at the frame's time. Per RSU: the mean error (x, y in cm, yaw in deg:
the bias a drift detector must not mistake for a turned camera), its spread, and the mean reported
sigma (how honest the covariance is). Use it to choose `[filter] drift_min_pos_m` / `drift_min_yaw_deg`
for a bus on this pipeline (docs/time-and-trust.md). Writes DIR/results.json when --out is given.
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
from toptag.progress import Progress
from toptag.rsu.pipeline import RsuPipeline
from toptag.units import NS_PER_MS, NS_PER_S


def run(scenario_path: Path, bus: str, seconds: float, every_ms: float) -> dict:
    world = World(load_scenario(scenario_path))
    world.start(0)
    if bus not in {b.vehicle.id for b in world.buses}:
        raise InputError(f"--bus {bus}: not in the scenario (buses: {', '.join(b.vehicle.id for b in world.buses)})")
    ticks = range(0, int(min(world.legs_end_ns, seconds * NS_PER_S)), int(every_ms * NS_PER_MS))
    out = {}
    bar = Progress(len(world.rsu_ids) * len(ticks), "toptag eval livefix")
    for rsu in world.rsu_ids:
        pipe = RsuPipeline(world.camera(rsu))
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
            sd = np.sqrt(np.diag(f.cov))
            rows.append([100 * (f.x - st.x), 100 * (f.y - st.y), math.degrees(math.remainder(f.yaw - st.yaw, 2 * math.pi)),
                         100 * sd[0], 100 * sd[1], math.degrees(sd[2])])
        e = np.asarray(rows).reshape(-1, 6)
        out[rsu] = {"fixes": len(rows)} if not rows else {
            "fixes": len(rows), "mean_cm_deg": e[:, :3].mean(0).round(3).tolist(),
            "bias_cm": round(float(math.hypot(*e[:, :2].mean(0))), 2),
            "std_cm_deg": e[:, :3].std(0).round(3).tolist(), "reported_sigma_cm_deg": e[:, 3:].mean(0).round(3).tolist()}
    bar.close()
    return {"scenario": str(scenario_path), "bus": bus, "seconds": seconds, "every_ms": every_ms,
            "image_model": world.model.model_dump() if hasattr(world.model, "model_dump") else str(world.model),
            "rsus": out}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="toptag eval livefix", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", type=Path, default=None, help="scenario file (default: the bundled demo)")
    p.add_argument("--bus", default="bus-17")
    p.add_argument("--seconds", type=float, default=60.0, help="scenario seconds to play (default 60)")
    p.add_argument("--every-ms", type=float, default=100.0, help="one frame per RSU this often (default 100)")
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    try:
        res = run(a.scenario or bundled_scenario_path(), a.bus, a.seconds, a.every_ms)
    except InputError as e:
        return report("eval livefix", e)
    res["command"] = " ".join(["toptag eval livefix"] + list(sys.argv[1:] if argv is None else argv))
    for rsu, r in res["rsus"].items():
        if r["fixes"] == 0:
            print(f"{rsu}: no fixes")
            continue
        m, s, q = r["mean_cm_deg"], r["std_cm_deg"], r["reported_sigma_cm_deg"]
        print(f"{rsu}: {r['fixes']} fixes; mean error x {m[0]:+.1f} cm y {m[1]:+.1f} cm yaw {m[2]:+.2f} deg "
              f"(bias {r['bias_cm']:.1f} cm); spread {s[0]:.1f} / {s[1]:.1f} cm, {s[2]:.2f} deg; "
              f"reported sigma {q[0]:.1f} / {q[1]:.1f} cm, {q[2]:.2f} deg")
    if a.out:
        print(f"wrote {write_results(a.out, res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
