"""Image-to-maplet registration: per-image pixel offsets that correct pointing (SPC's align step).

Each image is compared with the brightness the maplet predicts at its nodes (albedo times the
lunar-Lambert G of the node normals, `pwm.photoclinometry.predict`). The offset (sample, line), px,
is added to the projected node positions. Coarse to fine: normalised cross-correlation over whole
pixel shifts, a quadratic fit of its peak, then Gauss-Newton on the least-squares misfit
I(x + offset) - (gain * predicted + bias) to a fraction of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.maplets import Maplet
from pwm.photoclinometry import MapletImages, bilinear, bilinear_gradient, node_pixels, predict


@dataclass
class Alignment:
    """offsets: (K, 2) pointing corrections (sample, line), px; correlation: (K,) normalised
    cross-correlation of image and prediction at the offset (NaN where too few nodes)."""

    offsets: np.ndarray
    correlation: np.ndarray


def align(
    maplet: Maplet,
    data: MapletImages,
    *,
    heights: np.ndarray | None = None,
    albedo: np.ndarray | float | None = None,
    offsets: np.ndarray | None = None,
    search_px: int = 4,
    min_nodes: int = 50,
    max_iterations: int = 20,
) -> Alignment:
    """Register each image to the maplet's predicted brightness.

    heights, albedo: the maplet's shape and albedo to predict from (default the maplet's own;
    albedo 1 if it has none: then only shading carries the signal). offsets: (K, 2) starting
    offsets, px (zero if None); the search covers +-search_px whole pixels around them. Nodes with
    data weight 0 are not compared. An image with fewer than min_nodes usable nodes keeps its
    starting offset.
    """
    start = np.zeros((data.count, 2)) if offsets is None else np.asarray(offsets, float)
    pixels = node_pixels(maplet, data, heights=heights, offsets=start)
    model = predict(maplet, data, heights=heights, albedo=albedo)
    out = start.copy()
    correlation = np.full(data.count, np.nan)
    for k, image in enumerate(data.images):
        use = (data.weights[k] > 0) & np.isfinite(pixels[k, ..., 0]) & (model[k] > 0)
        if use.sum() < min_nodes:
            continue
        found = _track(image, pixels[k][use], model[k][use], search_px=search_px, min_nodes=min_nodes,
                       max_iterations=max_iterations)
        if found is not None:
            out[k] = start[k] + found[0]
            correlation[k] = found[1]
    return Alignment(offsets=out, correlation=correlation)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else np.nan


def _track(image: np.ndarray, pixels: np.ndarray, model: np.ndarray, *, search_px: int, min_nodes: int,
           max_iterations: int) -> tuple[np.ndarray, float] | None:
    """Offset (sample, line) of `image` that best matches `model` at `pixels`, and its NCC."""
    shifts = np.arange(-search_px, search_px + 1)
    score = np.full((len(shifts), len(shifts)), -np.inf)
    for i, dl in enumerate(shifts):
        for j, ds in enumerate(shifts):
            values = bilinear(image, pixels + (ds, dl))
            ok = np.isfinite(values)
            if ok.sum() >= min_nodes:
                score[i, j] = np.nan_to_num(_ncc(values[ok], model[ok]), nan=-np.inf)
    if not np.isfinite(score).any():
        return None
    i, j = np.unravel_index(np.argmax(score), score.shape)
    coarse = np.array([shifts[j], shifts[i]], float) + _peak(score, i, j)

    offset = coarse.copy()
    values = bilinear(image, pixels + offset)
    ok = np.isfinite(values)
    gain, bias = np.polyfit(model[ok], values[ok], 1)
    for _ in range(max_iterations):
        at = pixels + offset
        values, grad = bilinear_gradient(image, at)
        ok = np.isfinite(values) & np.isfinite(grad).all(axis=1)
        if ok.sum() < min_nodes:
            return None
        # Unknowns: offset (sample, line), gain and bias of I(x + offset) ~ gain * model + bias
        jac = np.column_stack([grad[ok], -model[ok], -np.ones(ok.sum())])
        resid = values[ok] - gain * model[ok] - bias
        step = np.linalg.lstsq(jac, -resid, rcond=None)[0]
        offset += step[:2]
        gain += step[2]
        bias += step[3]
        if np.hypot(*step[:2]) < 1e-4:
            break
    if np.hypot(*(offset - coarse)) > 1.0:
        # Gauss-Newton left the correlation peak it started on: trust the peak.
        offset = coarse
    values = bilinear(image, pixels + offset)
    ok = np.isfinite(values)
    return offset, _ncc(values[ok], model[ok])


def _vertex(lo: float, mid: float, hi: float) -> float:
    """Position (-0.5..0.5) of the maximum of the parabola through three equally spaced scores."""
    den = lo - 2 * mid + hi
    return float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) if np.isfinite(den) and den < 0 else 0.0


def _peak(score: np.ndarray, i: int, j: int) -> np.ndarray:
    """Sub-pixel (sample, line) correction to the whole-pixel peak score[i, j] (line i, sample j)."""
    rows, cols = score.shape
    ds = _vertex(*score[i, j - 1 : j + 2]) if 0 < j < cols - 1 else 0.0
    dl = _vertex(*score[i - 1 : i + 2, j]) if 0 < i < rows - 1 else 0.0
    return np.array([ds, dl])
