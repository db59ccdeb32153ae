"""The renderer's per-pixel work at edges, compiled (numba): most of the cost of a vehicle near a camera
(a bus 5-8 m from a camera covers a third of the frame, and its silhouette, face and tag-cell edge pixels
take 16 samples each). `python -m sim.bench_render --live`, thread CPU per frame of the demo scenario,
three alternating runs on the 2-core AMD EPYC at load 5.5-7.8 (2026-11-23): mean 6.1 against 8.4 ms
with the numpy code before, p90 14-16 against 21-22 ms; the frames are bit-identical (360 frames of the
demo scenario without noise and JPEG, compared).

- `supersample_box`: coverage and colour of edge pixels, each the mean of its samples: a sample's ray from
  the cached normalized-coordinate maps (first order around the pixel centre), the slab test against the
  vehicle's box, the roof's tag cells through each tag's homography;
- `supersample_tags`: the same for roof pixels at tag-cell edges (the tags' homographies alone);
- `near_edges`: which pixels an edge can cross (those alone are supersampled);
- `tag_cells`: a tag's cell at each pixel centre, and which pixels' footprints span two cells.

The same arithmetic, in the same order, as the numpy expressions they replace (a pixel's mean is summed
in sample order, where numpy's pairwise sum may differ in the last bit of a float32). Tags are passed as
stacked arrays: H (T, 3, 3), n (T,), levels (T, nmax, nmax) float32 (a tag's n x n in the top-left
corner), bounds (T, 4) with has_bounds (T,) bool (sim.render._Tag.bounds; None: unknown)."""
from __future__ import annotations

import math

import numpy as np

from toptag.jit import compiled

ROOF_LABEL = 5  # sim.render.ROOF


@compiled
def _ray_lattice(X, Y, W, H, y, x):
    """Pixel (y, x)'s ray in normalized coordinates and its derivatives along the image axes: a sample at
    sub-pixel offset (ou, ov) is (x0 + xu ou + xv ov, y0 + yu ou + yv ov) (central differences of the cached
    maps: the lens map is smooth, the second-order error over half a pixel is ~1e-5 px)."""
    xm, xp = max(x - 1, 0), min(x + 1, W - 1)
    ym, yp = max(y - 1, 0), min(y + 1, H - 1)
    sx, sy = float(xp - xm), float(yp - ym)
    here, left, right, up, down = y * W + x, y * W + xm, y * W + xp, ym * W + x, yp * W + x
    return (float(X[here]), (X[right] - X[left]) / sx, (X[down] - X[up]) / sy,
            float(Y[here]), (Y[right] - Y[left]) / sx, (Y[down] - Y[up]) / sy)


@compiled
def _sample(lattice, ou, ov):
    """The ray (xn, yn) at sub-pixel offset (ou, ov) of a pixel's _ray_lattice."""
    x0, xu, xv, y0, yu, yv = lattice
    xn = xu * ou
    xn += x0
    xn += xv * ov
    yn = yu * ou
    yn += y0
    yn += yv * ov
    return xn, yn


@compiled
def _grid_cell(Ht, x, y):
    """(row, col), fractional, of the tag grid cell that the ray (x, y) meets, through the tag's homography."""
    w = Ht[2, 0] * x + Ht[2, 1] * y + Ht[2, 2]
    return (Ht[0, 0] * x + Ht[0, 1] * y + Ht[0, 2]) / w, (Ht[1, 0] * x + Ht[1, 1] * y + Ht[1, 2]) / w


@compiled
def _tag_level(xn, yn, base, tag_H, tag_n, tag_levels, tag_bounds, has_bounds):
    """The roof's grey level along the ray: the last tag whose printed grid it meets, else base."""
    out = base
    for t in range(tag_n.shape[0]):
        if has_bounds[t]:
            b = tag_bounds[t]
            if not (xn >= b[0] and xn <= b[1] and yn >= b[2] and yn <= b[3]):
                continue
        r, c = _grid_cell(tag_H[t], xn, yn)
        n = tag_n[t]
        if r >= 0 and r < n and c >= 0 and c < n:
            out = tag_levels[t, int(r), int(c)]
    return out


@compiled
def _nan_min(a, b):  # np.minimum: NaN if either is
    if a != a or b != b:
        return math.nan
    return a if a < b else b


@compiled
def _nan_max(a, b):  # np.maximum: NaN if either is
    if a != a or b != b:
        return math.nan
    return a if a > b else b


