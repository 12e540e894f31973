"""Tests of :class:`sb3_sfgpi.ols.OLS`: the paper's worked example (Figs. 1-2), corner weights against a brute
force, priorities, termination with an exact CCS, checkpoint round trips and input validation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import BAD_WEIGHTS
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from momdp import all_policy_values, convex_coverage_values, optimal_policy, policy_value
from ols_reference import brute_force_corner_weights

from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.ols import OLS

TOL = 1e-6
PROPERTY_SETTINGS = settings(max_examples=30, deadline=None, database=None)


# --- helpers ------------------------------------------------------------------------------------------
def value_sets(min_dim: int = 2, max_dim: int = 5, max_values: int = 8) -> st.SearchStrategy[np.ndarray]:
    """Value sets of shape (n, d): integers in [-10, 10] (many ties and coplanar points) or multiples of 0.01."""

    def of_dim(d: int) -> st.SearchStrategy[np.ndarray]:
        shape = st.tuples(st.integers(1, max_values), st.just(d))
        integers = st.integers(-10, 10).map(float)
        hundredths = st.integers(-1000, 1000).map(lambda x: x / 100)
        return st.one_of(arrays(np.float64, shape, elements=integers), arrays(np.float64, shape, elements=hundredths))

    return st.integers(min_dim, max_dim).flatmap(of_dim)


def ols_with_values(values: np.ndarray) -> OLS:
    """An OLS holding ``values`` (the weights they are added with do not affect the corner weights)."""
    ols = OLS(values.shape[1], tolerance=TOL)
    for v in values:
        ols.add_solution(v, np.ones(values.shape[1]))
    return ols


def assert_same_points(found, expected, atol: float = 1e-6) -> None:
    """Equal as sets up to ``atol`` (max-norm): every point of each has a match in the other."""
    found, expected = np.atleast_2d(np.array(found)), np.atleast_2d(np.array(expected))
    for a, b, what in ((found, expected, "unexpected"), (expected, found, "missing")):
        for p in a:
            assert np.min(np.max(np.abs(b - p), axis=1)) <= atol, f"{what} point {p.tolist()}; other set {b.tolist()}"


def solve_exactly(policy_values: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The 'learner': the value of the best policy for ``w`` (the first one on ties)."""
    return policy_values[int(np.argmax(policy_values @ w))]


def run_ols(policy_values: np.ndarray, max_iterations: int = 500) -> OLS:
    """OLS with an exact solver over a finite set of policies, until the queue is empty."""
    ols = OLS(policy_values.shape[1], tolerance=TOL)
    for _ in range(max_iterations):
        w = ols.next_weight()
        if w is None:
            return ols
        ols.add_solution(solve_exactly(policy_values, w), w)
    raise AssertionError(f"OLS did not end after {max_iterations} iterations")


def minimal_ccs(values: np.ndarray) -> np.ndarray:
    """
    The values strictly best at some weight, by brute force: a value's region of the simplex is the convex hull
    of the corner weights where it is maximal, so it is strictly best at their centroid iff that region is
    full-dimensional.
    """
    distinct = np.unique(values, axis=0)
    corners = brute_force_corner_weights(distinct)
    kept = []
    for i, v in enumerate(distinct):
        scores = distinct @ corners.T  # (value, corner)
        attained = corners[scores[i] >= scores.max(axis=0) - 1e-9]
        if len(attained) == 0:
            continue
        centroid = attained.mean(axis=0)
        others = np.delete(distinct, i, axis=0)
        if len(others) == 0 or v @ centroid > np.max(others @ centroid) + TOL:
            kept.append(v)
    return np.array(kept)


