"""Vectorised environments and monitors for vector rewards.

SB3's ``Monitor``, ``DummyVecEnv``, ``VecMonitor`` and ``VecNormalize(norm_reward=True)`` assume scalar
rewards. This module holds the multi-objective replacements and the checks that refuse the rest.
Environments follow the MO-Gymnasium convention: ``reward`` is an array of shape ``(d,)`` and the env
exposes ``reward_space``.
"""

from __future__ import annotations

import importlib
import time
import warnings
from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecEnvWrapper, VecMonitor, VecNormalize
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs
from stable_baselines3.common.vec_env.util import dict_to_obs

from sb3_sfgpi.common.reward_space import env_reward_dim, reward_dim_of_space


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

    def _obs_from_buf(self) -> VecEnvObs:
        # SB3 deep-copies the dict of observation buffers at every step: copying each array gives the same
        # observations without deepcopy's walk over the dict (docs: the performance page).
        return dict_to_obs(self.observation_space, {key: array.copy() for key, array in self.buf_obs.items()})


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
    return reward_dim_of_space(venv.get_attr("reward_space", indices=[0])[0], venv)


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


def make_mo_vec_env(
    env_id: str | Callable[..., gym.Env],
    n_envs: int = 1,
    seed: int | None = None,
    vec_env_cls: type[DummyVecEnv] | type[SubprocVecEnv] = MODummyVecEnv,
    env_kwargs: dict[str, Any] | None = None,
    wrapper_class: Callable[..., gym.Env] | None = None,
    wrapper_kwargs: dict[str, Any] | None = None,
    vec_env_kwargs: dict[str, Any] | None = None,
) -> VecEnv:
    """
    A vectorised, monitored vector-reward env: the counterpart of SB3's ``make_vec_env``, whose ``Monitor`` and
    ``DummyVecEnv`` break on vector rewards.

    Each env is made by ``env_id``, wrapped in :class:`MOMonitor` (then in ``wrapper_class``, if given) and seeded
    as SB3 seeds its envs: the action space of env ``i`` at once with ``seed + i``, the env itself with
    ``seed + i`` at its first reset.

    :param env_id: a registered env id (an MO-Gymnasium id such as ``"deep-sea-treasure-v0"`` imports
        MO-Gymnasium, which registers its envs, when the id is not registered yet), or a callable returning an env
    :param n_envs: number of envs
    :param seed: the first env's seed, ``None`` for random seeds
    :param vec_env_cls: :class:`MODummyVecEnv` (one process) or SB3's ``SubprocVecEnv`` (one process per env)
    :param env_kwargs: keyword arguments of ``gym.make`` or of the callable
    :param wrapper_class: a wrapper applied to each env after :class:`MOMonitor`
    :param wrapper_kwargs: its keyword arguments
    :param vec_env_kwargs: keyword arguments of ``vec_env_cls`` (e.g. ``start_method`` of ``SubprocVecEnv``)
    :return: the VecEnv, with vector rewards of shape ``(n_envs, d)``
    :raises ValueError: ``n_envs < 1``, an unknown id, a scalar-reward env, or a VecEnv class that breaks vectors
    :raises ImportError: an id that is not registered while MO-Gymnasium is not installed
    """
    if n_envs < 1:
        raise ValueError(f"n_envs must be at least 1, got {n_envs}")
    if isinstance(env_id, str):
        _register_env_id(env_id)  # here, to fail before any process starts

    def make_env(rank: int) -> Callable[[], gym.Env]:
        def make() -> gym.Env:
            env = _make_env(env_id, env_kwargs or {})
            if seed is not None:
                env.action_space.seed(seed + rank)
            env = MOMonitor(env)
            return env if wrapper_class is None else wrapper_class(env, **(wrapper_kwargs or {}))

        return make

    venv = vec_env_cls([make_env(rank) for rank in range(n_envs)], **(vec_env_kwargs or {}))
    try:
        vec_env_reward_dim(venv)
    except ValueError:
        venv.close()
        raise
    venv.seed(seed)
    return venv


def _make_env(env_id: str | Callable[..., gym.Env], env_kwargs: dict[str, Any]) -> gym.Env:
    if not isinstance(env_id, str):
        return env_id(**env_kwargs)
    _register_env_id(env_id)  # again: a fresh worker process of SubprocVecEnv has not imported MO-Gymnasium
    # Gymnasium's env checker wants scalar rewards (MO-Gymnasium's own ``make`` turns it off too).
    return gym.make(env_id, **{"disable_env_checker": True, **env_kwargs})


def import_registering_package(package: str) -> None:
    """Import ``package``, whose import registers env ids in Gymnasium's registry (MO-Gymnasium does).

    Hides the one warning of its import that is not the user's business: pygame, which MO-Gymnasium's envs import,
    warns that ``pkg_resources`` is deprecated under a recent setuptools; a CLI error must stay one line.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="pkg_resources is deprecated", category=UserWarning)
        importlib.import_module(package)


def _register_env_id(env_id: str) -> None:
    """Make sure Gymnasium knows ``env_id``, importing MO-Gymnasium (which registers its envs) if it does not."""
    try:
        gym.spec(env_id)
        return
    except gym.error.Error:
        pass
    try:
        import_registering_package("mo_gymnasium")
    except ImportError as error:
        raise ImportError(
            f"{env_id!r} is not a registered Gymnasium env id; if it is an MO-Gymnasium env, install mo-gymnasium"
        ) from error
    try:
        gym.spec(env_id)
    except gym.error.Error as error:
        raise ValueError(f"{env_id!r} is neither a Gymnasium nor an MO-Gymnasium env id: {error}") from None
