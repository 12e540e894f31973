"""Multi-objective metrics: expected utility over test weights and the hypervolume of a set of value vectors."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sb3_sfgpi.common.weights import weighted_sum


def expected_utility(weights: np.ndarray, returns: np.ndarray) -> float:
    """
    Mean scalarised return ``mean_i w_i · G_i`` over test weights.

    The same bits on every machine and for every order of the rows: each ``w_i · G_i`` is
    :func:`~sb3_sfgpi.common.weights.weighted_sum` and their sum is exactly rounded (``math.fsum``), so two sets of
    episodes with the same scalarised returns in another order (e.g. the agents' roles swapped) score exactly the
    same, and policy validation's "no worse" comparison sees a tie as a tie.

    :param weights: shape ``(n, d)``
    :param returns: the vector return obtained for each weight, shape ``(n, d)``
    """
    weights, returns = np.asarray(weights, dtype=np.float64), np.asarray(returns, dtype=np.float64)
    if weights.shape != returns.shape:
        raise ValueError(f"weights {weights.shape} and returns {returns.shape} must have the same shape")
    if len(returns) == 0:
        return math.nan  # as the mean of nothing
    return math.fsum(weighted_sum(returns, weights).tolist()) / len(returns)


def hypervolume(points: Sequence[np.ndarray] | np.ndarray, reference: Sequence[float] | np.ndarray) -> float:
    """
    Volume dominated by ``points`` (maximisation) and bounded below by ``reference``.

    Exact, by slicing along the last objective; meant for the few dozen points of a coverage set.

    :param points: shape ``(n, d)``
    :param reference: shape ``(d,)``; points not strictly above it in every objective add nothing
    """
    ref = np.asarray(reference, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, ref.shape[0])
    pts = pts[np.all(pts > ref, axis=1)]
    return _hypervolume(pts - ref)


def _hypervolume(pts: np.ndarray) -> float:
    # Points are relative to the reference (all coordinates > 0).
    if len(pts) == 0:
        return 0.0
    if pts.shape[1] == 1:
        return float(pts.max())
    order = np.argsort(-pts[:, -1])
    pts = pts[order]
    volume = 0.0
    for i in range(len(pts)):
        lower = pts[i + 1, -1] if i + 1 < len(pts) else 0.0
        height = pts[i, -1] - lower
        if height > 0:
            volume += height * _hypervolume(pts[: i + 1, :-1])
    return volume
