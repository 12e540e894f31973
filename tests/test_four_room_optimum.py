"""The exact optimum of single-agent ``four-room-v0`` (``sfgpi_envs.four_room_optimum``).

Checked against the real MO-Gymnasium env (rollouts), against every other policy tried (other weights' optimal
policies, random policies), against brute-force value iteration over all states, against values derived by hand,
and through OLS: the CCS it finds with the exact oracle covers every weight.
"""

from __future__ import annotations

import gymnasium as gym
import mo_gymnasium
import numpy as np
import pytest
from four_room_reference import exact_ccs, value_iteration
from hypothesis import given, settings
from hypothesis import strategies as st
from mo_gymnasium.envs.four_room.four_room import MAZE as MO_MAZE
from sfgpi_envs.four_room_optimum import FourRoomOptimum

GAMMA = 0.95
EXTREMA = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
WEIGHTS = [*EXTREMA, (1 / 3, 1 / 3, 1 / 3), *np.random.default_rng(1).dirichlet(np.ones(3), size=4)]
START = 12 * 13 + 0  # the start cell (12, 0) as a flat index


@pytest.fixture(scope="module")
def optimum() -> FourRoomOptimum:
    return FourRoomOptimum(gamma=GAMMA)


def episode(env: gym.Env, act, seed: int = 0) -> tuple[np.ndarray, bool]:
    """The discounted vector return of one episode acting with ``act(observation)``, and whether it terminated."""
    observation, _ = env.reset(seed=seed)
    total, discount = np.zeros(3), 1.0
    while True:
        observation, reward, terminated, truncated, _ = env.step(act(observation))
        total += discount * np.asarray(reward, dtype=np.float64)
        discount *= GAMMA
        if terminated or truncated:
            return total, terminated


def test_from_env_reads_four_room_v0(optimum):
    env = mo_gymnasium.make("four-room-v0")
    from_env = FourRoomOptimum.from_env(env, gamma=GAMMA)
    assert from_env.max_steps == 200
    for w in WEIGHTS:
        assert from_env.value(w) == optimum.value(w)


@pytest.mark.parametrize("w", WEIGHTS, ids=lambda w: np.array2string(np.asarray(w), precision=2))
def test_greedy_policy_in_the_real_env_returns_the_vector_value(optimum, w):
    env = mo_gymnasium.make("four-room-v0")
    returned, terminated = episode(env, lambda observation: optimum.greedy_action(observation, w))
    assert terminated, "the optimal policy reaches the goal within the time limit"
    np.testing.assert_allclose(returned, optimum.vector_value(w), rtol=0, atol=1e-9)
    assert np.asarray(w) @ returned == pytest.approx(optimum.value(w), rel=0, abs=1e-12)


def test_no_other_policy_beats_the_optimum(optimum):
    values = np.array([optimum.value(w) for w in WEIGHTS])
    vectors = np.array([optimum.vector_value(w) for w in WEIGHTS])
    scalarised = np.array(WEIGHTS) @ vectors.T  # [i, j]: w_i · V^{π*(w_j)}
    assert np.all(scalarised <= values[:, None] + 1e-12)
    np.testing.assert_allclose(np.diag(scalarised), values, rtol=0, atol=1e-12)
    assert np.sum(scalarised < values[:, None] - 1e-3) >= len(WEIGHTS), "the weights' optimal policies differ"
    env, rng = mo_gymnasium.make("four-room-v0"), np.random.default_rng(0)
    for seed in range(10):
        returned, _ = episode(env, lambda _: int(rng.integers(4)), seed)
        assert np.all(np.array(WEIGHTS) @ returned <= values)


def test_brute_force_value_iteration_agrees_everywhere(optimum):
    w = np.array([0.2, 0.5, 0.3])
    q, values = value_iteration(MO_MAZE, w, GAMMA)
    assert values[START, 0] == pytest.approx(optimum.value(w), rel=0, abs=1e-12)
    rng, checked = np.random.default_rng(0), 0
    for mask in rng.integers(4096, size=60):
        flags = mask >> np.arange(12) & 1
        for cell in range(169):
            observation = [*divmod(cell, 13), *flags]
            try:
                action = optimum.greedy_action(observation, w)
            except ValueError:  # a wall, the goal or an object not collected: no such state
                continue
            assert q[action, cell, mask] == pytest.approx(values[cell, mask], rel=0, abs=1e-12)
            checked += 1
    assert checked > 60 * 100


