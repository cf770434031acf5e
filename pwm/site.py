"""Site products on a regular height grid: slope, roughness, relief and hazard.

Heights are in metres along the site frame's z axis (the regional normal: pwm.frames.local_frame
of the site's mean normal), on a square grid of `spacing_m` between nodes, arrays [line, sample]
= [y, x]; NaN where there is no surface. A result is NaN (roughness, relief, slope) where its
stencil or window reaches a node without data or past the grid's edge.

A site's grid comes from a mesh (`resample_site`, `sample_grid`): the site frame at the surface
point of a latitude and longitude, the grid at the spacing of the faces there, each node where a
ray down the frame's z first meets the surface (pwm.sampling).

Slope, roughness and relief of a site are taken over one baseline: the least-squares plane
fitted over a square window of that side about each node gives the slope (its tilt), the
roughness (the RMS residual about it) and the relief (the height above it). The baseline is the
scale a team asks about, e.g. a spacecraft's or a sampler's footprint; slopes at the grid's own
spacing (central differences, no baseline) are what the evaluation uses to find steep walls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import correlate, uniform_filter

from pwm.frames import LocalFrame, latlon_to_unit, local_frame
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.sampling import drop_rays

BASELINE_M = 1.0
"""Side (m) of the square window a plane is fitted over for slope, roughness and relief, by
default."""


@dataclass(frozen=True)
class SiteGrid:
    """Heights (km, along the frame's z) and albedo on the regular grid x_km, y_km of the site
    frame; arrays (ny, nx), NaN where the surface is not found or has no albedo; sigma_km the
    surface's 1-sigma heights there (pwm.uncertainty), None where the mesh has none."""

    frame: LocalFrame
    x_km: np.ndarray
    y_km: np.ndarray
    height_km: np.ndarray
    albedo: np.ndarray
    sigma_km: np.ndarray | None = None


def resample_site(mesh: Mesh, *, lat_deg: float, lon_deg: float, radius_km: float,
                  max_half_nodes: int) -> SiteGrid:
    """Resample `mesh` (km, body-fixed) on a square grid about the site at planetocentric
    latitude and east longitude (deg).

    The site frame's origin is the outermost surface point along the site's radial line; its
    z axis the area-weighted mean normal of the faces within radius_km of it (x east, y north,
    pwm.frames.local_frame); the grid spacing the mean edge of those faces, at most
    2 max_half_nodes + 1 nodes a side, spanning +-radius_km. Each node is where a ray down
    the frame's z axis first meets the surface (`sample_grid`). ValueError if the radial line
    misses.
    """
    tracer = RayTracer(mesh)
    reach = 2.0 * float(np.linalg.norm(mesh.vertices, axis=1).max())
    direction = latlon_to_unit(lat_deg, lon_deg)
    down = tracer.intersect((reach * direction)[None], -direction[None])
    if not down.hit[0]:
        raise ValueError(f"no surface along latitude {lat_deg}, longitude {lon_deg}")
    origin = tracer.hit_points((reach * direction)[None], -direction[None], down)[0]
    corners = mesh.vertices[mesh.faces]
    near = np.linalg.norm(corners.mean(axis=1) - origin, axis=1) <= radius_km
    near[down.face[0]] = True
    normals = np.cross(corners[near, 1] - corners[near, 0], corners[near, 2] - corners[near, 0])
    frame = local_frame(origin, normals.sum(axis=0))
    edge = float(np.linalg.norm(corners[near] - np.roll(corners[near], 1, axis=1), axis=2).mean())
    half = min(max_half_nodes, max(1, math.ceil(radius_km / edge)))
    axis = np.linspace(-radius_km, radius_km, 2 * half + 1)
    return sample_grid(mesh, frame, axis, axis)


def sample_grid(mesh: Mesh, frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray) -> SiteGrid:
    """The heights, albedo and 1-sigma heights of `mesh` at the nodes x_km, y_km of `frame`: where
    a ray down the frame's z axis first meets the surface (NaN where it misses). ValueError when no vertex lies
    within the grid's reach of the frame's z axis."""
    tracer = RayTracer(mesh)
    # Rays start above everything within the grid's horizontal reach, so the first hit is the top.
    local = frame.to_local(mesh.vertices)
    reach = 1.5 * max(np.abs(x_km).max(), np.abs(y_km).max())
    beside = np.hypot(local[:, 0], local[:, 1]) <= reach
    if not beside.any():
        raise ValueError("the grid lies beside the surface")
    top = float(local[beside, 2].max()) + 1e-3 * reach
    xx, yy = np.meshgrid(x_km, y_km)
    hits, height = drop_rays(tracer, frame, xx.ravel(), yy.ravel(), top_km=top, on_facets=True)
    albedo = (np.where(hits.hit, tracer.interpolate(mesh.albedo, hits), np.nan)
              if mesh.albedo is not None else np.full(len(height), np.nan))
    sigma = None if mesh.sigma is None else np.where(hits.hit, tracer.interpolate(mesh.sigma, hits), np.nan)
    return SiteGrid(frame=frame, x_km=np.asarray(x_km), y_km=np.asarray(y_km),
                    height_km=height.reshape(xx.shape), albedo=albedo.reshape(xx.shape),
                    sigma_km=None if sigma is None else sigma.reshape(xx.shape))


@dataclass(frozen=True)
class HazardThresholds:
    """A node is hazardous where the slope (deg from the regional normal) is above
    max_slope_deg, where the surface stands more than max_relief_m above the plane fitted over
    the baseline about it (a boulder), or where either is unknown (no data)."""

    max_slope_deg: float = 20.0
    max_relief_m: float = 0.5

    def __post_init__(self) -> None:
        if not (0.0 < self.max_slope_deg < 90.0 and self.max_relief_m > 0.0):
            raise ValueError(f"thresholds must be a slope in (0, 90) deg and a relief > 0 m, "
                             f"got {self.max_slope_deg}, {self.max_relief_m}")


def slope_deg(height_m: np.ndarray, *, spacing_m: float,
              baseline_m: float | None = None) -> np.ndarray:
    """The angle (deg) between the surface normal and the regional normal at each node.

    baseline_m None: from central differences at the grid's spacing (one-sided at the edges),
    NaN at and beside nodes without data. A baseline: the tilt of the least-squares plane fitted
    over the square window of side baseline_m (window_nodes) centred on each node."""
    if baseline_m is not None:
        return _plane_fit(height_m, spacing_m=spacing_m, baseline_m=baseline_m)[2]
    height = _grid(height_m, spacing_m)
    dh_dy, dh_dx = np.gradient(height, spacing_m)
    slope = np.degrees(np.arctan(np.hypot(dh_dx, dh_dy)))
    slope[np.isnan(height)] = np.nan
    return slope


def window_nodes(*, spacing_m: float, baseline_m: float) -> int:
    """Nodes on a side of the window spanning `baseline_m`: odd, at least 3."""
    if not baseline_m > 0:
        raise ValueError(f"baseline_m must be > 0, got {baseline_m}")
    return max(3, 2 * round(baseline_m / spacing_m / 2) + 1)


def roughness_m(height_m: np.ndarray, *, spacing_m: float,
                baseline_m: float = BASELINE_M) -> np.ndarray:
    """RMS deviation (m) of the heights from the least-squares plane fitted over the square
    window of side `baseline_m` (window_nodes) centred on each node."""
    return _plane_fit(height_m, spacing_m=spacing_m, baseline_m=baseline_m)[1]


def relief_m(height_m: np.ndarray, *, spacing_m: float,
             baseline_m: float = BASELINE_M) -> np.ndarray:
    """Height (m) of each node above the least-squares plane fitted over the square window of
    side `baseline_m` centred on it: a boulder stands out by about its height."""
    height = _grid(height_m, spacing_m)
    return height - _plane_fit(height, spacing_m=spacing_m, baseline_m=baseline_m)[0]


def hazard(slope: np.ndarray, relief: np.ndarray, thresholds: HazardThresholds) -> np.ndarray:
    """Boolean map of hazardous nodes (HazardThresholds says which), from slope_deg and
    relief_m of the same grid."""
    slope, relief = np.asarray(slope, dtype=float), np.asarray(relief, dtype=float)
    if slope.shape != relief.shape:
        raise ValueError(f"slope {slope.shape} and relief {relief.shape} differ in shape")
    with np.errstate(invalid="ignore"):
        return ((slope > thresholds.max_slope_deg) | (relief > thresholds.max_relief_m)
                | np.isnan(slope) | np.isnan(relief))


def _grid(height_m: np.ndarray, spacing_m: float) -> np.ndarray:
    height = np.asarray(height_m, dtype=np.float64)
    if height.ndim != 2 or min(height.shape) < 3:
        raise ValueError(f"height_m must be a 2-D grid of at least 3 x 3 nodes, got {height.shape}")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
    return height


def _plane_fit(height_m: np.ndarray, *, spacing_m: float,
               baseline_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fitted plane's height at each window's centre, the RMS residual (m) and the plane's
    tilt (deg).

    The window's offsets u, v from its centre are symmetric, so Σu = Σv = Σuv = 0 and the fit
    h ≈ a + b u + c v separates: a = mean h, b = Σuh / Σu², c = Σvh / Σv²; the residual sum of
    squares is Σh² - n a² - b² Σu² - c² Σv². Heights are taken about the grid's mean first so
    that large heights do not cancel in Σh² - n a².
    """
    height = _grid(height_m, spacing_m)
    n = window_nodes(spacing_m=spacing_m, baseline_m=baseline_m)
    half = n // 2
    missing = np.isnan(height)
    if missing.all():
        nan = np.full(height.shape, np.nan)
        return nan, nan.copy(), nan.copy()
    level = float(np.nanmean(height))
    filled = np.where(missing, 0.0, height - level)
    # windows that reach a node without data, or past the edge, give NaN
    incomplete = uniform_filter(missing.astype(float), n, mode="constant", cval=1.0) > 1e-9
    mean = uniform_filter(filled, n, mode="constant")
    offsets = np.arange(-half, half + 1, dtype=float)
    u = np.broadcast_to(offsets[None, :], (n, n))
    v = np.broadcast_to(offsets[:, None], (n, n))
    su2 = float((u ** 2).sum())
    b = correlate(filled, u, mode="constant") / su2
    c = correlate(filled, v, mode="constant") / su2
    # per node: (Σh² - n a² - (b² + c²) Σu²) / n
    square = uniform_filter(filled ** 2, n, mode="constant") - mean ** 2
    residual = np.maximum(square - (b ** 2 + c ** 2) * su2 / n ** 2, 0.0)
    plane = mean + level
    tilt = np.degrees(np.arctan(np.hypot(b, c) / spacing_m))  # b, c: height per node step
    for values in (plane, residual, tilt):
        values[incomplete] = np.nan
    return plane, np.sqrt(residual), tilt
