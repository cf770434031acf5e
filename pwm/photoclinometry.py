"""Photoclinometric refinement of one maplet: heights and albedo from the brightness of K images.

Unknowns: the node heights themselves (the slopes p = -dz/dx, q = -dz/dy follow by finite
differences), the albedo per node, and per image a brightness scale and a pointing offset
(sample, line), px. Solving for heights rather than for free slopes makes the slope field
integrable by construction: the PWM integrability term w_i (p_y - q_x)^2 is identically zero (its
w_i -> infinity limit), and no slope integration step is needed before re-projecting. The
objective (METHOD.md section 5), with reflectance normalised by the mean data brightness I_ref:

    sum_k sum_nodes (w_k (I_k(x_k + o_k) - s_k A G_k(p, q)) / I_ref)^2
      + (slope_weight / w_PWM) sum_edges rho(p - p0) + rho(q - q0)
      + (height_weight / w_PWM) sum_nodes ((z - z0) / spacing)^2
      + albedo_weight sum_nodes ((A - A_ref) / A_ref)^2 + offset_weight sum_k |o_k - o_k,start|^2
      + shadow_weight sum_k sum_nodes h_k(z)^2
      + lidar_weight sum_spots ((z(x_l, y_l) - z_l) / sigma_l)^2

rho(d) = 2 c^2 (sqrt(1 + (d / c)^2) - 1) with c = slope_scale: the pseudo-Huber function, d^2 for
slope changes well below c and growing only linearly beyond, so that the relief the start lacks
(boulders, whose flanks differ from the start's slopes by far more than noise does) is not held
down as hard as noise is. I_k(x) is sampled by cubic convolution, which does not blur detail
between the pixel centres as bilinear sampling does.
h_k: the shadow term, in node spacings. Where image k shows a node in a shadow (`shade`, read
from the images: the node weighs nothing there), the node must lie below its horizon towards
that image's Sun over the maplet's own nodes (`horizons`), and where it shows the node plainly
lit, above it; h_k is how far the shape is on the wrong side, 0 where it is on the right one.
A low Sun that always comes from one side leaves the far flanks of boulders and the near walls
of craters dark in every image, and the shadows' edges are then all that the images say of them.
x_k: the nodes projected into image k at their current heights; G: the McEwen lunar-Lambert
function of pwm.photometry with the node normal from central differences of the heights
(one-sided on the border). The slope tie uses forward differences, which also see the odd-even
height patterns that central differences cannot. The height tie holds what brightness barely
sees: the longest wavelengths. Gauges, which the starting shape and poses fix: the scales keep a
geometric mean of 1 (the data fix only s_k * A); the offsets never move as a sideways shift of
the whole maplet would move them (photometry cannot see that shift); and the mean height stays
the start's (the offsets can absorb a common rise's parallax, so the data see it only by
perspective, and a direction that weak took many steps to drift along, to no gain).
The lidar term: each laser altimeter spot over the maplet (`pwm.maplets.MapletSpots`) measured
the height z_l at its x_l, y_l with the range's sigma; z(x, y) is bilinear between the nodes. It
weighs the spots against the images (lidar_weight: a spot one sigma off costs what one image node
off by sqrt(lidar_weight) of the mean brightness does). They hold the tilts and the bends that
brightness barely sees; the mean height stays the start's even so, since freed it drifts with the
offsets (bench/RESULTS.md), and the spots place the start first (pwm.pipeline.placed_on_spots).
Gauss-Newton with backtracking on the objective re-projected at the trial heights, until the RMS
height change of a step, or the relative decrease of the objective, is below its tolerance. The
Jacobian includes each node's parallax: as a node rises it moves in every image, and its sample
changes along the image gradient. Without that term the steps ignore what re-projection does to
the data, stall short of the objective's minimum (bench/RESULTS.md), and the heights see no
stereo at all.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy import ndimage
from scipy.linalg import block_diag

from pwm.camera import Camera, Pose, project
from pwm.maplets import NO_SPOTS, MapletGrid, MapletSpots, interpolation_matrix
from pwm.photometry import lunar_lambert, mcewen_l
from pwm.spd import Cholesky

Mode = Literal["pwm", "standard"]


@dataclass
class MapletImages:
    """The K images of one maplet with their geometry and per-node masks and weights.

    images: K arrays [line, sample] of reflectance-like values (I/F), NaN where missing;
    cameras, poses: their intrinsics (pixels) and body-fixed poses; sun_directions: (K, 3) unit
    vectors towards the Sun, body-fixed; visible, lit: (K, n, n) booleans per node (not occluded,
    not shadowed); weights: (K, n, n) per-node weight w_k (0 excludes the node from image k);
    region_weight: the maplet's w_PWM in (0, 1]; shade: (K, n, n) int8, -1 where the image shows
    the node in a shadow, +1 plainly lit, 0 neither (pwm.weights.shade; None: no shadow term).
    """

    images: list[np.ndarray]
    cameras: list[Camera]
    poses: list[Pose]
    sun_directions: np.ndarray
    visible: np.ndarray
    lit: np.ndarray
    weights: np.ndarray
    region_weight: float = 1.0
    shade: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.images)
        # the compiled samplers (cubic_gradient, pwm.registration_sums) take native doubles
        self.images = [np.ascontiguousarray(image, dtype=float) for image in self.images]
        self.sun_directions = np.asarray(self.sun_directions, float).reshape(k, 3)
        self.sun_directions = self.sun_directions / np.linalg.norm(self.sun_directions, axis=1, keepdims=True)
        self.visible = np.asarray(self.visible, bool)
        self.lit = np.asarray(self.lit, bool)
        self.weights = np.asarray(self.weights, float)
        if not (len(self.cameras) == len(self.poses) == k):
            raise ValueError("one camera and one pose per image")
        if not (self.visible.shape == self.lit.shape == self.weights.shape) or self.weights.shape[0] != k:
            raise ValueError("visible, lit and weights must all be (K, n, n)")
        if self.shade is not None and np.shape(self.shade) != self.weights.shape:
            raise ValueError("shade must be (K, n, n) like the weights")
        if not 0.0 < self.region_weight <= 1.0:
            raise ValueError(f"region weight {self.region_weight} is outside (0, 1]")

    @property
    def count(self) -> int:
        return len(self.images)

    def data_weights(self, mode: Mode) -> tuple[np.ndarray, float]:
        """Per-node weights (K, n, n) and region weight for a refinement mode: 'pwm' uses the
        pixel and region weights; 'standard' weighs every visible node 1, shadowed ones included."""
        if mode == "pwm":
            return self.weights, self.region_weight
        if mode == "standard":
            return self.visible.astype(float), 1.0
        raise ValueError(f"unknown mode {mode!r}")


@dataclass
class Refinement:
    """Result of `refine`. heights (km) and albedo: (n, n); scales: (K,) brightness scale per
    image (geometric mean 1); offsets: (K, 2) pointing corrections (sample, line), px; rms: (K,)
    RMS of I - s A G over the nodes each image weighs (reflectance units; NaN if none);
    iterations: Gauss-Newton steps taken; converged: the last step's RMS height change, or the
    objective's relative decrease, was below its tolerance. How the images agree with the solved
    shape, node by node (pwm.uncertainty.node_sigma): weights (K, n, n) each image's weight in
    the solution; misfit (K, n, n) its brightness I - s A G over the mean brightness (NaN where
    unweighed); slope_gradients (K, n, n, 2) that relative brightness's derivatives with respect
    to the slopes p and q. lidar_rms: RMS of the spots' height residuals in their sigmas (NaN
    without spots)."""

    heights: np.ndarray
    albedo: np.ndarray
    scales: np.ndarray
    offsets: np.ndarray
    rms: np.ndarray
    iterations: int
    converged: bool
    weights: np.ndarray
    misfit: np.ndarray
    slope_gradients: np.ndarray
    lidar_rms: float = float("nan")


def node_pixels(maplet: MapletGrid, data: MapletImages, *, heights: np.ndarray | None = None,
                offsets: np.ndarray | None = None) -> np.ndarray:
    """(K, n, n, 2) pixel coordinates (sample, line) of the nodes in each image, plus the per-image
    offsets (K, 2) (pointing corrections from `pwm.alignment.align`); NaN behind the camera."""
    points = maplet.nodes_body(heights).reshape(-1, 3)
    out = np.empty((data.count, maplet.n, maplet.n, 2))
    for k, (camera, pose) in enumerate(zip(data.cameras, data.poses, strict=True)):
        cam = pose.to_camera(points)
        pix = camera.project_camera(cam)
        pix[cam[:, 2] <= 0] = np.nan
        out[k] = pix.reshape(maplet.n, maplet.n, 2)
    if offsets is not None:
        out += np.asarray(offsets, float)[:, None, None, :]
    return out


def bilinear(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear samples of an image [line, sample] at pixels (..., 2) = (sample, line) with pixel
    centres at integers; NaN outside the frame (or next to a NaN pixel)."""
    height, width = image.shape
    s, line = pixels[..., 0], pixels[..., 1]
    inside = (s >= 0) & (s <= width - 1) & (line >= 0) & (line <= height - 1)
    s = np.where(inside, s, 0.0)
    line = np.where(inside, line, 0.0)
    s0 = np.minimum(np.floor(s).astype(np.intp), max(width - 2, 0))
    l0 = np.minimum(np.floor(line).astype(np.intp), max(height - 2, 0))
    fs, fl = s - s0, line - l0
    flat = image.ravel()
    i00 = l0 * width + s0
    i10 = i00 + (width if height > 1 else 0)
    right = 1 if width > 1 else 0
    p00, p10 = flat[i00], flat[i10]
    top = p00 + fs * (flat[i00 + right] - p00)
    bottom = p10 + fs * (flat[i10 + right] - p10)
    return np.where(inside, top + fl * (bottom - top), np.nan)


