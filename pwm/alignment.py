"""Image-to-maplet registration: per-image pixel offsets that correct pointing (SPC's align step).

Each image is compared with the brightness the maplet predicts at its nodes (albedo times the
lunar-Lambert G of the node normals, `pwm.photoclinometry.predict`). The offset (sample, line), px,
is added to the projected node positions.

- `align`, for a maplet whose albedo is known: normalised cross-correlation over whole pixel
  shifts, a quadratic fit of its peak, then Gauss-Newton on the least-squares misfit
  I(x + offset) - (gain * predicted + bias) to a fraction of a pixel.
- `register`, for a maplet still without albedo and images off by many pixels (navigation
  knowledge errors of metres): the albedo each image is compared with comes from the other images
  (leave-one-out least squares at the current offsets); the search runs on a coarse copy of the
  maplet and Gaussian-smoothed images first, then at full resolution, re-estimating the albedo
  after every pass. Its result seeds the joint solution of `pwm.photoclinometry.refine`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pwm.camera import project
from pwm.maplets import MapletGrid
from pwm.photoclinometry import (
    MapletImages,
    bilinear,
    datum_complement,
    image_motion,
    node_pixels,
    predict,
    resampled,
)
from pwm.registration_sums import normal_sums, shift_sums


@dataclass(frozen=True)
class Registration:
    """The settings of registering images to a maplet that no call gives (pwm.config nests them
    in RefinementConfig, whose digest names them).

    align_min_nodes: fewest usable nodes an image is registered by (`align`, `window_rises`); with
    fewer it keeps its offset. align_max_iterations: Gauss-Newton iterations of `align`'s
    sub-pixel step. min_coarse_nodes: fewest nodes a side of a coarser grid worth solving or
    registering on (`register`'s levels, pwm.pipeline's coarse-first solution).
    """

    align_min_nodes: int = 50  # fewest usable nodes an image is registered by
    align_max_iterations: int = 20  # Gauss-Newton iterations of align's sub-pixel step
    min_coarse_nodes: int = 8  # fewest nodes a side of a coarser grid worth solving or registering on


REGISTRATION = Registration()


@dataclass
class Alignment:
    """offsets: (K, 2) pointing corrections (sample, line), px; correlation: (K,) normalised
    cross-correlation of image and prediction at the offset (NaN where too few nodes)."""

    offsets: np.ndarray
    correlation: np.ndarray


def align(
    maplet: MapletGrid,
    data: MapletImages,
    *,
    heights: np.ndarray | None = None,
    albedo: np.ndarray | float | None = None,
    offsets: np.ndarray | None = None,
    search_px: int = 4,
    registration: Registration = REGISTRATION,
) -> Alignment:
    """Register each image to the maplet's predicted brightness.

    heights, albedo: the maplet's shape and albedo to predict from (default the maplet's own;
    albedo 1 if it has none: then only shading carries the signal). offsets: (K, 2) starting
    offsets, px (zero if None); the search covers +-search_px whole pixels around them. Nodes with
    data weight 0 are not compared. An image with fewer than registration.align_min_nodes usable
    nodes keeps its starting offset.
    """
    start = np.zeros((data.count, 2)) if offsets is None else np.asarray(offsets, float)
    pixels = node_pixels(maplet, data, heights=heights, offsets=start)
    model = predict(maplet, data, heights=heights, albedo=albedo)
    return _align_at(data, pixels, model, start, search_px=search_px, min_nodes=registration.align_min_nodes,
                     max_iterations=registration.align_max_iterations)[0]


def _align_at(data: MapletImages, pixels: np.ndarray, model: np.ndarray, start: np.ndarray, *, search_px: int,
              min_nodes: int, max_iterations: int, parts: np.ndarray | None = None) -> list[Alignment]:
    """`align` over the nodes that data.weights keep, from the node pixels (K, n, n, 2) at the
    start offsets (K, 2) and the predicted brightness (K, n, n); with parts, an (n, n) label per
    node (0..P-1; -1: none), each part is registered on its own nodes alone, all at once: one
    Alignment per part (one in all without parts)."""
    labels = np.zeros(pixels.shape[1:3], np.intp) if parts is None else np.asarray(parts, np.intp)
    count = int(labels.max(initial=-1)) + 1
    out = np.repeat(start[None].astype(float), count, axis=0)
    correlation = np.full((count, data.count), np.nan)
    for k, image in enumerate(data.images):
        use = (data.weights[k] > 0) & np.isfinite(pixels[k, ..., 0]) & (model[k] > 0) & (labels >= 0)
        found, offsets, ncc = _track(image, pixels[k][use], model[k][use], labels[use], count, search_px=search_px,
                                     min_nodes=min_nodes, max_iterations=max_iterations)
        out[found, k] = start[k] + offsets[found]
        correlation[found, k] = ncc[found]
    return [Alignment(offsets=o, correlation=c) for o, c in zip(out, correlation, strict=True)]


def _part_sums(x: np.ndarray, labels: np.ndarray, parts: int) -> np.ndarray:
    """Sums (..., parts) of x (..., N) over each part's nodes (labels (N,), ascending in
    0..parts-1); 0 for a part without nodes."""
    present, starts = np.unique(labels, return_index=True)
    out = np.zeros(x.shape[:-1] + (parts,))
    if len(present):
        out[..., present] = np.add.reduceat(x, starts, axis=-1)
    return out


def _ncc(values: np.ndarray, model: np.ndarray, *, min_nodes: int, labels: np.ndarray | None = None,
         parts: int = 1) -> np.ndarray:
    """Zero-mean normalised cross-correlation of values (..., N) with model (N,) over the nodes
    where each row of values is finite; with labels (N,), ascending in 0..parts-1, over each part's
    nodes apart (..., parts). -inf where fewer than min_nodes are, or where either side is
    constant."""
    ok = np.isfinite(values)
    a = np.where(ok, values, 0.0)
    b = np.where(ok, model, 0.0)

    def total(x: np.ndarray) -> np.ndarray:
        return x.sum(axis=-1) if labels is None else _part_sums(x, labels, parts)
    return _correlation(*(total(x) for x in (ok.astype(float), a, b, a * a, b * b, a * b)), min_nodes=min_nodes)


def _correlation(count: np.ndarray, sa: np.ndarray, sb: np.ndarray, saa: np.ndarray, sbb: np.ndarray,
                 sab: np.ndarray, *, min_nodes: int) -> np.ndarray:
    """`_ncc` from its sums over the nodes used: their count and the sums of a, b, a^2, b^2, ab."""
    n = np.maximum(count, 1.0)
    cov = sab - sa * sb / n
    var = np.maximum(saa - sa * sa / n, 0.0) * np.maximum(sbb - sb * sb / n, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = cov / np.sqrt(var)
    # the sums' rounding leaves a constant side a variance of about 1e-16 of its square
    return np.where((count >= min_nodes) & (var > 1e-24 * saa * sbb) & (var > 0), ncc, -np.inf)


def _track(image: np.ndarray, pixels: np.ndarray, model: np.ndarray, labels: np.ndarray, parts: int, *,
           search_px: int, min_nodes: int, max_iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offset (sample, line) of `image` that best matches `model` at `pixels` (N, 2), for each
    part of the nodes (labels (N,) in 0..parts-1) on its own: whether found (parts,), the offsets
    (parts, 2) and their NCC (parts,). Whole shifts by NCC, a parabola through the peak's
    neighbours, then Gauss-Newton on I(x + offset) ~ gain * model + bias."""
    order = np.argsort(labels, kind="stable")
    pixels, model, labels = pixels[order], model[order], labels[order]
    shifts = np.arange(-search_px, search_px + 1)
    # every whole shift at once: [line shift i, sample shift j, part]
    score = _correlation(*shift_sums(image, pixels, model, labels, parts, search_px), min_nodes=min_nodes)
    found = np.isfinite(score).any(axis=(0, 1))
    coarse = np.zeros((parts, 2))
    for p in np.flatnonzero(found):
        i, j = map(int, np.unravel_index(np.argmax(score[..., p]), score.shape[:2]))
        coarse[p] = np.array([shifts[j], shifts[i]], float) + _peak(score[..., p], i, j)

    offset = coarse.copy()
    values = bilinear(image, pixels + offset[labels])
    ok = np.isfinite(values)
    # the straight line values ~ gain * model + bias through each part's nodes
    m, v = np.where(ok, model, 0.0), np.where(ok, values, 0.0)
    n, sm, sv, smv, smm = _part_sums(np.stack([ok, m, v, m * v, m * m]), labels, parts)
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = (n * smv - sm * sv) / (n * smm - sm * sm)
        bias = (sv - gain * sm) / n
    active = found.copy()
    for _ in range(max_iterations):
        if not active.any():
            break
        totals = normal_sums(image, pixels, offset, labels, active, model, gain, bias)
        short = active & (totals[:, 0] < min_nodes)
        found &= ~short
        active &= ~short
        normal, right = totals[:, 1:17].reshape(parts, 4, 4), totals[:, 17:]
        step = np.zeros((parts, 4))
        step[active] = -np.einsum("pij,pj->pi", np.linalg.pinv(normal[active]), right[active])
        offset += step[:, :2]
        gain += step[:, 2]
        bias += step[:, 3]
        active &= np.hypot(step[:, 0], step[:, 1]) >= 1e-4
    # where Gauss-Newton left the correlation peak it started on, trust the peak
    far = np.hypot(*(offset - coarse).T) > 1.0
    offset[far] = coarse[far]
    final = _ncc(bilinear(image, pixels + offset[labels]), model, min_nodes=2, labels=labels, parts=parts)
    return found, offset, np.where(np.isfinite(final), final, np.nan)


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


