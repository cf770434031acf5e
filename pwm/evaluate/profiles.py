"""How much of each boulder's height a model recovers (SPC recovered steep boulders at 50-70%).

Heights are along the site frame's z on a regular local x-y grid, km: x_km and y_km increasing,
heights[i, j] the node at (x_km[j], y_km[i]).
"""

from __future__ import annotations

import numpy as np


def boulder_height_ratio(
    x_km: np.ndarray,
    y_km: np.ndarray,
    truth_heights_km: np.ndarray,
    model_heights_km: np.ndarray,
    *,
    centres_km: np.ndarray,
    diameters_km: np.ndarray,
    annulus_diameters: tuple[float, float] = (1.0, 1.5),
    curved: bool = False,
    ground: np.ndarray | None = None,
) -> np.ndarray:
    """Model relief over truth relief for each boulder, (B,).

    A boulder's relief is the highest node within its radius minus the median of the ring of
    nodes between annulus_diameters[0] and [1] diameters from its centre (its surroundings).
    curved: the surroundings are a quadric fitted to the ring instead, for boulders large beside
    the body's radius of curvature, whose ring lies metres below their foot.
    ground: (len(y_km), len(x_km)) True where a node may be a boulder's surroundings (off every
    boulder, as the truth knows them): a ring that crosses a neighbour, taller or smaller, would
    otherwise measure the boulder from the neighbour's top and the model's error there.
    centres_km: (B, 2) local x, y; diameters_km: (B,). nan nodes (no model) are ignored; a
    boulder whose disc or ring has no valid node, or whose truth relief is not positive, gives nan.
    """
    x = np.asarray(x_km, float)
    y = np.asarray(y_km, float)
    truth = np.asarray(truth_heights_km, float)
    model = np.asarray(model_heights_km, float)
    if truth.shape != (len(y), len(x)) or model.shape != truth.shape:
        raise ValueError("heights must be (len(y_km), len(x_km)) for truth and model alike")
    usable = np.ones(truth.shape, bool) if ground is None else np.asarray(ground, bool)
    if usable.shape != truth.shape:
        raise ValueError("ground must be (len(y_km), len(x_km)) as the heights are")
    centres = np.asarray(centres_km, float).reshape(-1, 2)
    diameters = np.asarray(diameters_km, float).reshape(-1)
    outer = annulus_diameters[1] * diameters
    ratios = np.full(len(centres), np.nan)
    for i, ((cx, cy), diameter, reach) in enumerate(zip(centres, diameters, outer, strict=True)):
        # Only the window around the boulder is searched: the grid is sorted in x and y.
        cols = slice(np.searchsorted(x, cx - reach), np.searchsorted(x, cx + reach, side="right"))
        rows = slice(np.searchsorted(y, cy - reach), np.searchsorted(y, cy + reach, side="right"))
        r = np.hypot(x[cols][None, :] - cx, y[rows][:, None] - cy)
        disc = r <= 0.5 * diameter
        ring = (r >= annulus_diameters[0] * diameter) & (r <= reach) & usable[rows, cols]
        dx, dy = np.meshgrid(x[cols] - cx, y[rows] - cy)
        basis = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=-1) if curved else None
        truth_relief = _relief(truth[rows, cols], disc, ring, basis)
        model_relief = _relief(model[rows, cols], disc, ring, basis)
        if truth_relief > 0:
            ratios[i] = model_relief / truth_relief
    return ratios


def _relief(heights: np.ndarray, disc: np.ndarray, ring: np.ndarray, basis: np.ndarray | None) -> float:
    """Highest node of the disc above its surroundings: the ring's median, or with a basis (per
    node, the quadric's terms) the quadric fitted to the ring by least squares."""
    on_disc, on_ring = disc & np.isfinite(heights), ring & np.isfinite(heights)
    if not on_disc.any() or on_ring.sum() < (1 if basis is None else 6):
        return np.nan
    if basis is None:
        return float(heights[on_disc].max() - np.median(heights[on_ring]))
    coefficients = np.linalg.lstsq(basis[on_ring], heights[on_ring], rcond=None)[0]
    return float(np.max(heights[on_disc] - basis[on_disc] @ coefficients))