# --- 1. the paper's worked example (Section 4.1, Figs. 1-2) ------------------------------------------------
def test_paper_worked_example():
    ols = OLS(2)
    np.testing.assert_array_equal(ols.next_weight(), [1.0, 0.0])
    np.testing.assert_array_equal(ols.next_weight(), [0.0, 1.0])
    assert ols.add_solution([29, 24], [1, 0]) == []
    assert ols.add_solution([16, 30], [0, 1]) == []

    # Corner: 29 w0 + 24 (1 - w0) = 16 w0 + 30 (1 - w0)  <=>  19 w0 = 6.
    # Priority: visited W = {[1, 0], [0, 1]} bound v0 <= V^CB([1,0]) = 29 and v1 <= V^CB([0,1]) = 30, so the
    # optimistic value is (6 * 29 + 13 * 30) / 19 = 564 / 19; V^CB = (6 * 29 + 13 * 24) / 19 = 486 / 19;
    # Δ = 78 / 19.
    corner = np.array([6 / 19, 13 / 19])
    assert len(ols.queue) == 1
    np.testing.assert_allclose(ols.queue[0][0], 78 / 19, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ols.priority(corner), 78 / 19, rtol=0, atol=1e-9)
    w = ols.next_weight()
    np.testing.assert_allclose(w, corner, rtol=0, atol=1e-9)

    # (23, 30) ties (16, 30) only at [0, 1] and beats it elsewhere: (16, 30) (index 1) leaves the CCS.
    assert ols.add_solution([23, 30], w) == [1]
    # Corner: 29 w0 + 24 (1 - w0) = 23 w0 + 30 (1 - w0)  <=>  12 w0 = 6.
    # Priority at [0.5, 0.5]: W now also holds w' = [6/19, 13/19] with V^CB(w') = (6 * 23 + 13 * 30) / 19 = 528 / 19,
    # i.e. 6 v0 + 13 v1 <= 528. Maximise v0 + v1 under v0 <= 29, v1 <= 30, 6 v0 + 13 v1 <= 528: v0 costs less in
    # the last constraint, so v0 = 29, v1 = (528 - 174) / 13 = 354 / 13, and the optimistic value is
    # (29 + 354 / 13) / 2 = 731 / 26. V^CB([0.5, 0.5]) = max(53, 46, 53) / 2 = 689 / 26, so Δ = 42 / 26 = 21 / 13.
    np.testing.assert_allclose(ols.priority([0.5, 0.5]), 21 / 13, rtol=0, atol=1e-9)
    assert len(ols.queue) == 1
    np.testing.assert_allclose(ols.queue[0][0], 21 / 13, rtol=0, atol=1e-9)
    w = ols.next_weight()
    np.testing.assert_allclose(w, [0.5, 0.5], rtol=0, atol=1e-9)

    assert ols.add_solution([23, 30], w) == []  # already known: not added again
    assert ols.next_weight() is None
    assert ols.ended
    assert_same_points(ols.values, [[29, 24], [16, 30], [23, 30]], atol=0)
    # The CCS proper: (16, 30) is weakly dominated by (23, 30), as in tests/momdp.convex_coverage_values().
    assert_same_points(ols.ccs, [[29, 24], [23, 30]], atol=0)
    assert_same_points(ols.weights, [[1, 0], [0, 1], corner, [0.5, 0.5]], atol=1e-9)


def test_worked_example_from_the_momdp():
    """Solving Fig. 1's MOMDP exactly (first optimal policy on ties) takes OLS through the same weights."""
    ols = OLS(2)
    popped = []
    while (w := ols.next_weight()) is not None:
        popped.append(w)
        ols.add_solution(policy_value(optimal_policy(w)), w)
    np.testing.assert_allclose(popped, [[1, 0], [0, 1], [6 / 19, 13 / 19], [0.5, 0.5]], rtol=0, atol=1e-9)
    assert_same_points(ols.ccs, convex_coverage_values(), atol=1e-9)
    for w in random_weights(2, 50, rng=0):
        assert ols.max_scalarized_value(w) == pytest.approx(np.max(all_policy_values() @ w), abs=1e-9)


# --- 2. corner weights against the brute force ------------------------------------------------------------
@PROPERTY_SETTINGS
@given(values=value_sets())
def test_corner_weights_match_brute_force(values):
    assert_same_points(ols_with_values(values).corner_weights(), brute_force_corner_weights(values))


