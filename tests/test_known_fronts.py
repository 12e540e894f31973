"""The exact references of the known-fronts benchmark: MO-Gymnasium's fronts of deep-sea-treasure and fruit-tree
against hand-played episodes and value iteration, and the exact optimum of resource-gathering (whose MO-Gymnasium
front is too low) against hand-computed paths and Monte-Carlo rollouts."""

from __future__ import annotations

import numpy as np
import pytest
from sfgpi_envs.resource_gathering_optimum import optimal_value, resource_gathering_mdp
from sfgpi_envs.tabular_optimum import TabularMDP, deep_sea_treasure_mdp, fruit_tree_mdp

from sb3_sfgpi.common.weights import random_weights

mo = pytest.importorskip("mo_gymnasium")

GAMMA = 0.99
UP, DOWN, LEFT, RIGHT = range(4)


def play(env, actions, gamma: float = GAMMA) -> np.ndarray:
    """The discounted vector return of playing ``actions`` from the reset; the episode must end with the last one."""
    env.reset(seed=0)
    total, discount = 0.0, 1.0
    for i, action in enumerate(actions):
        _, reward, terminated, truncated, _ = env.step(action)
        total, discount = total + discount * np.asarray(reward, dtype=np.float64), discount * gamma
        assert (terminated or truncated) == (i == len(actions) - 1), f"the episode ended at step {i + 1}"
    return total