def register(
    maplet: MapletGrid,
    data: MapletImages,
    *,
    offsets: np.ndarray | None = None,
    levels: tuple[tuple[int, float], ...] = ((8, 32.0), (4, 24.0), (1, 1.0)),
    passes: int = 2,
    min_nodes: int = 30,
    keep_datum: bool = False,
    registration: Registration = REGISTRATION,
) -> Alignment:
    """Offsets (K, 2, px) that register every image to the maplet's shape and to the other images.

    Heights are the maplet's; its albedo is not used. levels: (f, search px) from coarse to fine:
    the maplet is resampled every f spacings and the images smoothed to f pixels, and each of
    `passes` passes compares every image, over whole shifts of f px within +-search px of its
    current offset (+-f px after the first pass), with a template, keeping the correlation peak
    (with a quadratic sub-step). On the first level the template is the shading of the maplet
    alone: it ties the images to the shape's relief (the datum that photometry cannot fix).
    Afterwards it is the leave-one-out albedo times the shading, which registers the images to
    each other. Images with fewer than min_nodes usable nodes at a level keep their offsets.
    keep_datum=False (default) then removes from the change of the offsets the part that a
    sideways shift of the whole maplet would cause: the shading anchor is only good to about a
    pixel, maplet by maplet, whereas the poses' own datum error is common to the maplets that
    share images (a rigid shift of the fused model); `pwm.photoclinometry.refine` keeps that part.
    A level whose grid has fewer than registration.min_coarse_nodes a side is skipped.
    """
    out = np.zeros((data.count, 2)) if offsets is None else np.asarray(offsets, float).copy()
    correlation = np.full(data.count, np.nan)
    # a search wider than a quarter of the maplet finds chance peaks in what little overlaps
    scales = [_pixels_per_spacing(maplet, c, p) for c, p in zip(data.cameras, data.poses, strict=True)]
    limit = 0.25 * maplet.n * float(np.median(scales))
    for level, (factor, reach) in enumerate(levels):
        reach = min(reach, max(limit, factor))
        if (maplet.n - 1) // factor + 1 < registration.min_coarse_nodes:
            continue
        coarse, weights = resampled(maplet, data.weights, factor)
        shading = predict(coarse, data, albedo=1.0).reshape(data.count, -1)
        margin = reach + factor * (passes + 3)
        first = node_pixels(coarse, data, offsets=out)
        windows = [_window(image, first[k], margin=margin, sigma=0.5 * factor if factor > 1 else 0.0)
                   for k, image in enumerate(data.images)]
        steps = np.arange(-np.ceil(reach / factor), np.ceil(reach / factor) + 1) * factor
        for _ in range(passes):
            pixels = node_pixels(coarse, data, offsets=out).reshape(data.count, -1, 2)
            values = np.stack([bilinear(w, pixels[k] - origin) for k, (w, origin) in enumerate(windows)])
            use = (weights > 0) & np.isfinite(values) & (shading > 0)
            if level == 0:
                albedo = np.ones_like(shading)
            else:
                albedo = _leave_one_out_albedo(np.where(use, values, 0.0), np.where(use, shading, 0.0), weights * use)
            for k, (window, origin) in enumerate(windows):
                template = albedo[k] * shading[k]
                ok = use[k] & (template > 0)
                if ok.sum() < min_nodes:
                    continue
                found = _search(window, pixels[k][ok] - origin, template[ok], steps, min_nodes=min_nodes)
                if found is not None:
                    out[k] += found[0]
                    correlation[k] = found[1]
            steps = np.arange(-1, 2) * factor
    # a coarse level can lock onto a chance peak: keep the starting offsets of an image that
    # matches the others better there, at full resolution
    start = np.zeros((data.count, 2)) if offsets is None else np.asarray(offsets, float)
    worse = _full_scores(maplet, data, out) < _full_scores(maplet, data, start)
    out[worse] = start[worse]
    if not keep_datum:
        basis = datum_complement(maplet, data)
        out = start + (basis @ (basis.T @ (out - start).ravel())).reshape(-1, 2)
    return Alignment(offsets=out, correlation=correlation)