@pytest.mark.parametrize(
    "values",
    [
        pytest.param([[1.0, 2.0, 3.0]], id="single-value"),
        pytest.param([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + 1e-9]], id="duplicates-within-tolerance"),
        pytest.param([[5.0, 5.0, 5.0], [0.0, 0.0, 0.0], [1.0, 4.0, 2.0]], id="dominated-everywhere"),
        pytest.param([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 0.0]], id="collinear"),
        pytest.param([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.5]], id="coplanar-ties"),
        pytest.param([[3.0, 3.0, 3.0, 3.0], [3.0, 3.0, 3.0, 3.0]], id="constant"),
        pytest.param([[1e6, -1e6], [-1e6, 1e6], [0.5, 0.5]], id="large-magnitudes"),
    ],
)
def test_corner_weights_degenerate_sets(values):
    values = np.array(values)
    assert_same_points(ols_with_values(values).corner_weights(), brute_force_corner_weights(values))


def test_corners_closer_than_the_tolerance_are_one_corner():
    # (1 + ε, -1 + ε) is on top only for w0 in [(1 - ε) / 2, (1 + ε) / 2]: two corners 1e-7 apart, one within 1e-6.
    eps = 1e-7
    ols = ols_with_values(np.array([[0.0, 0.0], [2.0, -2.0], [1 + eps, -1 + eps]]))
    corners = ols.corner_weights()
    assert len(corners) == 3
    assert_same_points(corners, [[0, 1], [0.5, 0.5], [1, 0]], atol=1e-6)
    assert_same_points(ols.ccs, [[0, 0], [2, -2]], atol=0)  # it beats the others by ε <= tolerance only
    fine = OLS(2, tolerance=1e-9)  # a finer tolerance keeps both
    for v in ([0.0, 0.0], [2.0, -2.0], [1 + eps, -1 + eps]):
        fine.add_solution(v, [0.5, 0.5])
    assert len(fine.corner_weights()) == 4


def test_corner_weights_known_d3():
    # Three unit values: V^CB(w) = max_k w_k has corners at the extrema, the edge midpoints and the centre.
    ols = ols_with_values(np.eye(3))
    expected = [*np.eye(3), [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5], [1 / 3, 1 / 3, 1 / 3]]
    assert_same_points(ols.corner_weights(), expected, atol=1e-9)


def test_corner_weights_without_values_are_the_extrema():
    assert_same_points(OLS(4).corner_weights(), np.eye(4), atol=0)


# --- 3. properties --------------------------------------------------------------------------------------
@PROPERTY_SETTINGS
@given(values=value_sets())
def test_corner_weights_are_vertices_of_the_upper_surface(values):
    d = values.shape[1]
    corners = ols_with_values(values).corner_weights()
    assert_same_points([c for c in corners if c.max() >= 1 - TOL], np.eye(d), atol=1e-12)  # extrema are corners
    for i, w in enumerate(corners):
        assert np.all(w >= 0) and abs(w.sum() - 1) <= 1e-12, f"{w} is not on the simplex"
        assert all(np.max(np.abs(w - u)) > TOL for u in corners[i + 1 :]), f"{w} is listed twice"
        # A vertex of {(w, c)} in d + 1 unknowns: Σw = 1 plus active constraints of full rank d + 1.
        scores = values @ w
        rows = [np.append(np.ones(d), 0.0)]
        rows += [np.append(v, -1.0) for v in values[scores >= scores.max() - TOL]]
        rows += [np.append(np.eye(d)[k], 0.0) for k in range(d) if w[k] <= TOL]
        assert np.linalg.matrix_rank(np.array(rows), tol=1e-9) == d + 1, f"{w} is not a vertex"