@compiled
def supersample_box(X, Y, W, H, ys, xs, offsets, M, o, lo, hi, faces, colors, tag_H, tag_n, tag_levels,
                    tag_bounds, has_bounds):
    """Coverage (float32) and premultiplied colour (float32) of pixels (ys, xs) by the box, each the mean
    of its samples at `offsets`: a sample's ray (camera-normalized, through M and o into the box frame)
    meets the box [lo, hi] when it enters before it leaves, in front of the camera; its colour is the
    entered face's (faces: (3, 2) labels entered when the ray runs toward -k / +k along axis k), the
    roof's tag level where it meets a tag."""
    n = ys.shape[0]
    s = offsets.shape[0]
    alpha = np.empty(n, np.float32)
    premult = np.empty(n, np.float32)
    for i in range(n):
        hits = 0
        acc = np.float32(0.0)
        lattice = _ray_lattice(X, Y, W, H, ys[i], xs[i])
        for j in range(s):
            xn, yn = _sample(lattice, offsets[j, 0], offsets[j, 1])
            t_near, t_far, label = -math.inf, math.inf, 0
            for k in range(3):
                d = xn * M[k, 0] + yn * M[k, 1] + M[k, 2]
                t1 = (lo[k] - o[k]) / d
                t2 = (hi[k] - o[k]) / d
                t_far = _nan_min(t_far, _nan_max(t1, t2))
                tmin = _nan_min(t1, t2)
                if tmin > t_near:
                    label = faces[k, 0] if d < 0 else faces[k, 1]
                    t_near = tmin
            if t_near <= t_far and t_near > 0 and label > 0:
                hits += 1
                c = colors[label]
                if label == ROOF_LABEL and tag_n.shape[0] > 0:
                    c = _tag_level(xn, yn, c, tag_H, tag_n, tag_levels, tag_bounds, has_bounds)
                acc += c
        alpha[i] = hits / s
        premult[i] = acc / np.float32(s)
    return alpha, premult


@compiled
def supersample_tags(X, Y, W, H, ys, xs, offsets, base, tag_H, tag_n, tag_levels, tag_bounds, has_bounds):
    """Mean grey level (float32) of pixels (ys, xs) inside the roof, over their samples at `offsets`:
    the tags' cells through their homographies, `base` (the roof's colour) elsewhere."""
    n = ys.shape[0]
    s = offsets.shape[0]
    out = np.empty(n, np.float32)
    for i in range(n):
        acc = np.float32(0.0)
        lattice = _ray_lattice(X, Y, W, H, ys[i], xs[i])
        for j in range(s):
            xn, yn = _sample(lattice, offsets[j, 0], offsets[j, 1])
            acc += _tag_level(xn, yn, base, tag_H, tag_n, tag_levels, tag_bounds, has_bounds)
        out[i] = acc / np.float32(s)
    return out


@compiled
def near_edges(a, b, h, w, reach, piece):
    """(h, w) bool: the pixels whose centre lies within `reach` of a segment a[i] -> b[i] (pixel
    coordinates of the crop). Each segment is cut into pieces at most `piece` long, and each piece is
    tested against the pixels of its box only."""
    mask = np.zeros((h, w), np.bool_)
    r2 = reach * reach
    for e in range(a.shape[0]):
        dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        m = max(1, int(math.ceil(math.hypot(dx, dy) / piece)))
        for k in range(m):
            fk, fk1 = k / m, (k + 1) / m
            px, py = a[e, 0] + fk * dx, a[e, 1] + fk * dy
            qx, qy = a[e, 0] + fk1 * dx, a[e, 1] + fk1 * dy
            pqx, pqy = qx - px, qy - py
            L2 = max(pqx * pqx + pqy * pqy, 1e-12)
            gx0 = max(int(math.floor(min(px, qx) - reach)), 0)
            gx1 = min(int(math.ceil(max(px, qx) + reach)) + 1, w)
            gy0 = max(int(math.floor(min(py, qy) - reach)), 0)
            gy1 = min(int(math.ceil(max(py, qy) + reach)) + 1, h)
            for gy in range(gy0, gy1):
                uy = gy - py
                for gx in range(gx0, gx1):
                    if mask[gy, gx]:
                        continue
                    ux = gx - px
                    t = min(max((ux * pqx + uy * pqy) / L2, 0.0), 1.0)
                    ex, ey = ux - t * pqx, uy - t * pqy
                    if ex * ex + ey * ey <= r2:
                        mask[gy, gx] = True
    return mask


@compiled
def _cell_level(levels, n, r, c):
    """The tag's grey level of cell (r, c) (fractional), -1 outside its n x n grid."""
    if r >= 0 and r < n and c >= 0 and c < n:
        return float(levels[int(r), int(c)])
    return -1.0


