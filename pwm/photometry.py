"""Photometric functions. Angles in radians unless a name says otherwise."""

from __future__ import annotations

import numpy as np

# McEwen (1991, 1996) polynomial for the limb-darkening weight L(g), phase g in degrees.
MCEWEN_L_COEFFS = (1.0, -0.019, 2.42e-4, -1.46e-6)


def mcewen_l(phase: np.ndarray | float) -> np.ndarray:
    """Lunar-Lambert weight L(g) for phase angle g (radians), clipped to [0, 1]."""
    g = np.degrees(np.asarray(phase, float))
    a0, a1, a2, a3 = MCEWEN_L_COEFFS
    return np.clip(a0 + g * (a1 + g * (a2 + g * a3)), 0.0, 1.0)


def lunar_lambert(mu0: np.ndarray, mu: np.ndarray, phase: np.ndarray | float) -> np.ndarray:
    """McEwen lunar-Lambert reflectance G = (1 - L) mu0 + 2 L mu0 / (mu0 + mu).

    mu0 = cos(incidence), mu = cos(emission). Returns 0 where the Sun or the camera is below
    the local horizon (mu0 <= 0 or mu <= 0).
    """
    mu0 = np.asarray(mu0, float)
    mu = np.asarray(mu, float)
    lit = (mu0 > 0) & (mu > 0)
    m0 = np.where(lit, mu0, 0.0)
    m = np.where(lit, mu, 1.0)
    L = mcewen_l(phase)
    return np.where(lit, (1.0 - L) * m0 + 2.0 * L * m0 / (m0 + m), 0.0)


def angles(normals: np.ndarray, to_sun: np.ndarray, to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """mu0, mu and phase (radians) from unit normals and unit vectors towards Sun and camera."""
    mu0 = np.einsum("...i,...i->...", normals, to_sun)
    mu = np.einsum("...i,...i->...", normals, to_camera)
    phase = np.arccos(np.clip(np.einsum("...i,...i->...", to_sun, to_camera), -1.0, 1.0))
    return mu0, mu, phase
