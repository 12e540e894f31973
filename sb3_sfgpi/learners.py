"""The runner's learners: how one is made, and how a joint step's transitions reach it.

A learner of :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` is an SB3 off-policy algorithm that does not step its
own env: the runner steps the shared one. :func:`learner_step` hands it its agents' transitions as SB3's
``collect_rollouts`` would (counted, shown to its callback, stored, trained on when due, logged), so its callbacks,
logger and schedules work as in its own ``learn()``. This is the one place that drives SB3's per-step machinery
from outside.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_sfgpi.common.agent_views import Rows, Transitions, folderless_logger, remove_interrupted_logs, replaced
from sb3_sfgpi.common.rollouts import JointPolicy
from sb3_sfgpi.sfdqn import SFDQN

#: Builds the learner of an agent: ``(agent, per-agent VecEnv, weights, seed) -> SFDQN``.
LearnerFactory = Callable[[str, VecEnv, np.ndarray, int], SFDQN]


def default_learner_factory(**sfdqn_kwargs: Any) -> LearnerFactory:
    """
    A factory making ``SFDQN(policy, view, weights=..., seed=..., **kwargs)``.

    :param sfdqn_kwargs: SFDQN arguments (``policy`` defaults to ``"MlpPolicy"``)
    """
    kwargs = {"policy": "MlpPolicy", **sfdqn_kwargs}

    def make(agent: str, view: VecEnv, weights: np.ndarray, seed: int) -> SFDQN:
        return SFDQN(env=view, weights=weights, seed=seed, **kwargs)

    return make


def replay_sized(learner_kwargs: Mapping[str, Any], steps_per_iteration: int, slots: int) -> dict[str, Any]:
    """
    SFDQN arguments whose replay buffer holds what a learner of the runner stores in one iteration, no more.

    A learner stores at most one step of its slots per joint step (SB3's ``buffer_size`` counts rows: ``n_envs`` per
    step), and it lives one iteration: a buffer of ``steps_per_iteration + 1`` steps never fills, so it holds and
    samples exactly what a larger one would (the same random draws), without the larger one's memory (SB3 allocates
    all of it up front, and glibc may hand out reused, hence resident, memory).

    :param learner_kwargs: SFDQN arguments; a ``buffer_size`` below the cap is kept
    :param steps_per_iteration: joint steps of an iteration
    :param slots: the most slots (agents times env copies) a learner has
    :return: a new dict of arguments
    """
    cap = (steps_per_iteration + 1) * slots
    return {**learner_kwargs, "buffer_size": min(learner_kwargs.get("buffer_size", cap), cap)}


class EpisodeMonitor:
    """
    The vector return and length of each slot's episode so far, added to the info of the step that ends it (what
    :class:`~sb3_sfgpi.common.vec_env.MOMonitor` adds for a learner that steps its own env).
    """

    def __init__(self, reward_dim: int):
        self.reward_dim = reward_dim
        self._start_time = time.time()
        self._episodes: dict[tuple[int, str], list] = {}

    def clear(self) -> None:
        """Forget the episodes under way (the env was reset)."""
        self._episodes = {}

    def episode(self, copy: int, agent: str) -> tuple[np.ndarray, int]:
        """The vector return and length of an agent's episode so far (zero where it has just started)."""
        episode = self._entry((copy, agent))
        return episode[0], episode[1]

    def add_steps(self, copy: int, agent: str, episode_return: np.ndarray, steps: int) -> None:
        """Record ``steps`` more steps of an agent's episode, which brought its return to ``episode_return``."""
        episode = self._entry((copy, agent))
        episode[0], episode[1] = episode_return, episode[1] + steps

    def _entry(self, key: tuple[int, str]) -> list:
        """The ``[vector return, length]`` of the episode of ``key`` (``(copy, agent)``), started if there is none."""
        return self._episodes.setdefault(key, [np.zeros(self.reward_dim), 0])

    def info(self, key: tuple[int, str], step: Transitions) -> dict[str, Any]:
        """The info of ``key`` (``(copy, agent)``), with the episode's vector return where it ended."""
        info = step.infos[key]
        episode = self._entry(key)
        episode[0] = episode[0] + step.rewards[key]
        episode[1] += 1
        if step.terminations[key] or step.truncations[key]:
            info = dict(info)
            info["terminal_observation"] = step.obs[key]
            info["TimeLimit.truncated"] = step.truncations[key] and not step.terminations[key]
            info["episode"] = {"r_vec": episode[0], "l": episode[1], "t": round(time.time() - self._start_time, 6)}
            del self._episodes[key]
        return info


