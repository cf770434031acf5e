"""The sums over a maplet's nodes that register an image to a template, compiled (numba).

`pwm.alignment` registers every image to the brightness a maplet predicts, at once for up to
several dozen parts of the maplet (`pwm.alignment.window_rises`), first by correlation at every
whole shift within a reach, then by Gauss-Newton. Each needs, per part, a handful of sums over
the part's nodes of products of bilinear image samples; as numpy expressions they passed over
temporaries of (2 reach + 1)^2 x nodes values several times, and were most of a maplet's
refinement (bench/RESULTS.md). Here each is one pass over the nodes.

Samples are `pwm.photoclinometry.bilinear`'s: pixel centres at integers, NaN outside the frame
or next to a NaN pixel; a node with a NaN sample adds nothing to any sum. The sums' order is
the nodes', so they differ from numpy's by rounding alone.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _bilinear(image: np.ndarray, s: float, line: float) -> float:
    """`pwm.photoclinometry.bilinear` at one pixel (sample s, line)."""
    height, width = image.shape
    if not (0.0 <= s <= width - 1 and 0.0 <= line <= height - 1):
        return np.nan
    s0 = min(int(np.floor(s)), max(width - 2, 0))
    l0 = min(int(np.floor(line)), max(height - 2, 0))
    fs, fl = s - s0, line - l0
    s1 = s0 + 1 if width > 1 else s0
    l1 = l0 + 1 if height > 1 else l0
    top = image[l0, s0] + fs * (image[l0, s1] - image[l0, s0])
    bottom = image[l1, s0] + fs * (image[l1, s1] - image[l1, s0])
    return top + fl * (bottom - top)


@njit(cache=True)
def shift_sums(image: np.ndarray, pixels: np.ndarray, model: np.ndarray, labels: np.ndarray, parts: int,
               reach: int) -> np.ndarray:
    """(6, 2 reach + 1, 2 reach + 1, parts) sums over each part's nodes, where the image sampled at
    pixels (N, 2; sample, line) moved by a whole shift within +-reach px [line shift, sample
    shift] is finite, of 1, that sample a, the template model (N,) b, a^2, b^2 and ab (`pwm.alignment`
    correlates them). labels (N,): each node's part, 0..parts-1. The shifts share a node's
    fractions: its neighbourhood is read once for all of them."""
    height, width = image.shape
    size = 2 * reach + 1
    out = np.zeros((6, size, size, parts))
    for k in range(pixels.shape[0]):
        s, line = pixels[k, 0], pixels[k, 1]
        if not (np.isfinite(s) and np.isfinite(line)):
            continue
        s0, l0 = np.floor(s), np.floor(line)
        fs, fl = s - s0, line - l0
        col, row = int(s0) - reach, int(l0) - reach
        b, part = model[k], labels[k]
        for i in range(size):
            if not (0.0 <= line + (i - reach) <= height - 1):
                continue
            # a shift whose next row or column has weight 0 may take it from beyond the frame's
            # edge: clipped, as the frame's last pixel centre is still inside
            r0, r1 = min(max(row + i, 0), height - 1), min(max(row + i + 1, 0), height - 1)
            for j in range(size):
                if not (0.0 <= s + (j - reach) <= width - 1):
                    continue
                c0, c1 = min(max(col + j, 0), width - 1), min(max(col + j + 1, 0), width - 1)
                top = image[r0, c0] + fs * (image[r0, c1] - image[r0, c0])
                bottom = image[r1, c0] + fs * (image[r1, c1] - image[r1, c0])
                a = top + fl * (bottom - top)
                if not np.isfinite(a):
                    continue
                out[0, i, j, part] += 1.0
                out[1, i, j, part] += a
                out[2, i, j, part] += b
                out[3, i, j, part] += a * a
                out[4, i, j, part] += b * b
                out[5, i, j, part] += a * b
    return out


@njit(cache=True)
def normal_sums(image: np.ndarray, pixels: np.ndarray, offsets: np.ndarray, labels: np.ndarray,
                active: np.ndarray, model: np.ndarray, gain: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """(parts, 21) Gauss-Newton sums of the misfit I(x + offset) - (gain * model + bias) over each
    active part's nodes (pixels (N, 2), labels (N,) in 0..parts-1, model (N,); offsets (parts, 2),
    gain, bias and active (parts,)): the count of nodes used, J'J (4 x 4, row by row) and J'r,
    with the unknowns offset (sample, line), gain and bias. The image's derivatives are central
    differences over one pixel: unlike the bilinear interpolant's own, which jumps at cell edges,
    they keep sub-pixel registration free of a bias towards whole pixels."""
    out = np.zeros((offsets.shape[0], 21))
    jac = np.empty(4)
    for k in range(pixels.shape[0]):
        part = labels[k]
        if not active[part]:
            continue
        s, line = pixels[k, 0] + offsets[part, 0], pixels[k, 1] + offsets[part, 1]
        value = _bilinear(image, s, line)
        jac[0] = _bilinear(image, s + 0.5, line) - _bilinear(image, s - 0.5, line)
        jac[1] = _bilinear(image, s, line + 0.5) - _bilinear(image, s, line - 0.5)
        if not (np.isfinite(value) and np.isfinite(jac[0]) and np.isfinite(jac[1])):
            continue
        jac[2], jac[3] = -model[k], -1.0
        residual = value - gain[part] * model[k] - bias[part]
        out[part, 0] += 1.0
        for a in range(4):
            for c in range(4):
                out[part, 1 + 4 * a + c] += jac[a] * jac[c]
            out[part, 17 + a] += jac[a] * residual
    return out
