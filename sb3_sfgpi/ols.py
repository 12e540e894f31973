"""
Optimistic Linear Support (OLS): which weight to solve next, and when the solutions form a CCS.

OLS (the paper's Algorithm 1, Theorem 1 and Eqs. 13-15) keeps the value vectors ``V`` of the policies found so
far, the weights ``W`` they were trained for (the *visited* weights) and a priority queue of weights still to try.
The upper surface ``V^CB(w) = max_{V in V} w · V`` is piecewise linear and convex on the weight simplex; its
vertices, the *corner weights*, are where a new policy can improve it most (Theorem 1). A corner weight ``w``
is queued with the optimistic improvement (Eq. 15)

    ``Δ(w) = max_v {w · v : w_j · v <= V^CB(w_j) for every w_j in W} - V^CB(w)``,

an upper bound of ``max_π w · V^π - V^CB(w)`` whenever the policies trained for ``W`` were optimal for them.
The queue starts with the simplex extrema at infinite priority; once it is empty, the values cover every weight.

**Tolerance.** One absolute ``tolerance`` (default :data:`TOLERANCE`) is used everywhere:

* two value vectors are the same value when no component differs by more than it (duplicates are not added);
* two weights are the same weight when no component differs by more than it (corner deduplication, visited
  weights, weights already queued);
* a corner weight is queued only when its priority exceeds it, and two priorities within it of each other are equal
  (the tie rule: the weight queued first is popped first, so that LP round-off between corners of mathematically
  equal priority, e.g. symmetric ones, never decides the order);
* a new value makes a queued corner weight obsolete when it raises ``V^CB`` there by more than it, and a value
  is in the CCS when, at some weight, it beats every other value by more than it.

Every ``w · V`` is :func:`~sb3_sfgpi.common.weights.weighted_sum` (products added in the order of the objectives,
no BLAS), so the upper surface, the LPs' bounds and therefore the queue are the same on every machine. The
tolerance is far above the round-off of these sums (values are returns of order 1 to 100, their round-off about
``1e-14``) and far below the differences between the values of distinct policies that matter.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import HalfspaceIntersection, cKDTree

from sb3_sfgpi.common.weights import simplex_extrema, validate_weights, weighted_sum

#: The default absolute tolerance of :class:`OLS` (equal values, equal weights, equal priorities; module docstring).
TOLERANCE = 1e-6

# Values are rescaled into [0, 1] before the vertex enumeration, so the upper surface lies below c = 1; the cap
# c <= _CAP bounds the polytope and its own vertices (at c = _CAP) are dropped afterwards.
_CAP = 2.0


def _same(a: np.ndarray, b: np.ndarray, tolerance: float) -> bool:
    return bool(np.max(np.abs(a - b)) <= tolerance)


def _margin(values: np.ndarray, i: int, w: np.ndarray) -> float:
    """``min_{j != i} w · (V_i - V_j)``: by how much value ``i`` beats every other at ``w`` (inf if it is alone)."""
    return float(np.min(weighted_sum(np.delete(values[i] - values, i, axis=0), w), initial=np.inf))


def _corner_weights(values: np.ndarray, tolerance: float) -> list[np.ndarray]:
    """
    Vertices of ``{(w, c): w in simplex, c >= w · V for every row V of values}``, projected on ``w``.

    The polytope is written in the free coordinates ``z = (w_0, ..., w_{d-2}, c)`` (``w_{d-1} = 1 - Σ z[:-1]``),
    capped by ``c <= _CAP`` and handed to Qhull's halfspace intersection.

    :param values: shape ``(n, d)``, ``n >= 1``, ``d >= 2``
    :param tolerance: vertices closer than this (max-norm on ``w``) are one corner
    :return: the corner weights, sorted lexicographically
    """
    n, d = values.shape
    low, span = values.min(), values.max() - values.min()
    # w · V and the corners are unchanged (up to an affine map of c) by V -> (V - low) / span, as Σw = 1.
    scaled = (values - low) / span if span > 0 else np.zeros_like(values)
    last = scaled[:, -1:]
    # Each row (a, b) is the halfspace a · z + b <= 0.
    halfspaces = np.vstack(
        [
            np.hstack([scaled[:, :-1] - last, -np.ones((n, 1)), last]),  # w · V - c <= 0
            np.hstack([-np.eye(d - 1), np.zeros((d - 1, 2))]),  # -w_k <= 0 for k < d - 1
            np.concatenate([np.ones(d - 1), [0.0, -1.0]]),  # -w_{d-1} <= 0
            np.concatenate([np.zeros(d - 1), [1.0, -_CAP]]),  # c <= _CAP
        ]
    )
    center = np.full(d, 1.0 / d)
    top = np.max(weighted_sum(scaled, center))
    interior = np.append(center[:-1], (top + _CAP) / 2)  # strictly inside every halfspace
    vertices = HalfspaceIntersection(halfspaces, interior).intersections
    vertices = vertices[vertices[:, -1] < (1.0 + _CAP) / 2]  # keep the upper surface (c <= 1), drop the cap
    free = vertices[:, :-1]
    weights = np.clip(np.hstack([free, 1.0 - free.sum(axis=1, keepdims=True)]), 0.0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    return unique_points(weights[np.lexsort(weights.T[::-1])], tolerance)


def unique_points(points: np.ndarray, tolerance: float) -> list[np.ndarray]:
    """
    The points, in order, without those within ``tolerance`` (max-norm) of a point kept before them.

    Qhull reports a vertex once per facet it closes, so a corner comes many times; a k-d tree finds each
    point's near neighbours at once instead of comparing it with every kept point.
    """
    neighbours = cKDTree(points).query_ball_point(points, r=tolerance, p=np.inf)
    kept = np.zeros(len(points), dtype=bool)
    for i, near in enumerate(neighbours):
        kept[i] = not kept[near].any()
    return list(points[kept])


class OLS:
    """
    Optimistic Linear Support over value vectors (see the module docstring for the tolerance).

    Typical loop: ``w = ols.next_weight()``; solve the task scalarized by ``w``; ``ols.add_solution(V, w)``;
    repeat until ``next_weight()`` returns None (then ``ols.ended`` and ``ols.ccs`` is a convex coverage set).

    :param reward_dim: number of objectives ``d >= 2``
    :param tolerance: absolute tolerance for equal values, equal weights, priorities and improvements (> 0)
    """

    def __init__(self, reward_dim: int, tolerance: float = TOLERANCE):
        if int(reward_dim) != reward_dim or reward_dim < 2:
            raise ValueError(f"reward_dim must be an integer >= 2, got {reward_dim!r}")
        if not (math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"tolerance must be a positive finite number, got {tolerance!r}")
        self.reward_dim = int(reward_dim)
        self.tolerance = float(tolerance)
        self._values: list[np.ndarray] = []
        self._visited: list[np.ndarray] = []
        # The CCS: index into self._values -> a weight at which that value beats every other by more than the
        # tolerance (a witness; a new value that does not come close to it there leaves the member in the CCS).
        self._witnesses: dict[int, np.ndarray] = {}
        # (priority, weight), highest priority first; equal priorities in insertion order.
        self._queue: list[tuple[float, np.ndarray]] = [(math.inf, e) for e in simplex_extrema(self.reward_dim)]

    # --- the loop -------------------------------------------------------------------------------------
    def next_weight(self) -> np.ndarray | None:
        """
        Pop the weight with the highest priority (Algorithm 1, line 8).

        :return: the weight, or None when the queue is empty
        """
        return self._queue.pop(0)[1].copy() if self._queue else None

    def add_solution(self, value, weight) -> list[int]:
        """
        Record the value vector of a policy solved for ``weight`` (Algorithm 1, lines 12 and 20-28).

        ``weight`` becomes visited (and leaves the queue if it is there). If ``value`` is new, it is appended to
        :attr:`values`; queued weights where it raises ``V^CB`` by more than the tolerance are dropped (simplex
        extrema stay: they are always corners); then the corner weights where it is on the upper surface are queued
        with their priority, unless visited, already queued or of priority <= tolerance.

        :param value: the policy's value vector, length ``d``
        :param weight: the weight the policy was trained for
        :return: indices into :attr:`values` of the values that left the CCS because of ``value``
        :raises ValueError: ``value`` of the wrong length or not finite; invalid ``weight``
        """
        value = self._validate_value(value)
        weight = validate_weights(weight, self.reward_dim, "weight")
        tol = self.tolerance
        if not any(_same(weight, u, tol) for u in self._visited):
            self._visited.append(weight)
        self._queue = [(p, u) for p, u in self._queue if not _same(u, weight, tol)]
        if any(_same(value, v, tol) for v in self._values):
            return []

        old_best = [self._max_value(u) for _, u in self._queue]
        self._values.append(value)
        # Where the new value raises V^CB, a queued weight stops being a corner (the simplex extrema never do).
        self._queue = [
            (p, u)
            for (p, u), best in zip(self._queue, old_best, strict=True)
            if weighted_sum(u, value) <= best + tol or u.max() >= 1 - tol
        ]
        for corner in self._new_corners(value):
            priority = self._priority(corner)
            if priority > tol:
                self._push(priority, corner)

        old_ccs = list(self._witnesses)
        self._witnesses = self._coverage([*old_ccs, len(self._values) - 1])
        return [i for i in old_ccs if i not in self._witnesses]

    # --- the upper surface ----------------------------------------------------------------------------
    def corner_weights(self) -> list[np.ndarray]:
        """
        Corner weights of the current values: the vertices of the upper surface ``V^CB``, simplex extrema included.

        :return: the corner weights (the simplex extrema while there is no value), deduplicated within the tolerance
        """
        if not self._values:
            return simplex_extrema(self.reward_dim)
        return _corner_weights(np.array(self._values), self.tolerance)

    def max_scalarized_value(self, w) -> float:
        """
        ``V^CB(w) = max_V w · V`` over the values found so far (Eq. 14).

        :param w: a weight (normalised onto the simplex, like everywhere)
        :return: the maximum, ``-inf`` while there is no value
        """
        return self._max_value(validate_weights(w, self.reward_dim, "w"))

    def priority(self, w) -> float:
        """
        The optimistic improvement ``Δ(w)`` (Eq. 15) given the current values and visited weights.

        :param w: a weight
        :return: ``Δ(w) >= 0``; ``inf`` while the LP is unbounded (e.g. before every simplex extremum is visited)
        """
        return self._priority(validate_weights(w, self.reward_dim, "w"))

    # --- state ----------------------------------------------------------------------------------------
    @property
    def ended(self) -> bool:
        """True when the queue is empty after at least one solution was added: the values form a CCS."""
        return not self._queue and bool(self._visited)

    @property
    def ccs(self) -> list[np.ndarray]:
        """The values in the (minimal) convex coverage set: those that beat all others at some weight."""
        return [self._values[i].copy() for i in self._witnesses]

    @property
    def values(self) -> list[np.ndarray]:
        """Every distinct value added, in order of addition (indices never change: values are only appended)."""
        return [v.copy() for v in self._values]

    @property
    def weights(self) -> list[np.ndarray]:
        """The visited weights (the set ``W``), in order of first visit."""
        return [w.copy() for w in self._visited]

    @property
    def queue(self) -> list[tuple[float, np.ndarray]]:
        """The queued ``(priority, weight)`` pairs in the order :meth:`next_weight` pops them."""
        return [(p, w.copy()) for p, w in self._queue]

    def state_dict(self) -> dict[str, Any]:
        """
        The full state as JSON-compatible data (infinite priorities are the string ``"inf"``).

        :return: a dict for :meth:`from_state_dict`; ``json.dumps(..., allow_nan=False)`` accepts it
        """
        return {
            "reward_dim": self.reward_dim,
            "tolerance": self.tolerance,
            "values": [v.tolist() for v in self._values],
            "weights": [w.tolist() for w in self._visited],
            "queue": [["inf" if math.isinf(p) else p, w.tolist()] for p, w in self._queue],
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> OLS:
        """
        Rebuild an :class:`OLS` from :meth:`state_dict`; it then behaves exactly like the original.

        :param state: the output of :meth:`state_dict` (possibly through JSON)
        :return: the restored instance
        """
        ols = cls(state["reward_dim"], state["tolerance"])
        ols._values = [np.asarray(v, dtype=np.float64) for v in state["values"]]
        ols._visited = [np.asarray(w, dtype=np.float64) for w in state["weights"]]
        ols._queue = [(float(p), np.asarray(w, dtype=np.float64)) for p, w in state["queue"]]
        ols._witnesses = ols._coverage(range(len(ols._values)))
        return ols

    # --- helpers --------------------------------------------------------------------------------------
    def _validate_value(self, value) -> np.ndarray:
        try:
            v = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise ValueError(f"value must be a sequence of {self.reward_dim} numbers, got {value!r}") from error
        if v.ndim != 1 or v.shape[0] != self.reward_dim:
            raise ValueError(f"value must have length {self.reward_dim} (one per objective), got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"value must be finite, got {v.tolist()} (NaN or inf)")
        return v

    def _new_corners(self, value: np.ndarray) -> np.ndarray:
        """The corner weights where ``value`` is on the upper surface, neither visited nor queued."""
        corners = np.array(self.corner_weights())
        surface = weighted_sum(corners[:, None, :], np.array(self._values)[None]).max(axis=1)
        on_surface = corners[surface - weighted_sum(corners, value) <= self.tolerance]
        known = np.array([*self._visited, *(u for _, u in self._queue)])
        distance, _ = cKDTree(known).query(on_surface, p=np.inf)  # to the nearest known weight
        return on_surface[distance > self.tolerance]

    def _max_value(self, w: np.ndarray) -> float:
        return float(np.max(weighted_sum(np.array(self._values), w))) if self._values else -math.inf

    def _priority(self, w: np.ndarray) -> float:
        """Eq. 15 at ``w``: how much the optimistic value could exceed the best known value there."""
        if not self._visited:
            return math.inf
        visited = np.array(self._visited)
        bounds = [self._max_value(u) for u in visited]
        result = linprog(-w, A_ub=visited, b_ub=bounds, bounds=[(None, None)] * self.reward_dim, method="highs")
        if result.status == 3:  # unbounded
            return math.inf
        if result.status != 0:
            raise RuntimeError(f"OLS priority LP failed at w={w.tolist()}: {result.message}")
        return max(0.0, -result.fun - self._max_value(w))

    def _push(self, priority: float, w: np.ndarray) -> None:
        """Queue ``w`` after every weight of higher or equal priority (equal: within the tolerance)."""
        position = next((i for i, (p, _) in enumerate(self._queue) if p < priority - self.tolerance), len(self._queue))
        self._queue.insert(position, (priority, w))

    def _coverage(self, candidates: Iterable[int]) -> dict[int, np.ndarray]:
        """
        The candidates that beat every other value by more than the tolerance at some weight, with such a weight.

        A candidate's known witness is checked first (one product per value); only where it fails is the LP solved.
        """
        values = np.array(self._values)
        witnesses = {}
        for i in candidates:
            witness = self._witnesses.get(i)
            if witness is None or _margin(values, i, witness) <= self.tolerance:
                witness = self._witness(values, i)
            if witness is not None:
                witnesses[i] = witness
        return witnesses

    def _witness(self, values: np.ndarray, i: int) -> np.ndarray | None:
        """
        A weight maximising ``min_{j != i} w · (V_i - V_j)`` over the simplex (an LP in ``(w, t)``), if that
        maximum exceeds the tolerance; else None.

        :param values: the values, as one array (built once per :meth:`_coverage`)
        :param i: the row of the candidate
        """
        others = np.delete(values, i, axis=0)
        d = self.reward_dim
        if len(others) == 0:
            return np.full(d, 1.0 / d)
        result = linprog(
            np.append(np.zeros(d), -1.0),  # maximise t
            A_ub=np.hstack([others - values[i], np.ones((len(others), 1))]),  # t <= w · (V_i - V_j)
            b_ub=np.zeros(len(others)),
            A_eq=np.append(np.ones(d), 0.0)[None],
            b_eq=[1.0],
            bounds=[(0.0, None)] * d + [(None, None)],
            method="highs",
        )
        if result.status != 0:
            raise RuntimeError(f"OLS coverage LP failed for value {i}: {result.message}")
        return result.x[:d] if -result.fun > self.tolerance else None
