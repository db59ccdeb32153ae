"""Per-camera rasterisation state of the renderer, computed once per camera and cached.

- The exact undistorted normalized coordinates (x/z, y/z) of every pixel centre (the camera's lens
  model inverted by Newton to ~1e-12), from which every ray of the frame is taken.
- The static background: asphalt and pavement with texture, lane marks, zebra crossings and stop
  lines of SPEC's intersection (roads along world x and y, 4 lanes of 3.7 m), box-filtered per pixel
  (analytic coverage of every mark over the pixel's ground footprint: no aliasing, no supersampling).
- The blurred, gain-applied uint8 background per (blur, gain) and a bank of sensor noise samples.
"""
from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from sim.scene import LANE_WIDTH, ROAD_HALF_WIDTH
from toptag.camera import Camera
from toptag.lens import distort_normalized, undistort_normalized

# Ground radiance, grey levels before the illumination gain.
ASPHALT = 92.0
PAVEMENT = 138.0
PAINT = 200.0
SKY = 185.0
MAX_GROUND_RANGE = 400.0

# Road marks (m), in road coordinates a (along the road, from the intersection centre) and b (across).
EDGE_LINE = (ROAD_HALF_WIDTH - 0.35, ROAD_HALF_WIDTH - 0.2)
CENTRE_LINES = (0.06, 0.18)  # double centre line, |b| in this interval
DIVIDER_HALF = 0.075
DASH_ON, DASH_PERIOD = 3.0, 9.0
ZEBRA = (ROAD_HALF_WIDTH + 1.0, ROAD_HALF_WIDTH + 4.0)  # |a| span of the crossing
ZEBRA_STRIPE, ZEBRA_PERIOD = 0.5, 1.0
STOP_LINE = (ROAD_HALF_WIDTH + 4.6, ROAD_HALF_WIDTH + 5.0)

_CACHE: "OrderedDict[tuple, CameraRaster]" = OrderedDict()
CACHE_BYTES = 1_200_000_000  # about ten 3200x2400 cameras (115 MB each) or any number of small ones


def camera_key(camera: Camera) -> tuple:
    return (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), camera.R.tobytes(),
            camera.t.tobytes())


NOISE_BANK_EXTRA = 1 << 20  # distinct noise fields per camera (offsets into the bank)
NOISE_BANK_SEED = 0x5EED


def raster_for(camera: Camera) -> "CameraRaster":
    """The cached raster state of a camera (built on first use; least recently used ones are dropped
    beyond CACHE_BYTES)."""
    key = camera_key(camera)
    r = _CACHE.get(key)
    if r is None:
        r = CameraRaster(camera)
        _CACHE[key] = r
        while len(_CACHE) > 1 and sum(c.nbytes for c in _CACHE.values()) > CACHE_BYTES:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(key)
    return r