@njit(cache=True, inline="always")
def _keys(f: float, tap: int) -> tuple[float, float]:
    """Weight of Keys' cubic convolution (a = -1/2) for the pixel at tap - 1 (tap 0..3) from the
    one below a sample at fraction f in [0, 1), and its derivative in f."""
    f2, f3 = f * f, f * f * f
    if tap == 0:
        return 0.5 * (-f3 + 2 * f2 - f), 0.5 * (-3 * f2 + 4 * f - 1)
    if tap == 1:
        return 0.5 * (3 * f3 - 5 * f2 + 2), 0.5 * (9 * f2 - 10 * f)
    if tap == 2:
        return 0.5 * (-3 * f3 + 4 * f2 + f), 0.5 * (-9 * f2 + 8 * f + 1)
    return 0.5 * (f3 - f2), 0.5 * (3 * f2 - 2 * f)


@njit(cache=True)
def cubic_gradient(image: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic-convolution samples (N,) of an image [line, sample] at pixels (N, 2) = (sample,
    line), pixel centres at integers, and the interpolant's derivatives (N, 2) per px (it is
    continuously differentiable); NaN outside the frame or next to a NaN pixel. Unlike bilinear
    sampling, it does not blur what lies between the pixel centres. Compiled (numba): it samples
    every image at every node at each of the solution's evaluations."""
    height, width = image.shape
    count = pixels.shape[0]
    values, gradient = np.full(count, np.nan), np.full((count, 2), np.nan)
    for k in range(count):
        s, line = pixels[k, 0], pixels[k, 1]
        if not (0.0 <= s <= width - 1 and 0.0 <= line <= height - 1):
            continue
        s0, l0 = np.floor(s), np.floor(line)
        col, row = int(s0), int(l0)
        value = ds = dl = 0.0
        for tap in range(4):
            r = min(max(row + tap - 1, 0), height - 1)
            along = d_along = 0.0
            for j in range(4):
                w, dw = _keys(s - s0, j)
                pixel = image[r, min(max(col + j - 1, 0), width - 1)]
                along += pixel * w
                d_along += pixel * dw
            w, dw = _keys(line - l0, tap)
            value += w * along
            ds += w * d_along
            dl += dw * along
        values[k], gradient[k, 0], gradient[k, 1] = value, ds, dl
    return values, gradient


