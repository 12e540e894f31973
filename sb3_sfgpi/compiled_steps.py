"""The runner's joint steps in compiled batches, where its learners are tables and its env offers a packed step.

:class:`CompiledSteps` hands :func:`~sb3_sfgpi.tabular.joint_steps.joint_steps_kernel` the env's packed state and
each learner's arrays (table, replay buffer, counters, the schedules' values for every step of the iteration, its
generators), and afterwards gives the learners back what SB3's per-step machinery would have left them: counters,
exploration rate, learning rate, the logger's last records, the episode's return so far, the generators' states. The
steps Python must take itself (one that ends an episode, one where a learner plans) are the runner's own
:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.step`, with the actions the kernel chose. Tables, buffers and every
random draw end as the step-by-step path leaves them (``tests/test_compiled_steps.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback
from stable_baselines3.common.type_aliases import TrainFrequencyUnit

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy

if TYPE_CHECKING:
    from sb3_sfgpi.learners import EpisodeMonitor
    from sb3_sfgpi.tabular.joint_steps import LearnerArrays

#: The pending step of a runner: each copy's actions, and each learner's sampled slots and buffer actions.
PendingStep = tuple[list[dict[str, int]], dict[str, tuple[list[int], np.ndarray]]]


def compiled_steps(
    env: Any,
    learners: dict[str, SFDQN],
    callbacks: dict[str, BaseCallback],
    monitor: EpisodeMonitor,
    runner_callback: BaseCallback,
    steps: int,
) -> CompiledSteps | None:
    """
    Compiled batches of a runner's next ``steps`` joint steps where they give what its steps give, else None: the env's
    own class offers a packed step (``packed_dynamics``), each agent's learner a table of its own with one update per
    training step and no separate target table, no callbacks of the learners, and runner-level callbacks that take
    their steps in batches (``takes_steps_in_batches``). The runner checks the rest (one env copy, no action masks).

    :param env: the runner's env (one copy)
    :param learners: agent -> its learner; ``callbacks``: agent -> the learner's callback
    :param monitor: the runner's episode returns so far
    :param runner_callback: the runner-level callback(s) of the call
    """  # fmt: skip
    env_class = type(env)
    if getattr(env_class, "packed_dynamics", None) is None or not hasattr(env_class, "restore_packed_state"):
        return None
    shown = runner_callback.callbacks if isinstance(runner_callback, CallbackList) else [runner_callback]
    if not all(getattr(type(c), "takes_steps_in_batches", False) for c in shown):
        return None
    if not all(_plain_table_learner(learners[agent], callbacks[agent]) for agent in learners):
        return None
    if len({id(learner.action_space.np_random) for learner in learners.values()}) < len(learners):
        return None  # agents exploring from one generator: the kernel draws from a copy per learner
    from sb3_sfgpi.tabular.joint_steps import PACKED_STEP_SIGNATURE
    from sb3_sfgpi.tabular.numpy_random import global_stream

    step = env.packed_dynamics().step
    if global_stream() is None or PACKED_STEP_SIGNATURE not in getattr(step, "nopython_signatures", ()):
        return None
    return CompiledSteps(env, learners, callbacks, monitor, steps)


def _plain_table_learner(learner: SFDQN, callback: BaseCallback) -> bool:
    """Whether a learner's step is what the kernel does: SFDQN with a table, as built, one update per step."""
    buffer = learner.replay_buffer
    action_space = learner.action_space
    return (
        type(learner) is SFDQN
        and type(learner.policy) is TabularPolicy
        and not learner.policy.target_network
        and learner.gradient_steps <= 1
        and learner.train_freq.unit == TrainFrequencyUnit.STEP  # type: ignore[union-attr]
        and learner._vec_normalize_env is None
        and type(callback) is ConvertCallback
        and callback.callback is None
        and type(buffer) is MOReplayBuffer
        and buffer.n_envs == 1
        and not buffer.optimize_memory_usage
        and buffer.handle_timeout_termination
        and buffer.next_forbidden is None
        and buffer.observations.dtype.kind in "iu"  # integers the kernel stores (the buffer picks their width)
        and buffer.actions.dtype == np.int64
        and isinstance(action_space, spaces.Discrete)
        and action_space.start == 0
        and isinstance(action_space.np_random.bit_generator, np.random.PCG64)
    )


