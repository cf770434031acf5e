"""Photometric functions. Angles in radians unless a name says otherwise.

The solver models reflectance as albedo times McEwen's lunar-Lambert function (`lunar_lambert`).
The proving ground may render its truth with another function (`Photometry`): lunar-Lambert with
another phase law, or Hapke's model with an opposition surge and macroscopic roughness, so that
the solver meets photometry it does not assume.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

# McEwen (1991, 1996) polynomial for the limb-darkening weight L(g), phase g in degrees.
MCEWEN_L_COEFFS = (1.0, -0.019, 2.42e-4, -1.46e-6)


def mcewen_l(phase: np.ndarray | float, coeffs: tuple[float, ...] = MCEWEN_L_COEFFS) -> np.ndarray:
    """Lunar-Lambert weight L(g) for phase angle g (radians): a polynomial in g (degrees) with
    `coeffs` from the constant term up, clipped to [0, 1]."""
    g = np.degrees(np.asarray(phase, float))
    return np.clip(np.polynomial.polynomial.polyval(g, coeffs), 0.0, 1.0)


def lunar_lambert(mu0: np.ndarray, mu: np.ndarray, phase: np.ndarray | float,
                  coeffs: tuple[float, ...] = MCEWEN_L_COEFFS) -> np.ndarray:
    """McEwen lunar-Lambert reflectance G = (1 - L) mu0 + 2 L mu0 / (mu0 + mu), L = L(g).

    mu0 = cos(incidence), mu = cos(emission). Returns 0 where the Sun or the camera is below
    the local horizon (mu0 <= 0 or mu <= 0).
    """
    mu0 = np.asarray(mu0, float)
    mu = np.asarray(mu, float)
    lit = (mu0 > 0) & (mu > 0)
    m0 = np.where(lit, mu0, 0.0)
    m = np.where(lit, mu, 1.0)
    L = mcewen_l(phase, coeffs)
    return np.where(lit, (1.0 - L) * m0 + 2.0 * L * m0 / (m0 + m), 0.0)


def angles(normals: np.ndarray, to_sun: np.ndarray, to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """mu0, mu and phase (radians) from unit normals and unit vectors towards Sun and camera."""
    mu0 = np.einsum("...i,...i->...", normals, to_sun)
    mu = np.einsum("...i,...i->...", normals, to_camera)
    phase = np.arccos(np.clip(np.einsum("...i,...i->...", to_sun, to_camera), -1.0, 1.0))
    return mu0, mu, phase


class Photometry(Protocol):
    """A reflectance law: G(mu0, mu, phase), multiplied by the albedo; 0 unlit or unseen."""

    def __call__(self, mu0: np.ndarray, mu: np.ndarray, phase: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class LunarLambert:
    """lunar_lambert with the phase law L(g) of `coeffs` (McEwen's by default: the solver's)."""

    coeffs: tuple[float, ...] = MCEWEN_L_COEFFS

    def __call__(self, mu0: np.ndarray, mu: np.ndarray, phase: np.ndarray) -> np.ndarray:
        return lunar_lambert(mu0, mu, phase, self.coeffs)


# Hapke's model is scaled to equal lunar-Lambert at this geometry (incidence 30 deg, emission 0),
# so that an albedo map means about the same brightness under either law.
_REFERENCE = (np.array([np.cos(np.radians(30.0))]), np.array([1.0]), np.array([np.radians(30.0)]))


@dataclass(frozen=True)
class Hapke:
    """Hapke's bidirectional reflectance (Hapke 1981, 1984; H functions as Hapke 2002):
    r = w/4 mu0e/(mu0e + mue) [(1 + B(g)) P(g) + H(mu0e) H(mue) - 1] S(i, e, g), scaled to
    lunar-Lambert's value at incidence 30 deg, emission 0.

    w: single-scattering albedo; b: asymmetry of the one-term Henyey-Greenstein phase function
    (b > 0 scatters back); b0, h: amplitude and angular width of the shadow-hiding opposition
    surge B(g) = b0 / (1 + tan(g/2) / h); roughness_deg: Hapke's mean slope angle theta-bar of
    the unresolved surface."""

    w: float = 0.05
    b: float = 0.3
    b0: float = 1.0
    h: float = 0.06
    roughness_deg: float = 28.0

    def __call__(self, mu0: np.ndarray, mu: np.ndarray, phase: np.ndarray) -> np.ndarray:
        arrays = np.broadcast_arrays(*(np.asarray(a, float) for a in (mu0, mu, phase)))
        mu0, mu, phase = (a.ravel() for a in arrays)
        lit = (mu0 > 0) & (mu > 0)
        value = np.zeros(mu0.shape)
        value[lit] = self._radiance_factor(mu0[lit], mu[lit], phase[lit])
        scale = lunar_lambert(*_REFERENCE) / self._radiance_factor(*_REFERENCE)
        return (value * scale).reshape(arrays[0].shape)

    def _radiance_factor(self, mu0: np.ndarray, mu: np.ndarray, g: np.ndarray) -> np.ndarray:
        mu0e, mue, shadowing = self._roughness(mu0, mu, g)
        p = (1 - self.b**2) / (1 - 2 * self.b * np.cos(g) + self.b**2) ** 1.5
        surge = self.b0 / (1 + np.tan(np.minimum(g, np.pi - 1e-6) / 2) / self.h)
        multiple = _chandrasekhar_h(mu0e, self.w) * _chandrasekhar_h(mue, self.w) - 1
        return self.w / 4 * mu0e / (mu0e + mue) * ((1 + surge) * p + multiple) * shadowing

    def _roughness(self, mu0: np.ndarray, mu: np.ndarray, g: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Effective cosines and the shadowing function S of Hapke (1984) for mean slope
        theta-bar; with theta-bar 0, (mu0, mu, 1)."""
        if self.roughness_deg <= 0:
            return mu0, mu, np.ones_like(mu0)
        tan_t = np.tan(np.radians(self.roughness_deg))
        chi = 1 / np.sqrt(1 + np.pi * tan_t**2)
        i, e = np.arccos(np.clip(mu0, 0, 1)), np.arccos(np.clip(mu, 0, 1))
        # tan of angles clipped away from 0, where E1 and E2 tend to 0
        tan_i, tan_e = np.maximum(np.tan(i), 1e-9), np.maximum(np.tan(e), 1e-9)

        def e1(tan_x: np.ndarray) -> np.ndarray:
            return np.exp(-2 / (np.pi * tan_t * tan_x))

        def e2(tan_x: np.ndarray) -> np.ndarray:
            return np.exp(-1 / (np.pi * tan_t**2 * tan_x**2))

        def eta(x: np.ndarray, tan_x: np.ndarray) -> np.ndarray:
            return chi * (np.cos(x) + np.sin(x) * tan_t * e2(tan_x) / (2 - e1(tan_x)))

        sin_ie = np.sin(i) * np.sin(e)
        cos_psi = np.where(sin_ie > 1e-12, (np.cos(g) - mu0 * mu) / np.maximum(sin_ie, 1e-12), 1.0)
        psi = np.arccos(np.clip(cos_psi, -1, 1))
        f = np.exp(-2 * np.tan(np.minimum(psi, np.pi - 1e-6) / 2))
        s2 = np.sin(psi / 2) ** 2
        e1i, e1e, e2i, e2e = e1(tan_i), e1(tan_e), e2(tan_i), e2(tan_e)
        eta_i, eta_e = eta(i, tan_i), eta(e, tan_e)
        small_i = i <= e
        # i <= e
        d1 = 2 - e1e - psi / np.pi * e1i
        mu0e_1 = chi * (mu0 + np.sin(i) * tan_t * (cos_psi * e2e + s2 * e2i) / d1)
        mue_1 = chi * (mu + np.sin(e) * tan_t * (e2e - s2 * e2i) / d1)
        s_1 = mue_1 / eta_e * mu0 / eta_i * chi / (1 - f + f * chi * mu0 / eta_i)
        # e < i
        d2 = 2 - e1i - psi / np.pi * e1e
        mu0e_2 = chi * (mu0 + np.sin(i) * tan_t * (e2i - s2 * e2e) / d2)
        mue_2 = chi * (mu + np.sin(e) * tan_t * (cos_psi * e2i + s2 * e2e) / d2)
        s_2 = mue_2 / eta_e * mu0 / eta_i * chi / (1 - f + f * chi * mu / eta_e)
        return (np.where(small_i, mu0e_1, mu0e_2), np.where(small_i, mue_1, mue_2),
                np.where(small_i, s_1, s_2))


def _chandrasekhar_h(x: np.ndarray, w: float) -> np.ndarray:
    """Hapke's (2002) approximation of Chandrasekhar's H function (error under 1%)."""
    gamma = np.sqrt(1 - w)
    r0 = (1 - gamma) / (1 + gamma)
    x = np.maximum(x, 1e-12)
    return 1 / (1 - w * x * (r0 + (1 - 2 * r0 * x) / 2 * np.log((1 + x) / x)))


MCEWEN = LunarLambert()
"""The solver's own law."""

PHOTOMETRY: dict[str, Photometry] = {
    "mcewen": MCEWEN,
    # lunar-Lambert whose limb darkening fades half as fast with phase as McEwen's
    "lunar-lambert-slow": LunarLambert(coeffs=(1.0, -0.0095, 6.05e-5, -1.8e-7)),
    # a dark, rough, back-scattering regolith with an opposition surge
    "hapke": Hapke(),
}
"""The reflectance laws a simulation can render its truth with, by name."""