def _full_scores(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray) -> np.ndarray:
    """(K,) NCC of each image at the offsets with its leave-one-out albedo times the shading, over
    the maplet's nodes (-inf where too few)."""
    shading = predict(maplet, data, albedo=1.0).reshape(data.count, -1)
    pixels = node_pixels(maplet, data, offsets=offsets).reshape(data.count, -1, 2)
    values = np.stack([bilinear(image, pixels[k]) for k, image in enumerate(data.images)])
    weights = data.weights.reshape(data.count, -1)
    use = (weights > 0) & np.isfinite(values) & (shading > 0)
    albedo = _leave_one_out_albedo(np.where(use, values, 0.0), np.where(use, shading, 0.0), weights * use)
    scores = np.full(data.count, -np.inf)
    for k in range(data.count):
        ok = use[k] & (albedo[k] > 0)
        scores[k] = _ncc(values[k][ok], albedo[k][ok] * shading[k][ok], min_nodes=2)
    return scores


def _pixels_per_spacing(maplet: MapletGrid, camera, pose) -> float:
    """Pixels between neighbouring nodes at the maplet's centre in one image."""
    ends = maplet.frame.to_body(np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]) * maplet.spacing_km)
    return float(np.linalg.norm(np.diff(project(ends, camera, pose), axis=0)))


