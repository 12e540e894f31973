"""Brute-force corner weights: the ground truth :class:`sb3_sfgpi.ols.OLS` is tested (and benchmarked) against.

Deliberately simple and slow (``C(n + d, d)`` linear solves): a vertex of
``{(w, c): w >= 0, Σw = 1, c >= w · V_i for all i}`` is a feasible point where ``Σw = 1`` and ``d`` linearly
independent hyperplanes among ``{c = w · V_i}`` and ``{w_k = 0}`` meet, so every ``d``-subset of them is tried.
"""

from __future__ import annotations

import itertools

import numpy as np


def brute_force_corner_weights(values: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """
    All corner weights of the upper surface ``max_i w · V_i`` by enumerating every candidate vertex.

    :param values: value vectors, shape ``(n, d)`` with ``n >= 1``
    :param tol: feasibility slack, and the max-norm distance under which two corners are the same
    :return: the corner weights, shape ``(m, d)``
    """
    values = np.asarray(values, dtype=np.float64)
    n, d = values.shape
    # Rows of [a, b] in the unknowns x = (w_0, ..., w_{d-1}, c): the hyperplane a · x = b.
    hyperplanes = [(np.append(v, -1.0), 0.0) for v in values]  # w · V_i - c = 0
    hyperplanes += [(np.append(np.eye(d)[k], 0.0), 0.0) for k in range(d)]  # w_k = 0
    simplex = (np.append(np.ones(d), 0.0), 1.0)  # Σw = 1, always active
    corners: list[np.ndarray] = []
    for subset in itertools.combinations(hyperplanes, d):
        rows = [simplex, *subset]
        matrix = np.array([a for a, _ in rows])
        if np.linalg.matrix_rank(matrix) < d + 1:
            continue
        solution = np.linalg.solve(matrix, np.array([b for _, b in rows]))
        w, c = solution[:d], solution[d]
        if np.all(w >= -tol) and c >= np.max(values @ w) - tol:
            if not any(np.max(np.abs(w - u)) <= tol for u in corners):
                corners.append(w)
    return np.array(corners).reshape(-1, d)
