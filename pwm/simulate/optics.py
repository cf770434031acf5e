"""What a real camera does to the light before it is counted: blur by its point-spread function,
smear by motion during the exposure, and a flat field that calibration leaves imperfect. Pure
array operations on reflectance images indexed [line, sample]; lengths in pixels."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, Field
from scipy import ndimage


class Optics(BaseModel):
    """psf_sigma_px: the Gaussian point-spread function's standard deviation; smear_px: the
    length of the straight motion smear, along smear_azimuth_deg (from +sample towards +line);
    flat_field_rms: the relative RMS of the flat-field residual, fixed for the camera (half
    smooth over a quarter of the frame, half pixel to pixel). All 0: a perfect camera."""

    psf_sigma_px: float = Field(0.0, ge=0.0, le=10.0)
    smear_px: float = Field(0.0, ge=0.0, le=50.0)
    smear_azimuth_deg: float = 30.0
    flat_field_rms: float = Field(0.0, ge=0.0, le=0.2)

    @property
    def perfect(self) -> bool:
        return self.psf_sigma_px == 0 and self.smear_px == 0 and self.flat_field_rms == 0


def blur(image: np.ndarray, optics: Optics) -> np.ndarray:
    """The image through the point-spread function and the motion smear (energy kept; edges
    continued by reflection)."""
    out = np.asarray(image, float)
    if optics.psf_sigma_px > 0:
        out = ndimage.gaussian_filter(out, optics.psf_sigma_px, mode="reflect")
    if optics.smear_px > 0:
        out = ndimage.convolve(out, smear_kernel(optics.smear_px, optics.smear_azimuth_deg), mode="reflect")
    return out


def smear_kernel(length_px: float, azimuth_deg: float) -> np.ndarray:
    """A normalised kernel of a straight smear of `length_px` centred on the pixel, sampled by
    many points along the segment and spread bilinearly to the pixels they fall in."""
    half = length_px / 2
    size = 2 * int(np.ceil(half)) + 3
    kernel = np.zeros((size, size))
    t = np.linspace(-half, half, max(16, int(length_px * 16)))
    a = np.radians(azimuth_deg)
    x, y = size // 2 + t * np.cos(a), size // 2 + t * np.sin(a)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dy, dx, w in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), w)
    return kernel / kernel.sum()


def flat_field(shape: tuple[int, int], rms: float, rng: np.random.Generator) -> np.ndarray:
    """A multiplicative flat-field residual of relative RMS `rms` around 1: half of its variance
    smooth (a Gaussian field correlated over a quarter of the frame), half pixel to pixel."""
    if rms == 0:
        return np.ones(shape)
    smooth = ndimage.gaussian_filter(rng.normal(size=shape), max(shape) / 8, mode="wrap")
    # a flat field is normalised to a mean of 1: the residual is a pattern, not a gain
    smooth = (smooth - smooth.mean()) / max(float(smooth.std()), 1e-300)
    pixel = rng.normal(size=shape)
    return 1 + rms * np.sqrt(0.5) * (smooth + pixel)
