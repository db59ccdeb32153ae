"""`toptag sim examples`: rendered RSU images with ground truth, for `toptag locate` and its tests.

Each image shows the double-tag bus at a random pose 5-20 m from the RSU, with the default image
model (blur, noise, JPEG, motion blur), a random roof-height bounce, and now and then a second tagged
bus or a truck hiding part of the roof. Writes camera.json, the vehicle files, the images and truth.json."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sim.image_model import ImageModel
from sim.render import render_jpeg
from sim.sampling import occluding_truck, second_bus, sector_pose
from sim.scene import bundled_vehicle, rsu_camera

EXAMPLE_DIST = [-0.12, 0.03, 0.0005, -0.0003, 0.0]  # a mild barrel lens, as real RSU cameras have


def write_examples(out: Path, count: int, width: int = 960, height: int = 720, seed: int = 0,
                   bounce: float = 0.10, model: ImageModel | None = None, prefix: str = "frame") -> list[dict]:
    """Render `count` images into `out`; returns the truth records (also written to truth.json)."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    camera = rsu_camera("sw", width, height, dist=EXAMPLE_DIST)
    bus, other = bundled_vehicle("bus_double"), bundled_vehicle("bus_second")
    cam_file = out / f"rsu-sw-{width}x{height}.json"
    cam_file.write_text(camera.to_model().model_dump_json(indent=1))
    for v in (bus, other):
        (out / f"{v.id}.json").write_text(json.dumps(v.to_dict(), indent=1))
    truth = []
    for i in range(count):
        distance = 5.0 + 15.0 * (i + rng.uniform()) / count
        pv = None
        while pv is None:
            pv = sector_pose(rng, camera, bus, distance, roof_dz=rng.uniform(-bounce, bounce))
        pv.speed = rng.uniform(0, 8.0)
        extras, occluders, note = [], [], "clear view"
        if i % 3 == 1:
            b2 = second_bus(rng, camera, other, [pv])
            if b2 is not None:
                extras, note = [b2], f"second tagged bus {other.id} in view"
        elif i % 3 == 2:
            truck = occluding_truck(rng, camera, pv)
            if truck is not None:
                occluders, note = [truck], "truck hides part of the roof"
        name = f"{prefix}-{width}x{height}-{i:02d}.jpg"
        (out / name).write_bytes(render_jpeg(camera, [pv] + extras, occluders, model, rng))
        truth.append({"image": name, "x": pv.x, "y": pv.y, "yaw": pv.yaw, "z": pv.roof_z,
                      "distance_m": round(distance, 2), "scene": note})
    (out / f"truth-{width}x{height}.json").write_text(json.dumps(truth, indent=1))
    return truth


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag sim examples", description=__doc__)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--count", type=int, default=6)
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    truth = write_examples(args.out, args.count, args.width, args.height, args.seed)
    for t in truth:
        print(f"{t['image']}: bus at {t['distance_m']:.1f} m, {t['scene']}")
    return 0