@PROPERTY_SETTINGS
@given(policy_values=value_sets(max_dim=4, max_values=8), seed=st.integers(0, 2**16))
def test_ols_with_exact_solver_ends_with_a_ccs(policy_values, seed):
    """Queue invariants at every step, then termination with a set that is exactly a CCS of the policies."""
    d = policy_values.shape[1]
    ols = OLS(d, tolerance=TOL)
    for _ in range(500):
        w = ols.next_weight()
        if w is None:
            break
        ols.add_solution(solve_exactly(policy_values, w), w)

        queue, visited = ols.queue, ols.weights
        priorities = [p for p, _ in queue]
        # highest first; priorities within the tolerance are a tie, queued in the order they came
        slack = ols.tolerance * len(priorities)
        assert all(later <= earlier + slack for earlier, later in zip(priorities, priorities[1:], strict=False))
        assert all(p > TOL for p in priorities)
        corners = ols.corner_weights()
        for i, (p, u) in enumerate(queue):
            assert min(np.max(np.abs(np.array(corners) - u), axis=1)) <= TOL, f"queued {u} is not a corner"
            assert all(np.max(np.abs(u - v)) > TOL for v in visited), f"queued {u} was visited"
            assert all(np.max(np.abs(u - v)) > TOL for _, v in queue[i + 1 :]), f"{u} queued twice"
            assert p >= np.max(policy_values @ u) - ols.max_scalarized_value(u) - 1e-9, "priority not optimistic"
        for c in corners:  # Theorem 1: a corner where the set can still improve must be waiting in the queue
            if np.max(policy_values @ c) - ols.max_scalarized_value(c) > TOL:
                assert any(np.max(np.abs(c - u)) <= TOL for _, u in queue), f"improvable corner {c} not queued"
    else:
        raise AssertionError("OLS did not end")

    assert ols.ended
    ccs = np.array(ols.ccs)
    test_weights = np.vstack([np.eye(d), random_weights(d, 200, rng=seed)])
    np.testing.assert_allclose(
        np.max(test_weights @ ccs.T, axis=1), np.max(test_weights @ policy_values.T, axis=1), rtol=0, atol=1e-9
    )
    assert_same_points(ccs, minimal_ccs(policy_values), atol=0)


@PROPERTY_SETTINGS
@given(values=value_sets(max_dim=5, max_values=12))
def test_ccs_kept_by_witness_weights_is_the_ccs_of_all_coverage_lps(values):
    """After every addition, the CCS (members kept by a witness weight, LPs only where it fails) is the one that
    solving every coverage LP from scratch gives, and every member beats all other values at its witness."""
    ols = OLS(values.shape[1], tolerance=TOL)
    for v in values:
        left = ols.add_solution(v, np.ones(values.shape[1]))
        fresh = OLS.from_state_dict(ols.state_dict())  # no witnesses: one LP per value
        assert len(ols.ccs) == len(fresh.ccs) > 0
        assert_same_points(ols.ccs, fresh.ccs, atol=0)
        for i, witness in ols._witnesses.items():
            others = np.delete(np.array(ols.values), i, axis=0)
            assert len(others) == 0 or np.min((ols.values[i] - others) @ witness) > TOL
        assert all(i not in ols._witnesses for i in left)


@PROPERTY_SETTINGS
@given(policy_values=value_sets(max_values=6), steps=st.integers(0, 8), seed=st.integers(0, 2**16))
def test_priorities_are_optimistic_and_non_negative(policy_values, steps, seed):
    """Mid-run, with exact solutions at the visited weights: true gap <= Δ(w), Δ >= 0, and Δ = 0 where visited."""
    d = policy_values.shape[1]
    ols = OLS(d, tolerance=TOL)
    for _ in range(steps):
        w = ols.next_weight()
        if w is None:
            break
        ols.add_solution(solve_exactly(policy_values, w), w)
    for w in [*random_weights(d, 5, rng=seed), *ols.corner_weights()]:
        gap = np.max(policy_values @ w) - ols.max_scalarized_value(w)
        assert ols.priority(w) >= max(gap - 1e-9, 0.0)
    for w in ols.weights:
        assert ols.priority(w) == pytest.approx(0.0, abs=1e-9)


# Three policies, solved exactly at the three extrema: the queue then holds four corner weights, the first two
# next to each other (max-norm distance 0.29) and 2.9 and 2.6 to gain, the third farther away with 1.4.
NEIGHBOUR_POLICIES = np.array([[7.0, 3.0, 4.0], [9.0, 3.0, 2.0], [2.0, 8.0, 2.0]])