def stored_rows(
    learner: SFDQN, step: Transitions, monitor: EpisodeMonitor, next_masks: np.ndarray | None
) -> tuple[Rows, list[dict[str, Any]]]:
    """
    A learner's transitions of a joint step, as its replay buffer stores them, and their infos; its last observations
    move on to theirs.

    :param next_masks: the action masks of the next observations, one row per live slot, or None
    """
    # np.array of a list of equal arrays is np.stack of them, faster for the few agents of a step.
    next_obs = np.array([step.obs[agent] for agent in step.agents])
    rewards = np.array([step.rewards[agent] for agent in step.agents], dtype=np.float32)
    dones = np.array([step.terminations[agent] or step.truncations[agent] for agent in step.agents])
    infos = [monitor.info(agent, step) for agent in step.agents]
    timeouts = np.array([info.get("TimeLimit.truncated", False) for info in infos])
    last_obs = learner._last_obs
    learner._last_obs = next_obs if len(step.slots) == learner.n_envs else replaced(last_obs, step.slots, next_obs)  # type: ignore[arg-type, assignment]
    return Rows(last_obs[step.slots], next_obs, step.buffer_actions, rewards, dones, timeouts, next_masks), infos  # type: ignore[index]


def learner_step(
    learner: SFDQN, callback: BaseCallback, rows: Rows, infos: list[dict[str, Any]], log_interval: int
) -> bool:
    """
    Hand a learner its transitions of a joint step as SB3's ``collect_rollouts`` would: count them, call its callback,
    store them, and train when due.

    :param log_interval: the learner writes its logs every ``log_interval`` of its episodes
    :return: False where its callback asked to stop
    """
    learner.num_timesteps += len(infos)
    callback.update_locals({"new_obs": rows.next_obs, "rewards": rows.rewards, "dones": rows.dones, "infos": infos})
    keep_going = callback.on_step()
    learner._update_info_buffer(infos, rows.dones)
    learner.replay_buffer.add_rows(*rows)
    learner._update_current_progress_remaining(learner.num_timesteps, learner._total_timesteps)
    learner._on_step()
    episodes_before = learner._episode_num
    learner._episode_num += np.count_nonzero(rows.dones)
    if learner._episode_num // log_interval > episodes_before // log_interval:
        learner.dump_logs()  # SB3's log_interval: a point of the learning curve (at most one per joint step)
    if learner.num_timesteps > learner.learning_starts and learner._n_calls % learner.train_freq.frequency == 0:  # type: ignore[union-attr]
        callback.on_rollout_end()
        learner.train(gradient_steps=max(learner.gradient_steps, 1), batch_size=learner.batch_size)
        callback.on_rollout_start()
    return bool(keep_going)


def start_learning(
    learner: SFDQN, log_name: str, total_timesteps: int, callback: BaseCallback | None, tensorboard_log: str | None
) -> BaseCallback:
    """
    Start a learner's ``learn()`` of an iteration as SB3's own does (its schedules, logger and callback), without its
    loop: the runner's steps feed it.

    :param log_name: the name of its logs (TensorBoard's run: logs of an interrupted earlier attempt are removed)
    :param total_timesteps: joint steps of the iteration (each brings the learner ``n_envs`` transitions)
    :param callback: the learner's own callback, or None
    :param tensorboard_log: the folder of TensorBoard's logs, or None (then it logs nowhere but to stdout)
    :return: its callback, started
    """
    if tensorboard_log is not None:
        learner.tensorboard_log = tensorboard_log
        remove_interrupted_logs(tensorboard_log, log_name)
    else:  # SB3's own logger would make a folder in the temporary directory for every learner
        learner.set_logger(folderless_logger(learner.verbose))
    _, started = learner._setup_learn(
        total_timesteps * learner.n_envs,  # in transitions, as SB3 counts them
        callback,
        reset_num_timesteps=not learner.conditioned,  # a conditioned learner goes on counting across iterations
        tb_log_name=log_name,
    )
    started.on_training_start(locals(), globals())
    started.on_rollout_start()
    return started


def end_learning(learner: SFDQN, callback: BaseCallback) -> None:
    """
    End a learner's iteration: remove its optimism, end its callback, write its last logs and close the logger its
    iteration opened (TensorBoard's writer and its thread; a logger the user set is the user's to close). The
    callback's ``locals`` (SB3 hands callbacks the loop's ``locals()``, the callback itself among them) are cleared:
    that cycle would keep the learner and its replay buffer until the garbage collector's oldest generation runs.
    """
    learner.remove_optimism()
    callback.on_rollout_end()
    callback.on_training_end()
    callback.locals.clear()
    if learner._episode_num > 0:
        learner.dump_logs()
    if not learner._custom_logger:
        learner.logger.close()


def greedy_joint_policy(learners: Mapping[str, SFDQN], learner_of: Mapping[str, str] | None) -> JointPolicy:
    """
    The joint policy of learners acting greedily, each for the agents it acts for.

    :param learners: name -> learner
    :param learner_of: agent -> the name of its learner; None: every agent acts with the one learner of ``learners``
    """

    def act(observations: dict[str, Any], action_masks: Mapping[str, Any] | None = None) -> dict[str, int]:
        chosen: dict[str, int] = {}
        for name, learner in learners.items():
            names = [a for a in observations if learner_of is None or learner_of[a] == name]
            if names:
                batch = np.stack([observations[a] for a in names])
                masks = None if action_masks is None else np.stack([action_masks[a] for a in names])
                actions, _ = learner.predict(batch, deterministic=True, action_masks=masks)
                chosen.update(zip(names, actions.tolist(), strict=True))
        return {agent: chosen[agent] for agent in observations}

    return act
