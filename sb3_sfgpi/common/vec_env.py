"""Vectorised environments and monitors for vector rewards.

SB3's ``Monitor``, ``DummyVecEnv``, ``VecMonitor`` and ``VecNormalize(norm_reward=True)`` assume scalar
rewards. This module holds the multi-objective replacements and the checks that refuse the rest.
Environments follow the MO-Gymnasium convention: ``reward`` is an array of shape ``(d,)`` and the env
exposes ``reward_space``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecEnvWrapper, VecMonitor, VecNormalize


def env_reward_dim(env: gym.Env) -> int:
    """
    Number of objectives of a vector-reward Gymnasium env, read from its ``reward_space``.

    :param env: a Gymnasium env (possibly wrapped) following the MO-Gymnasium convention
    :return: ``d``, the length of the reward vector
    :raises ValueError: the env has no ``reward_space`` (a scalar-reward env) or it is not a 1-D Box
    """
    try:
        reward_space = env.get_wrapper_attr("reward_space")
    except AttributeError:
        reward_space = None
    return _reward_dim_of_space(reward_space, env)


def _reward_dim_of_space(reward_space: Any, env: Any) -> int:
    if reward_space is None:
        raise ValueError(
            f"{env} has scalar rewards (no `reward_space`): successor features need a vector-reward env "
            "following the MO-Gymnasium convention (reward of shape (d,) and a `reward_space` Box of shape (d,))"
        )
    if not isinstance(reward_space, spaces.Box) or len(reward_space.shape) != 1:
        raise ValueError(f"`reward_space` of {env} must be a 1-D gymnasium Box, got {reward_space}")
    return int(reward_space.shape[0])


class MOMonitor(gym.Wrapper):
    """
    Episode statistics for vector rewards.

    At the end of an episode ``info["episode"]`` holds ``r_vec`` (the undiscounted vector return),
    ``l`` (length) and ``t`` (seconds since the monitor was created), like SB3's ``Monitor``
    but without a scalar ``r``: SFDQN adds ``r = w · r_vec`` with the weights it is training for.

    :param env: a vector-reward Gymnasium env
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.reward_dim = env_reward_dim(env)
        self._start_time = time.time()
        self._return = np.zeros(self.reward_dim, dtype=np.float64)
        self._length = 0

    def reset(self, **kwargs) -> tuple[Any, dict[str, Any]]:
        self._return[:] = 0.0
        self._length = 0
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        reward = np.asarray(reward, dtype=np.float32)
        if reward.shape != (self.reward_dim,):
            raise ValueError(
                f"{self.env} declared a reward_space of dimension {self.reward_dim} but returned a reward of shape "
                f"{reward.shape}"
            )
        self._return += reward
        self._length += 1
        if terminated or truncated:
            info = dict(info)
            info["episode"] = {
                "r_vec": self._return.copy(),
                "l": self._length,
                "t": round(time.time() - self._start_time, 6),
            }
        return obs, reward, terminated, truncated, info


class MODummyVecEnv(DummyVecEnv):
    """
    :class:`~stable_baselines3.common.vec_env.DummyVecEnv` whose reward buffer has shape ``(n_envs, d)``.

    :param env_fns: functions returning vector-reward Gymnasium envs, all with the same ``reward_space``
    """

    vector_rewards = True

    def __init__(self, env_fns: list[Callable[[], gym.Env]]):
        super().__init__(env_fns)
        dims = {env_reward_dim(env) for env in self.envs}
        if len(dims) != 1:
            raise ValueError(f"all envs of a MODummyVecEnv must have the same reward dimension, got {sorted(dims)}")
        self.reward_dim = dims.pop()
        self.reward_space = self.envs[0].get_wrapper_attr("reward_space")
        self.buf_rews = np.zeros((self.num_envs, self.reward_dim), dtype=np.float32)


def vec_env_reward_dim(venv: VecEnv) -> int:
    """
    Check that a VecEnv passes vector rewards through unchanged and return their dimension.

    Accepted: VecEnvs that declare ``vector_rewards = True`` (:class:`MODummyVecEnv`, the per-agent views of
    :mod:`sb3_sfgpi.multiagent`) and SB3's ``SubprocVecEnv`` over vector-reward envs, wrapped in any VecEnv
    wrapper except ``VecMonitor`` and reward-normalising ``VecNormalize``.

    :param venv: the VecEnv to check
    :return: ``d``
    :raises ValueError: naming the wrapper or env that would break vector rewards
    """
    inner: VecEnv = venv
    while isinstance(inner, VecEnvWrapper):
        if isinstance(inner, VecMonitor):
            raise ValueError("VecMonitor sums scalar rewards; wrap each env in sb3_sfgpi's MOMonitor instead")
        if isinstance(inner, VecNormalize) and inner.norm_reward:
            raise ValueError(
                "VecNormalize(norm_reward=True) normalises scalar returns and breaks vector rewards: "
                "use norm_reward=False"
            )
        inner = inner.venv
    if isinstance(inner, DummyVecEnv) and not isinstance(inner, MODummyVecEnv):
        raise ValueError("DummyVecEnv stores scalar rewards; use sb3_sfgpi.common.vec_env.MODummyVecEnv")
    if not (getattr(inner, "vector_rewards", False) or isinstance(inner, SubprocVecEnv)):
        raise ValueError(f"unsupported VecEnv {type(inner).__name__}: use MODummyVecEnv or SubprocVecEnv")
    return _reward_dim_of_space(venv.get_attr("reward_space", indices=[0])[0], venv)


def wrap_mo_env(env: gym.Env | VecEnv) -> VecEnv:
    """
    Turn a vector-reward env into a VecEnv that keeps vector rewards (with episode statistics).

    :param env: a Gymnasium env following the MO-Gymnasium convention, or an already vectorised one
    :return: the VecEnv
    :raises ValueError: a scalar-reward env, or a VecEnv or wrapper that breaks vector rewards
    """
    if isinstance(env, VecEnv):
        vec_env_reward_dim(env)
        return env
    env_reward_dim(env)
    monitored = env if _is_wrapped_in(env, MOMonitor) else MOMonitor(env)
    return MODummyVecEnv([lambda: monitored])


def _is_wrapped_in(env: gym.Env, wrapper_class: type[gym.Wrapper]) -> bool:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, wrapper_class):
            return True
        env = env.env
    return False