def _window(image: np.ndarray, pixels: np.ndarray, *, margin: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The part of `image` around `pixels` (..., 2) with `margin` px to spare, smoothed by a
    Gaussian of `sigma` px (none if 0), and its first (sample, line)."""
    ok = np.isfinite(pixels).all(axis=-1)
    if not ok.any():
        return image[:2, :2], np.zeros(2)
    lo = np.maximum(np.floor(pixels[ok].min(axis=0) - margin), 0).astype(int)
    hi = np.minimum(np.ceil(pixels[ok].max(axis=0) + margin) + 1, image.shape[::-1]).astype(int)
    hi = np.maximum(hi, lo + 2)
    window = image[lo[1] : hi[1], lo[0] : hi[0]]
    if sigma > 0:
        # NaN pixels (no data) would spread through the filter: smooth with them at the mean and
        # put them back afterwards
        missing = ~np.isfinite(window)
        filled = np.where(missing, np.nanmean(window) if (~missing).any() else 0.0, window)
        window = np.where(ndimage.binary_dilation(missing, iterations=int(np.ceil(2 * sigma))), np.nan,
                          ndimage.gaussian_filter(filled, sigma))
    return window, lo.astype(float)


def _leave_one_out_albedo(values: np.ndarray, shading: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K, N) least-squares albedo of each node from all images but the k-th (0 where none):
    sum w^2 I G / sum w^2 G^2 over the other images."""
    w2 = weights**2
    num = w2 * values * shading
    den = w2 * shading**2
    num_others = num.sum(axis=0) - num
    den_others = den.sum(axis=0) - den
    return np.where(den_others > 1e-12 * den.sum(axis=0).max(initial=1.0),
                    num_others / np.where(den_others > 0, den_others, 1.0), 0.0)


def _search(image: np.ndarray, pixels: np.ndarray, model: np.ndarray, steps: np.ndarray, *,
            min_nodes: int) -> tuple[np.ndarray, float] | None:
    """Shift (sample, line) among steps x steps with the best NCC of image at pixels + shift and
    model, refined by a parabola through its neighbours; with that NCC."""
    ds, dl = np.meshgrid(steps, steps)
    shifts = np.column_stack([ds.ravel(), dl.ravel()])
    score = _ncc(bilinear(image, pixels[None] + shifts[:, None, :]), model, min_nodes=min_nodes)
    if not np.isfinite(score).any():
        return None
    score = score.reshape(ds.shape)
    i, j = map(int, np.unravel_index(np.argmax(score), score.shape))
    step = float(steps[1] - steps[0]) if len(steps) > 1 else 1.0
    best = np.array([steps[j], steps[i]], float) + step * _peak(score, i, j)
    return best, float(score[i, j])


def rise_motion(maplet: MapletGrid, data: MapletImages, axis: np.ndarray | None = None, *,
                node: tuple[int, int] | None = None) -> np.ndarray:
    """(K, 2) how each image's view of a node (default the maplet's centre) moves (sample, line;
    px per km) as the node moves along `axis` (default the maplet's local z: a rise)."""
    row, col = (maplet.n // 2, maplet.n // 2) if node is None else node
    point = maplet.node_body(row, col)
    return image_motion(data, point, maplet.frame.rotation[2] if axis is None else axis, step_km=maplet.spacing_km)


def parallax_height(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray, *,
                    sigma_px: np.ndarray, node: tuple[int, int] | None = None) -> tuple[float, float]:
    """The rise of the maplet (km, along its local z) whose parallax best explains the images'
    offsets (K, 2; sample, line, px) beside a sideways shift of the whole maplet, and its 1 sigma
    (km), for offsets each good to sigma_px (K,) px (inf: an image that says nothing).

    Photometry cannot place a maplet: the offsets that register its images take up whatever
    the poses and the start's height leave (pwm.photoclinometry holds the mean height). A
    sideways shift moves every image alike over the ground (the albedo moves with it: the datum
    the poses fix), but a rise moves each image along its own parallax; where the poses are
    known better than that parallax, the offsets measure the height the start got wrong, as
    stereo does.
    """
    jac = np.column_stack([rise_motion(maplet, data, axis, node=node).ravel()
                           for axis in maplet.frame.rotation])  # (2K, 3)
    weight = np.repeat(1.0 / np.square(np.asarray(sigma_px, float)), 2)
    normal = jac.T @ (weight[:, None] * jac)
    if np.linalg.matrix_rank(normal) < 3:
        return 0.0, float("inf")
    covariance = np.linalg.inv(normal)
    shift = covariance @ (jac.T @ (weight * np.asarray(offsets, float).ravel()))
    return float(shift[2]), float(np.sqrt(covariance[2, 2]))


def window_rises(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray, *, albedo: np.ndarray,
                 sigma_px: np.ndarray, windows: int, search_px: int,
                 registration: Registration = REGISTRATION) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rise (km, along the maplet's local z) of each of windows x windows square parts of the
    maplet that the parallax of its images' offsets there shows (`parallax_height` at the part's
    centre), with its 1 sigma (km; inf where fewer than two images register there), and the
    parts' centres (node index along either axis, (windows,)): (centres, rises, sigmas).

    offsets: the images' offsets for the whole maplet (K, 2, px); each part is registered
    (`align`, within search_px of them, with `registration`'s settings) to the maplet's brightness
    with this albedo. A start
    tilted or bent across the maplet keeps its tilt through photoclinometry: the images' brightness
    scales take up a uniform tilt, and its parallax, several pixels across a survey maplet, lies
    beyond the joint solution's reach. Each part's own offsets measure it, as SPC's landmarks do.
    sigma_px: (K,) how well an image's offsets are known over one part.
    """
    n = maplet.n
    edges = np.linspace(0, n, windows + 1).round().astype(int)
    # node (row, col) belongs to part i * windows + j of rows edges[i]:edges[i+1], cols edges[j]:...
    band = np.searchsorted(edges, np.arange(n), side="right") - 1
    start = np.asarray(offsets, float)
    pixels = node_pixels(maplet, data, offsets=start)
    model = predict(maplet, data, albedo=albedo)
    found = _align_at(data, pixels, model, start, search_px=search_px, min_nodes=registration.align_min_nodes,
                      max_iterations=registration.align_max_iterations, parts=band[:, None] * windows + band[None, :])
    rises = np.zeros((windows, windows))
    sigmas = np.full((windows, windows), np.inf)
    for (i, j), part in zip(np.ndindex(windows, windows), found, strict=True):
        said = np.where(np.isfinite(part.correlation), sigma_px, np.inf)
        centre = ((edges[i] + edges[i + 1]) // 2, (edges[j] + edges[j + 1]) // 2)
        rises[i, j], sigmas[i, j] = parallax_height(maplet, data, part.offsets, sigma_px=said, node=centre)
    return 0.5 * (edges[:-1] + edges[1:] - 1), rises, sigmas


def sweep_height(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray, *, reach_px: float,
                 max_rise_km: float, follow: bool = False, step_px: float = 1.0) -> float:
    """The rise of the whole maplet (km, along its local z) at which its images agree best with
    one another: plane-sweep stereo over rises whose parallax between the images spans up to
    reach_px (step_px apart), and at most max_rise_km. At each, every image is compared with the
    albedo the others give times its shading (`_full_scores`, on every second or third node: the
    agreement needs no more); the rise of the best mean correlation is kept, refined by a
    parabola. It finds a start's height error many pixels of parallax wide, far beyond the
    photoclinometric solution's reach of about a pixel. With `follow`, where the agreement still
    rises at an end of the sweep, the sweep goes on that way, within max_rise_km, until it
    falls: a start off by more than reach_px is then found at the same cost per step (with a
    few images, the agreement can also rise at an end towards no height at all). 0 when the
    images are too few, their parallax too small to sweep, or the best agreement lies at an end
    the sweep may not pass."""
    if data.count < 2:
        return 0.0
    motion = rise_motion(maplet, data)
    spread = float(np.max(np.linalg.norm(motion[:, None] - motion[None], axis=-1)))  # px per km between images
    if spread * maplet.spacing_km < 1e-3:
        return 0.0
    sparse, sparse_data = _every(maplet, data)
    step = step_px / spread
    half = min(reach_px / spread, max_rise_km)

    def score(rise: float) -> float:
        return _mean_score(dataclasses.replace(sparse, heights=sparse.heights + rise), sparse_data, offsets)

    rises = list(np.arange(-half, half + 0.5 * step, step))
    scores = [score(rise) for rise in rises]
    if not np.isfinite(scores).any():
        return 0.0
    best = int(np.nanargmax(scores))
    while follow and best == len(rises) - 1 and rises[-1] + step <= max_rise_km:
        rises.append(rises[-1] + step)
        scores.append(score(rises[-1]))
        best = int(np.nanargmax(scores))
    while follow and best == 0 and rises[0] - step >= -max_rise_km:
        rises.insert(0, rises[0] - step)
        scores.insert(0, score(rises[0]))
        best = int(np.nanargmax(scores))
    if not (0 < best < len(rises) - 1 and np.isfinite(scores[best - 1 : best + 2]).all()):
        return 0.0
    return float(rises[best] + _vertex(*scores[best - 1 : best + 2]) * step)


def _every(maplet: MapletGrid, data: MapletImages) -> tuple[MapletGrid, MapletImages]:
    """The maplet and its images' node masks at every third (or second) node, where that spans
    the same square."""
    factor = next(f for f in (3, 2, 1) if (maplet.n - 1) % f == 0)
    if factor == 1:
        return maplet, data
    pick = (slice(None), slice(None, None, factor), slice(None, None, factor))
    return (dataclasses.replace(maplet, heights=maplet.heights[::factor, ::factor], albedo=None,
                                spacing_km=maplet.spacing_km * factor),
            dataclasses.replace(data, visible=data.visible[pick], lit=data.lit[pick], weights=data.weights[pick],
                                shade=None if data.shade is None else data.shade[pick]))


def _mean_score(maplet: MapletGrid, data: MapletImages, offsets: np.ndarray) -> float:
    scores = _full_scores(maplet, data, offsets)
    return float(np.mean(scores[np.isfinite(scores)])) if np.isfinite(scores).sum() >= 2 else np.nan
