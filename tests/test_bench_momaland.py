"""The MOMAland benchmark's env and score: item gathering with terminations and truncations in their places, the
team's EU summed over the agents, and the centralised peer's episodes scored by the same discounting."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("momaland")

from benchmarks import bench_momaland as bench  # noqa: E402


def test_the_env_truncates_at_its_time_limit_and_terminates_when_every_item_is_gathered():
    env = bench.make_env()
    env.reset(seed=0)
    for step in range(1, 51):  # standing still: nothing gathered, the time limit ends the episode
        _, rewards, terminations, truncations, _ = env.step({agent: 0 for agent in env.agents})
        assert not any(terminations.values())
        if step < 50:
            assert not any(truncations.values())
    assert all(truncations.values()) and sum(np.sum(r) for r in rewards.values()) == 0


def test_the_team_score_sums_the_agents_returns():
    test = [
        {"weights": [1.0, 0.0, 0.0], "agents": {"a": {"discounted": [1.0, 2.0, 0.0]}, "b": {"discounted": [3, 0, 0]}}},
        {"weights": [0.0, 0.5, 0.5], "agents": {"a": {"discounted": [0.0, 2.0, 2.0]}, "b": {"discounted": [0, 0, 4]}}},
    ]
    assert bench._team_expected_utility(test) == pytest.approx((4.0 + 4.0) / 2)


def test_a_centralised_episode_is_discounted_as_ours():
    parallel_wrappers = pytest.importorskip("momaland.utils.parallel_wrappers")
    env = parallel_wrappers.CentraliseAgent(bench.make_env(), action_mapping=True)
    assert np.array_equal(bench._centralised_return(env, lambda obs, w: 0, np.ones(3) / 3, seed=0), np.zeros(3))
    rng = np.random.default_rng(0)
    returns = bench._centralised_return(env, lambda obs, w: int(rng.integers(25)), np.ones(3) / 3, seed=1)
    rng, rewards, done = np.random.default_rng(0), [], False
    env.reset(seed=1)
    while not done:  # the same episode, its rewards discounted here step by step
        _, reward, terminated, truncated, _ = env.step(int(rng.integers(25)))
        rewards.append(reward)
        done = terminated or truncated
    assert (returns > 0).any() and (returns <= bench.ITEMS).all()  # items gathered, each counted once at most
    np.testing.assert_allclose(returns, sum(bench.GAMMA**t * np.asarray(r) for t, r in enumerate(rewards)))
