"""Sparse symmetric positive definite systems, factored by CHOLMOD's supernodal Cholesky (through
cvxopt): a maplet's normal equations (pwm.photoclinometry), once each Gauss-Newton step. On a
100 x 100-node maplet CHOLMOD factors them about five times faster than SuperLU's LU, which does
not use their symmetry (bench/RESULTS.md)."""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import scipy.sparse as sp
from cvxopt import cholmod, matrix, spmatrix


class _System(IntEnum):
    """cholmod.solve's systems, with P A P' = L D L' (D = I for a supernodal factor)."""

    A = 0  # A x = b
    L = 4  # L x = b
    D = 6  # D x = b
    P = 7  # P' x = b: x = P b


class Cholesky:
    """The factorization of a sparse symmetric positive definite (n, n) matrix, of which only the
    lower triangle is read; ArithmeticError where it is not positive definite."""

    def __init__(self, a: sp.spmatrix | sp.sparray) -> None:
        lower = sp.tril(a, format="coo")
        n = lower.shape[0]
        matrix_ = spmatrix(lower.data.astype(float), lower.row.astype(int), lower.col.astype(int), size=(n, n))
        self._factor = cholmod.symbolic(matrix_, uplo="L")
        cholmod.numeric(matrix_, self._factor)
        self.n = n

    def _solved(self, b: np.ndarray, *systems: _System) -> np.ndarray:
        x = matrix(np.asarray(b, float).reshape(self.n, -1))
        for system in systems:
            cholmod.solve(self._factor, x, sys=int(system))
        return np.array(x)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x with A x = b, for b (n,) or (n, m)."""
        b = np.asarray(b, float)
        return self._solved(b, _System.A).reshape(b.shape)

    def inverse_form(self, b: np.ndarray) -> np.ndarray:
        """b' A^-1 b (m, m) for b (n, m): with half the work of solving for A^-1 b, as
        (L^-1 P b)' D^-1 (L^-1 P b)."""
        half = self._solved(b, _System.P, _System.L)
        return half.T @ self._solved(half, _System.D)