def test_hand_derived_values(optimum):
    g = GAMMA
    # Green triangles only (w = e_1): from (12, 0) up 2, right 6 into the triangle at (10, 6) (8 steps); right 1,
    # up 3 to (7, 7) (12); down 2, left 4 through the door (9, 6), up 4 through the door (6, 3), left 3 to (5, 0)
    # (25); up 5, right 5 to (0, 5) (35, over the blue square at (0, 0) or not); to the blue square (2, 6) and on
    # through the door (3, 6) to the goal (0, 12) (46). The goal pays w · (1, 1, 1) = 1.
    assert optimum.value(EXTREMA[1]) == pytest.approx(g**7 + g**11 + g**24 + g**34 + g**45, rel=0, abs=1e-12)
    # A corridor: start at column 3; a green triangle 3 steps left; a blue square 3 steps right, next to the goal.
    corridor = FourRoomOptimum(["2.._..1G"], start=(0, 3), gamma=g)
    right, left = np.array([g**2, 0, 0]) + g**3, np.array([g**8, g**2, 0]) + g**9
    for w, best in [((1, 0, 0), right), ((0, 1, 0), left), ((0.5, 0.5, 0), left)]:
        np.testing.assert_allclose(corridor.vector_value(w), best, rtol=0, atol=1e-12)
        assert corridor.value(w) == pytest.approx(np.asarray(w) @ best, rel=0, abs=1e-12)
        assert corridor.value(w) > np.asarray(w) @ (right + left - best)  # strictly better than the other way
        assert corridor.greedy_action([0, 3, 0, 0], w) == (2 if best is right else 0)


def test_value_refuses_a_binding_time_limit():
    short = FourRoomOptimum(["2.._..1G"], start=(0, 3), gamma=GAMMA, max_steps=9)
    assert short.value((1, 0, 0)) == pytest.approx(GAMMA**2 + GAMMA**3)  # 4 steps: within the limit
    with pytest.raises(RuntimeError, match="10 > max_steps=9"):
        short.value((0, 1, 0))  # 10 steps


@pytest.fixture(scope="module")
def ccs(optimum) -> np.ndarray:
    values, iterations = exact_ccs(optimum)
    assert 1 < len(values) <= iterations
    return np.array(values)


@settings(max_examples=80, deadline=None, database=None)
@given(st.tuples(*[st.floats(0.0, 1.0)] * 3).filter(lambda w: sum(w) > 1e-3))
def test_exact_ccs_covers_every_weight(optimum, ccs, w):
    w = np.asarray(w) / sum(w)
    assert np.max(ccs @ w) == pytest.approx(optimum.value(w), rel=0, abs=1e-6)


def test_weights_are_normalised(optimum):
    assert optimum.value((2.0, 0.0, 0.0)) == optimum.value((1.0, 0.0, 0.0))
    np.testing.assert_array_equal(optimum.vector_value((1, 2, 3)), optimum.vector_value(np.array([1, 2, 3]) / 6))


@pytest.mark.parametrize(
    "w, match",
    [((1.0, 0.0), "length"), ((-0.1, 0.6, 0.5), "non-negative"), ((np.nan, 1.0, 0.0), "finite"), ((0, 0, 0), "zero")],
)
def test_bad_weights_are_refused(optimum, w, match):
    with pytest.raises(ValueError, match=match):
        optimum.value(w)


@pytest.mark.parametrize(
    "observation",
    [[6, 0] + [0] * 12, [0, 12] + [0] * 12, [0, 0] + [0] * 12, [13, 0] + [0] * 12, [12, 0] + [2] + [0] * 11, [12, 0]],
    ids=["wall", "goal", "object-not-taken", "outside", "flag-2", "short"],
)
def test_impossible_observations_are_refused(optimum, observation):
    with pytest.raises(ValueError):
        optimum.greedy_action(observation, (1, 0, 0))
