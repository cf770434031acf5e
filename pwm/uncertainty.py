"""Height uncertainty: a 1-sigma height per node of a refined maplet, and per vertex of the model
fused from maplets.

A node's sigma is a calibrated proxy, not the solution's formal covariance: the errors that
remain after photoclinometry are mostly systematic (a boulder's top held low, a shadowed flank),
and the formal covariance of a least-squares fit does not see them. What does see them is where
the images disagree with the solved shape. At each node:

    sigma = spacing * sqrt(floor^2 + (misfit_gain * relative_misfit * slope_sensitivity)^2)

- relative_misfit: the images' brightness misfit at the node (the RMS over the images, weighed
  as the solution weighed them, smoothed over `smoothing_nodes`), over the maplet's median
  misfit. Dividing by the median takes out what every node of the maplet shares (image noise,
  the photometric law's mismatch): that is not height error.
- slope_sensitivity: how little the images' brightness says of the slope there, sqrt(trace
  (M^-1) / 2), with M the weighed mean over the images of g g^T, g the gradient of the
  relative brightness with respect to the slopes (p, q): high where every Sun lies on one side or
  the images graze the surface.
- floor: what even nodes where images and shape agree keep (the placement of the maplet by
  parallax, the regularization).

The fused model's sigma at a vertex is the RMS of the sigmas of the maplets over it, weighed as
fusion weighs them (region weight times the edge taper, pwm.fusion.edge_taper). Overlapping
maplets share their images, so their errors are not independent and their sigmas are not
combined as if they were; nor is their spread about the fused surface added, which fusion
averages away. The constants were calibrated on the proving ground's sites against the
truth (bench/RESULTS.md, "height uncertainty"); `pwm evaluate` reports the share of vertices
within one and two sigma of the truth on any model that carries a sigma.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pwm.fusion import edge_taper
from pwm.maplets import MapletGrid
from pwm.tiling import level_of


@dataclass(frozen=True)
class Uncertainty:
    """How a refined node's 1-sigma height is made (module docstring). floor_spacings: the sigma
    of a node where the images agree with the shape, in node spacings; misfit_gain: node spacings
    of sigma per unit of relative misfit times slope sensitivity; smoothing_nodes: the Gaussian
    sigma, in nodes, over which the misfit is averaged (an error in height shows as misfit on the
    slopes about it)."""

    floor_spacings: float = 0.08
    misfit_gain: float = 0.052
    smoothing_nodes: float = 2.0

    def __post_init__(self) -> None:
        if not (self.floor_spacings > 0 and self.misfit_gain >= 0 and self.smoothing_nodes >= 0):
            raise ValueError("uncertainty: a positive floor, a non-negative gain and smoothing")


UNCERTAINTY = Uncertainty()


def node_sigma(*, weights: np.ndarray, misfit: np.ndarray, slope_gradients: np.ndarray, spacing_km: float,
               uncertainty: Uncertainty = UNCERTAINTY) -> np.ndarray:
    """(n, n) 1-sigma heights (km) of a refined maplet's nodes; NaN at nodes that no image weighed.

    weights: (K, n, n) each image's weight at each node in the solution; misfit: (K, n, n) the
    relative brightness misfit (observed minus predicted, over the mean brightness) there;
    slope_gradients: (K, n, n, 2) the relative brightness's derivatives with respect to the
    slopes p and q."""
    w = np.where(np.isfinite(misfit), np.clip(weights, 0.0, None), 0.0)
    total = w.sum(axis=0)
    seen = total > 0
    if not seen.any():
        return np.full(total.shape, np.nan)
    squared = (w * np.nan_to_num(misfit) ** 2).sum(axis=0)
    if uncertainty.smoothing_nodes > 0:
        # weights smoothed alike: a node's neighbours count as much as their images weighed
        squared = ndimage.gaussian_filter(squared, uncertainty.smoothing_nodes, mode="nearest")
        total_smooth = ndimage.gaussian_filter(total, uncertainty.smoothing_nodes, mode="nearest")
    else:
        total_smooth = total
    local = np.sqrt(squared / np.where(total_smooth > 0, total_smooth, 1.0))
    relative = local / max(float(np.median(local[seen])), 1e-12)
    gp, gq = np.nan_to_num(slope_gradients[..., 0]), np.nan_to_num(slope_gradients[..., 1])
    # M, the weighed mean of g g^T: its three distinct entries
    scale = 1.0 / np.where(seen, total, 1.0)
    pp, pq, qq = ((w * a * b).sum(axis=0) * scale for a, b in ((gp, gp), (gp, gq), (gq, gq)))
    det = pp * qq - pq**2
    trace = pp + qq
    # a node whose images all lie in one plane of slopes (det 0) says nothing of the other slope
    blind = seen & (det <= 1e-12 * np.maximum(trace, 1e-300) ** 2)
    sensitivity = np.sqrt(trace / (2.0 * np.where(det > 0, det, 1.0)))
    excess = np.where(blind, np.inf, uncertainty.misfit_gain * relative * sensitivity)
    return np.where(seen, spacing_km * np.hypot(uncertainty.floor_spacings, excess), np.nan)


def vertex_sigma(vertices: np.ndarray, maplets: Iterable[MapletGrid], *, taper_fraction: float) -> np.ndarray:
    """(N,) 1-sigma heights (km) of a fused model's vertices (N, 3, body-fixed km) from the
    maplets it was fused from, read one at a time (module docstring); NaN where no maplet with
    sigmas reaches. Where maplets of several levels reach a vertex, the finest level's say: a
    finer level is laid over the coarser ones (pwm.levels), whose distance from it is no error."""
    tree = cKDTree(vertices)
    sums: dict[int, np.ndarray] = {}  # per level: total weight, weighted sum of variances
    for maplet in maplets:
        if maplet.sigma is None:
            continue
        half = maplet.axis_km[-1]
        near = np.asarray(tree.query_ball_point(maplet.frame.origin, half * np.sqrt(2.0) * 1.05), dtype=np.int64)
        if not len(near):
            continue
        local = maplet.frame.to_local(vertices[near])
        # fractional node indices: x along columns, y along rows
        col = local[:, 0] / maplet.spacing_km + (maplet.n - 1) / 2
        row = local[:, 1] / maplet.spacing_km + (maplet.n - 1) / 2
        inside = (col >= 0) & (col <= maplet.n - 1) & (row >= 0) & (row <= maplet.n - 1)
        near, at = near[inside], np.stack([row[inside], col[inside]])
        taper = edge_taper(maplet.n, maplet.spacing_km, taper_fraction)
        sigma = ndimage.map_coordinates(maplet.sigma, at, order=1, mode="nearest")
        w = maplet.weight * ndimage.map_coordinates(taper, at, order=1, mode="nearest")
        ok = np.isfinite(sigma) & (w > 0)
        level = sums.setdefault(int(level_of(maplet.spacing_km)), np.zeros((2, len(vertices))))
        np.add.at(level[0], near[ok], w[ok])
        np.add.at(level[1], near[ok], w[ok] * sigma[ok] ** 2)
    out = np.full(len(vertices), np.nan)
    for key in sorted(sums, reverse=True):  # coarsest first: each finer level overwrites where it reaches
        weight, second = sums[key]
        reached = weight > 0
        out[reached] = np.sqrt(second[reached] / weight[reached])
    return out


def sigma_summary(sigma_km: np.ndarray) -> dict:
    """A model's 1-sigma heights in figures: the share of its vertices that have one, and their
    median and 90th percentile (m)."""
    told = np.isfinite(sigma_km)
    if not told.any():
        return {"vertex_share": 0.0}
    median, p90 = np.percentile(sigma_km[told], [50, 90]) * 1e3
    return {"vertex_share": float(np.mean(told)), "median_m": float(median), "p90_m": float(p90)}
