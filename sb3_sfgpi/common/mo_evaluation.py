"""Evaluation of a policy on a vector-reward env: SB3's ``evaluate_policy`` for vector returns.

SB3's ``evaluate_policy`` sums rewards into a float per episode, which fails on rewards of shape ``(d,)``.
:func:`mo_evaluate_policy` keeps the vector: it returns the mean and standard deviation of every objective, or every
episode's vector return, and leaves scalarising (``w · return``) to the caller, who knows the weights.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from sb3_sfgpi.common.vec_env import MOMonitor, vec_env_reward_dim, wrap_mo_env

#: Called after every step of every env still evaluating, with ``locals()`` and ``globals()``, as the ``callback`` of
#: SB3's ``evaluate_policy`` (``locals_["info"]`` and ``locals_["done"]`` are those of the env).
EvaluationCallback = Callable[[dict[str, Any], dict[str, Any]], None]


def mo_evaluate_policy(
    model: Any,
    env: gym.Env | VecEnv,
    n_eval_episodes: int = 10,
    deterministic: bool = True,
    gamma: float = 1.0,
    render: bool = False,
    callback: EvaluationCallback | None = None,
    return_episode_rewards: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """
    Run a policy for ``n_eval_episodes`` episodes and return its vector returns.

    As SB3's ``evaluate_policy``, the episodes are divided among the envs of a VecEnv beforehand, as evenly as
    possible (env ``i`` of ``n`` runs ``(n_eval_episodes + i) // n`` of them), so that the short episodes of a fast
    env do not outnumber the others; and where the envs are wrapped in :class:`~sb3_sfgpi.common.vec_env.MOMonitor`,
    an episode ends where the monitor says it does and its undiscounted return is the monitor's, which wrappers
    applied after it do not change.

    :param model: anything with SB3's ``predict(observation, state, episode_start, deterministic)``: an SFDQN
        (acting for its weights), a GPI set bound to a weight (:meth:`sb3_sfgpi.gpi.GPIPolicy.for_weights`), an SB3
        policy
    :param env: a vector-reward Gymnasium env (MO-Gymnasium convention), or a VecEnv of them that keeps vector
        rewards (:class:`~sb3_sfgpi.common.vec_env.MODummyVecEnv`, ``SubprocVecEnv``); a plain env is wrapped in a
        monitor and a ``MODummyVecEnv``, and is reset
    :param n_eval_episodes: number of episodes, in all envs together
    :param deterministic: whether the model acts deterministically
    :param gamma: discount of the returns: 1 for the plain sum of the rewards (what SB3 reports), below 1 for
        ``Σ_t γ^t r_t``, the discounted return the project's evaluation protocol averages
    :param render: render the env after every step
    :param callback: called after every step of every env still evaluating, as the ``callback`` of SB3's
        ``evaluate_policy`` (``EvalCallback`` uses it to read ``is_success``)
    :param return_episode_rewards: return every episode's vector return and length instead of their mean and std
    :return: the mean and the standard deviation of the vector return over the episodes, each of shape ``(d,)``;
        with ``return_episode_rewards``, the returns, shape ``(n_eval_episodes, d)``, and the episode lengths, shape
        ``(n_eval_episodes,)``, in the order the episodes ended
    :raises ValueError: ``n_eval_episodes < 1``, ``gamma`` outside ``(0, 1]``, a model without ``predict``, a
        scalar-reward env, or a VecEnv or wrapper that breaks vector rewards
    """
    _check_arguments(model, n_eval_episodes, gamma)
    venv = wrap_mo_env(env)
    episodes = _EpisodeRecorder(venv, int(n_eval_episodes), gamma)
    observations = venv.reset()
    states = None
    episode_starts = np.ones(venv.num_envs, dtype=bool)
    while not episodes.complete():
        actions, states = model.predict(
            observations, state=states, episode_start=episode_starts, deterministic=deterministic
        )
        observations, rewards, dones, infos = venv.step(actions)
        episodes.record(rewards, dones, infos, callback)
        episode_starts = dones.copy()
        if render:
            venv.render()
    returns, lengths = episodes.results()
    if return_episode_rewards:
        return returns, lengths
    return returns.mean(axis=0), returns.std(axis=0)


def _check_arguments(model: Any, n_eval_episodes: Any, gamma: float) -> None:
    """
    Refuse in one line a count of episodes or a discount out of range, or a model whose ``predict`` SB3's call would
    not fit (e.g. a GPI set not bound to a weight).
    """
    if isinstance(n_eval_episodes, bool) or not isinstance(n_eval_episodes, (int, np.integer)) or n_eval_episodes < 1:
        raise ValueError(f"n_eval_episodes must be an integer of at least 1, got {n_eval_episodes!r}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must be in (0, 1], got {gamma}")
    predict = getattr(model, "predict", None)
    if not callable(predict):
        raise ValueError(f"{type(model).__name__} has no predict(observation, state, episode_start, deterministic)")
    try:
        parameters = list(inspect.signature(predict).parameters.items())
    except (TypeError, ValueError):  # no signature to read (a builtin): let the call tell
        return
    required = [
        name
        for name, parameter in parameters[1:]
        if parameter.default is inspect.Parameter.empty
        and parameter.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    ]
    if required:
        raise ValueError(
            f"{type(model).__name__}.predict needs {', '.join(required)} besides the observation: bind it first "
            "(a GPIPolicy: gpi.for_weights(w))"
        )


class _EpisodeRecorder:
    """The returns of the episodes of a VecEnv, counted against each env's share of the episodes."""

    def __init__(self, venv: VecEnv, n_episodes: int, gamma: float):
        n_envs = venv.num_envs
        self.reward_dim = vec_env_reward_dim(venv)
        self.gamma = gamma
        self.monitored = bool(venv.env_is_wrapped(MOMonitor)[0])
        self.targets = np.array([(n_episodes + i) // n_envs for i in range(n_envs)])
        self.counts = np.zeros(n_envs, dtype=int)
        self.current = np.zeros((n_envs, self.reward_dim))
        self.discount = np.ones(n_envs)
        self.length = np.zeros(n_envs, dtype=int)
        self.returns: list[np.ndarray] = []
        self.lengths: list[int] = []

    def complete(self) -> bool:
        return bool((self.counts >= self.targets).all())

    def record(self, rewards: np.ndarray, dones: np.ndarray, infos: Any, callback: EvaluationCallback | None) -> None:
        rewards = np.asarray(rewards, dtype=np.float64)
        if rewards.shape != self.current.shape:
            raise ValueError(
                f"the env returned rewards of shape {rewards.shape}, expected {self.current.shape} (n_envs, d): "
                "a wrapper that scalarises rewards?"
            )
        self.current += self.discount[:, None] * rewards
        self.discount *= self.gamma
        self.length += 1
        for i in np.flatnonzero(self.counts < self.targets):
            info, done = infos[i], bool(dones[i])
            if callback is not None:
                callback(locals(), globals())
            if done:
                self._end_episode(int(i), info)

    def _end_episode(self, i: int, info: dict[str, Any]) -> None:
        episode = info.get("episode")
        if self.monitored and episode is None:
            return  # not the true end of the episode (e.g. the loss of a life): the return goes on
        if episode is not None and self.gamma == 1.0:
            self.returns.append(np.asarray(episode["r_vec"], dtype=np.float64))
            self.lengths.append(int(episode["l"]))
        else:
            self.returns.append(self.current[i].copy())
            self.lengths.append(int(self.length[i]))
        self.counts[i] += 1
        self.current[i], self.discount[i], self.length[i] = 0.0, 1.0, 0

    def results(self) -> tuple[np.ndarray, np.ndarray]:
        """The vector returns, shape ``(n_episodes, d)``, and the lengths of the episodes, in the order they ended."""
        return np.array(self.returns).reshape(-1, self.reward_dim), np.array(self.lengths, dtype=int)