def extract(maplet: MapletGrid, data: MapletImages, *, heights: np.ndarray | None = None,
            offsets: np.ndarray | None = None) -> np.ndarray:
    """(K, n, n) image values at the nodes (bilinear), NaN outside the frames or behind a camera."""
    pixels = node_pixels(maplet, data, heights=heights, offsets=offsets)
    return np.stack([bilinear(image, pixels[k]) for k, image in enumerate(data.images)])


def resampled(maplet: MapletGrid, weights: np.ndarray, factor: int) -> tuple[MapletGrid, np.ndarray]:
    """The maplet with every `factor`-th spacing over the same square (heights smoothed to that
    spacing and interpolated) and per-node weights (K, m*m) that are positive where the fine
    weights are positive all around."""
    if factor == 1:
        return maplet, weights.reshape(len(weights), -1)
    n = maplet.n
    m = (n - 1) // factor + 1
    at = np.linspace(0, n - 1, m)
    grid = np.meshgrid(at, at, indexing="ij")
    heights = ndimage.map_coordinates(ndimage.gaussian_filter(maplet.heights, 0.5 * factor, mode="nearest"), grid,
                                      order=1, mode="nearest")
    good = np.stack([ndimage.map_coordinates(ndimage.minimum_filter((w > 0).astype(float), size=factor), grid,
                                             order=0, mode="nearest") for w in weights])
    coarse = dataclasses.replace(maplet, heights=heights, albedo=None, spacing_km=maplet.spacing_km * (n - 1) / (m - 1))
    return coarse, good.reshape(len(weights), -1)


def coarsened(maplet: MapletGrid, data: MapletImages, factor: int) -> tuple[MapletGrid, MapletImages]:
    """The maplet every `factor`-th spacing (`resampled`) and its images smoothed to that many
    pixels (a Gaussian of factor / 2 px, NaN where less than half its weight fell on data); each
    coarse node keeps the masks and weight of the fine node under it, where the fine weights are
    positive all around."""
    coarse, good = resampled(maplet, data.weights, factor)
    at = np.linspace(0, maplet.n - 1, coarse.n)
    grid = np.meshgrid(at, at, indexing="ij")

    def under(masks: np.ndarray) -> np.ndarray:
        return np.stack([ndimage.map_coordinates(mask.astype(float), grid, order=0, mode="nearest")
                         for mask in masks])

    weights = under(data.weights) * good.reshape(data.count, coarse.n, coarse.n)
    images = [_smoothed(image, 0.5 * factor) for image in data.images]
    return coarse, MapletImages(images=images, cameras=data.cameras, poses=data.poses,
                                sun_directions=data.sun_directions, visible=under(data.visible) > 0,
                                lit=under(data.lit) > 0, weights=weights, region_weight=data.region_weight)


def _smoothed(image: np.ndarray, sigma: float) -> np.ndarray:
    valid = np.isfinite(image)
    total = ndimage.gaussian_filter(np.where(valid, image, 0.0), sigma)
    share = ndimage.gaussian_filter(valid.astype(float), sigma)
    return np.where(share > 0.5, total / np.maximum(share, 0.5), np.nan)


