"""The simulator's image model: every realism knob of SPEC.md with its default.

The defaults are calibrated to real cameras (`toptag eval imagemodel`, docs/image-model.md): rendered
tags of 45-110 px give the corner errors of real photographs of tags that size (median and 95th
percentile within ±30 %, and the same inward bias of AprilTag's edges). Quote the model beside every
figure; `ImageModel().describe()` prints it on one line:
- supersample = 4: anti-aliasing, 4x4 = 16 samples per pixel (rank-1 lattice, box pixel filter),
  taken ONLY at pixels crossed by an edge (face, silhouette, tag cell); other pixels are exact.
- blur_sigma = 0.5 px and defocus_px = 0.7 px: Gaussian optical blur (lens + demosaicing) and a
  defocus disc, whole frame, both in linear light;
- gamma = 2.2: the camera stores light^(1/gamma) (blur in linear light, stored gamma-encoded: this
  puts AprilTag's detected edges inside the black square, as on real cameras);
- vignetting = 0.3: light falls off to 70 % at the image corners;
- noise_sigma = 7 grey levels: additive Gaussian sensor noise, independent per pixel and frame.
- codec = "h264", video_qp = 36: each frame as an RSU's H.264 stream at a limited bitrate delivers it
  (an intra frame by x264 at quantizer 36, 4:2:0: about 14 kB for a 960x720 frame, 1.1 Mbit/s at 10 fps;
  "h265" too); codec "jpeg" uses jpeg_quality instead (0 = off).
- readout_s = 0 (global shutter), shadow = 0, glare = 0: rolling shutter, a shadow edge across the
  roof and a specular highlight on it, off by default (the calibration photographs have none; each is
  a parameter for studies: docs/image-model.md measures their effect).
- exposure = 0.004 s: motion blur of each moving vehicle over its displacement during the exposure
  (speed x exposure, projected into the image); 0 = off. Static scenery is not blurred.
- tag_black = 45, tag_white = 160 grey levels: printed black and white of the tag as the camera sees
  them at gain 1 (tag contrast); roof and body are shaded by a fixed sun.
- gain = 1.0: global illumination/exposure gain applied to the whole scene (clipped at 255).
- calib_rot_sigma_deg = 0.05 deg, calib_trans_sigma = 0.02 m: RSU extrinsic calibration error
  (per axis). Not used for rendering: studies hand `perturb_camera(camera, model, rng)` to the
  solver in place of the true camera.
- Lens distortion is the camera's own `dist` (OpenCV model), rendered exactly.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toptag.camera import Camera
from toptag.geometry import rodrigues


class ImageModel(BaseModel):
    """Image realism parameters; see the module docstring for every default."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    supersample: int = Field(default=4, ge=1, le=16,
                             description="samples per axis at edge pixels (4 -> 16 per pixel); default 4")
    blur_sigma: float = Field(default=0.5, ge=0.0, description="Gaussian blur sigma, px; default 0.5")
    noise_sigma: float = Field(default=7.0, ge=0.0, description="sensor noise sigma, grey levels; default 7")
    jpeg_quality: int = Field(default=90, ge=0, le=100, description="JPEG quality, 0 = off; default 90")
    exposure: float = Field(default=0.004, ge=0.0, description="exposure time for motion blur, s; default 0.004")
    tag_black: float = Field(default=45.0, ge=0.0, le=255.0, description="printed black, grey level; default 45")
    tag_white: float = Field(default=160.0, ge=0.0, le=255.0, description="printed white, grey level; default 160")
    gain: float = Field(default=1.0, gt=0.0, description="global illumination gain; default 1.0")
    gamma: float = Field(default=2.2, ge=1.0, le=3.0,
                         description="encoding gamma: optics blur linear light, the camera stores light^(1/gamma); "
                                     "1 = linear; default 2.2")
    defocus_px: float = Field(default=0.7, ge=0.0, description="defocus: disc (pillbox) blur radius, px; default 0.7")
    vignetting: float = Field(default=0.3, ge=0.0, lt=1.0,
                              description="light fall-off at the image corners (quadratic in radius); default 0.3")
    readout_s: float = Field(default=0.0, ge=0.0,
                             description="rolling shutter: time to read the frame top to bottom, s; 0 = global")
    codec: Literal["jpeg", "h264", "h265"] = Field(
        default="h264", description="stream codec: jpeg (jpeg_quality) or an intra-coded H.264/H.265 frame (video_qp)")
    video_qp: int = Field(default=36, ge=0, le=51,
                          description="x264/x265 quantizer of each (intra) frame: the stream's bitrate limit; default 36")
    shadow: float = Field(default=0.0, ge=0.0, le=1.0,
                          description="a shadow edge across each roof, darkening by this fraction; default 0")
    glare: float = Field(default=0.0, ge=0.0,
                         description="a specular highlight on each roof, peak grey levels added; default 0")
    calib_rot_sigma_deg: float = Field(default=0.05, ge=0.0,
                                       description="RSU rotation calibration error per axis, deg; default 0.05")
    calib_trans_sigma: float = Field(default=0.02, ge=0.0,
                                     description="RSU position calibration error per axis, m; default 0.02")

    @classmethod
    def ideal(cls, **overrides) -> "ImageModel":
        """Anti-aliased geometry only: no blur, noise, JPEG, motion blur or calibration error."""
        base = dict(blur_sigma=0.0, noise_sigma=0.0, jpeg_quality=0, exposure=0.0, gamma=1.0, defocus_px=0.0,
                    vignetting=0.0, readout_s=0.0, codec="jpeg", shadow=0.0, glare=0.0,
                    calib_rot_sigma_deg=0.0, calib_trans_sigma=0.0)
        base.update(overrides)
        return cls(**base)

    def describe(self) -> str:
        """One line stating the model, to print beside a figure."""
        if self.codec != "jpeg":
            codec = f"{self.codec.upper()} intra QP {self.video_qp}"
        else:
            codec = f"JPEG q{self.jpeg_quality}" if self.jpeg_quality else "no JPEG"
        extra = "".join([f", defocus {self.defocus_px:g} px" if self.defocus_px else "",
                         f", vignetting {self.vignetting:g}" if self.vignetting else "",
                         f", rolling shutter {self.readout_s * 1e3:g} ms" if self.readout_s else "",
                         f", roof shadow {self.shadow:g}" if self.shadow else "",
                         f", roof glare {self.glare:g} GL" if self.glare else ""])
        return (f"AA {self.supersample}x{self.supersample} at edges, blur {self.blur_sigma:g} px, gamma {self.gamma:g}"
                f"{extra}, noise {self.noise_sigma:g} GL, {codec}, exposure {self.exposure * 1e3:g} ms, "
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