def ols_after_the_extrema(policy_values: np.ndarray) -> OLS:
    ols = OLS(policy_values.shape[1], tolerance=TOL)
    for _ in range(policy_values.shape[1]):
        w = ols.next_weight()
        ols.add_solution(solve_exactly(policy_values, w), w)
    return ols


def test_next_weight_pops_the_corner_weights_by_priority():
    """After the extrema, the queue holds the four corner weights by priority, and ``next_weight`` pops them in that
    order (the two neighbouring corners first: ``batch="top"`` hands them to a round's two agents)."""
    ols = ols_after_the_extrema(NEIGHBOUR_POLICIES)
    assert [round(p, 4) for p, _ in ols.queue] == [2.9167, 2.6471, 1.4286, 1.0]
    np.testing.assert_allclose(ols.next_weight(), [5 / 12, 7 / 12, 0])
    np.testing.assert_allclose(ols.next_weight(), [5 / 17, 7 / 17, 5 / 17])
    assert [round(p, 4) for p, _ in ols.queue] == [1.4286, 1.0]
    assert_same_points([w for _, w in ols.queue], [[0, 2 / 7, 5 / 7], [0.5, 0, 0.5]])


def test_priority_is_infinite_until_every_extremum_is_visited():
    ols = OLS(3)
    for k, e in enumerate(np.eye(3)):
        assert math.isinf(ols.priority([1, 1, 1]))
        np.testing.assert_array_equal(ols.next_weight(), e)  # extrema pop in index order
        ols.add_solution(np.roll([3.0, 1.0, 0.0], k), e)
    assert math.isfinite(ols.priority([1, 1, 1]))


def test_extrema_stay_queued_until_popped():
    ols = OLS(3)
    ols.next_weight()
    ols.add_solution([10.0, 10.0, 10.0], [1, 0, 0])  # raises V^CB at e1 and e2 from -inf
    assert_same_points([w for _, w in ols.queue], [[0, 1, 0], [0, 0, 1]], atol=0)
    assert all(math.isinf(p) for p, _ in ols.queue)


def test_obsolete_corner_weight_is_dropped():
    ols = OLS(2)
    for w, v in (([1, 0], [10, 0]), ([0, 1], [0, 10])):
        ols.next_weight()
        ols.add_solution(v, w)
    np.testing.assert_allclose(ols.queue[0][1], [0.5, 0.5])
    # (6, 6), found for another weight, lifts V^CB at the unvisited corner [0.5, 0.5] from 5 to 6: that weight
    # is no corner any more and leaves the queue; the new corners [0.4, 0.6] and [0.6, 0.4] (where 10 w = 6) come.
    ols.add_solution([6, 6], [0.3, 0.7])
    queued = [w for _, w in ols.queue]
    assert_same_points(queued, [[0.4, 0.6], [0.6, 0.4]], atol=1e-9)


def test_new_value_dominated_everywhere_changes_nothing_but_values():
    ols = OLS(2)
    for w, v in (([1, 0], [10, 0]), ([0, 1], [0, 10])):
        ols.next_weight()
        ols.add_solution(v, w)
    queue = ols.queue
    assert ols.add_solution([1, 1], [0.9, 0.1]) == []
    assert len(ols.values) == 3
    assert_same_points(ols.ccs, [[10, 0], [0, 10]], atol=0)
    assert [(p, w.tolist()) for p, w in ols.queue] == [(p, w.tolist()) for p, w in queue]


def test_duplicate_value_is_not_added_but_its_weight_is_visited():
    ols = OLS(2)
    ols.add_solution([1.0, 2.0], [1, 0])
    ols.add_solution([1.0 + TOL / 2, 2.0], [0, 1])
    assert len(ols.values) == 1
    assert_same_points(ols.weights, [[1, 0], [0, 1]], atol=0)
    assert ols.queue == []  # both extrema visited, so nothing left
    assert ols.ended


