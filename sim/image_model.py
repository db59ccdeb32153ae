"""The simulator's image model: every realism knob of SPEC.md with its default.

Defaults (quote them beside every figure; `ImageModel().describe()` prints them on one line):
- supersample = 4: anti-aliasing, 4x4 = 16 samples per pixel (rank-1 lattice, box pixel filter),
  taken ONLY at pixels crossed by an edge (face, silhouette, tag cell); other pixels are exact.
- blur_sigma = 0.6 px: Gaussian optical blur (lens + demosaicing), whole frame.
- noise_sigma = 3.0 grey levels: additive Gaussian sensor noise, independent per pixel and frame.
- jpeg_quality = 90: JPEG compression of the RSU stream (0 = off).
- exposure = 0.004 s: motion blur of each moving vehicle over its displacement during the exposure
  (speed x exposure, projected into the image); 0 = off. Static scenery is not blurred.
- tag_black = 30, tag_white = 215 grey levels: printed black and white of the tag as the camera sees
  them at gain 1 (tag contrast); roof and body are shaded by a fixed sun.
- gain = 1.0: global illumination/exposure gain applied to the whole scene (clipped at 255).
- calib_rot_sigma_deg = 0.05 deg, calib_trans_sigma = 0.02 m: RSU extrinsic calibration error
  (per axis). Not used for rendering: studies hand `perturb_camera(camera, model, rng)` to the
  solver in place of the true camera.
- Lens distortion is the camera's own `dist` (OpenCV model), rendered exactly.
"""
from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.camera import Camera
from toptag.geometry import rodrigues


class ImageModel(BaseModel):
    """Image realism parameters; see the module docstring for every default."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    supersample: int = Field(default=4, ge=1, le=16,
                             description="samples per axis at edge pixels (4 -> 16 per pixel); default 4")
    blur_sigma: float = Field(default=0.6, ge=0.0, description="Gaussian blur sigma, px; default 0.6")
    noise_sigma: float = Field(default=3.0, ge=0.0, description="sensor noise sigma, grey levels; default 3")
    jpeg_quality: int = Field(default=90, ge=0, le=100, description="JPEG quality, 0 = off; default 90")
    exposure: float = Field(default=0.004, ge=0.0, description="exposure time for motion blur, s; default 0.004")
    tag_black: float = Field(default=30.0, ge=0.0, le=255.0, description="printed black, grey level; default 30")
    tag_white: float = Field(default=215.0, ge=0.0, le=255.0, description="printed white, grey level; default 215")
    gain: float = Field(default=1.0, gt=0.0, description="global illumination gain; default 1.0")
    calib_rot_sigma_deg: float = Field(default=0.05, ge=0.0,
                                       description="RSU rotation calibration error per axis, deg; default 0.05")
    calib_trans_sigma: float = Field(default=0.02, ge=0.0,
                                     description="RSU position calibration error per axis, m; default 0.02")

    @classmethod
    def ideal(cls, **overrides) -> "ImageModel":
        """Anti-aliased geometry only: no blur, noise, JPEG, motion blur or calibration error."""
        base = dict(blur_sigma=0.0, noise_sigma=0.0, jpeg_quality=0, exposure=0.0,
                    calib_rot_sigma_deg=0.0, calib_trans_sigma=0.0)
        base.update(overrides)
        return cls(**base)

    def describe(self) -> str:
        """One line stating the model, to print beside a figure."""
        jpeg = f"JPEG q{self.jpeg_quality}" if self.jpeg_quality else "no JPEG"
        return (f"AA {self.supersample}x{self.supersample} at edges, blur {self.blur_sigma:g} px, "
                f"noise {self.noise_sigma:g} GL, {jpeg}, exposure {self.exposure * 1e3:g} ms, "
                f"tag {self.tag_black:g}/{self.tag_white:g} GL, gain {self.gain:g}, "
                f"calib error {self.calib_rot_sigma_deg:g} deg / {self.calib_trans_sigma * 100:g} cm, "
                f"lens distortion from the camera")


def perturb_camera(camera: Camera, model: ImageModel, rng: np.random.Generator | None = None) -> Camera:
    """The camera as a slightly wrong calibration would describe it: rotation error (rad per axis
    sigma = calib_rot_sigma_deg, about the camera axes) and camera-centre error (calib_trans_sigma
    per world axis). Intrinsics and distortion are kept."""
    rng = np.random.default_rng() if rng is None else rng
    drot = rng.normal(0.0, np.deg2rad(model.calib_rot_sigma_deg), 3)
    dpos = rng.normal(0.0, model.calib_trans_sigma, 3)
    R = rodrigues(drot) @ camera.R
    c = camera.center + dpos
    return camera.with_extrinsics(R, -R @ c)
