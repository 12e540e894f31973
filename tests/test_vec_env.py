"""MODummyVecEnv, MOMonitor and wrap_mo_env: vector rewards through SB3's vectorised env and monitor."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from momdp import REWARDS, Fig1MOMDP, policy_value
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_sfgpi.common.vec_env import MODummyVecEnv, MOMonitor, wrap_mo_env


def test_mo_dummy_vec_env_steps_vector_rewards():
    venv = MODummyVecEnv([Fig1MOMDP, Fig1MOMDP, Fig1MOMDP])
    assert venv.reward_dim == 2
    obs = venv.reset()
    np.testing.assert_array_equal(obs.flatten(), [0, 0, 0])
    _, rewards, dones, _ = venv.step(np.array([0, 1, 2]))
    assert rewards.shape == (3, 2) and rewards.dtype == np.float32
    np.testing.assert_array_equal(rewards, REWARDS[0])
    assert not dones.any()
    # SB3's DummyVecEnv stores one float per env: vector rewards do not fit.
    with pytest.raises(ValueError):
        sb3_venv = DummyVecEnv([Fig1MOMDP, Fig1MOMDP])
        sb3_venv.reset()
        sb3_venv.step(np.array([0, 1]))


def test_mo_dummy_vec_env_observations_are_copies_that_later_steps_leave_alone():
    venv = MODummyVecEnv([Fig1MOMDP, Fig1MOMDP])
    first = venv.reset()
    second, *_ = venv.step(np.array([0, 1]))
    third, *_ = venv.step(np.array([0, 1]))
    assert first.flatten().tolist() == [0, 0] and second.flatten().tolist() == [1, 1]  # not overwritten by the buffer
    assert third.flatten().tolist() == [2, 2] and not np.shares_memory(third, venv.buf_obs[None])


def test_mo_dummy_vec_env_refuses_a_scalar_env():
    with pytest.raises(ValueError, match="scalar rewards"):
        MODummyVecEnv([lambda: gym.make("CartPole-v1")])


def test_mo_monitor_reports_the_vector_return():
    env = MOMonitor(Fig1MOMDP())
    actions = (1, 0, 2, 1)
    for _ in range(2):  # the second episode must not carry the first one's sums
        env.reset()
        for action in actions:
            _, _, terminated, truncated, info = env.step(action)
        assert terminated
        np.testing.assert_array_equal(info["episode"]["r_vec"], policy_value(actions))  # (21, 24)
        assert info["episode"]["l"] == 4
        assert "r" not in info["episode"]


def test_mo_monitor_refuses_a_reward_of_the_wrong_shape():
    class WrongShape(Fig1MOMDP):
        def step(self, action):
            obs, reward, terminated, truncated, info = super().step(action)
            return obs, np.append(reward, 0.0), terminated, truncated, info

    env = MOMonitor(WrongShape())
    env.reset()
    with pytest.raises(ValueError, match="shape"):
        env.step(0)


def test_wrap_mo_env_adds_a_single_monitor():
    venv = wrap_mo_env(MOMonitor(Fig1MOMDP()))
    assert isinstance(venv, MODummyVecEnv)
    env = venv.envs[0]
    assert isinstance(env, MOMonitor) and not isinstance(env.env, MOMonitor)
