"""pwm.spd: the sparse Cholesky factorization a maplet's Gauss-Newton steps solve with."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from pwm.spd import Cholesky


def _grid_system(n: int, seed: int) -> sp.csr_matrix:
    """A 2-D Laplacian with a small ridge and random positive diagonal: symmetric positive definite
    with the stencil of a maplet's normal equations."""
    rng = np.random.default_rng(seed)
    line = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    laplacian = sp.kronsum(line, line)
    return (laplacian @ laplacian + sp.diags(rng.uniform(1e-3, 1.0, n * n))).tocsr()


def test_the_factor_solves_and_forms_the_inverse_as_a_general_solver_does() -> None:
    a = _grid_system(30, seed=1)
    rng = np.random.default_rng(2)
    b = rng.normal(size=(a.shape[0], 7))
    factor = Cholesky(a)
    expected = spsolve(a.tocsc(), b)
    np.testing.assert_allclose(factor.solve(b), expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(factor.solve(b[:, 0]), expected[:, 0], rtol=1e-9,
                               atol=1e-12 * np.abs(expected).max())
    assert factor.solve(b[:, 0]).shape == (a.shape[0],)
    form = factor.inverse_form(b)
    np.testing.assert_allclose(form, b.T @ expected, rtol=1e-9, atol=1e-12 * np.abs(form).max())
    np.testing.assert_allclose(form, form.T, rtol=1e-12, atol=1e-12 * np.abs(form).max())


def test_only_the_lower_triangle_is_read_and_an_indefinite_matrix_is_refused() -> None:
    a = _grid_system(12, seed=3)
    b = np.arange(a.shape[0], dtype=float)
    lower = sp.tril(a).tocsr()
    np.testing.assert_allclose(Cholesky(lower).solve(b), spsolve(a.tocsc(), b), rtol=1e-10)
    with pytest.raises(ArithmeticError):
        Cholesky(a - 5.0 * sp.identity(a.shape[0]))
