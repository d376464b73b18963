"""numpy.linalg on stacks of small matrices (a refit's bands, a page of windows) where one bad matrix does not fail
the stack: numpy raises LinAlgError for the whole stack when one matrix is singular or not finite."""

from __future__ import annotations

import numpy as np


def solve_stack(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.linalg.solve of stacked systems (a: (k, n, n), b: (k, n, m)), NaN for the singular ones."""
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        out = np.full(b.shape, np.nan)
        for k in range(len(a)):
            try:
                out[k] = np.linalg.solve(a[k], b[k])
            except np.linalg.LinAlgError:
                pass
        return out


def eig_stack(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.linalg.eig of stacked matrices, NaN for those it cannot take (not finite, or no convergence)."""
    try:
        return np.linalg.eig(m)
    except np.linalg.LinAlgError:
        values, vectors = np.full(m.shape[:2], np.nan, complex), np.full(m.shape, np.nan, complex)
        for k in range(len(m)):
            try:
                values[k], vectors[k] = np.linalg.eig(m[k])
            except np.linalg.LinAlgError:
                pass
        return values, vectors
