"""Detector model: reflectance to quantised DN with exposure error, shot and read noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Exposure:
    """How one image was exposed. scaling: reflectance per DN as the label states it (nominal
    calibration); true_gain: the actual brightness factor, unknown to processing (close to 1)."""

    scaling: float
    true_gain: float


def choose_exposure(expected_max: float, *, full_well_dn: float, fill: float, error: float,
                    rng: np.random.Generator) -> Exposure:
    """Scale so the brightest expected reflectance fills `fill` of full scale; draw the gain error."""
    return Exposure(scaling=expected_max / (fill * full_well_dn), true_gain=float(1.0 + rng.normal(0.0, error)))


def to_dn(reflectance: np.ndarray, exposure: Exposure, *, full_well_dn: float, gain_e_per_dn: float,
          read_noise_dn: float, rng: np.random.Generator) -> np.ndarray:
    """Quantised int16 DN: photon (Poisson) noise, Gaussian read noise, rounding, saturation."""
    signal_dn = np.asarray(reflectance, float) * exposure.true_gain / exposure.scaling
    electrons = rng.poisson(np.clip(signal_dn, 0.0, None) * gain_e_per_dn)
    dn = electrons / gain_e_per_dn + rng.normal(0.0, read_noise_dn, signal_dn.shape)
    return np.clip(np.rint(dn), 0, full_well_dn).astype(np.int16)
