"""The height error split by wavelength: which scales a model gets wrong.

Shading constrains short wavelengths well and long ones weakly, so a start model's long-wavelength
error survives a refinement that only follows the shading. The split is by Gaussian filters whose
gain is 1/2 at each boundary wavelength (ISO 16610-21, as the truth's low-pass), applied to the
error map with its gaps (nan) left out of every mean, so the bands add up to the error itself.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pwm.simulate.terrain import gaussian_sigma_km

BOUNDARIES_GSD = (10.0, 50.0, 200.0)
"""Band edges in GSD: at 10 cm, below 1 m, 1-5 m, 5-20 m and above 20 m."""


def band_names(boundaries_km: tuple[float, ...]) -> list[str]:
    """'<1 m', '1-5 m', ... '>20 m' for the boundaries (km)."""
    edges = [f"{b * 1e3:g}" for b in boundaries_km]
    return [f"<{edges[0]} m", *(f"{a}-{b} m" for a, b in zip(edges, edges[1:], strict=False)), f">{edges[-1]} m"]


def smooth(error: np.ndarray, *, spacing_km: float, wavelength_km: float) -> np.ndarray:
    """The Gaussian low-pass of a map with gaps: mean of the valid values under the filter
    (normalised convolution); nan where the map is nan."""
    valid = np.isfinite(error)
    sigma = gaussian_sigma_km(wavelength_km) / spacing_km
    num = ndimage.gaussian_filter(np.where(valid, error, 0.0), sigma, mode="constant")
    den = ndimage.gaussian_filter(valid.astype(float), sigma, mode="constant")
    return np.where(valid, num / np.maximum(den, 1e-12), np.nan)


def split(error: np.ndarray, *, spacing_km: float, boundaries_km: tuple[float, ...]) -> list[np.ndarray]:
    """The map as len(boundaries) + 1 bands, shortest first, that sum to it (nan kept)."""
    lows = [smooth(error, spacing_km=spacing_km, wavelength_km=b) for b in boundaries_km]
    return [error - lows[0], *(a - b for a, b in zip(lows, lows[1:], strict=False)), lows[-1]]


def band_rms(error: np.ndarray, *, spacing_km: float, boundaries_km: tuple[float, ...]) -> dict[str, float]:
    """RMS (same unit as the map) of each band over the valid nodes, by band name."""
    bands = split(error, spacing_km=spacing_km, boundaries_km=boundaries_km)
    return {name: float(np.sqrt(np.nanmean(band**2)))
            for name, band in zip(band_names(boundaries_km), bands, strict=True)}
