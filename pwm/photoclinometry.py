"""Photoclinometric refinement of one maplet: heights and albedo from the brightness of K images.

Unknowns are the node heights themselves (with the slopes p = -dz/dx, q = -dz/dy taken by finite
differences), the albedo per node and a brightness scale per image. Solving for heights rather
than for free slopes makes the slope field integrable by construction: the PWM integrability term
w_i (p_y - q_x)^2 is identically zero (its w_i -> infinity limit), and no separate slope
integration step is needed between re-projections. The objective (METHOD.md section 5), in
reflectance normalised by the mean data brightness I_ref:

    sum_k sum_nodes (w_k (I_k - s_k A G_k(p, q)) / I_ref)^2
      + (slope_weight / w_PWM) sum_edges ((p - p0)^2 + (q - q0)^2)
      + (height_weight / w_PWM) sum_nodes ((z - z0) / spacing)^2
      + albedo_weight sum_nodes ((A - A_ref) / A_ref)^2

G is the McEwen lunar-Lambert function of pwm.photometry evaluated with the node normal from
central differences of the heights (one-sided on the maplet border). The slope tie uses forward
differences, which also see the odd-even height patterns that central differences cannot. The
height tie fixes what brightness cannot: the mean height and the long-wavelength shape. The
brightness scales are gauged to a geometric mean of 1 (A * s is all the data can tell).
Each Gauss-Newton iteration re-projects the nodes at their current heights, re-extracts the
images and solves one linearised step, until the RMS height change is below the tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from pwm.camera import Camera, Pose
from pwm.maplets import Maplet
from pwm.photometry import lunar_lambert, mcewen_l

Mode = Literal["pwm", "standard"]


@dataclass
class MapletImages:
    """The K images of one maplet with their geometry and per-node masks and weights.

    images: K arrays [line, sample] of reflectance-like values (I/F), NaN where missing;
    cameras, poses: their intrinsics (pixels) and body-fixed poses; sun_directions: (K, 3) unit
    vectors towards the Sun, body-fixed; visible, lit: (K, n, n) booleans per node (not occluded,
    not shadowed); weights: (K, n, n) per-node weight w_k (0 excludes the node from image k);
    region_weight: the maplet's w_PWM in (0, 1].
    """

    images: list[np.ndarray]
    cameras: list[Camera]
    poses: list[Pose]
    sun_directions: np.ndarray
    visible: np.ndarray
    lit: np.ndarray
    weights: np.ndarray
    region_weight: float = 1.0

    def __post_init__(self) -> None:
        k = len(self.images)
        self.sun_directions = np.asarray(self.sun_directions, float).reshape(k, 3)
        self.sun_directions = self.sun_directions / np.linalg.norm(self.sun_directions, axis=1, keepdims=True)
        self.visible = np.asarray(self.visible, bool)
        self.lit = np.asarray(self.lit, bool)
        self.weights = np.asarray(self.weights, float)
        if not (len(self.cameras) == len(self.poses) == k):
            raise ValueError("one camera and one pose per image")
        if not (self.visible.shape == self.lit.shape == self.weights.shape) or self.weights.shape[0] != k:
            raise ValueError("visible, lit and weights must all be (K, n, n)")
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
    image (geometric mean 1); rms: (K,) RMS of I - s A G over the nodes each image weighs
    (reflectance units; NaN if none); iterations: Gauss-Newton steps taken; converged: the RMS
    height change of the last step fell below the tolerance."""

    heights: np.ndarray
    albedo: np.ndarray
    scales: np.ndarray
    rms: np.ndarray
    iterations: int
    converged: bool


def node_pixels(maplet: Maplet, data: MapletImages, *, heights: np.ndarray | None = None,
                offsets: np.ndarray | None = None) -> np.ndarray:
    """(K, n, n, 2) pixel coordinates (sample, line) of the nodes in each image, plus the per-image
    offsets (K, 2) (pointing corrections from `pwm.alignment.align`); NaN behind the camera."""
    points = maplet.nodes_body(heights).reshape(-1, 3)
    out = np.empty((data.count, maplet.n, maplet.n, 2))
    for k, (camera, pose) in enumerate(zip(data.cameras, data.poses)):
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
    s, l = pixels[..., 0], pixels[..., 1]
    inside = (s >= 0) & (s <= width - 1) & (l >= 0) & (l <= height - 1)
    s = np.where(inside, s, 0.0)
    l = np.where(inside, l, 0.0)
    s0 = np.minimum(np.floor(s).astype(np.intp), max(width - 2, 0))
    l0 = np.minimum(np.floor(l).astype(np.intp), max(height - 2, 0))
    fs, fl = s - s0, l - l0
    flat = image.ravel()
    i00 = l0 * width + s0
    s1 = 1 if width > 1 else 0
    l1 = width if height > 1 else 0
    top = (1 - fs) * flat[i00] + fs * flat[i00 + s1]
    bottom = (1 - fs) * flat[i00 + l1] + fs * flat[i00 + l1 + s1]
    return np.where(inside, (1 - fl) * top + fl * bottom, np.nan)


def extract(maplet: Maplet, data: MapletImages, *, heights: np.ndarray | None = None,
            offsets: np.ndarray | None = None) -> np.ndarray:
    """(K, n, n) image values at the nodes (bilinear), NaN outside the frames or behind a camera."""
    pixels = node_pixels(maplet, data, heights=heights, offsets=offsets)
    return np.stack([bilinear(image, pixels[k]) for k, image in enumerate(data.images)])


@lru_cache(maxsize=8)
def _gradient_operators(n: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse d/dj and d/di on an n x n row-major grid in units of one spacing, as np.gradient:
    central differences inside, one-sided on the border."""
    rows = np.arange(n)
    lo = np.clip(rows - 1, 0, n - 1)
    hi = np.clip(rows + 1, 0, n - 1)
    step = (hi - lo).astype(float)
    d = sp.csr_matrix((np.concatenate([1 / step, -1 / step]), (np.tile(rows, 2), np.concatenate([hi, lo]))), shape=(n, n))
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


def _geometry(maplet: Maplet, data: MapletImages, heights: np.ndarray) -> _Geometry:
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


def predict(maplet: Maplet, data: MapletImages, *, heights: np.ndarray | None = None,
            albedo: np.ndarray | float | None = None) -> np.ndarray:
    """(K, n, n) brightness A * G predicted at the nodes from the maplet's shape (render by formula,
    no cast shadows). albedo: per node or scalar; the maplet's own, or 1, if None."""
    h = maplet.heights if heights is None else heights
    a = albedo if albedo is not None else (maplet.albedo if maplet.albedo is not None else 1.0)
    p, q = slopes(h, maplet.spacing_km)
    G, _, _ = _shading(p.ravel(), q.ravel(), _geometry(maplet, data, h))
    return (np.broadcast_to(a, h.shape).ravel() * G).reshape(data.count, maplet.n, maplet.n)