def front_best(front: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    return (weights @ np.array(front).T).max(axis=1)


# --- deep-sea-treasure -----------------------------------------------------------------------------------------------
def test_deep_sea_treasure_front_is_discounted_as_the_env_plays():
    env = mo.make("deep-sea-treasure-v0")
    front = env.unwrapped.pareto_front(GAMMA)
    # 8.2 is reached in 3 steps: right, down, down; every step costs -1
    assert play(env, [RIGHT, DOWN, DOWN]) == pytest.approx([8.2 * GAMMA**2, -(1 + GAMMA + GAMMA**2)])
    assert np.allclose(front[1], play(env, [RIGHT, DOWN, DOWN]))
    assert np.allclose(front[0], play(env, [DOWN]))  # 0.7 in one step
    assert np.allclose(front[-1], play(env, [RIGHT] * 9 + [DOWN] * 10))  # 23.7 in 19 steps


def test_deep_sea_treasure_value_iteration_agrees_with_the_front():
    env = mo.make("deep-sea-treasure-v0")
    mdp = deep_sea_treasure_mdp(env, GAMMA)
    weights = random_weights(2, 50, rng=0)
    exact = np.array([mdp.value(w) for w in weights])
    assert exact == pytest.approx(front_best(env.unwrapped.pareto_front(GAMMA), weights), abs=1e-9)
    # the optimal policy's value vector is a point of the front, and its scalarisation is the value
    point = mdp.vector_value([0.5, 0.5])
    assert any(np.allclose(point, p) for p in env.unwrapped.pareto_front(GAMMA))
    assert float(np.dot([0.5, 0.5], point)) == pytest.approx(mdp.value([0.5, 0.5]))


# --- fruit-tree ------------------------------------------------------------------------------------------------------
def test_fruit_tree_depth_6_front_is_its_leaves_discounted_by_five_steps():
    env = mo.make("fruit-tree-v0", depth=6)
    assert env.unwrapped.reward_space.shape == (6,) and env.unwrapped.tree_depth == 6
    front = np.array(env.unwrapped.pareto_front(GAMMA))
    assert front.shape == (64, 6)
    # always right: the last leaf, reached on the 6th step
    assert play(env, [1] * 6) == pytest.approx(front[-1], rel=1e-6)
    weights = random_weights(6, 50, rng=0)
    mdp = fruit_tree_mdp(env, GAMMA)
    exact = np.array([mdp.value(w) for w in weights])
    assert exact == pytest.approx(front_best(list(front), weights), rel=1e-6)  # the env's rewards are float32


# --- resource-gathering ----------------------------------------------------------------------------------------------
#: Shortest paths around both enemies (E1 at (1, 2), E2 at (0, 3)) from home (4, 2), checked by playing them.
TO_GOLD = [UP, UP, LEFT, UP, UP, RIGHT]  # 6 steps to (0, 2)
GOLD_HOME = [LEFT, DOWN, DOWN, RIGHT, DOWN, DOWN]  # 6 steps back
TO_GEM = [UP, RIGHT, UP, RIGHT, UP]  # 5 steps to (1, 4)
GEM_HOME = [DOWN, LEFT, DOWN, LEFT, DOWN]
GOLD_TO_GEM = [LEFT, DOWN, DOWN, RIGHT, RIGHT, UP, RIGHT]  # 7 steps around both enemies


@pytest.fixture(scope="module")
def resource_gathering():
    env = mo.make("resource-gathering-v0")
    return env, resource_gathering_mdp(env, GAMMA)


def test_single_resource_values_are_the_shortest_safe_trips(resource_gathering):
    env, mdp = resource_gathering
    assert mdp.horizon == 100 and mdp.n_states == 100
    assert play(env, TO_GOLD + GOLD_HOME) == pytest.approx([0, GAMMA**11, 0])  # 12 steps
    assert play(env, TO_GEM + GEM_HOME) == pytest.approx([0, 0, GAMMA**9])  # 10 steps
    assert mdp.value([0, 1, 0]) == pytest.approx(GAMMA**11, abs=1e-12)
    assert mdp.value([0, 0, 1]) == pytest.approx(GAMMA**9, abs=1e-12)
    assert mdp.value([1, 0, 0]) == 0.0  # staying away from the enemies costs nothing
    assert optimal_value(env, [0, 0, 1], GAMMA) == pytest.approx(GAMMA**9, abs=1e-12)


def test_both_resources_by_safe_paths_is_optimal_for_equal_weights(resource_gathering):
    """The policy MO-Gymnasium's front misses: 18 safe steps home with both resources."""
    env, mdp = resource_gathering
    assert play(env, TO_GOLD + GOLD_TO_GEM + GEM_HOME) == pytest.approx([0, GAMMA**17, GAMMA**17])
    assert mdp.value([0, 0.5, 0.5]) == pytest.approx(GAMMA**17, abs=1e-12)
    assert mdp.vector_value([0, 0.5, 0.5]) == pytest.approx([0, GAMMA**17, GAMMA**17], abs=1e-12)
    assert all(not np.allclose(p, [0, GAMMA**17, GAMMA**17]) for p in env.unwrapped.pareto_front(GAMMA))


def test_the_exact_optimum_is_above_mo_gymnasiums_front(resource_gathering):
    env, mdp = resource_gathering
    weights = random_weights(3, 50, rng=0)
    exact = np.array([mdp.value(w) for w in weights])
    front = front_best(env.unwrapped.pareto_front(GAMMA), weights)
    assert np.all(exact >= front)
    assert np.max(exact / front) > 1.05  # the front understates the optimum by more than 5% somewhere
    assert exact.mean() > 1.05 * front.mean()  # and EU* by more than 5%


def test_monte_carlo_rollouts_of_the_optimal_policy_match_its_value():
    """With γ = 0.9 the optimal trip for equal weights risks an enemy, so the rollouts test the attack model."""
    gamma, w = 0.9, np.array([0.1, 0.45, 0.45])
    env = mo.make("resource-gathering-v0")
    mdp = resource_gathering_mdp(env, gamma)
    assert mdp.vector_value(w)[0] < 0  # the optimal policy may be killed
    actions, episodes = mdp.greedy_actions(w), 3_000
    returns = np.zeros((episodes, 3))
    env.reset(seed=1)
    for episode in range(episodes):
        observation, _ = env.reset()
        discount, done, t = 1.0, False, 0
        while not done:
            observation, reward, terminated, truncated, _ = env.step(actions[t, mdp.state_of(observation)])
            returns[episode] += discount * reward
            discount, done, t = discount * gamma, terminated or truncated, t + 1
    scalar = returns @ w
    tolerance = 4 * scalar.std() / np.sqrt(episodes)
    assert abs(scalar.mean() - mdp.value(w)) <= tolerance
    assert np.all(np.abs(returns.mean(axis=0) - mdp.vector_value(w)) <= 4 * returns.std(axis=0) / np.sqrt(episodes))


def test_policy_value_of_a_table_of_actions():
    """A two-state chain: the exact value of a stationary policy, and the checks of the model's inputs."""
    # state 0: action 0 ends with (1, 0); action 1 moves to state 1 with (0, 0); state 1: both actions end with (0, 2)
    next_state = np.array([[[2], [1]], [[2], [2]]])
    reward = np.array([[[[1.0, 0.0]], [[0.0, 0.0]]], [[[0.0, 2.0]], [[0.0, 2.0]]]])
    mdp = TabularMDP(next_state, np.ones((2, 2, 1)), reward, np.array([[0], [1]]), 0, horizon=5, gamma=0.5)
    assert mdp.policy_value(np.array([1, 0])) == pytest.approx([0.0, 1.0])
    assert mdp.policy_value(np.array([0, 0])) == pytest.approx([1.0, 0.0])
    assert mdp.value([0.2, 0.8]) == pytest.approx(0.8) and mdp.greedy_actions([0.2, 0.8])[0, 0] == 1
    assert mdp.state_of([1]) == 1
    short = TabularMDP(next_state, np.ones((2, 2, 1)), reward, np.array([[0], [1]]), 0, horizon=1, gamma=0.5)
    assert short.value([0.2, 0.8]) == pytest.approx(0.2)  # one step left: only the immediate reward counts
    with pytest.raises(ValueError, match="sum to 1"):
        TabularMDP(next_state, np.full((2, 2, 1), 0.5), reward, np.array([[0], [1]]), 0, 5, 0.5)
    with pytest.raises(ValueError, match="2 finite numbers"):
        mdp.value([1.0, 0.0, 0.0])


def test_expected_utility_of_tables_of_actions():
    """The exact EU of a policy asked for its actions in every state (how the benchmark scores GPI): EU* for the
    optimal actions, the first treasure's value for always going down."""
    mdp = deep_sea_treasure_mdp(mo.make("deep-sea-treasure-v0"), GAMMA)
    weights = random_weights(2, 10, rng=0)
    optimal = mdp.expected_utility(lambda observations, w: mdp.greedy_actions(w)[0], weights)
    assert optimal == pytest.approx(np.mean([mdp.value(w) for w in weights]), abs=1e-9)
    always_down = mdp.expected_utility(lambda observations, w: np.full(len(observations), DOWN), weights)
    assert always_down == pytest.approx(np.mean(weights @ [0.7, -1.0]))  # the first treasure, in one step
