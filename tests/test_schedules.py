"""Weight schedules: OLS (MA-SFOLS), Random + GPI and fixed weights, their state round trip and their errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_sfgpi.schedules import FixedSchedule, OLSSchedule, RandomSchedule, WeightSchedule, make_schedule


def arc_values(angles, d: int = 2) -> np.ndarray:
    """Value vectors on a strictly concave arc (every one is in the CCS): ``(cos θ, sin θ)``, or on an octant."""
    angles = np.asarray(angles, dtype=np.float64)
    if d == 2:
        return np.c_[np.cos(angles), np.sin(angles)]
    # d == 3: points on the positive octant of the unit sphere, (polar, azimuth) pairs
    polar, azimuth = angles[:, 0], angles[:, 1]
    return np.c_[np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]


def run_to_the_end(schedule: WeightSchedule, values: np.ndarray, agents=("a",), seed: int = 0, cap: int = 200):
    """Feed the schedule the exact optimal value for every weight it hands out until it ends; the weights handed."""
    rng = np.random.default_rng(seed)
    handed = []
    for _ in range(cap):
        weights = schedule.next_weights(list(agents), rng)
        if weights is None:
            return handed
        for w in weights.values():
            handed.append(w)
            schedule.add(values[np.argmax(values @ w)], w)
    raise AssertionError(f"the schedule did not end within {cap} iterations")


def same_rows(a, b, tolerance=1e-9) -> bool:
    """Whether two collections of vectors hold the same vectors (in any order)."""
    a, b = np.array(sorted(map(tuple, a))), np.array(sorted(map(tuple, b)))
    return a.shape == b.shape and bool(np.allclose(a, b, atol=tolerance))


# --- OLSSchedule ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("d", [2, 3])
def test_ols_hands_out_the_simplex_extrema_first_one_per_agent(d):
    schedule = OLSSchedule()
    schedule.start(d)
    agents = [f"agent_{i}" for i in range(d)]
    weights = schedule.next_weights(agents, np.random.default_rng(0))
    assert list(weights) == agents
    for i, agent in enumerate(agents):
        np.testing.assert_array_equal(weights[agent], np.eye(d)[i])


def test_ols_gives_agents_beyond_the_queue_random_weights_inside_the_simplex():
    schedule = OLSSchedule()
    schedule.start(2)
    agents = ["a", "b", "c", "d"]
    weights = schedule.next_weights(agents, np.random.default_rng(1))
    np.testing.assert_array_equal(weights["a"], [1.0, 0.0])
    np.testing.assert_array_equal(weights["b"], [0.0, 1.0])
    for agent in ("c", "d"):
        assert weights[agent].sum() == pytest.approx(1.0)
        assert np.all(weights[agent] > 0) and np.all(weights[agent] < 1)
    assert not np.allclose(weights["c"], weights["d"])  # independent draws


def test_ols_ends_with_none_once_every_corner_weight_is_visited():
    values = arc_values([0.1, 0.4, 0.7, 1.0, 1.3])
    values = np.vstack([values, 0.9 * values])  # dominated values are never in the CCS
    schedule = OLSSchedule()
    schedule.start(2)
    handed = run_to_the_end(schedule, values)
    assert len(handed) > 2  # more than the extrema: the inner corners were visited too
    assert schedule.next_weights(["a"], np.random.default_rng(0)) is None  # and it stays ended
    assert schedule.ols.ended and schedule.ols.queue == []
    assert same_rows(schedule.ols.ccs, values[:5])
    visited = np.array(schedule.ols.weights)
    for corner in schedule.ols.corner_weights():
        assert np.min(np.abs(visited - corner).max(axis=1)) <= 1e-6, f"corner {corner} was never visited"


def test_ols_with_three_objectives_finds_the_ccs_and_ends():
    values = arc_values([(0.2, 0.3), (0.8, 0.4), (1.2, 1.0), (0.6, 1.3), (1.0, 0.8)], d=3)
    values = np.vstack([values, 0.8 * values, np.eye(3) * 0.5])
    schedule = OLSSchedule()
    schedule.start(3)
    run_to_the_end(schedule, values, agents=("a", "b"))
    assert schedule.next_weights(["a", "b"], np.random.default_rng(0)) is None
    assert same_rows(schedule.ols.ccs, values[:5])


@settings(max_examples=25, deadline=None)
@given(
    angles=st.lists(st.floats(0.0, np.pi / 2), min_size=1, max_size=7).filter(
        lambda xs: len(xs) < 2 or np.min(np.diff(np.sort(xs))) > 0.05
    ),
    n_agents=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
def test_ols_with_exact_values_ends_with_the_ccs(angles, n_agents, seed):
    ccs = arc_values(angles)
    values = np.vstack([ccs, 0.5 * ccs])
    schedule = OLSSchedule()
    schedule.start(2)
    run_to_the_end(schedule, values, agents=[f"agent_{i}" for i in range(n_agents)], seed=seed)
    assert same_rows(schedule.ols.ccs, ccs)


#: Three policies whose exact values, after the extrema, queue four corner weights (tests/test_ols.py)
THREE_POLICIES = np.array([[7.0, 3.0, 4.0], [9.0, 3.0, 2.0], [2.0, 8.0, 2.0]])


def test_top_batch_hands_a_round_the_corner_weights_of_highest_priority():
    """After the extrema (exact values of three policies), top-2 gives the two agents the two corners of highest
    priority, here neighbouring ones (tests/test_ols.py shows the priorities)."""
    schedule = OLSSchedule("top")
    schedule.start(3)
    rng = np.random.default_rng(0)
    for w in [*schedule.next_weights(["a", "b"], rng).values(), *schedule.next_weights(["a"], rng).values()]:
        schedule.add(THREE_POLICIES[np.argmax(THREE_POLICIES @ w)], w)  # the three extrema
    round_ = schedule.next_weights(["a", "b"], rng)
    np.testing.assert_allclose(round_["a"], [5 / 12, 7 / 12, 0])
    np.testing.assert_allclose(round_["b"], [5 / 17, 7 / 17, 5 / 17])


def test_ols_and_random_refuse_a_duplicate_value_into_the_set():
    for schedule in (OLSSchedule(), RandomSchedule()):
        schedule.start(2)
        assert schedule.add(np.array([1.0, 2.0]), np.array([1.0, 0.0])) is True
        assert schedule.add(np.array([1.0, 2.0]), np.array([0.0, 1.0])) is False
        assert schedule.add(np.array([1.0, 2.0 + 1e-8]), np.array([0.5, 0.5])) is False  # within the tolerance
        assert schedule.add(np.array([2.0, 1.0]), np.array([0.5, 0.5])) is True
        assert len(schedule.ols.values) == 2


# --- RandomSchedule ---------------------------------------------------------------------------------------------
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), d=st.integers(2, 5), n_agents=st.integers(1, 4))
def test_random_schedule_draws_dirichlet_weights_reproducibly(seed, d, n_agents):
    agents = [f"agent_{i}" for i in range(n_agents)]
    schedule = RandomSchedule()
    schedule.start(d)
    first = schedule.next_weights(agents, np.random.default_rng(seed))
    again = schedule.next_weights(agents, np.random.default_rng(seed))
    reference = np.random.default_rng(seed)
    for agent in agents:
        np.testing.assert_array_equal(first[agent], again[agent])
        np.testing.assert_array_equal(first[agent], reference.dirichlet(np.ones(d)))  # Dirichlet(1), agent order
        assert first[agent].shape == (d,) and first[agent].sum() == pytest.approx(1.0)
        assert np.all(first[agent] > 0)


def test_random_schedule_never_ends():
    values = arc_values([0.3, 1.2])
    schedule = RandomSchedule()
    schedule.start(2)
    rng = np.random.default_rng(0)
    drawn = []
    for _ in range(30):  # far beyond the point where OLS would have found this two-value CCS
        weights = schedule.next_weights(["a", "b"], rng)
        assert weights is not None
        for w in weights.values():
            drawn.append(tuple(w))
            schedule.add(values[np.argmax(values @ w)], w)
    assert same_rows(schedule.ols.ccs, values)
    assert len(set(drawn)) == len(drawn)  # fresh draws every time


# --- FixedSchedule ----------------------------------------------------------------------------------------------
def test_fixed_schedule_gives_every_agent_a_copy_of_its_weights():
    schedule = FixedSchedule([0.3, 0.7])
    schedule.start(2)
    rng = np.random.default_rng(0)
    weights = schedule.next_weights(["a", "b", "c"], rng)
    for w in weights.values():
        np.testing.assert_array_equal(w, [0.3, 0.7])
    weights["a"][0] = 99.0  # a caller changing its array changes neither the others nor the schedule
    np.testing.assert_array_equal(weights["b"], [0.3, 0.7])
    np.testing.assert_array_equal(schedule.next_weights(["a"], rng)["a"], [0.3, 0.7])
    np.testing.assert_array_equal(schedule.weights, [0.3, 0.7])


def test_fixed_schedule_never_ends_and_keeps_every_policy():
    schedule = FixedSchedule([0.3, 0.7])
    schedule.start(2)
    rng = np.random.default_rng(0)
    for _ in range(5):
        weights = schedule.next_weights(["a", "b"], rng)
        assert weights is not None
        for w in weights.values():
            assert schedule.add(np.array([1.0, 2.0]), w) is True  # the same value every time, kept anyway
    assert len(schedule.ols.values) == 1  # the OLS still records the distinct values only


def test_fixed_schedule_normalises_its_weights_at_start():
    schedule = FixedSchedule([2.0, 1.0])
    schedule.start(2)
    np.testing.assert_allclose(schedule.next_weights(["a"], np.random.default_rng(0))["a"], [2 / 3, 1 / 3])


@pytest.mark.parametrize(
    "weights, message",
    [([0.5, 0.5], "length 3"), ([0.2, 0.3, 0.4, 0.1], "length 3"), ([-1.0, 1.0, 1.0], "non-negative")],
)
def test_fixed_schedule_validates_its_weights_at_start(weights, message):
    schedule = FixedSchedule(weights)  # not known to be wrong before the number of objectives is
    with pytest.raises(ValueError, match=message) as error:
        schedule.start(3)
    assert "fixed weights" in str(error.value)


def test_same_after_extrema_hands_the_extrema_out_as_top_then_the_top_corner_weight_to_every_agent():
    policies = THREE_POLICIES
    rounds = {}
    for batch in ("top", "same-after-extrema"):
        schedule = OLSSchedule(batch)
        schedule.start(3)
        rng, rounds[batch] = np.random.default_rng(0), []
        for _ in range(3):
            weights = schedule.next_weights(["a", "b"], rng)
            rounds[batch].append(weights)
            for w in weights.values():
                schedule.add(policies[np.argmax(policies @ w)], w)
    top, mixed = rounds["top"], rounds["same-after-extrema"]
    for agent in ("a", "b"):  # the same first round (e1, e2) and the same second (e3 and top's first corner)
        for i in (0, 1):
            np.testing.assert_array_equal(mixed[i][agent], top[i][agent])
    np.testing.assert_array_equal(mixed[1]["a"], [0, 0, 1])
    np.testing.assert_allclose(mixed[1]["b"], [5 / 12, 7 / 12, 0])
    np.testing.assert_allclose(mixed[2]["a"], [5 / 17, 7 / 17, 5 / 17])  # no extremum left: one weight for both
    np.testing.assert_allclose(mixed[2]["b"], [5 / 17, 7 / 17, 5 / 17])
    assert mixed[2]["a"] is not mixed[2]["b"]  # each agent its own copy
    assert not np.allclose(top[2]["a"], top[2]["b"])


# --- state round trip -------------------------------------------------------------------------------------------
def make(kind: str) -> WeightSchedule:
    schedules = {
        "ols": OLSSchedule,
        "ols-same-after-extrema": lambda: OLSSchedule("same-after-extrema"),
        "random": RandomSchedule,
    }
    return FixedSchedule([0.3, 0.7]) if kind == "fixed" else schedules[kind]()


@pytest.mark.parametrize("kind", ["ols", "ols-same-after-extrema", "random", "fixed"])
def test_state_dict_through_json_restores_identical_behaviour(kind):
    values = arc_values([0.1, 0.5, 0.9, 1.3])
    original = make(kind)
    original.start(2)
    rng = np.random.default_rng(7)
    for _ in range(2):  # part of the run: the queue is not empty yet
        for w in original.next_weights(["a", "b"], rng).values():
            original.add(values[np.argmax(values @ w)], w)
    state = json.loads(json.dumps(original.state_dict(), allow_nan=False))
    assert state["kind"] == kind.partition("-")[0]

    restored = make(kind)
    restored.start(2)
    restored.load_state_dict(state)
    assert same_rows(restored.ols.ccs, original.ols.ccs)
    assert restored.ols.state_dict() == original.ols.state_dict()
    # The rest of the run is the same: same weights handed out, same values recorded, same end.
    for step in range(6):
        a = original.next_weights(["a", "b"], np.random.default_rng(step))
        b = restored.next_weights(["a", "b"], np.random.default_rng(step))
        assert (a is None) == (b is None)
        if a is None:
            break
        assert list(a) == list(b)
        for agent in a:
            np.testing.assert_array_equal(a[agent], b[agent])
            v = values[np.argmax(values @ a[agent])]
            assert original.add(v, a[agent]) == restored.add(v, b[agent])
    assert same_rows(restored.ols.ccs, original.ols.ccs)


@pytest.mark.parametrize("saved, loading", [("ols", "random"), ("random", "ols"), ("fixed", "ols"), ("ols", "fixed")])
def test_load_state_dict_refuses_another_kind(saved, loading):
    schedule = make(saved)
    schedule.start(2)
    target = make(loading)
    target.start(2)
    with pytest.raises(ValueError, match=f"{saved!r} schedule, not {loading!r}"):
        target.load_state_dict(schedule.state_dict())


def test_load_state_dict_refuses_a_fixed_schedule_with_other_weights():
    saved = FixedSchedule([0.3, 0.7])
    saved.start(2)
    other = FixedSchedule([0.5, 0.5])
    other.start(2)
    with pytest.raises(ValueError, match="weights"):
        other.load_state_dict(saved.state_dict())
    # ... but the same weights, written differently before normalisation, are the same setting.
    same = FixedSchedule([3.0, 7.0])
    same.start(2)
    same.load_state_dict(json.loads(json.dumps(saved.state_dict())))
    np.testing.assert_allclose(same.weights, [0.3, 0.7])


def test_load_state_dict_refuses_another_batch_or_none():
    saved = OLSSchedule("same-after-extrema")
    saved.start(3)
    top = OLSSchedule("top")
    top.start(3)
    with pytest.raises(ValueError, match="batch=same-after-extrema, not top"):
        top.load_state_dict(saved.state_dict())
    without = top.state_dict()
    del without["batch"]
    with pytest.raises(ValueError, match="batch=None, not top"):
        top.load_state_dict(without)


@pytest.mark.parametrize("state", [None, [], "ols", {"ols": {}}])
def test_load_state_dict_refuses_what_is_not_a_schedule_state(state):
    schedule = OLSSchedule()
    schedule.start(2)
    with pytest.raises(ValueError, match="schedule"):
        schedule.load_state_dict(state)


# --- make_schedule and misuse -----------------------------------------------------------------------------------
def test_make_schedule_builds_each_kind():
    assert type(make_schedule("ols")) is OLSSchedule
    assert type(make_schedule("random")) is RandomSchedule
    fixed = make_schedule(np.array([0.25, 0.75]), tolerance=1e-3)
    assert type(fixed) is FixedSchedule and fixed.tolerance == 1e-3
    np.testing.assert_array_equal(fixed.weights, [0.25, 0.75])
    assert make_schedule("ols", tolerance=1e-4).tolerance == 1e-4


def test_ols_batch_is_only_for_ols_weights():
    assert make_schedule("ols", ols_batch="same-after-extrema").batch == "same-after-extrema"
    for weights in ("random", [0.5, 0.5]):
        with pytest.raises(ValueError, match="ols_batch='same-after-extrema' is only for OLS weights"):
            make_schedule(weights, ols_batch="same-after-extrema")
    for removed in ("widest", "spread", "same"):  # spread and same were measured and removed
        with pytest.raises(ValueError, match="batch must be one of"):
            make_schedule("ols", ols_batch=removed)


@pytest.mark.parametrize("name", ["nonsense", "OLS", "fixed", ""])
def test_make_schedule_refuses_an_unknown_name(name):
    with pytest.raises(ValueError, match="'ols', 'random'"):
        make_schedule(name)


@pytest.mark.parametrize(
    "kind",
    ["ols", "random", "fixed"],
)
def test_a_schedule_must_be_started_first(kind):
    schedule = make(kind)
    with pytest.raises(ValueError, match="start"):
        schedule.next_weights(["a"], np.random.default_rng(0))
    with pytest.raises(ValueError, match="start"):
        schedule.add(np.array([1.0, 0.0]), np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="start"):
        schedule.state_dict()


def test_start_forgets_what_was_recorded():
    schedule = OLSSchedule()
    schedule.start(2)
    schedule.next_weights(["a", "b"], np.random.default_rng(0))
    schedule.add(np.array([1.0, 0.0]), np.array([1.0, 0.0]))
    schedule.start(2)
    assert schedule.ols.values == []
    weights = schedule.next_weights(["a", "b"], np.random.default_rng(0))
    np.testing.assert_array_equal(weights["a"], [1.0, 0.0])