def _distorted_rows(camera: Camera, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The observed (distorted) normalized coordinates (float64, (len(v), W)) of the pixel centres of rows
    v: Camera.normalized's numbers (the same to the bit, skewed K too), with K's inverse broadcast over the
    grid, because its (N, 2) matrix product takes ~45 ms per 128 rows of a 3200x2400 image against 0.1."""
    Ki = np.linalg.inv(camera.K[:2, :2])
    du = np.arange(camera.width, dtype=float) - camera.K[0, 2]
    dv = v - camera.K[1, 2]
    xd = Ki[0, 0] * du[None, :] + Ki[0, 1] * dv[:, None]
    return xd, np.broadcast_to(Ki[1, 1] * dv[:, None], xd.shape)


def _undistorted_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """float32 (H, W) maps; with distortion: exact on a coarse grid, bicubic in between, then two
    Newton steps at every pixel (residual checked)."""
    H, W = camera.height, camera.width
    if not camera.has_distortion:
        x, y = _distorted_rows(camera, np.arange(H, dtype=float))
        return x.astype(np.float32), y.astype(np.float32)
    step = 16
    uc = np.unique(np.r_[np.arange(0, W, step), W - 1]).astype(float)
    vc = np.unique(np.r_[np.arange(0, H, step), H - 1]).astype(float)
    pix = np.stack(np.meshgrid(uc, vc), axis=-1).reshape(-1, 2)
    nc = camera.normalized(pix).reshape(len(vc), len(uc), 2)
    sx = RectBivariateSpline(vc, uc, nc[..., 0])
    sy = RectBivariateSpline(vc, uc, nc[..., 1])
    u = np.arange(W, dtype=float)
    xs = np.empty((H, W), np.float32)
    ys = np.empty((H, W), np.float32)
    worst = 0.0
    for r0 in range(0, H, 128):
        r1 = min(H, r0 + 128)
        v = np.arange(r0, r1, dtype=float)
        xd, yd = _distorted_rows(camera, v)
        observed = np.column_stack([xd.ravel(), yd.ravel()])
        x = undistort_normalized(observed, np.column_stack([sx(v, u).ravel(), sy(v, u).ravel()]), camera.lens, 2)
        worst = max(worst, float(np.max(np.abs(distort_normalized(x, camera.lens) - observed))))
        xs[r0:r1] = x[:, 0].reshape(xd.shape)
        ys[r0:r1] = x[:, 1].reshape(xd.shape)
    if not worst < 1e-9:
        raise ValueError(f"camera {camera.id}: lens model not invertible over the image (residual {worst:.2g})")
    return xs, ys


# ---- coverage helpers (box filter over the pixel footprint) ------------------------------------
def _interval(c, w, lo, hi):
    """Fraction of [c - w/2, c + w/2] inside [lo, hi]."""
    return (np.clip(c + 0.5 * w, lo, hi) - np.clip(c - 0.5 * w, lo, hi)) / w


def _abs_interval(c, w, lo, hi):
    """Fraction of the pixel interval with |coordinate| in [lo, hi]."""
    return _interval(c, w, lo, hi) + _interval(c, w, -hi, -lo)


def _periodic(c, w, period, on, phase=0.0):
    """Fraction of [c - w/2, c + w/2] where mod(x - phase, period) < on."""
    def F(x):
        x = x - phase
        return np.floor(x / period) * on + np.clip(np.mod(x, period), 0.0, on)

    return (F(c + 0.5 * w) - F(c - 0.5 * w)) / w


def _road_marks(a, b, wa, wb):
    """Paint coverage of one road (along a) at road coordinates; only its arms (|a| > half width)."""
    arm = _abs_interval(a, wa, ROAD_HALF_WIDTH, np.inf)
    edge = _abs_interval(b, wb, *EDGE_LINE)
    centre = _abs_interval(b, wb, *CENTRE_LINES) * _abs_interval(a, wa, STOP_LINE[0], np.inf)
    sa = np.abs(a)
    dash = _periodic(sa, wa, DASH_PERIOD, DASH_ON, STOP_LINE[1]) * _abs_interval(a, wa, STOP_LINE[1], np.inf)
    divider = _abs_interval(b, wb, LANE_WIDTH - DIVIDER_HALF, LANE_WIDTH + DIVIDER_HALF) * dash
    zebra = (_abs_interval(a, wa, *ZEBRA) * _periodic(b, wb, ZEBRA_PERIOD, ZEBRA_STRIPE, 0.25)
             * _abs_interval(b, wb, 0.0, ROAD_HALF_WIDTH - 0.6))
    # Stop line across the incoming half: b has the sign of a (right-hand traffic).
    incoming = np.where(a > 0, _interval(b, wb, 0.25, ROAD_HALF_WIDTH - 0.35),
                        _interval(b, wb, -(ROAD_HALF_WIDTH - 0.35), -0.25))
    stop = _abs_interval(a, wa, *STOP_LINE) * incoming
    return np.minimum(1.0, arm * (edge + centre + divider) + zebra + stop)


def _value_noise(seed: int, size: int, smooth: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = rng.normal(0.0, 1.0, (size, size)).astype(np.float32)
    if smooth > 0:
        t = cv2.GaussianBlur(np.tile(t, (3, 3)), (0, 0), smooth)[size:2 * size, size:2 * size]
    return (t / t.std()).astype(np.float32)


_TEXTURES = {}


def _texture(name: str) -> np.ndarray:
    if name not in _TEXTURES:
        _TEXTURES[name] = {"coarse": lambda: _value_noise(7, 128, 2.0),
                           "fine": lambda: _value_noise(11, 256, 0.7)}[name]()
    return _TEXTURES[name]


def _sample_wrapped(tex: np.ndarray, X, Y, cell: float) -> np.ndarray:
    n = tex.shape[0]
    mx = np.mod(X / cell, n).astype(np.float32)
    my = np.mod(Y / cell, n).astype(np.float32)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def ground_radiance(camera: Camera, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    """Static background radiance (float32, grey levels before gain) of every pixel."""
    Rt = camera.R.T
    C = camera.center
    H, W = xn.shape
    out = np.empty((H, W), np.float32)
    chunk = 256
    for r0 in range(0, H, chunk):
        r1 = min(H, r0 + chunk)
        q0, q1 = max(0, r0 - 1), min(H, r1 + 1)  # one row of context for the footprint gradients
        x = xn[q0:q1].astype(np.float64)
        y = yn[q0:q1].astype(np.float64)
        dx = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2]
        dy = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2]
        dz = Rt[2, 0] * x + Rt[2, 1] * y + Rt[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(dz < 0, -C[2] / dz, np.inf)
        s = np.minimum(s, MAX_GROUND_RANGE / np.maximum(np.hypot(dx, dy), 1e-9))
        X = C[0] + s * dx
        Y = C[1] + s * dy
        gXv, gXu = np.gradient(X)
        gYv, gYu = np.gradient(Y)
        inner = slice(r0 - q0, r0 - q0 + (r1 - r0))
        X, Y = X[inner], Y[inner]
        wX = np.maximum(np.abs(gXu) + np.abs(gXv), 1e-4)[inner]
        wY = np.maximum(np.abs(gYu) + np.abs(gYv), 1e-4)[inner]
        sky = ~(dz[inner] < 0)
        # Road surface: |Y| < half width (road along x) or |X| < half width (road along y).
        road = 1.0 - (1.0 - _abs_interval(Y, wY, 0.0, ROAD_HALF_WIDTH)) * (1.0 - _abs_interval(X, wX, 0.0, ROAD_HALF_WIDTH))
        paint = np.maximum(_road_marks(X, Y, wX, wY), _road_marks(Y, -X, wY, wX))
        coarse = _sample_wrapped(_texture("coarse"), X, Y, 0.5)
        fine = _sample_wrapped(_texture("fine"), X, Y, 0.05)
        foot = np.maximum(wX, wY)
        fine_gain = np.clip(1.0 - foot / 0.1, 0.0, 1.0)  # fade detail finer than the pixel footprint
        base = road * ASPHALT + (1.0 - road) * PAVEMENT
        base = base + 5.0 * coarse + 5.0 * fine_gain * fine
        val = base * (1.0 - paint) + (PAINT + 3.0 * coarse) * paint
        far = np.clip((s[inner] * np.hypot(dx, dy)[inner] - 150.0) / 250.0, 0.0, 1.0)
        val = val * (1.0 - far) + SKY * far
        out[r0:r1] = np.where(sky, SKY, val)
    return out


class CameraRaster:
    """Everything the renderer needs that depends on the camera alone."""

    def __init__(self, camera: Camera):
        self.camera = camera
        self.width, self.height = camera.width, camera.height
        self.xn, self.yn = _undistorted_maps(camera)
        span_x = float(self.xn.max() - self.xn.min())
        span_y = float(self.yn.max() - self.yn.min())
        # Polygons are clipped to this normalized rectangle before distortion (no fold-over).
        self.rect = (float(self.xn.min()) - 0.05 * span_x, float(self.xn.max()) + 0.05 * span_x,
                     float(self.yn.min()) - 0.05 * span_y, float(self.yn.max()) + 0.05 * span_y)
        self.center = camera.center
        self.radiance = ground_radiance(camera, self.xn, self.yn)
        self._finished: dict[tuple, np.ndarray] = {}
        self._noise_bank = np.zeros(0, np.int16)
        self._noise_sigma: float | None = None

    @property
    def nbytes(self) -> int:
        return (self.xn.nbytes + self.yn.nbytes + self.radiance.nbytes + self._noise_bank.nbytes
                + sum(a.nbytes for a in self._finished.values()))

    def noise(self, sigma: float, rng: np.random.Generator) -> np.ndarray:
        """(H, W) int16 sensor noise: N(0, sigma²) rounded to grey levels, independent per pixel, a
        fresh field per call. Drawing 0.7 M normal samples per 960x720 frame cost more than the rest
        of a frame; the field is instead a window, at an offset drawn from rng, into a bank of
        independent samples drawn once per camera and sigma (H·W + NOISE_BANK_EXTRA of them). Within a
        frame it is i.i.d. as before; two frames share a pixel's sample only if their offsets are equal
        (one time in a million)."""
        return self.noise_window(sigma, int(rng.integers(0, NOISE_BANK_EXTRA + 1)))

    def noise_window(self, sigma: float, offset: int) -> np.ndarray:
        """The field of noise() at a given offset into the bank (0 <= offset <= NOISE_BANK_EXTRA)."""
        n = self.height * self.width
        if self._noise_sigma != sigma:
            draw = np.random.default_rng(NOISE_BANK_SEED).standard_normal(n + NOISE_BANK_EXTRA, dtype=np.float32)
            self._noise_bank = np.rint(draw * np.float32(sigma)).astype(np.int16)
            self._noise_sigma = sigma
        return self._noise_bank[offset:offset + n].reshape(self.height, self.width)

    def finished_background(self, model) -> np.ndarray:
        """The static background as the camera delivers it before noise (uint8, cached per optics)."""
        key = (float(model.blur_sigma), float(model.gamma), float(model.defocus_px), float(model.gain),
               float(model.vignetting))
        img = self._finished.get(key)
        if img is None:
            img = self.develop(self.radiance, model)
            if len(self._finished) >= 4:
                self._finished.pop(next(iter(self._finished)))
            self._finished[key] = img
        return img

    def develop(self, F: np.ndarray, model, x0: int = 0, y0: int = 0) -> np.ndarray:
        """The camera's optics on float32 stored grey levels F (the window of the frame at x0, y0): blur and
        defocus in linear light, vignetting, gain; uint8, before sensor noise. One path for the static
        background, the vehicles' composite (sim.render) and the calibration targets (sim.targets)."""
        F = optics(F, model)
        if model.vignetting:
            h, w = F.shape
            F = F * self.vignette(model)[y0:y0 + h, x0:x0 + w]
        return cv2.convertScaleAbs(F, alpha=model.gain)

    def vignette(self, model) -> np.ndarray:
        """float32 (H, W) factor on the stored (gamma-encoded) grey level: light falls off as
        1 − vignetting·(r / r_corner)²."""
        key = ("vignette", float(model.vignetting), float(model.gamma))
        v = self._finished.get(key)
        if v is None:
            yy, xx = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
            cx, cy = self.camera.K[0, 2], self.camera.K[1, 2]
            r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / float(max(cx, self.width - cx) ** 2 + max(cy, self.height - cy) ** 2)
            v = np.power(1.0 - model.vignetting * r2, 1.0 / model.gamma).astype(np.float32)
            self._finished[key] = v
        return v

    def project_polygon(self, points_world) -> np.ndarray | None:
        """Pixel outline (M, 2) of a planar world polygon, clipped to the part in front of the camera
        and near the image; edges subdivided so that lens distortion bends them exactly."""
        cam = self.camera
        Pc = cam.to_camera(points_world)
        poly = _clip(Pc, 2, 0.02, keep_greater=True)
        if len(poly) < 3:
            return None
        n = poly[:, :2] / poly[:, 2:3]
        x0, x1, y0, y1 = self.rect
        for axis, bound, greater in ((0, x0, True), (0, x1, False), (1, y0, True), (1, y1, False)):
            n = _clip(n, axis, bound, keep_greater=greater)
            if len(n) < 3:
                return None
        if cam.has_distortion:
            # Each edge a -> b as m points a + (k/m)(b - a), k < m, m ~ one per 12 px (all edges at once).
            a = n
            d = np.roll(n, -1, axis=0) - a
            m = np.clip(np.ceil(np.linalg.norm(d, axis=1) * cam.K[0, 0] / 12.0), 1, 512).astype(int)
            edge = np.repeat(np.arange(len(n)), m)
            k = np.arange(len(edge)) - np.repeat(np.cumsum(m) - m, m)
            n = cam.distort_normalized(a[edge] + (k / m[edge])[:, None] * d[edge])
        return n @ cam.K[:2, :2].T + cam.K[:2, 2]


def optics_reach(model) -> int:
    """Pixels an image point spreads to through the optics (blur and defocus)."""
    if model.blur_sigma <= 0 and model.defocus_px <= 0:
        return 0
    return int(np.ceil(4 * model.blur_sigma + model.defocus_px)) + 1


def optics(F: np.ndarray, model) -> np.ndarray:
    """The lens's blur on a float32 image of stored grey levels: in linear light (grey/255)^gamma, a
    Gaussian (blur_sigma) and a defocus disc (defocus_px), stored back as light^(1/gamma). With blurred
    edges in linear light a real camera's dark side has the steeper stored gradient: detected edges sit
    inside a tag's black square, as on real photographs."""
    if model.blur_sigma <= 0 and model.defocus_px <= 0:
        return F
    g = float(model.gamma)
    L = np.power(np.maximum(F, 0.0) / 255.0, g, dtype=np.float32) if g != 1.0 else F
    if model.blur_sigma > 0:
        L = cv2.GaussianBlur(L, (0, 0), model.blur_sigma)
    if model.defocus_px > 0:
        r = float(model.defocus_px)
        n = int(np.ceil(r))
        yy, xx = np.mgrid[-n:n + 1, -n:n + 1]
        # Pillbox with anti-aliased rim (coverage of each kernel pixel by the disc, approximately).
        k = np.clip(r + 0.5 - np.hypot(xx, yy), 0.0, 1.0).astype(np.float32)
        L = cv2.filter2D(L, -1, k / k.sum(), borderType=cv2.BORDER_REPLICATE)
    return (255.0 * np.power(np.maximum(L, 0.0), 1.0 / g)).astype(np.float32) if g != 1.0 else L


def _clip(poly: np.ndarray, axis: int, bound: float, keep_greater: bool) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon against coordinate `axis` >= / <= bound."""
    if len(poly) == 0:
        return poly
    sign = 1.0 if keep_greater else -1.0
    if np.all(sign * (poly[:, axis] - bound) >= 0):
        return poly  # wholly inside: what the loop below would return, vertex for vertex
    out = []
    m = len(poly)
    for i in range(m):
        a, b = poly[i], poly[(i + 1) % m]
        ia = sign * (a[axis] - bound) >= 0
        ib = sign * (b[axis] - bound) >= 0
        if ia:
            out.append(a)
        if ia != ib:
            s = (bound - a[axis]) / (b[axis] - a[axis])
            out.append(a + s * (b - a))
    return np.array(out) if out else np.zeros((0, poly.shape[1]))
