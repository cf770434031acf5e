"""Photometry: McEwen lunar-Lambert against values worked out by hand from the published formula, and
the truth's other laws (Hapke with roughness and opposition surge, lunar-Lambert with another phase law)."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.photometry import PHOTOMETRY, Hapke, LunarLambert, angles, lunar_lambert, mcewen_l


@pytest.mark.parametrize(
    "phase_deg, expected",
    [
        (0.0, 1.0),
        # 1 - 0.019 g + 2.42e-4 g^2 - 1.46e-6 g^3
        (30.0, 1 - 0.57 + 0.2178 - 0.03942),   # 0.60838
        (60.0, 1 - 1.14 + 0.8712 - 0.31536),   # 0.41584
        (90.0, 1 - 1.71 + 1.9602 - 1.06434),   # 0.18586
        (150.0, 0.0),                           # the cubic goes negative: clipped
    ],
)
def test_limb_weight_polynomial(phase_deg: float, expected: float) -> None:
    assert mcewen_l(np.radians(phase_deg)) == pytest.approx(expected, abs=1e-12)


def test_lunar_lambert_by_hand() -> None:
    # Sun 30 degrees from the normal, camera along it: g = 30 deg, L = 0.60838.
    mu0, mu, L = np.cos(np.radians(30.0)), 1.0, 0.60838
    G = lunar_lambert(mu0, mu, np.radians(30.0))
    assert G == pytest.approx((1 - L) * mu0 + 2 * L * mu0 / (mu0 + 1.0), rel=1e-12)
    assert G == pytest.approx(0.903854, abs=1e-6)
    # Opposition (g = 0, L = 1) with i = e: pure Lommel-Seeliger 2 mu0 / (mu0 + mu) = 1.
    assert lunar_lambert(0.5, 0.5, 0.0) == pytest.approx(1.0)
    # Lambert limit (L = 0 at g = 150 deg): G = mu0.
    assert lunar_lambert(0.3, 0.2, np.radians(150.0)) == pytest.approx(0.3)
    # Sun or camera below the local horizon: dark.
    assert lunar_lambert(-0.1, 0.9, 0.5) == 0.0
    assert lunar_lambert(0.6, -0.2, 0.5) == 0.0


def test_angles_from_vectors() -> None:
    normal = np.array([0.0, 0.0, 1.0])
    sun = np.array([np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))])
    cam = np.array([0.0, -np.sin(np.radians(25.0)), np.cos(np.radians(25.0))])
    mu0, mu, phase = angles(normal, sun, cam)
    assert mu0 == pytest.approx(np.cos(np.radians(40.0)))
    assert mu == pytest.approx(np.cos(np.radians(25.0)))
    # Sun and camera in perpendicular vertical planes: cos g = cos i cos e.
    assert np.cos(phase) == pytest.approx(np.cos(np.radians(40.0)) * np.cos(np.radians(25.0)))


# The truth's other laws (pwm.photometry.Hapke, LunarLambert with another phase law)

def _smooth_hapke(w, b, b0, h, mu0, mu, g):
    """Hapke's smooth-surface radiance factor written out from the formula, H of Hapke (2002)."""
    gamma = np.sqrt(1 - w)
    r0 = (1 - gamma) / (1 + gamma)

    def H(x):
        return 1 / (1 - w * x * (r0 + (1 - 2 * r0 * x) / 2 * np.log((1 + x) / x)))

    p = (1 - b**2) / (1 - 2 * b * np.cos(g) + b**2) ** 1.5
    surge = b0 / (1 + np.tan(g / 2) / h)
    return w / 4 * mu0 / (mu0 + mu) * ((1 + surge) * p + H(mu0) * H(mu) - 1)


def test_hapke_without_roughness_is_the_smooth_formula_scaled_at_the_reference():
    law = Hapke(w=0.1, b=0.25, b0=0.8, h=0.05, roughness_deg=0.0)
    mu0, mu, g = np.array([0.9, 0.5, 0.3]), np.array([0.8, 0.95, 0.6]), np.radians([20.0, 45.0, 70.0])
    scale = lunar_lambert(np.cos(np.radians(30)), 1.0, np.radians(30)) / _smooth_hapke(
        0.1, 0.25, 0.8, 0.05, np.cos(np.radians(30)), 1.0, np.radians(30))
    np.testing.assert_allclose(law(mu0, mu, g), scale * _smooth_hapke(0.1, 0.25, 0.8, 0.05, mu0, mu, g),
                               rtol=1e-12)
    # a tiny roughness changes nothing measurable: the rough branch joins the smooth one
    np.testing.assert_allclose(Hapke(w=0.1, b=0.25, b0=0.8, h=0.05, roughness_deg=1e-3)(mu0, mu, g),
                               law(mu0, mu, g), rtol=1e-6)


def test_rough_hapke_obeys_reciprocity_and_darkens_grazing_light():
    """The BRDF r / mu0 is symmetric in incidence and emission (Hapke 1984's S keeps it so);
    macroscopic roughness shadows the surface more the lower the Sun."""
    law, smooth = Hapke(), Hapke(roughness_deg=0.0)
    for i, e, g in ((50, 20, 40), (75, 10, 70), (30, 60, 80)):
        mu0, mu, phase = np.cos(np.radians(i)), np.cos(np.radians(e)), np.radians(g)
        assert law(mu0, mu, phase) / mu0 == pytest.approx(law(mu, mu0, phase) / mu, rel=1e-9)
    grazing = [law(np.cos(np.radians(i)), 1.0, np.radians(i)) / smooth(np.cos(np.radians(i)), 1.0, np.radians(i))
               for i in (30, 60, 80)]
    assert grazing[0] == pytest.approx(1.0, abs=1e-9)  # both equal lunar-Lambert at the reference
    assert 1.0 > grazing[1] > grazing[2] > 0.3


def test_hapke_opposition_surge_and_shadows():
    law, no_surge = Hapke(b0=1.0, h=0.06, roughness_deg=0.0), Hapke(b0=0.0, h=0.06, roughness_deg=0.0)

    def surge(phase_deg):
        """Brightness with the surge over brightness without, both unscaled: ((1 + B) P + M) / (P + M)."""
        mu, g = np.array([0.9]), np.radians(np.array([phase_deg]))
        return law._radiance_factor(mu, mu, g)[0] / no_surge._radiance_factor(mu, mu, g)[0]

    # B(0) = b0 = 1: nearly twice as bright (the multiple scattering M of a dark surface is small),
    # fading over a few times h = 0.06 rad (B(60 deg) = 0.09)
    assert 1.9 < surge(0.01) < 2.0
    assert 1.0 < surge(60.0) < 1.1
    assert law(-0.1, 0.9, 0.5) == 0.0 and law(0.6, -0.2, 0.5) == 0.0
    assert law(np.zeros((2, 3)), np.ones((2, 3)), np.ones((2, 3))).shape == (2, 3)


def test_the_laws_by_name():
    assert PHOTOMETRY["mcewen"](0.7, 0.9, 0.4) == lunar_lambert(0.7, 0.9, 0.4)
    slow = PHOTOMETRY["lunar-lambert-slow"]
    assert isinstance(slow, LunarLambert)
    # its limb darkening fades more slowly with phase than McEwen's
    assert mcewen_l(np.radians(60), slow.coeffs) > mcewen_l(np.radians(60)) + 0.1
