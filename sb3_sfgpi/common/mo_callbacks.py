"""SB3's ``EvalCallback`` for vector rewards.

SB3's ``EvalCallback`` evaluates with ``evaluate_policy``, which fails on rewards of shape ``(d,)``.
:class:`MOEvalCallback` evaluates with :func:`~sb3_sfgpi.common.mo_evaluation.mo_evaluate_policy` and ranks models
by the scalarised return ``w · (mean vector return)`` for the weights the model is trained for, while it logs and
saves every objective.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.vec_env import VecEnv, sync_envs_normalization

from sb3_sfgpi.common.mo_evaluation import mo_evaluate_policy
from sb3_sfgpi.common.vec_env import vec_env_reward_dim, wrap_mo_env
from sb3_sfgpi.common.weights import validate_weights


class MOEvalCallback(EvalCallback):
    """
    Evaluate the model every ``eval_freq`` calls on a vector-reward env, log and save the results, keep the best model.

    It logs ``eval/mean_reward`` (``w · mean vector return``), ``eval/mean_reward_<i>`` for every objective ``i``
    (named by index, as SFDQN's ``rollout/ep_rew_mean_<i>``), ``eval/mean_ep_length`` and, where the env reports
    ``is_success``, ``eval/success_rate``. ``evaluations.npz`` in ``log_path`` holds ``timesteps`` ``(n_evals,)``,
    ``results`` ``(n_evals, n_eval_episodes, d)`` (every episode's vector return), ``ep_lengths``
    ``(n_evals, n_eval_episodes)`` and ``weights`` ``(n_evals, d)`` (the weights of each evaluation).
    The best model is the one of the highest ``eval/mean_reward``; when the model's weights change between
    evaluations (an OLS iteration), so does the scale it is ranked on.

    As SB3's ``EvalCallback`` (of which it is a subclass), it counts calls, not env steps: with ``n_envs``
    training envs, evaluate every ``eval_freq * n_envs`` steps. ``StopTrainingOnRewardThreshold`` and the other
    callbacks SB3 runs on a new best model or after an evaluation work with it.

    :param eval_env: a vector-reward env (MO-Gymnasium convention) or a VecEnv that keeps vector rewards
    :param callback_on_new_best: callback to run when the model is the best so far
    :param callback_after_eval: callback to run after every evaluation
    :param n_eval_episodes: episodes per evaluation
    :param eval_freq: evaluate every ``eval_freq`` calls of the callback (0: never)
    :param log_path: folder of ``evaluations.npz``, rewritten after every evaluation (``None``: no file)
    :param best_model_save_path: folder of ``best_model.zip`` (``None``: not saved)
    :param deterministic: evaluate the deterministic policy
    :param render: render the env during evaluations
    :param verbose: 0: silent, 1: print every evaluation, with the objectives' names where the env has
        ``objective_names``
    :param weights: the preference weights that scalarise the returns; ``None``: the model's (``model.weights``,
        as SFDQN's) at every evaluation
    :param gamma: discount of the evaluated returns (1: the plain sum of rewards, as SB3's ``EvalCallback``)
    :raises ValueError: a scalar-reward env, ``n_eval_episodes < 1``, bad weights
    """

    def __init__(
        self,
        eval_env: gym.Env | VecEnv,
        callback_on_new_best: BaseCallback | None = None,
        callback_after_eval: BaseCallback | None = None,
        n_eval_episodes: int = 5,
        eval_freq: int = 10_000,
        log_path: str | None = None,
        best_model_save_path: str | None = None,
        deterministic: bool = True,
        render: bool = False,
        verbose: int = 1,
        weights: np.ndarray | Sequence[float] | None = None,
        gamma: float = 1.0,
    ):
        if n_eval_episodes < 1:
            raise ValueError(f"n_eval_episodes must be at least 1, got {n_eval_episodes}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        venv = wrap_mo_env(eval_env)
        super().__init__(
            venv,
            callback_on_new_best=callback_on_new_best,
            callback_after_eval=callback_after_eval,
            n_eval_episodes=n_eval_episodes,
            eval_freq=eval_freq,
            log_path=log_path,
            best_model_save_path=best_model_save_path,
            deterministic=deterministic,
            render=render,
            verbose=verbose,
            warn=False,
        )
        self.reward_dim = vec_env_reward_dim(venv)
        self.fixed_weights = None if weights is None else validate_weights(weights, self.reward_dim)
        self.gamma = gamma
        self.last_mean_return = np.full(self.reward_dim, np.nan)
        self.evaluations_weights: list[np.ndarray] = []

    def _init_callback(self) -> None:
        super()._init_callback()
        if self.fixed_weights is None and not hasattr(self.model, "weights"):
            raise ValueError(f"{type(self.model).__name__} has no `weights`: pass MOEvalCallback(weights=...)")

    def current_weights(self) -> np.ndarray:
        """The weights that scalarise the returns now: the fixed ones, else the model's."""
        if self.fixed_weights is not None:
            return self.fixed_weights
        return validate_weights(self.model.weights, self.reward_dim)  # type: ignore[attr-defined]

    def _on_step(self) -> bool:
        if self.eval_freq <= 0 or self.n_calls % self.eval_freq != 0:
            return True
        if self.model.get_vec_normalize_env() is not None:
            sync_envs_normalization(self.training_env, self.eval_env)
        self._is_success_buffer = []
        returns, lengths = mo_evaluate_policy(
            self.model,
            self.eval_env,
            n_eval_episodes=self.n_eval_episodes,
            deterministic=self.deterministic,
            gamma=self.gamma,
            render=self.render,
            callback=self._log_success_callback,
            return_episode_rewards=True,
        )
        weights = self.current_weights()
        self.last_mean_return = returns.mean(axis=0)
        self.last_mean_reward = float(weights @ self.last_mean_return)
        if self.log_path is not None:
            self._save_evaluations(returns, lengths, weights)
        self._log_evaluation(returns, lengths, weights)
        return self._after_evaluation()

    def _save_evaluations(self, returns: np.ndarray, lengths: np.ndarray, weights: np.ndarray) -> None:
        assert self.log_path is not None
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_results.append(returns)  # type: ignore[arg-type]
        self.evaluations_length.append(lengths)  # type: ignore[arg-type]
        self.evaluations_weights.append(weights)
        extra: dict[str, Any] = {}
        if self._is_success_buffer:
            self.evaluations_successes.append(self._is_success_buffer)
            extra["successes"] = self.evaluations_successes
        np.savez(
            self.log_path,
            timesteps=np.array(self.evaluations_timesteps),
            results=np.array(self.evaluations_results),
            ep_lengths=np.array(self.evaluations_length),
            weights=np.array(self.evaluations_weights),
            **extra,
        )

    def _log_evaluation(self, returns: np.ndarray, lengths: np.ndarray, weights: np.ndarray) -> None:
        if self.verbose >= 1:
            names = self._objective_names()
            scalarised = returns @ weights
            print(
                f"Eval num_timesteps={self.num_timesteps}, episode_reward={scalarised.mean():.2f} "
                f"+/- {scalarised.std():.2f} (w = {np.round(weights, 3).tolist()})"
            )
            means = returns.mean(axis=0)
            print("Episode return: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, means, strict=True)))
            print(f"Episode length: {lengths.mean():.2f} +/- {lengths.std():.2f}")
        self.logger.record("eval/mean_reward", self.last_mean_reward)
        for i, value in enumerate(self.last_mean_return):
            self.logger.record(f"eval/mean_reward_{i}", float(value))
        self.logger.record("eval/mean_ep_length", float(lengths.mean()))
        if self._is_success_buffer:
            self.logger.record("eval/success_rate", float(np.mean(self._is_success_buffer)))
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)

    def _objective_names(self) -> list[str]:
        """The env's ``objective_names`` where it has them, else ``objective <i>``."""
        if self.eval_env.has_attr("objective_names"):
            names = list(self.eval_env.get_attr("objective_names", indices=[0])[0])
            if len(names) == self.reward_dim:
                return [str(name) for name in names]
        return [f"objective {i}" for i in range(self.reward_dim)]

    def _after_evaluation(self) -> bool:
        """Keep a new best model and run the callbacks of a new best and of every evaluation."""
        continue_training = True
        if self.last_mean_reward > self.best_mean_reward:
            if self.verbose >= 1:
                print("New best mean reward!")
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
            self.best_mean_reward = self.last_mean_reward
            if self.callback_on_new_best is not None:
                continue_training = self.callback_on_new_best.on_step()
        if self.callback is not None:
            continue_training = continue_training and self._on_event()
        return continue_training