class CompiledSteps:
    """
    A runner's joint steps of one ``learn()`` call, run in compiled batches (see :func:`compiled_steps`): the env's
    packed state and the learners' arrays go in, the learners get back what SB3's per-step machinery would have left
    them.

    :param env: the env, its episode under way
    :param learners: agent -> its learner, its iteration started; ``callbacks``: agent -> its learner's callback
    :param monitor: the runner's episode returns so far
    :param steps: the joint steps of the call (how far the learners' schedules are read ahead)
    """

    def __init__(
        self,
        env: Any,
        learners: dict[str, SFDQN],
        callbacks: dict[str, BaseCallback],
        monitor: EpisodeMonitor,
        steps: int,
    ):
        self.env, self.learners, self.callbacks, self.monitor = env, learners, callbacks, monitor
        self.agents = list(learners)
        self._schedules = {agent: _schedule_values(learner, steps) for agent, learner in learners.items()}
        obs_size = int(np.prod(env.observation_space(self.agents[0]).shape))
        reward_dim = self.learners[self.agents[0]].reward_dim
        self._actions = np.zeros(len(self.agents), dtype=np.int64)
        self._observations = np.zeros((len(self.agents), obs_size), dtype=np.int64)
        self._rewards = np.zeros((len(self.agents), reward_dim), dtype=np.float32)
        #: the step :meth:`run` chose the actions of and Python must take (None: the learners choose theirs)
        self.pending: PendingStep | None = None
        self._kernel: Any = None  # typed once: numba's typing of the learners' arrays costs more than a call

    def run(self, max_steps: int, live_agents: set[str]) -> int:
        """
        Up to ``max_steps`` joint steps of the agents in ``live_agents``, stopping before one that Python must take
        (:attr:`pending` then holds its actions where it ends an episode).

        :return: the joint steps done
        :raises ValueError: a TD update diverged (as :meth:`~sb3_sfgpi.sfdqn.tabular_policy.TabularPolicy.td_update`)
        """
        from sb3_sfgpi.tabular.joint_steps import EPISODE_ENDS, TABLE_FULL, UPDATE_DIVERGED, joint_steps_kernel
        from sb3_sfgpi.tabular.numpy_random import global_stream

        live, total = np.array([agent in live_agents for agent in self.agents]), 0
        self.pending = None
        while True:
            dynamics = self.env.packed_dynamics()
            arrays = tuple(self._learner_arrays(agent) for agent in self.agents)
            stream = global_stream()
            if self._kernel is None:
                self._kernel = joint_steps_kernel(arrays, stream, self._observations)  # type: ignore[arg-type]
            stop, done = self._kernel(
                dynamics.step, dynamics.model, dynamics.constants, dynamics.state, live, arrays, *stream,
                max_steps - total, self._actions, self._observations, self._rewards,
            )  # fmt: skip
            if stop == UPDATE_DIVERGED:  # ``done`` is the learner's index
                raise _diverged(self.learners[self.agents[done]], arrays[done])
            total += done
            self.env.restore_packed_state(dynamics.state)
            for agent, is_live, learner_arrays in zip(self.agents, live, arrays, strict=True):
                self._give_back(agent, learner_arrays, done if is_live else 0)
            if stop != TABLE_FULL:
                break
            for agent, learner_arrays in zip(self.agents, arrays, strict=True):
                self.learners[agent].policy.sf_net.table.reserve(learner_arrays.scratch.shape[1])
        if stop == EPISODE_ENDS:
            self.pending = self._chosen(live)
        return total

    def _learner_arrays(self, agent: str) -> LearnerArrays:
        """The arrays of the agent's learner, as the kernel reads them."""
        from sb3_sfgpi.tabular.joint_steps import LearnerArrays
        from sb3_sfgpi.tabular.numpy_random import pcg64_words

        learner = self.learners[agent]
        net, buffer = learner.policy.sf_net, learner.replay_buffer
        psi, slot_map = net.table_storage()
        low, end, strides, first_row = net.geometry
        base, epsilons, learning_rates = self._schedules[agent]
        episode_return, _ = self.monitor.episode(0, agent)
        planning_interval = learner.planning_interval if learner.planning_sweeps else 0
        counters = [
            learner.num_timesteps,
            learner._n_calls,
            learner._n_updates,
            buffer.pos,
            buffer.full,
            len(net.table),
        ]
        settings = [base, first_row, buffer.buffer_size, learner.batch_size, learner.learning_starts]
        settings += [learner.train_freq.frequency, planning_interval, learner._plannings, learner.action_space.n]  # type: ignore[union-attr, attr-defined]
        return LearnerArrays(
            psi, slot_map, net.table.slot_rows(), tuple(buffer.flat_storage()), low, end, strides,
            learner.policy.weights_array(), epsilons, learning_rates,
            pcg64_words(learner.action_space.np_random), learner._last_obs.reshape(-1).copy(),  # type: ignore[union-attr, arg-type]
            episode_return.copy(), np.zeros((learner.batch_size, learner.reward_dim), dtype=np.float32),
            np.zeros((3, learner.batch_size), dtype=np.int64), np.array([*counters, -1], dtype=np.int64),
            np.array(settings, dtype=np.int64), np.array([learner.exploration_rate, learner.gamma]),
        )  # fmt: skip

    def _give_back(self, agent: str, arrays: LearnerArrays, steps: int) -> None:
        """What ``steps`` steps of SB3's machinery leave a learner, from the kernel's arrays."""
        from sb3_sfgpi.tabular.joint_steps import (
            EXPLORATION_RATE,
            FULL,
            LAST_TRAIN,
            N_CALLS,
            N_UPDATES,
            NUM_TIMESTEPS,
            POS,
            STORED,
        )
        from sb3_sfgpi.tabular.numpy_random import set_pcg64_words

        learner, counters = self.learners[agent], arrays.counters
        set_pcg64_words(learner.action_space.np_random, arrays.generator)
        learner.policy.sf_net.table.adopt_stored(int(counters[STORED]))
        if not steps:
            return
        learner.num_timesteps, learner._n_calls = int(counters[NUM_TIMESTEPS]), int(counters[N_CALLS])
        learner.replay_buffer.pos, learner.replay_buffer.full = int(counters[POS]), bool(counters[FULL])
        learner._last_obs = arrays.last_obs.reshape(1, -1)  # type: ignore[assignment]
        learner.exploration_rate = float(arrays.rates[EXPLORATION_RATE])
        self.monitor.add_steps(0, agent, arrays.episode_return, steps)
        callback = self.callbacks[agent]
        callback.n_calls += steps
        callback.num_timesteps = learner.num_timesteps
        if counters[LAST_TRAIN] >= 0:  # the records of its last update, made at that step's progress
            learner._update_current_progress_remaining(int(counters[LAST_TRAIN]), learner._total_timesteps)
            learner.policy.set_training_mode(True)
            learner._update_learning_rate(learner.policy.optimizer)
            learner._n_updates = int(counters[N_UPDATES])
            learner.logger.record("train/n_updates", learner._n_updates, exclude="tensorboard")
            learner.logger.record("train/loss", float(0.5 * np.square(arrays.td_error).sum()))
        learner._update_current_progress_remaining(learner.num_timesteps, learner._total_timesteps)
        learner.logger.record("rollout/exploration_rate", learner.exploration_rate)

    def _chosen(self, live: np.ndarray) -> PendingStep:
        """The step the kernel chose the actions of, in the runner's terms (one copy, one slot per learner)."""
        actions = {
            agent: int(action)
            for agent, action, is_live in zip(self.agents, self._actions, live, strict=True)
            if is_live
        }
        return [actions], {agent: ([0], np.array([action], dtype=np.int64)) for agent, action in actions.items()}


def _schedule_values(learner: SFDQN, steps: int) -> tuple[int, np.ndarray, np.ndarray]:
    """
    The exploration rate after, and the learning rate of an update at, each of the learner's next ``steps`` steps, from
    its own schedules at the progress SB3 computes: ``(first num_timesteps, exploration rates, learning rates)``.
    """
    base = learner.num_timesteps
    epsilons, learning_rates = np.empty(steps + 1), np.empty(steps + 1)
    for k in range(steps + 1):
        progress = 1.0 - float(base + k) / float(learner._total_timesteps)  # SB3's _update_current_progress_remaining
        epsilons[k] = learner.exploration_rate_at(base + k, progress)
        learning_rates[k] = learner.lr_schedule(progress)
    return base, epsilons, learning_rates


def _diverged(learner: SFDQN, arrays: LearnerArrays) -> ValueError:
    """The error of a learner whose compiled update diverged, with the learning rate of that update."""
    from sb3_sfgpi.sfdqn.tabular_policy import diverged_error
    from sb3_sfgpi.tabular.joint_steps import BASE, NUM_TIMESTEPS

    step = arrays.counters[NUM_TIMESTEPS] - arrays.settings[BASE]
    return diverged_error(float(arrays.learning_rates[step]), learner.batch_size)
