"""Similarity of a rendered image to a reference (truth or real) image over the pixels that count.

Both scores take a boolean mask of the pixels to compare: pixels in shadow or off the body in
either image are left out by the caller's mask.
"""

from __future__ import annotations

import numpy as np
from skimage.metrics import structural_similarity


def ncc(truth: np.ndarray, model: np.ndarray, mask: np.ndarray) -> float:
    """Zero-mean normalized cross-correlation of the masked pixels, in [-1, 1] (Lewis 1995)."""
    a, b = _masked_pair(truth, model, mask)
    a = a - a.mean()
    b = b - b.mean()
    return float(np.dot(a, b) / np.sqrt(np.dot(a, a) * np.dot(b, b)))


def ssim(truth: np.ndarray, model: np.ndarray, mask: np.ndarray) -> float:
    """Structural similarity (Wang et al. 2004: Gaussian window of sigma 1.5 px) averaged over
    the masked pixels of its map; data range from the truth's masked pixels.

    Pixels outside the mask are left out of the average but still sit in the windows of masked
    pixels within about 4 px of them.
    """
    a, _ = _masked_pair(truth, model, mask)
    _, similarity = structural_similarity(
        np.asarray(truth, float),
        np.asarray(model, float),
        data_range=float(a.max() - a.min()),
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        full=True,
    )
    return float(similarity[mask].mean())


def _masked_pair(truth: np.ndarray, model: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, ...]:
    if np.shape(truth) != np.shape(model) or np.shape(mask) != np.shape(truth):
        raise ValueError("truth, model and mask must have the same shape")
    mask = np.asarray(mask, bool)
    if mask.sum() < 2:
        raise ValueError("the mask selects fewer than 2 pixels")
    return np.asarray(truth, float)[mask], np.asarray(model, float)[mask]