@compiled
def tag_cells(xn, yn, Ht, n, levels, roof, color):
    """A tag's cells over a crop of the roof, pixel centres' rays (xn, yn): writes the cell's grey level into
    `color` where the centre sees the printed grid, and returns the pixels (bool) whose footprint (the
    linearised pixel square, 2 % larger) may span two cells or the grid's border: those need samples."""
    h, wd = xn.shape
    r = np.empty((h, wd))
    c = np.empty((h, wd))
    for i in range(h):
        for j in range(wd):
            r[i, j], c[i, j] = _grid_cell(Ht, xn[i, j], yn[i, j])
    edge = np.zeros((h, wd), np.bool_)
    for i in range(h):
        for j in range(wd):
            ri, ci = r[i, j], c[i, j]
            if roof[i, j] and ri >= 0 and ri < n and ci >= 0 and ci < n:
                color[i, j] = levels[int(ri), int(ci)]
            if not roof[i, j]:
                continue
            if h > 1 and wd > 1:  # np.gradient: central differences inside, one-sided at the border
                if i == 0:
                    rv, cv = r[1, j] - r[0, j], c[1, j] - c[0, j]
                elif i == h - 1:
                    rv, cv = r[h - 1, j] - r[h - 2, j], c[h - 1, j] - c[h - 2, j]
                else:
                    rv, cv = (r[i + 1, j] - r[i - 1, j]) / 2.0, (c[i + 1, j] - c[i - 1, j]) / 2.0
                if j == 0:
                    ru, cu = r[i, 1] - r[i, 0], c[i, 1] - c[i, 0]
                elif j == wd - 1:
                    ru, cu = r[i, wd - 1] - r[i, wd - 2], c[i, wd - 1] - c[i, wd - 2]
                else:
                    ru, cu = (r[i, j + 1] - r[i, j - 1]) / 2.0, (c[i, j + 1] - c[i, j - 1]) / 2.0
            else:
                rv = cv = ru = cu = 1.0
            er = 0.5 * (abs(ru) + abs(rv)) * 1.02 + 1e-3
            ec = 0.5 * (abs(cu) + abs(cv)) * 1.02 + 1e-3
            if not (ri + er >= 0 and ri - er <= n and ci + ec >= 0 and ci - ec <= n):
                continue
            if er > 0.5 or ec > 0.5:
                edge[i, j] = True
                continue
            v00 = _cell_level(levels, n, ri - er, ci - ec)
            edge[i, j] = (v00 != _cell_level(levels, n, ri - er, ci + ec) or v00 != _cell_level(levels, n, ri + er, ci - ec)
                          or v00 != _cell_level(levels, n, ri + er, ci + ec))
    return edge


def stack_tags(tags) -> tuple:
    """sim.render._Tag list -> the kernels' tag arrays (see the module doc)."""
    k = len(tags)
    nmax = max((t.n for t in tags), default=1)
    H = np.zeros((k, 3, 3))
    n = np.zeros(k, np.int64)
    levels = np.zeros((k, nmax, nmax), np.float32)
    bounds = np.zeros((k, 4))
    has = np.zeros(k, np.bool_)
    for i, t in enumerate(tags):
        H[i] = t.H
        n[i] = t.n
        levels[i, :t.n, :t.n] = t.levels
        if t.bounds is not None:
            bounds[i] = t.bounds
            has[i] = True
    return H, n, levels, bounds, has


def warm_up() -> float:
    """Compile the kernels (or load them from numba's on-disk cache) with the argument types the renderer
    passes, before a frame needs them; the seconds it took. `python -m sim.render_kernels` does it at setup
    and in the image build, as `python -m toptag.solvers.warmup` does for the solvers'."""
    import time

    t0 = time.perf_counter()
    X = np.zeros(4, np.float32)
    ys = xs = np.zeros(1, np.int64)
    offsets = np.zeros((1, 2))
    tags = stack_tags([])
    supersample_box(X, X, 2, 2, ys, xs, offsets, np.eye(3), np.ones(3), -np.ones(3), np.ones(3),
                    np.zeros((3, 2), np.int64), np.zeros(6, np.float32), *tags)
    supersample_tags(X, X, 2, 2, ys, xs, offsets, np.float32(0.0), *tags)
    near_edges(np.zeros((1, 2)), np.ones((1, 2)), 2, 2, 1.5, 8.0)
    grid = np.zeros((2, 2))
    levels, roof = np.zeros((10, 10), np.float32), np.ones((2, 2), np.bool_)
    # The renderer passes a crop of its colour array: strided, or contiguous when it spans whole rows.
    for color in (np.zeros((3, 3), np.float32)[:2, :2], np.zeros((2, 2), np.float32)):
        tag_cells(grid, grid, np.eye(3), 10, levels, roof, color)
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"sim's render kernels ready in {warm_up():.2f} s")
