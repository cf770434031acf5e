"""Site products (pwm.site): slope from the regional normal, roughness about a fitted plane,
relief and hazard, on synthetic height fields whose answers are known."""

import numpy as np
import pytest

from pwm.site import HazardThresholds, hazard, relief_m, roughness_m, slope_deg, window_nodes

SPACING_M = 0.1


def _field(ny: int = 120, nx: int = 150) -> tuple[np.ndarray, np.ndarray]:
    """Rolling terrain h = 2 sin(x / 3) + 1.5 cos(y / 2) + 0.2 x (m) and its true slope (deg)."""
    y, x = np.mgrid[0:ny, 0:nx] * SPACING_M
    height = 2.0 * np.sin(x / 3.0) + 1.5 * np.cos(y / 2.0) + 0.2 * x
    dh_dx = 2.0 / 3.0 * np.cos(x / 3.0) + 0.2
    dh_dy = -1.5 / 2.0 * np.sin(y / 2.0)
    return height, np.degrees(np.arctan(np.hypot(dh_dx, dh_dy)))


def test_slope_of_a_known_field_within_a_hundredth_of_a_degree():
    height, truth = _field()
    slope = slope_deg(height, spacing_m=SPACING_M)
    assert slope.shape == height.shape and truth.max() > 35
    rms = np.sqrt(np.mean((slope - truth)[1:-1, 1:-1] ** 2))
    assert rms < 0.01
    # the acceptance bound (2 deg RMS) over the whole grid, edges included
    assert np.sqrt(np.mean((slope - truth) ** 2)) < 2.0


def test_slope_of_a_tilted_plane_and_a_gap():
    y, x = np.mgrid[0:20, 0:30] * SPACING_M
    height = np.tan(np.radians(30.0)) * x
    height[5, 7] = np.nan
    slope = slope_deg(height, spacing_m=SPACING_M)
    np.testing.assert_allclose(slope[np.isfinite(slope)], 30.0, atol=1e-9)
    assert np.isnan(slope[5, 6]) and np.isnan(slope[4, 7]) and np.isfinite(slope[5, 9])


def test_slope_over_a_baseline_is_the_fitted_plane_tilt():
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:120, 0:120] * SPACING_M
    plane = np.tan(np.radians(25.0)) * (0.6 * x + 0.8 * y) + 40.0
    exact = slope_deg(plane, spacing_m=SPACING_M, baseline_m=1.0)
    np.testing.assert_allclose(exact[np.isfinite(exact)], 25.0, atol=1e-9)
    # noise of a third of the spacing: differences over two spacings turn it into degrees of
    # slope, a plane over 1 m (11 x 11 nodes) averages it away
    noisy = plane + rng.normal(0.0, SPACING_M / 3, plane.shape)
    at_nodes = slope_deg(noisy, spacing_m=SPACING_M)[5:-5, 5:-5]
    over_baseline = slope_deg(noisy, spacing_m=SPACING_M, baseline_m=1.0)[5:-5, 5:-5]
    assert np.sqrt(np.mean((at_nodes - 25.0) ** 2)) > 5.0
    assert np.sqrt(np.mean((over_baseline - 25.0) ** 2)) < 1.0
    # windows reaching a gap or past the edge give NaN, as roughness does
    plane[60, 60] = np.nan
    gap = slope_deg(plane, spacing_m=SPACING_M, baseline_m=1.0)
    assert np.isnan(gap[55:66, 55:66]).all() and np.isfinite(gap[60, 66])
    assert np.isnan(gap[:5]).all() and np.isfinite(gap[5, 5])


def test_roughness_of_a_plane_with_noise_is_the_noise():
    rng = np.random.default_rng(4)
    y, x = np.mgrid[0:200, 0:200] * SPACING_M
    plane = 0.4 * x - 0.3 * y + 120.0  # far from 0: no cancellation
    rough = roughness_m(plane, spacing_m=SPACING_M)
    assert np.nanmax(rough) < 1e-5
    noisy = roughness_m(plane + rng.normal(0.0, 0.03, plane.shape), spacing_m=SPACING_M,
                        baseline_m=2.0)
    # the plane takes 3 of the 21 x 21 window's degrees of freedom
    assert np.nanmean(noisy) == pytest.approx(0.03 * np.sqrt(1 - 3 / 441), rel=0.02)
    # windows past the edge have no value; 2 m at 0.1 m is 21 nodes
    assert window_nodes(spacing_m=SPACING_M, baseline_m=2.0) == 21
    assert np.isnan(noisy[:10]).all() and np.isfinite(noisy[10:-10, 10:-10]).all()


def test_a_boulder_stands_out_in_relief_and_hazard():
    y, x = np.mgrid[0:100, 0:100] * SPACING_M
    height = 0.1 * x
    height[48:52, 48:52] += 0.8  # a 0.4 m boulder, 0.8 m tall
    relief = relief_m(height, spacing_m=SPACING_M, baseline_m=2.0)
    assert relief[50, 50] == pytest.approx(0.8 * (1 - 16 / 441), abs=1e-9)
    assert abs(relief[20, 20]) < 1e-9
    thresholds = HazardThresholds(max_slope_deg=30.0, max_relief_m=0.5)
    slope = slope_deg(height, spacing_m=SPACING_M)
    hazardous = hazard(slope, relief, thresholds)
    assert hazardous[48:52, 48:52].all() and not hazardous[20:40, 20:40].any()
    assert hazardous[0].all()  # no relief at the edge: unknown counts as hazardous
    with pytest.raises(ValueError, match="thresholds"):
        HazardThresholds(max_slope_deg=95.0)
    with pytest.raises(ValueError, match="shape"):
        hazard(slope, relief[1:], thresholds)


def test_bad_grids_are_refused():
    with pytest.raises(ValueError, match="2-D"):
        slope_deg(np.zeros(10), spacing_m=1.0)
    with pytest.raises(ValueError, match="spacing"):
        roughness_m(np.zeros((5, 5)), spacing_m=0.0)
    with pytest.raises(ValueError, match="baseline"):
        roughness_m(np.zeros((5, 5)), spacing_m=1.0, baseline_m=-1.0)
