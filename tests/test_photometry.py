"""McEwen lunar-Lambert photometry against values worked out by hand from the published formula."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.photometry import angles, lunar_lambert, mcewen_l


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
