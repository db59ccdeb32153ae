"""One sample of the paper study, run in a worker process: render a random scene, detect once per RSU
(the RSU's own pipeline), solve with every solver, with the true and with miscalibrated cameras."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from sim.image_model import ImageModel, perturb_camera
from sim.render import render
from sim.sampling import horizontal_distance, plates_in_view, sector_pose
from sim.scene import bundled_vehicle, rsu_camera
from sim.studies.paper_bounds import calibration_sigmas
from sim.studies.paper_setup import CASES, DISTANCES, NEIGHBOURS, PRIMARY, SOLVERS, VEHICLE
from toptag.calibration.extrinsics import perturbed
from toptag.camera import Camera
from toptag.detection import TagObservation
from toptag.geometry import vehicle_to_world, wrap_angle
from toptag.solvers import Limits, solve
from toptag.vehicle import Vehicle

_WORKER: dict = {}


def worker_init() -> None:
    import cv2

    cv2.setNumThreads(1)
    _WORKER.clear()


def _pipeline(camera: Camera):
    from toptag.rsu.pipeline import PipelineSettings, RsuPipeline

    key = (camera.id, camera.width, camera.height)
    if key not in _WORKER:
        p = RsuPipeline(camera, PipelineSettings(tracking=False, workers=1))
        p.add_vehicle(bundled_vehicle(VEHICLE))
        _WORKER[key] = p
    return _WORKER[key]


def sample_rng(seed: int, case: str, index: int) -> np.random.Generator:
    """Each sample's own stream: results do not depend on the workers or on which cases run."""
    return np.random.default_rng(np.random.SeedSequence([seed, list(CASES).index(case), index]))


def _detect(camera: Camera, image: np.ndarray, vehicle: Vehicle) -> list[TagObservation]:
    return _pipeline(camera).process(image, 0).vehicles[vehicle.id].observations


def _solve_all(vehicle: Vehicle, obs1: list, obs2: list, cams: dict[str, Camera], truth,
               calib: tuple[float, float] | None, sigma_h: float) -> dict:
    """Every solver on the observations, the observations' cameras replaced by `cams` (by RSU id).
    calib: the extrinsic uncertainty the calibration-aware solvers are told (None: known exactly);
    sigma_h: the roof-height sigma the principled solvers are told (the paper's are not told anything).
    Per solver: None (no pose) or (position error m, |yaw error| deg, cameras used)."""
    def recam(obs):
        return [dataclasses.replace(o, camera=cams[o.camera.id]) for o in obs]

    limits = Limits(max_position_sigma_m=math.inf)
    told = {"calib_rot_sigma": calib[0], "calib_trans_sigma": calib[1]} if calib else {}
    out = {}
    for key, spec in SOLVERS.items():
        obs = recam(obs1 + obs2 if spec.two_cameras else obs1)
        if not obs:
            out[key] = None
            continue
        if spec.weighting == "principled":  # told the roof-height and calibration sigmas
            s = solve(vehicle, obs, spec.method, weighting="principled", sigma_h=sigma_h, limits=limits, **told)
        else:
            s = solve(vehicle, obs, spec.method, weighting=spec.weighting, limits=limits)
        if not s.ok:
            out[key] = None
            continue
        out[key] = (float(math.hypot(s.x - truth.x, s.y - truth.y)),
                    float(math.degrees(abs(wrap_angle(s.yaw - truth.yaw)))), len(s.cameras))
    return out


def run_sample(task: tuple) -> dict:
    """One random scene of one case: render, detect once per RSU, solve with every solver, with the
    true and with the miscalibrated cameras; corner errors for the noise measurement."""
    case_name, index, seed, model_json, speed_max, calib_errors = task
    case = CASES[case_name]
    model = ImageModel.model_validate_json(model_json)
    rng = sample_rng(seed, case_name, index)
    vehicle = bundled_vehicle(VEHICLE)
    cam1 = rsu_camera(PRIMARY, case.width, case.height)
    bin_m = DISTANCES[index % len(DISTANCES)]
    pv = None
    while pv is None:
        distance = bin_m + rng.uniform(-0.5, 0.5)
        dz = rng.uniform(-case.bounce, case.bounce) if case.bounce > 0 else 0.0
        pv = sector_pose(rng, cam1, vehicle, distance, roof_dz=dz)
    pv.speed = float(rng.uniform(0.0, speed_max))
    seeing = [c for c in (rsu_camera(n, case.width, case.height) for n in NEIGHBOURS) if plates_in_view(c, pv)]
    cam2 = min(seeing, key=lambda c: horizontal_distance(c, pv.x, pv.y)) if seeing else None

    t0 = time.perf_counter()
    obs = {}
    for cam in [cam1] + ([cam2] if cam2 is not None else []):
        obs[cam.id] = _detect(cam, render(cam, [pv], model=model, rng=rng), vehicle)
    obs1, obs2 = obs[cam1.id], (obs[cam2.id] if cam2 is not None else [])

    # (distance to the camera, true ideal corners (4, 2), detected - true (4, 2), camera id, tag id)
    corner_errors = []
    for cam in [cam1] + ([cam2] if cam2 is not None else []):
        d = horizontal_distance(cam, pv.x, pv.y)
        for o in obs[cam.id]:
            true_px = cam.project(vehicle_to_world(vehicle.tag_corners(o.tag_id), pv.x, pv.y, pv.yaw, pv.roof_z),
                                  distort=False)
            corner_errors.append((d, true_px.tolist(), (np.asarray(o.corners) - true_px).tolist(), cam.id,
                                  int(o.tag_id)))

    cams_true = {c.id: c for c in (cam1, cam2) if c is not None}
    if calib_errors is None:  # the image model's assumed error
        cams_bad = {cid: perturb_camera(c, model, rng) for cid, c in cams_true.items()}
        calib = calibration_sigmas(model)
    else:  # one of the calibrations the procedure left for each RSU
        pool = calib_errors["deltas"]
        pick = int(rng.integers(1 << 30))
        cams_bad = {cid: perturbed(c, pool[cid][(pick + k) % len(pool[cid])]) for k, (cid, c) in enumerate(cams_true.items())}
        calib = tuple(calib_errors["sigmas"])
    return {
        "case": case_name, "index": index, "bin": bin_m, "distance": horizontal_distance(cam1, pv.x, pv.y),
        "pose": (pv.x, pv.y, pv.yaw, pv.roof_z), "speed": pv.speed,
        "second": cam2.id[4:] if cam2 is not None else None,
        "distance2": horizontal_distance(cam2, pv.x, pv.y) if cam2 is not None else None,
        "tags1": sorted(o.tag_id for o in obs1), "tags2": sorted(o.tag_id for o in obs2),
        "corner_errors": corner_errors,
        "known": _solve_all(vehicle, obs1, obs2, cams_true, pv, None, case.sigma_h),
        "miscalibrated": _solve_all(vehicle, obs1, obs2, cams_bad, pv, calib, case.sigma_h),
        "calib_sigmas": calib,
        "seconds": time.perf_counter() - t0,
    }
