"""The paper study's bounds: the corner noise measured per case and distance, and each sample's
Cramér–Rao bound under it (sim.studies.paper_models holds the models)."""
from __future__ import annotations

import math

import numpy as np

from sim.image_model import ImageModel
from sim.scene import bundled_vehicle, rsu_camera
from sim.studies.paper_models import EdgeNoise, measure_noise, noise_at, outlier_flags, pose_bound
from sim.studies.paper_setup import PRIMARY, VEHICLE, Case
from toptag.solvers import position_crlb

def calibration_sigmas(model: ImageModel) -> tuple[float, float] | None:
    """(rotation sigma rad, centre sigma m) of the model's RSU calibration error, None if it has none."""
    cal = (math.radians(model.calib_rot_sigma_deg), model.calib_trans_sigma)
    return cal if min(cal) > 0 else None


def case_noise(samples: list[dict]) -> dict[int, EdgeNoise]:
    """The corner noise per whole-metre distance from the observing camera (paper_models.measure_noise).
    Marks every sample's failed detections (paper_models.outlier_flags) in s["outlier_tags"]: the bound
    is the limit given the tags that were detected correctly."""
    by_bin: dict[int, list] = {}
    flat = []
    for s in samples:
        s["outlier_tags"] = []
        for d, true_px, err, cam_id, tag_id in s["corner_errors"]:
            tag = (np.asarray(true_px), np.asarray(err))
            by_bin.setdefault(int(round(d)), []).append(tag)
            flat.append((s, cam_id, tag_id, tag))
    for (s, cam_id, tag_id, _), bad in zip(flat, outlier_flags([f[3] for f in flat])):
        if bad:
            s["outlier_tags"].append((cam_id, tag_id))
    return measure_noise(by_bin)


def sample_bounds(s: dict, case: Case, noise: dict[int, EdgeNoise], model: ImageModel) -> dict:
    """One sample's bounds (position RMS m, yaw RMS rad): "1cam" / "2cam" (edge noise model), the same
    with calibration error ("_calib"), and "1cam_iid" (position_crlb with the pooled sigma)."""
    vehicle = bundled_vehicle(VEHICLE)
    cam1 = rsu_camera(PRIMARY, case.width, case.height)
    bad = {tuple(t) for t in s.get("outlier_tags", [])}
    tags1 = [t for t in s["tags1"] if (cam1.id, t) not in bad]
    n1 = noise_at(noise, s["distance"])
    v1 = [(cam1, tags1, n1)]
    v2 = list(v1)
    if s["second"] is not None and s["tags2"]:
        cam2 = rsu_camera(s["second"], case.width, case.height)
        tags2 = [t for t in s["tags2"] if (cam2.id, t) not in bad]
        v2.append((cam2, tags2, noise_at(noise, s["distance2"])))
    calib = tuple(s["calib_sigmas"]) if s.get("calib_sigmas") else calibration_sigmas(model)
    out = {}
    if tags1:
        c = position_crlb(vehicle, [(cam1, tags1)], s["pose"], n1.sigma_px, case.sigma_h)
        out["1cam_iid"] = (c.position_rms, c.yaw_rms)
        out["1cam"] = pose_bound(vehicle, v1, s["pose"], case.sigma_h)
        out["1cam_calib"] = pose_bound(vehicle, v1, s["pose"], case.sigma_h, calib) if calib else out["1cam"]
    if any(len(ids) for _, ids, _ in v2):
        out["2cam"] = pose_bound(vehicle, v2, s["pose"], case.sigma_h)
        out["2cam_calib"] = pose_bound(vehicle, v2, s["pose"], case.sigma_h, calib) if calib else out["2cam"]
    return out
