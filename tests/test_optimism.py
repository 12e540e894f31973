"""Optimistic initial values (SFDQN's ``optimistic_init``): directed exploration, and a settled table afterwards."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import FIG1_TABULAR_KWARGS
from gymnasium import spaces
from momdp import Fig1MOMDP
from parallel_chain import ParallelChainEnv

from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.sfdqn import SFDQN

LENGTH, GAMMA, FAR_PRIZE = 20, 0.95, 10.0
W = np.array([0.5, 0.5])


class Corridor(gym.Env):
    """
    ``LENGTH`` cells in a row, the agent starts in the first. Action 0 takes the near prize ``(1, 0)`` and ends the
    episode, in any cell; action 1 moves one cell right, and from the last cell takes the far prize
    ``(0, FAR_PRIZE)`` and ends. For ``W`` the optimum walks to the end: ``0.5 · 10 · 0.95^19 = 1.89`` against 0.5
    for quitting at once; a random walk reaches the end with probability ``2^-20`` per episode.
    """

    observation_space = spaces.Discrete(LENGTH)
    action_space = spaces.Discrete(2)
    reward_space = spaces.Box(0.0, FAR_PRIZE, (2,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.cell = 0
        return self.cell, {}

    def step(self, action):
        if action == 0:
            return self.cell, np.array([1.0, 0.0], np.float32), True, False, {}
        if self.cell == LENGTH - 1:
            return self.cell, np.array([0.0, FAR_PRIZE], np.float32), True, False, {}
        self.cell += 1
        return self.cell, np.zeros(2, np.float32), False, False, {}


def corridor_learner(optimistic_init: float) -> SFDQN:
    return SFDQN(
        "TabularPolicy", Corridor(), weights=W, learning_rate=0.5, gamma=GAMMA, batch_size=8, train_freq=1,
        learning_starts=0, exploration_fraction=0.5, exploration_initial_eps=1.0, exploration_final_eps=0.05,
        planning_sweeps=50, planning_interval=100, optimistic_init=optimistic_init, seed=0,
    )  # fmt: skip


def greedy_return(model: SFDQN) -> float:
    env, total, discount = Corridor(), 0.0, 1.0
    obs, _ = env.reset()
    for _ in range(LENGTH + 1):
        obs, reward, terminated, _, _ = env.step(int(model.predict(obs, deterministic=True)[0]))
        total += discount * float(W @ reward)
        discount *= GAMMA
        if terminated:
            break
    return total


def test_optimism_finds_the_far_prize_that_epsilon_greedy_misses():
    optimum = W[1] * FAR_PRIZE * GAMMA ** (LENGTH - 1)
    assert greedy_return(corridor_learner(optimistic_init=6.0).learn(2_000)) == pytest.approx(optimum, rel=1e-5)
    assert greedy_return(corridor_learner(optimistic_init=0.0).learn(2_000)) == pytest.approx(0.5)


def test_remove_optimism_leaves_untried_pairs_at_zero_and_the_tried_ones_at_the_planned_fixed_point():
    model = corridor_learner(optimistic_init=6.0)
    model.learn(30)  # too short to try every pair: some keep the optimistic 6 until the end of learn()
    table = model.policy.sf_net.table.dense().reshape(-1, 2).copy()
    obs, actions, *_ = model.replay_buffer.stored_arrays()
    tried = np.zeros(len(table), dtype=bool)
    tried[obs.astype(np.int64).ravel() * 2 + actions.ravel()] = True
    assert 0 < tried.sum() < len(table)
    assert np.all(table[~tried] == 0.0)
    np.testing.assert_array_equal(model.policy.sf_net_target.table.dense(), table.reshape(LENGTH, 4))

    fresh = corridor_learner(optimistic_init=0.0)  # a zero table planned to convergence on the same data
    fresh.policy.plan(model.replay_buffer, GAMMA, max_sweeps=10_000)
    np.testing.assert_allclose(table, fresh.policy.sf_net.table.dense().reshape(-1, 2), atol=1e-5)


def test_a_second_learn_goes_on_from_the_settled_table():
    model = corridor_learner(optimistic_init=6.0).learn(30)
    model.learn(30, reset_num_timesteps=False)
    table = model.policy.sf_net.table.dense()
    assert table.max() < 6.0  # no optimism comes back


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"optimistic_init": 2.0}, "optimistic_init needs planning"),
        ({"optimistic_init": float("nan"), "planning_sweeps": 5}, "optimistic_init must be a finite number"),
        ({"optimistic_init": "high", "planning_sweeps": 5}, "optimistic_init must be a finite number"),
    ],
)
def test_bad_optimism_options_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        SFDQN("TabularPolicy", Fig1MOMDP(), **{**FIG1_TABULAR_KWARGS, **overrides})


def test_optimism_survives_save_and_load(tmp_path):
    model = corridor_learner(optimistic_init=6.0).learn(50)
    model.save(tmp_path / "model.zip")
    loaded = SFDQN.load(tmp_path / "model.zip", env=Corridor())
    assert loaded.optimistic_init == 6.0
    np.testing.assert_array_equal(loaded.policy.sf_net.table.dense(), model.policy.sf_net.table.dense())


def chain_runner(**overrides) -> MultiAgentRunner:
    factory = default_learner_factory(
        policy="TabularPolicy", learning_rate=0.5, gamma=0.9, learning_starts=0, batch_size=4, train_freq=1,
        planning_sweeps=20, planning_interval=10, **overrides,
    )  # fmt: skip
    return MultiAgentRunner(ParallelChainEnv(2), factory, seed=0)


def test_the_multi_agent_runner_settles_every_learner_at_the_end_of_an_iteration():
    runner = chain_runner(optimistic_init=100.0)
    runner.start_iteration({agent: np.array([0.5, 0.5]) for agent in runner.agents}, iteration=0, total_timesteps=5)
    for _ in range(5):
        runner.step()
    runner.end_iteration()
    for learner in runner.learners.values():
        assert learner.policy.sf_net.table.dense().max() < 100.0
