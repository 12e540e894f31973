"""SB3's off-policy algorithm for multi-objective envs: vector rewards checked and logged, action masks obeyed."""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecEnv

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask, sample_allowed, stacked_masks
from sb3_sfgpi.common.checks import check_finite, env_name
from sb3_sfgpi.common.vec_env import wrap_mo_env


class MOOffPolicyAlgorithm(OffPolicyAlgorithm):
    """
    An SB3 off-policy algorithm whose env follows the MO-Gymnasium convention (a vector reward of shape ``(d,)``)
    and may give action masks (``info["action_mask"]``, as sb3-contrib's maskable algorithms read them).

    What it adds to SB3's loop: the env is wrapped in :class:`~sb3_sfgpi.common.vec_env.MOMonitor` and
    :class:`~sb3_sfgpi.common.vec_env.MODummyVecEnv`; a step's reward and observation are refused where they are not
    finite, before they are stored; the behaviour policy acts within the masks of its last observations (its
    ``predict`` takes ``action_masks``); the mean episode return of each objective is logged
    (``rollout/ep_rew_mean_<i>``). Its subclass says what the scalar return SB3 logs is.
    """

    #: the action masks of ``_last_obs`` (``info["action_mask"]``), shape ``(n_envs, n_actions)``; None: all actions
    _last_action_masks: np.ndarray | None = None

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        return wrap_mo_env(env)  # type: ignore[arg-type]

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        resets = reset_num_timesteps or self._last_obs is None  # when SB3's _setup_learn resets the env
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        if resets:  # the masks of the observations the reset gave
            self._last_action_masks = self._masks_of(getattr(self.env, "reset_infos", []))
        return result

    def _masks_of(self, infos: list[dict[str, Any]]) -> np.ndarray | None:
        """The action masks the envs' infos carry, shape ``(n_envs, n_actions)``, or None where none has one."""
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        return stacked_masks([info_mask(info, n_actions, f"env {i}") for i, info in enumerate(infos)], n_actions)

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """SB3's behaviour action (uniform before ``learning_starts``, then :meth:`predict`), within the last masks."""
        masks = self._last_action_masks
        if masks is None:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        if self.num_timesteps < learning_starts:
            actions = np.array([sample_allowed(self.action_space, mask) for mask in masks])
        else:
            actions, _ = self.predict(self._last_obs, deterministic=False, action_masks=masks)  # type: ignore[arg-type]
        return actions, actions

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        SB3's ``_store_transition`` without its deep copy of the observation on every step.

        The buffer copies what it stores; the next observations need a copy of their own only where a finished
        episode's terminal observation replaces the first observation of the next one.
        """
        self._check_transition(new_obs, reward)
        self._last_action_masks = self._next_masks(infos, dones)
        if self._vec_normalize_env is not None or not isinstance(new_obs, np.ndarray):
            super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
            return
        self._last_original_obs = self._last_obs
        next_obs = new_obs
        for i, done in enumerate(dones):
            if done and infos[i].get("terminal_observation") is not None:
                if next_obs is new_obs:
                    next_obs = new_obs.copy()
                next_obs[i] = infos[i]["terminal_observation"]
        replay_buffer.add(self._last_original_obs, next_obs, buffer_action, reward, dones, infos)  # type: ignore[arg-type]
        self._last_obs = new_obs  # type: ignore[assignment]

    def _next_masks(self, infos: list[dict[str, Any]], dones: np.ndarray) -> np.ndarray | None:
        """The masks of the observations the envs go on from: a step's, or the next episode's first where one ended."""
        if self._last_action_masks is None and not any(ACTION_MASK in info for info in infos):
            return None  # an env without masks: nothing read
        reset_infos = getattr(self.env, "reset_infos", [{}] * len(infos))
        return self._masks_of(
            [reset_infos[i] if done else info for i, (info, done) in enumerate(zip(infos, dones, strict=True))]
        )

    def _check_transition(self, new_obs: np.ndarray | dict[str, np.ndarray], reward: np.ndarray) -> None:
        """Refuse a non-finite reward or observation of a step before it is stored, naming env (agent) and step."""
        if np.isfinite(reward).all() and all(
            np.isfinite(part).all() or np.asarray(part).dtype.kind not in "fc"
            for part in (new_obs.values() if isinstance(new_obs, dict) else (new_obs,))
        ):
            return
        name = env_name(self.env.envs[0]) if hasattr(self.env, "envs") else env_name(self.env)
        for i in range(len(reward)):
            row = {key: part[i] for key, part in new_obs.items()} if isinstance(new_obs, dict) else new_obs[i]
            check_finite(reward[i], "reward", name, f"env {i}", self.num_timesteps)
            check_finite(row, "observation", name, f"env {i}", self.num_timesteps)

    def dump_logs(self) -> None:
        assert self.ep_info_buffer is not None
        vector_returns = [ep_info["r_vec"] for ep_info in self.ep_info_buffer if "r_vec" in ep_info]
        if vector_returns:
            for i, value in enumerate(np.mean(vector_returns, axis=0)):
                self.logger.record(f"rollout/ep_rew_mean_{i}", safe_mean([value]))
        super().dump_logs()