@lru_cache(maxsize=8)
def _gradient_operators(n: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse d/dj and d/di on an n x n row-major grid in units of one spacing, as np.gradient:
    central differences inside, one-sided on the border."""
    rows = np.arange(n)
    lo = np.clip(rows - 1, 0, n - 1)
    hi = np.clip(rows + 1, 0, n - 1)
    step = (hi - lo).astype(float)
    d = sp.csr_matrix((np.concatenate([1 / step, -1 / step]), (np.tile(rows, 2), np.concatenate([hi, lo]))),
                      shape=(n, n))
    eye = sp.identity(n, format="csr")
    return sp.kron(eye, d, format="csr"), sp.kron(d, eye, format="csr")


@lru_cache(maxsize=8)
def _difference_operator(n: int) -> sp.csr_matrix:
    """Forward differences along j and along i on an n x n row-major grid, stacked: (2 n (n-1), n^2)."""
    d = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))
    eye = sp.identity(n)
    return sp.vstack([sp.kron(eye, d), sp.kron(d, eye)], format="csr")


def slopes(heights: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """p = -dz/dx and q = -dz/dy (n, n) of a height grid (x along j, y along i), as `refine` takes them."""
    n = heights.shape[0]
    dx, dy = _gradient_operators(n)
    u = heights.ravel() / spacing
    return -(dx @ u).reshape(n, n), -(dy @ u).reshape(n, n)


@dataclass
class _Geometry:
    """Local Sun directions (K, 3), view directions (K, N, 3) and phase angles (K, N), radians."""

    sun: np.ndarray
    view: np.ndarray
    phase: np.ndarray


def _geometry(maplet: MapletGrid, data: MapletImages, heights: np.ndarray) -> _Geometry:
    frame = maplet.frame
    sun = data.sun_directions @ frame.rotation.T
    nodes = maplet.nodes_local(heights).reshape(-1, 3)
    cams = frame.to_local(np.stack([pose.position for pose in data.poses]))
    view = cams[:, None, :] - nodes[None]
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    phase = np.arccos(np.clip(np.einsum("kni,ki->kn", view, sun), -1.0, 1.0))
    return _Geometry(sun=sun, view=view, phase=phase)


def _shading(p: np.ndarray, q: np.ndarray, geo: _Geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lunar-Lambert G and its derivatives dG/dp, dG/dq, (K, N), for flat slope arrays p, q (N,).

    With the unnormalised normal (p, q, 1), a = S.(p, q, 1) and b = V.(p, q, 1):
    G = (1 - L) a / m + 2 L a / (a + b), m = |(p, q, 1)|; G and its derivatives are zero where
    a or b <= 0 (Sun or camera below the local horizon).
    """
    sx, sy, sz = (geo.sun[:, c, None] for c in range(3))
    vx, vy, vz = geo.view[..., 0], geo.view[..., 1], geo.view[..., 2]
    m = np.sqrt(1.0 + p * p + q * q)
    a = p * sx + q * sy + sz
    b = p * vx + q * vy + vz
    G = lunar_lambert(a / m, b / m, geo.phase)
    L = mcewen_l(geo.phase)
    lit = (a > 0) & (b > 0)
    ab2 = np.where(lit, (a + b) ** 2, 1.0)
    m3 = m**3
    gp = (1 - L) * (sx / m - a * p / m3) + 2 * L * (sx * b - a * vx) / ab2
    gq = (1 - L) * (sy / m - a * q / m3) + 2 * L * (sy * b - a * vy) / ab2
    return G, np.where(lit, gp, 0.0), np.where(lit, gq, 0.0)


def predict(maplet: MapletGrid, data: MapletImages, *, heights: np.ndarray | None = None,
            albedo: np.ndarray | float | None = None) -> np.ndarray:
    """(K, n, n) brightness A * G predicted at the nodes from the maplet's shape (render by formula,
    no cast shadows). albedo: per node or scalar; the maplet's own, or 1, if None."""
    h = maplet.heights if heights is None else heights
    a = albedo if albedo is not None else (maplet.albedo if maplet.albedo is not None else 1.0)
    p, q = slopes(h, maplet.spacing_km)
    G, _, _ = _shading(p.ravel(), q.ravel(), _geometry(maplet, data, h))
    return (np.broadcast_to(a, h.shape).ravel() * G).reshape(data.count, maplet.n, maplet.n)


def _initial_albedo_and_scales(maplet: MapletGrid, values: np.ndarray, rows: np.ndarray,
                               G: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo per node (N,), scales (K,) and albedo prior (N,), gauged to unit geometric-mean scale.

    Without a maplet albedo, each node with data starts from its least-squares albedo at unit
    scales (clipped to a factor 10 of the median), and the prior is that median; nodes without data
    take it."""
    c2 = rows**2
    if maplet.albedo is not None:
        albedo = np.asarray(maplet.albedo, float).ravel().copy()
    else:
        den = (c2 * G * G).sum(axis=0)
        has = den > 0
        est = (c2 * G * values).sum(axis=0) / np.where(has, den, 1.0)
        typical = float(np.median(est[has])) if has.any() else 1.0
        albedo = np.where(has, np.clip(est, 0.1 * typical, 10 * typical), typical)
    P = albedo * G
    den = (c2 * P * P).sum(axis=1)
    scales = (c2 * P * values).sum(axis=1) / np.where(den > 0, den, 1.0)
    scales = np.where((den > 0) & (scales > 0), scales, 1.0)
    gauge = np.exp(np.mean(np.log(scales)))
    scales /= gauge
    albedo *= gauge
    if maplet.albedo is not None:
        return albedo, scales, np.asarray(maplet.albedo, float).ravel().copy()
    return albedo, scales, np.full_like(albedo, float(np.median(albedo)))


def horizons(u: np.ndarray, sun_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, N) the height (node spacings) below which each node of the height grid u (n, n, in
    node spacings; x along j, y along i) lies in the shadow that the grid's own nodes cast under
    each Sun (K, 3, unit vectors in the maplet's frame), and (K, N) the node (flat index) that
    casts it; -inf and -1 where none can (a Sun overhead or below the horizon). The ray towards
    the Sun is stepped one spacing at a time, each step taken at its nearest node, whose height
    is lowered by the Sun's rise over that node's distance along the Sun's azimuth."""
    n = u.shape[0]
    index = np.arange(n)
    top = np.full((len(sun_local), n, n), -np.inf)
    caster = np.full((len(sun_local), n * n), -1, dtype=np.int64)
    span = float(u.max() - u.min())
    azimuths, rises = _sun_paths(sun_local)
    for k, ((dx, dy), rise) in enumerate(zip(azimuths, rises, strict=True)):
        if not np.isfinite(rise):
            continue
        steps = np.zeros((n, n), np.int64)  # the step whose node casts the horizon, 0: none
        # beyond span / rise steps no node stands high enough to shade another
        for step in range(1, min(int(np.ceil(span / rise)) + 1, 2 * n) + 1):
            # a step's node lies step * dy rows and step * dx columns on: rows and columns apart
            ci = np.rint(index + step * dy).astype(np.int64)
            cj = np.rint(index + step * dx).astype(np.int64)
            rows = np.flatnonzero((ci >= 0) & (ci < n))
            cols = np.flatnonzero((cj >= 0) & (cj < n))
            if not (len(rows) and len(cols)):
                break
            # rint keeps the order: the rows (columns) whose step stays inside are consecutive
            at = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
            ri, cj = ci[at[0]], cj[at[1]]
            down, across = ri - rows, cj - cols
            if down.min() == down.max() and across.min() == across.max():
                # the step's nodes one block of the grid moved (no rounding tie split it): a view
                a, b = int(down[0]), int(across[0])
                h = u[rows[0] + a:rows[-1] + a + 1, cols[0] + b:cols[-1] + b + 1] - rise * (b * dx + a * dy)
            else:
                h = u[np.ix_(ri, cj)] - rise * (across * dx + down[:, None] * dy)
            np.copyto(steps[at], step, where=h > top[k][at])
            np.maximum(top[k][at], h, out=top[k][at])
        cast = steps.ravel() > 0
        i, j = np.divmod(np.flatnonzero(cast), n)
        shadowed = steps.ravel()[cast]
        caster[k, cast] = np.rint(i + shadowed * dy).astype(np.int64) * n + np.rint(j + shadowed * dx).astype(np.int64)
    return top.reshape(len(sun_local), -1), caster


def _sun_paths(sun_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 2) the unit vector of each Sun's azimuth in the maplet's (x, y), and (K,) the Sun's rise
    per unit of distance along it; NaN for a Sun overhead or below the horizon, which casts no
    shadow a maplet's own nodes could tell."""
    sun = np.asarray(sun_local, float).reshape(-1, 3)
    horizontal = np.hypot(sun[:, 0], sun[:, 1])
    ok = (horizontal >= 1e-9) & (sun[:, 2] > 0)
    safe = np.where(ok, horizontal, 1.0)
    return (np.where(ok[:, None], sun[:, :2] / safe[:, None], np.nan),
            np.where(ok, sun[:, 2] / safe, np.nan))


def _exit_steps(n: int, azimuths: np.ndarray) -> np.ndarray:
    """(K, N) distance (node spacings) from each node to the grid's border along each azimuth
    (`_sun_paths`; NaN where it is)."""
    i, j = np.divmod(np.arange(n * n), n)
    out = np.full((len(azimuths), n * n), np.inf)
    for k, (dx, dy) in enumerate(azimuths):
        if not np.isfinite(dx):
            out[k] = np.nan
            continue
        for d, at in ((dx, j), (dy, i)):
            if abs(d) > 1e-12:
                out[k] = np.minimum(out[k], ((n - 1 - at) if d > 0 else at) / abs(d))
    return out


_RISE = 0.01  # the height step (spacings) over which the parallax of a node is differenced


@dataclass
class _State:
    """Unknowns: heights in node spacings u (N,), albedo (N,), scales (K,), offsets (K, 2) px."""

    u: np.ndarray
    albedo: np.ndarray
    scales: np.ndarray
    offsets: np.ndarray


@dataclass
class _Evaluation:
    """The problem at one state: row weights c = w / I_ref (K, N) (0 where unused), image
    gradients (K, N, 2) at the samples, the change of each sample as its node rises by one
    spacing (K, N), shading and its slope derivatives (K, N), residuals c (I - s A G) (K, N), the
    shadow term's residuals and Jacobian (`_Problem._shadows`) and the objective."""

    rows: np.ndarray
    gradients: np.ndarray
    parallax: np.ndarray
    G: np.ndarray
    Gp: np.ndarray
    Gq: np.ndarray
    residuals: np.ndarray
    shadow: np.ndarray
    shadow_jac: sp.csr_matrix
    cost: float


class _Problem:
    """One maplet's refinement: data, operators on the node grid (units of one spacing), priors."""

    def __init__(self, maplet: MapletGrid, data: MapletImages, *, weights: np.ndarray, region: float,
                 offsets: np.ndarray, solve_offsets: bool, slope_weight: float, slope_scale: float,
                 height_weight: float, albedo_weight: float, offset_weight: float, shadow_weight: float,
                 spots: MapletSpots, lidar_weight: float) -> None:
        n = maplet.n
        self.maplet, self.data = maplet, data
        self.weights = weights.reshape(data.count, -1)
        self.dx, self.dy = _gradient_operators(n)
        self.fwd = _difference_operator(n)
        # u enters the residuals of a node three ways: by Dx u, Dy u and u itself (its parallax)
        self.operators = sp.vstack([self.dx, self.dy, sp.identity(n * n)], format="csr")
        self.slope_tie = slope_weight / region
        self.height_tie = height_weight / region
        self.slope_scale = slope_scale
        self.u0 = maplet.heights.ravel() / maplet.spacing_km
        self.offsets0 = offsets
        self.offset_weight = offset_weight
        self.albedo_weight = albedo_weight
        self.solve_offsets = solve_offsets
        if solve_offsets:
            self.image_basis = block_diag(np.eye(data.count), datum_complement(maplet, data))
        self.i_ref = 1.0
        self.albedo_prior = np.ones(n * n)
        self.shadow_weight = shadow_weight
        self.shade = None if data.shade is None or shadow_weight <= 0 else data.shade.reshape(data.count, -1)
        self.sun_local = data.sun_directions @ maplet.frame.rotation.T
        azimuths, self.rises = _sun_paths(self.sun_local)
        self.exit_steps = _exit_steps(n, azimuths)
        # the spots' heights and the interpolation onto them, in node spacings like u
        self.spot_matrix = interpolation_matrix(maplet, spots.local_km[:, :2])
        self.spot_u = spots.local_km[:, 2] / maplet.spacing_km
        self.spot_weights = lidar_weight * (maplet.spacing_km / spots.sigma_km) ** 2

    def spot_residuals(self, u: np.ndarray) -> np.ndarray:
        """(M,) the maplet's heights at the spots less the spots', in node spacings."""
        return self.spot_matrix @ u - self.spot_u

    def start(self) -> tuple[_State, _Evaluation]:
        """Starting state (albedo and scales estimated at the starting shape) and its evaluation."""
        state = _State(u=self.u0.copy(), albedo=np.ones_like(self.u0), scales=np.ones(self.data.count),
                       offsets=self.offsets0.copy())
        ev, values = self._evaluate(state)
        used = ev.rows > 0
        if used.any():
            self.i_ref = float(values[used].mean())
        albedo, scales, self.albedo_prior = _initial_albedo_and_scales(self.maplet, values, ev.rows, ev.G)
        state = _State(u=state.u, albedo=albedo, scales=scales, offsets=state.offsets)
        # the shape and offsets are the same: only the residuals change (rows were scaled by 1)
        rows = ev.rows / self.i_ref
        residuals = rows * (values - scales[:, None] * albedo * ev.G)
        return state, dataclasses.replace(ev, rows=rows, residuals=residuals,
                                          cost=self._cost(state, residuals, ev.shadow))

    def evaluate(self, state: _State) -> _Evaluation:
        return self._evaluate(state)[0]

    def _evaluate(self, state: _State) -> tuple[_Evaluation, np.ndarray]:
        maplet, data = self.maplet, self.data
        heights = (state.u * maplet.spacing_km).reshape(maplet.n, maplet.n)
        pixels = node_pixels(maplet, data, heights=heights, offsets=state.offsets).reshape(data.count, -1, 2)
        # a node that rises moves in the images: its samples change along the image gradients
        raised = node_pixels(maplet, data, heights=heights + _RISE * maplet.spacing_km,
                             offsets=state.offsets).reshape(data.count, -1, 2)
        sampled = [cubic_gradient(image, pixels[k]) for k, image in enumerate(data.images)]
        values = np.stack([v for v, _ in sampled])
        gradients = np.stack([g for _, g in sampled])
        used = (np.isfinite(values) & (self.weights > 0) & np.isfinite(gradients).all(axis=-1)
                & np.isfinite(raised).all(axis=-1))
        gradients = np.where(used[..., None], gradients, 0.0)
        parallax = np.einsum("kni,kni->kn", gradients, np.where(used[..., None], raised - pixels, 0.0)) / _RISE
        values = np.where(used, values, 0.0)
        rows = np.where(used, self.weights, 0.0) / self.i_ref
        G, Gp, Gq = _shading(-(self.dx @ state.u), -(self.dy @ state.u), _geometry(maplet, data, heights))
        residuals = rows * (values - state.scales[:, None] * state.albedo * G)
        shadow, shadow_jac = self._shadows(state.u)
        return _Evaluation(rows=rows, gradients=gradients, parallax=parallax, G=G, Gp=Gp, Gq=Gq, residuals=residuals,
                           shadow=shadow, shadow_jac=shadow_jac, cost=self._cost(state, residuals, shadow)), values

    def _cost(self, state: _State, residuals: np.ndarray, shadow: np.ndarray) -> float:
        """The objective at the state with these residuals (data and shadow term)."""
        du = state.u - self.u0
        da = (state.albedo - self.albedo_prior) / self.albedo_prior
        do = state.offsets - self.offsets0
        spots = self.spot_residuals(state.u)
        return float((residuals**2).sum() + self._tie_cost(du) + self.albedo_weight * (da @ da)
                     + self.offset_weight * (do * do).sum() + self.shadow_weight * (shadow @ shadow)
                     + self.spot_weights @ (spots * spots))

    def _shadows(self, u: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """The shadow term's residuals (node spacings) and their Jacobian (M, N): one row per node
        and image where the shape contradicts what the image shows, a node it shows in a shadow
        standing above its horizon (u - top), or one it shows lit below it (top - u). A row moves
        the node and the node that casts its horizon, the two ends of the ray to the Sun. A dark
        node that a node just beyond the grid's border, as high as the grid's highest, could shade
        has no row: the grid cannot tell."""
        n2 = len(u)
        if self.shade is None:
            return np.zeros(0), sp.csr_matrix((0, n2))
        top, caster = horizons(u.reshape(self.maplet.n, self.maplet.n), self.sun_local)
        gap = u[None, :] - top
        with np.errstate(invalid="ignore"):
            reach = (u.max() - u)[None, :] / self.rises[:, None]
        dark = (self.shade < 0) & (caster >= 0) & (gap > 0) & (reach <= self.exit_steps)
        lit = (self.shade > 0) & (caster >= 0) & (gap < 0)
        k_dark, node_dark = np.nonzero(dark)
        k_lit, node_lit = np.nonzero(lit)
        sign = np.concatenate([np.ones(len(k_dark)), -np.ones(len(k_lit))])
        node = np.concatenate([node_dark, node_lit])
        cast = np.concatenate([caster[k_dark, node_dark], caster[k_lit, node_lit]])
        residual = sign * np.concatenate([gap[k_dark, node_dark], gap[k_lit, node_lit]])
        m = np.arange(len(node))
        jac = sp.csr_matrix((np.concatenate([sign, -sign]), (np.tile(m, 2), np.concatenate([node, cast]))),
                            shape=(len(node), n2))
        return residual, jac

    def _tie_cost(self, du: np.ndarray) -> float:
        """The ties to the start: pseudo-Huber on the slope changes (quadratic below slope_scale,
        linear beyond, so that relief the start lacks is not held down as hard as noise), quadratic
        on the heights."""
        d = self.fwd @ du
        c = self.slope_scale
        slope = float(np.sum(2 * c * c * (np.sqrt(1 + (d / c) ** 2) - 1)))
        return self.slope_tie * slope + self.height_tie * float(du @ du)

    def _tie_matrix(self, du: np.ndarray) -> sp.csr_matrix:
        """The ties' Gauss-Newton matrix at du (IRLS weights on the slope changes): its product
        with du is half the gradient of `_tie_cost`."""
        n2 = len(du)
        d = self.fwd @ du
        w = 1.0 / np.sqrt(1 + (d / self.slope_scale) ** 2)
        return (self.slope_tie * (self.fwd.T @ sp.diags(w) @ self.fwd) + self.height_tie * sp.identity(n2)).tocsr()

    def step(self, state: _State, ev: _Evaluation) -> _State:
        """One Gauss-Newton step (as a _State of increments). The albedo (a diagonal block) is
        eliminated per node; the per-image unknowns (scales, offsets) by a Schur complement."""
        k_images = self.data.count
        c, s, albedo, r = ev.rows, state.scales[:, None], state.albedo, ev.residuals
        ja = -c * s * ev.G                 # dr / dA
        jx = c * s * albedo * ev.Gp        # dr / d(Dx u), as p = -Dx u
        jy = c * s * albedo * ev.Gq
        jz = c * ev.parallax               # dr / du through the node's move in the image
        # Per-image unknowns t: scales, then offsets (sample, line) image by image; image[t] is
        # the image each belongs to and jt[t] its derivative on that image's residuals.
        jt_blocks = [-c * albedo * ev.G]
        image_blocks = [np.arange(k_images)]
        if self.solve_offsets:
            jt_blocks.append((c[..., None] * ev.gradients).transpose(0, 2, 1).reshape(2 * k_images, -1))
            image_blocks.append(np.repeat(np.arange(k_images), 2))
        jt = np.vstack(jt_blocks)
        image = np.concatenate(image_blocks)

        a2 = self.albedo_weight / self.albedo_prior**2
        haa = (ja * ja).sum(axis=0) + a2
        ga = (ja * r).sum(axis=0) + a2 * (albedo - self.albedo_prior)
        inv = 1.0 / haa
        parts = (jx, jy, jz)
        pa = [(ja * j).sum(axis=0) for j in parts]
        m = [[(ji * jj).sum(axis=0) - pi * pj * inv for jj, pj in zip(parts, pa, strict=True)]
             for ji, pi in zip(parts, pa, strict=True)]
        g = [(j * r).sum(axis=0) - p * ga * inv for j, p in zip(parts, pa, strict=True)]
        xta = jt * ja[image]
        xt = [jt * j[image] - xta * (p * inv) for j, p in zip(parts, pa, strict=True)]
        htt = (jt @ jt.T) * (image[:, None] == image[None, :]) - (xta * inv) @ xta.T
        gt = (jt * r[image]).sum(axis=1) - xta @ (ga * inv)
        # The data fix only s_k * A: a penalty on sum(log s) holds the scales' geometric mean at 1.
        v = np.zeros(len(image))
        v[:k_images] = 1.0 / state.scales
        gamma = max(float(np.trace(htt[:k_images, :k_images])) / k_images, 1e-12)
        htt += gamma * np.outer(v, v) + 1e-12 * gamma * np.eye(len(image))
        gt += gamma * v * np.log(state.scales).sum()
        if self.solve_offsets:
            htt[k_images:, k_images:] += self.offset_weight * np.eye(2 * k_images)
            gt[k_images:] += self.offset_weight * (state.offsets - self.offsets0).ravel()
            # Solve in a basis that leaves out the offsets a sideways shift of the maplet would
            # cause: photometry cannot see that shift; the starting shape and poses fix it.
            basis = self.image_basis
            htt, gt = basis.T @ htt @ basis, basis.T @ gt
            xta, xt = basis.T @ xta, [basis.T @ x for x in xt]

        ops = self.operators
        tie = self._tie_matrix(state.u - self.u0)
        shadow, shadow_jac = ev.shadow, ev.shadow_jac
        spots, weighed = self.spot_matrix, sp.diags(self.spot_weights)
        huu = (ops.T @ sp.bmat([[sp.diags(mij) for mij in row] for row in m], format="csr") @ ops + tie
               + self.shadow_weight * (shadow_jac.T @ shadow_jac) + spots.T @ weighed @ spots)
        gu = (ops.T @ np.concatenate(g) + tie @ (state.u - self.u0) + self.shadow_weight * (shadow_jac.T @ shadow)
              + spots.T @ (weighed @ self.spot_residuals(state.u)))
        hut = ops.T @ np.vstack([x.T for x in xt])
        # The mean height stays the start's: a Lagrange multiplier joins the per-image unknowns.
        hut = np.column_stack([hut, np.ones(len(gu))])
        htt = np.block([[htt, np.zeros((len(htt), 1))], [np.zeros((1, len(htt) + 1))]])
        gt = np.append(gt, (state.u - self.u0).sum())
        # the per-image unknowns by their Schur complement: hut' huu^-1 [gu, hut] is all it needs
        factor = Cholesky(huu)
        form = factor.inverse_form(np.column_stack([gu, hut]))
        dt = np.linalg.solve(htt - form[1:, 1:], -gt + form[1:, 0])
        du = -factor.solve(gu + hut @ dt)
        dt = dt[:-1]  # the multiplier's part is done
        da = -(ga + (np.concatenate(pa) * (ops @ du)).reshape(3, -1).sum(axis=0) + xta.T @ dt) * inv
        if self.solve_offsets:
            dt = self.image_basis @ dt
            return _State(u=du, albedo=da, scales=dt[:k_images], offsets=dt[k_images:].reshape(k_images, 2))
        return _State(u=du, albedo=da, scales=dt, offsets=np.zeros((k_images, 2)))


def datum_complement(maplet: MapletGrid, data: MapletImages) -> np.ndarray:
    """(2K, m) orthonormal basis of the image offsets (sample, line per image) orthogonal to those
    a shift of the maplet along its local x and y would cause (m = 2K - 2 in general). A shift
    along z stays free: `refine` holds the mean height, and the offsets absorb its parallax."""
    shift = np.column_stack([image_motion(data, maplet.frame.origin, axis, step_km=maplet.spacing_km).ravel()
                             for axis in maplet.frame.rotation[:2]])
    u, sv, _ = np.linalg.svd(shift)
    rank = int((sv > 1e-9 * sv.max()).sum()) if sv.size and sv.max() > 0 else 0
    return u[:, rank:]


def image_motion(data: MapletImages, point: np.ndarray, direction: np.ndarray, *, step_km: float) -> np.ndarray:
    """(K, 2) how each image sees `point` (body-fixed, km) move as it moves along the unit
    `direction` (sample, line; px per km), by central differences over +-step_km."""
    step = step_km * np.asarray(direction, float)
    return np.array([project(point + step, camera, pose) - project(point - step, camera, pose)
                     for camera, pose in zip(data.cameras, data.poses, strict=True)]).reshape(-1, 2) / (2 * step_km)


def _advance(state: _State, step: _State, t: float) -> _State | None:
    """state + t * step with the scales re-gauged to geometric mean 1; None if a scale turns <= 0."""
    scales = state.scales + t * step.scales
    if np.any(scales <= 0):
        return None
    gauge = np.exp(np.mean(np.log(scales)))
    return _State(u=state.u + t * step.u, albedo=(state.albedo + t * step.albedo) * gauge,
                  scales=scales / gauge, offsets=state.offsets + t * step.offsets)


def _backtrack(problem: _Problem, state: _State, ev: _Evaluation, step: _State) -> tuple[_State, _Evaluation] | None:
    """The longest of the step, its half, quarter ... 1/32 that lowers the objective (re-projected
    at the trial heights), with its evaluation; None if none does."""
    t = 1.0
    while t >= 1 / 32:
        trial = _advance(state, step, t)
        if trial is not None:
            trial_ev = problem.evaluate(trial)
            if trial_ev.cost <= ev.cost:
                return trial, trial_ev
        t /= 2
    return None


@dataclass(frozen=True)
class Solver:
    """Every setting of `refine`.

    tolerance: RMS height change of one step that ends the iterations, in node spacings;
    cost_tolerance: the relative decrease of the objective in one step that ends them (the steps
    left after 1% move heights by about a tenth of a spacing RMS, mostly at nodes few images see,
    and take as long again: bench/RESULTS.md). slope_weight, height_weight: strengths of the
    ties to the starting slopes and heights (divided by w_PWM); slope_scale: the slope change
    (dimensionless, dz per spacing) beyond which the slope tie grows only linearly (lower keeps
    more of the boulders the start lacks, higher keeps shadow-poor maplets closer to the start);
    albedo_weight: of the tie to the maplet's albedo (or to the median albedo if it has none);
    solve_offsets: refine the images' pointing offsets too, jointly (image gradients as their
    derivatives), tied to the given ones by offset_weight per px^2. shadow_weight: of the shadow
    term, per image and node, on the shapes of maplets whose images carry their shadows
    (MapletImages.shade); higher pulls the shadows' casters up harder than the photometry holds
    them (bench/RESULTS.md). lidar_weight: of each laser altimeter spot's squared height
    residual in its sigmas, against the images' (module docstring; bench/maplet_lidar.py
    measures what it costs and gains).
    """

    max_iterations: int = 30
    tolerance: float = 0.01
    cost_tolerance: float = 1e-2
    slope_weight: float = 0.02
    slope_scale: float = 0.17
    height_weight: float = 1e-3
    albedo_weight: float = 1e-3
    offset_weight: float = 1e-3
    solve_offsets: bool = True
    shadow_weight: float = 0.05
    lidar_weight: float = 1e-3


SOLVER = Solver()


def refine(
    maplet: MapletGrid,
    data: MapletImages,
    *,
    mode: Mode = "pwm",
    offsets: np.ndarray | None = None,
    solver: Solver = SOLVER,
    spots: MapletSpots = NO_SPOTS,
) -> Refinement:
    """Refine the maplet's heights and albedo and the images' brightness scales (module docstring).

    mode: 'pwm' (pixel weights and region weight of `data`) or 'standard' (every visible node
    weighs 1, shadows included, w_PWM = 1). offsets: (K, 2) pointing corrections (sample, line),
    px, e.g. from `pwm.alignment.align`, the start of the joint solution. solver: the iteration's
    settings (`Solver`). spots: the laser altimeter's over the maplet, in its frame. Nodes without
    data keep the starting shape.
    """
    k_images = data.count
    weights, region = data.data_weights(mode)
    start = np.zeros((k_images, 2)) if offsets is None else np.asarray(offsets, float).reshape(k_images, 2)
    problem = _Problem(maplet, data, weights=weights, region=region, offsets=start, solve_offsets=solver.solve_offsets,
                       slope_weight=solver.slope_weight, slope_scale=solver.slope_scale,
                       height_weight=solver.height_weight, albedo_weight=solver.albedo_weight,
                       offset_weight=solver.offset_weight, shadow_weight=solver.shadow_weight,
                       spots=spots, lidar_weight=solver.lidar_weight)
    state, ev = problem.start()
    converged = not ev.rows.any()
    iterations = 0
    while not converged and iterations < solver.max_iterations:
        iterations += 1
        step = problem.step(state, ev)
        converged = float(np.sqrt(np.mean(step.u**2))) < solver.tolerance
        accepted = _backtrack(problem, state, ev, step)
        if accepted is None:
            break
        converged |= ev.cost - accepted[1].cost < solver.cost_tolerance * ev.cost
        state, ev = accepted

    n = maplet.n
    used = ev.rows > 0
    misfit = np.where(used, ev.residuals / np.where(used, ev.rows, 1.0), 0.0)
    count = used.sum(axis=1)
    rms = np.where(count > 0, np.sqrt((misfit**2).sum(axis=1) / np.maximum(count, 1)), np.nan)
    in_sigmas = problem.spot_residuals(state.u) * maplet.spacing_km / spots.sigma_km
    # the predicted brightness over the mean is s A G / I_ref: its slope derivatives scale alike
    gain = state.scales[:, None] * state.albedo[None, :] / problem.i_ref
    grid = (k_images, n, n)
    return Refinement(heights=(state.u * maplet.spacing_km).reshape(n, n), albedo=state.albedo.reshape(n, n),
                      scales=state.scales, offsets=state.offsets, rms=rms, iterations=iterations,
                      converged=converged, weights=(ev.rows * problem.i_ref).reshape(grid),
                      misfit=np.where(used, misfit / problem.i_ref, np.nan).reshape(grid),
                      slope_gradients=np.stack([gain * ev.Gp, gain * ev.Gq], axis=-1).reshape(*grid, 2),
                      lidar_rms=float(np.sqrt(np.mean(in_sigmas**2))) if spots.count else float("nan"))
