"""The number of objectives of a vector-reward env, read from its ``reward_space`` (MO-Gymnasium's convention).

Apart from :mod:`sb3_sfgpi.common.vec_env` so that what only wraps envs (the processes of
:mod:`~sb3_sfgpi.common.env_copies` among them) does not import Stable-Baselines3 and torch.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium import spaces


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
    return reward_dim_of_space(reward_space, env)


def reward_dim_of_space(reward_space: Any, env: Any) -> int:
    """
    ``d``, the length of a ``reward_space``.

    :param reward_space: the env's ``reward_space`` (None where it has none)
    :param env: the env, named in the error
    :raises ValueError: no reward space (a scalar-reward env), or one that is not a 1-D Box
    """
    if reward_space is None:
        raise ValueError(
            f"{env} has scalar rewards (no `reward_space`): successor features need a vector-reward env "
            "following the MO-Gymnasium convention (reward of shape (d,) and a `reward_space` Box of shape (d,))"
        )
    if not isinstance(reward_space, spaces.Box) or len(reward_space.shape) != 1:
        raise ValueError(f"`reward_space` of {env} must be a 1-D gymnasium Box, got {reward_space}")
    return int(reward_space.shape[0])