def test_max_scalarized_value():
    ols = OLS(2)
    assert ols.max_scalarized_value([1, 0]) == -math.inf
    ols.add_solution([29, 24], [1, 0])
    ols.add_solution([16, 30], [0, 1])
    assert ols.max_scalarized_value([0.5, 0.5]) == pytest.approx(26.5, abs=1e-12)
    assert ols.max_scalarized_value([1, 3]) == pytest.approx(max(29 + 72, 16 + 90) / 4, abs=1e-12)  # normalised


# --- 4. state_dict round trip -----------------------------------------------------------------------------
@pytest.mark.parametrize("d", [2, 3, 4])
@pytest.mark.parametrize("stop_after", [0, 1, 3, 6])
def test_state_dict_round_trip(d, stop_after):
    policy_values = np.random.default_rng(d).integers(0, 10, size=(12, d)).astype(float)
    ols = OLS(d)
    for _ in range(stop_after):
        w = ols.next_weight()
        if w is None:
            break
        ols.add_solution(solve_exactly(policy_values, w), w)
    state = json.loads(json.dumps(ols.state_dict(), allow_nan=False))
    clone = OLS.from_state_dict(state)
    assert clone.state_dict() == ols.state_dict()
    for a, b in zip(clone.ccs, ols.ccs, strict=True):
        np.testing.assert_array_equal(a, b)
    while True:
        w, w_clone = ols.next_weight(), clone.next_weight()
        if w is None:
            assert w_clone is None
            break
        np.testing.assert_array_equal(w, w_clone)
        value = solve_exactly(policy_values, w)
        assert ols.add_solution(value, w) == clone.add_solution(value, w_clone)
        assert clone.state_dict() == ols.state_dict()
    assert ols.ended and clone.ended


def test_state_dict_encodes_infinite_priorities():
    state = OLS(3).state_dict()
    json.dumps(state, allow_nan=False)
    assert [p for p, _ in state["queue"]] == ["inf", "inf", "inf"]
    assert all(math.isinf(p) for p, _ in OLS.from_state_dict(state).queue)


# --- 5. refusals --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("weight, message", BAD_WEIGHTS)
@pytest.mark.parametrize("method", ["add_solution", "priority", "max_scalarized_value"])
def test_bad_weights_are_refused(method, weight, message):
    ols = OLS(2)
    ols.add_solution([1.0, 2.0], [1, 0])
    before = ols.state_dict()
    call = {
        "add_solution": lambda: ols.add_solution([3.0, 4.0], weight),
        "priority": lambda: ols.priority(weight),
        "max_scalarized_value": lambda: ols.max_scalarized_value(weight),
    }[method]
    with pytest.raises(ValueError, match=message):
        call()
    assert ols.state_dict() == before


@pytest.mark.parametrize(
    "value, message",
    [
        pytest.param([1.0], "length 2", id="too-short"),
        pytest.param([1.0, 2.0, 3.0], "length 2", id="too-long"),
        pytest.param([[1.0, 2.0]], "length 2", id="wrong-shape"),
        pytest.param([float("nan"), 1.0], "finite", id="nan"),
        pytest.param([float("inf"), 1.0], "finite", id="inf"),
        pytest.param(["a", 1.0], "numbers", id="not-numbers"),
    ],
)
def test_bad_values_are_refused(value, message):
    ols = OLS(2)
    before = ols.state_dict()
    with pytest.raises(ValueError, match=f"value .*{message}"):
        ols.add_solution(value, [1, 0])
    assert ols.state_dict() == before


@pytest.mark.parametrize(
    "kwargs, message",
    [
        pytest.param({"reward_dim": 1}, "reward_dim", id="one-objective"),
        pytest.param({"reward_dim": 2.5}, "reward_dim", id="fractional-dim"),
        pytest.param({"reward_dim": 2, "tolerance": 0.0}, "tolerance", id="zero-tolerance"),
        pytest.param({"reward_dim": 2, "tolerance": float("nan")}, "tolerance", id="nan-tolerance"),
    ],
)
def test_bad_construction_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        OLS(**kwargs)
