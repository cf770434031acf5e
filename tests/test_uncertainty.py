"""A node's 1-sigma height from how its images agree with the solved shape, and a fused vertex's
from the maplets over it (pwm.uncertainty)."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.evaluate.report import calibration
from pwm.frames import local_frame
from pwm.io.fusion_state import read_maplet, write_maplet
from pwm.io.meshio import read_ply, write_ply
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.uncertainty import Uncertainty, node_sigma, vertex_sigma

N, K = 24, 4
SPACING = 1e-4
SETTINGS = Uncertainty(floor_spacings=0.1, misfit_gain=0.1, smoothing_nodes=0.0)


def _images(misfit: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K images weighing every node alike, each misfit by `misfit`, Suns from four azimuths."""
    weights = np.ones((K, N, N))
    residual = np.full((K, N, N), misfit)
    azimuths = np.arange(K) * np.pi / 2
    gradients = np.zeros((K, N, N, 2))
    gradients[..., 0] = np.cos(azimuths)[:, None, None]
    gradients[..., 1] = np.sin(azimuths)[:, None, None]
    return weights, residual, gradients


def test_a_node_where_the_images_disagree_is_less_certain():
    weights, misfit, gradients = _images()
    misfit[:, 10, 12] = 0.2
    sigma = node_sigma(weights=weights, misfit=misfit, slope_gradients=gradients, spacing_km=SPACING,
                       uncertainty=SETTINGS)
    # elsewhere: misfit at the maplet's median (relative 1); unit gradients from four sides make
    # M = I / 2, a sensitivity of sqrt(2)
    assert np.median(sigma) == pytest.approx(SPACING * np.hypot(0.1, 0.1 * np.sqrt(2)))
    assert sigma[10, 12] == pytest.approx(SPACING * np.hypot(0.1, 0.1 * 10 * np.sqrt(2)))
    # the common misfit of every node is no height error: doubled everywhere, the sigmas stay
    again = node_sigma(weights=weights, misfit=2 * misfit, slope_gradients=gradients, spacing_km=SPACING,
                       uncertainty=SETTINGS)
    np.testing.assert_allclose(again, sigma)


def test_images_that_barely_see_the_slopes_say_less_and_unseen_nodes_say_nothing():
    weights, misfit, gradients = _images()
    weights[:, :5] = 0.0
    flat = gradients.copy()
    flat[:, 20:] *= 0.25  # grazing light: the brightness moves a quarter as much with the slope
    sigma = node_sigma(weights=weights, misfit=misfit, slope_gradients=flat, spacing_km=SPACING,
                       uncertainty=SETTINGS)
    assert np.isnan(sigma[:5]).all() and np.isfinite(sigma[5:]).all()
    assert sigma[22, 3] == pytest.approx(SPACING * np.hypot(0.1, 0.1 * 4 * np.sqrt(2)))
    # Suns all from one azimuth: nothing says the slope across it
    one_side = gradients.copy()
    one_side[..., 1] = 0.0
    assert np.isinf(node_sigma(weights=weights, misfit=misfit, slope_gradients=one_side, spacing_km=SPACING,
                               uncertainty=SETTINGS)[10]).all()


def _maplet(name: str, centre_km: float, sigma_km: float, lift_km: float = 0.0) -> MapletGrid:
    frame = local_frame(np.array([centre_km, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    return MapletGrid(name=name, frame=frame, spacing_km=SPACING, heights=np.full((N, N), lift_km),
                      sigma=np.full((N, N), sigma_km))


def test_a_vertex_takes_the_rms_of_the_maplets_over_it():
    a = _maplet("a", 0.0, 2e-5)
    b = _maplet("b", 0.0, 4e-5, lift_km=3e-5)
    # vertices on a's surface: one at its centre, one beyond both maplets
    vertices = a.frame.to_body(np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]))
    alone = vertex_sigma(vertices, [a], taper_fraction=0.25)
    assert alone[0] == pytest.approx(2e-5) and np.isnan(alone[1])
    both = vertex_sigma(vertices, [a, b], taper_fraction=0.25)
    # equal weights: the mean of their variances; b's distance from the surface, which fusion
    # averages, adds nothing
    assert both[0] == pytest.approx(np.sqrt(0.5 * (2e-5**2 + 4e-5**2)))
    # a maplet without sigmas says nothing
    assert vertex_sigma(vertices, [MapletGrid("c", a.frame, SPACING, np.zeros((N, N)))],
                        taper_fraction=0.25)[0] != vertex_sigma(vertices, [a], taper_fraction=0.25)[0]


def test_sigmas_travel_with_the_maplet_and_the_mesh(tmp_path):
    maplet = _maplet("a", 0.0, 2e-5)
    maplet.sigma[3, 4] = np.nan
    write_maplet(tmp_path / "m.npz", maplet)
    back = read_maplet(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.sigma, maplet.sigma)
    mesh = Mesh(np.eye(3), np.array([[0, 1, 2]]), albedo=np.full(3, 0.04), sigma=np.array([1e-5, np.nan, 2e-5]))
    write_ply(tmp_path / "m.ply", mesh)
    again = read_ply(tmp_path / "m.ply")
    np.testing.assert_allclose(again.sigma, mesh.sigma, rtol=1e-6)
    np.testing.assert_allclose(again.albedo, mesh.albedo, rtol=1e-6)
    with pytest.raises(ValueError, match="one value per vertex"):
        Mesh(np.eye(3), np.array([[0, 1, 2]]), sigma=np.ones(2))


def test_calibration_counts_the_errors_within_one_and_two_sigma():
    distance = np.array([0.5, 1.5, 2.5, 0.1, 9.0])
    sigma = np.array([1.0, 1.0, 1.0, 1.0, np.nan])
    told = calibration(distance, sigma)
    assert told == {"vertex_share": 0.8, "within_1": 0.5, "within_2": 0.75, "median_m": 1000.0}


def test_the_finest_level_over_a_vertex_says():
    coarse = MapletGrid("coarse", _maplet("x", 0.0, 1.0).frame, 8 * SPACING, np.full((N, N), 5e-4),
                        sigma=np.full((N, N), 3e-4))
    fine = _maplet("fine", 0.0, 2e-5)
    vertices = fine.frame.to_body(np.array([[0.0, 0.0, 0.0], [0.006, 0.0, 0.0]]))
    sigma = vertex_sigma(vertices, iter([coarse, fine]), taper_fraction=0.25)
    # the fine maplet's alone where it reaches, not the coarse one's 0.5 m above it
    assert sigma[0] == pytest.approx(2e-5)
    # beyond it, the coarse level's
    assert sigma[1] == pytest.approx(3e-4)
