"""The SB3 policy of a tabular SFDQN: the table of :mod:`sb3_sfgpi.tabular`, its ε-greedy read and its TD update."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import is_vectorized_observation
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sfgpi.common.action_masks import checked_masks, sample_allowed
from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.sfdqn.policies import SFDQNPolicy
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.tabular.planning import Experience, plan_table


class StepSize:
    """
    The optimizer of a table: the learning rate ``α`` in ``param_groups``, as SB3's schedules set it.

    :meth:`TabularPolicy.td_update` updates the table in place, so there is nothing to optimise; a torch optimizer
    would only hold ``α``, and building one imports ``torch._dynamo`` and SymPy, which a tabular run never needs.
    The state dict has ``torch.optim.SGD``'s layout: models saved with either load with either.

    :param params: ignored (a table has no torch parameters), as an optimizer's first argument
    :param lr: the learning rate ``α``
    """

    def __init__(self, params: Any = (), lr: float = 0.1) -> None:
        self.param_groups = [{"lr": float(lr), "params": []}]  # SB3's load reads the number of params

    def state_dict(self) -> dict[str, Any]:
        return {"state": {}, "param_groups": [{"lr": self.param_groups[0]["lr"], "params": [0]}]}

    def load_state_dict(self, state_dict: dict[str, Any], strict: bool = True) -> None:
        """Read ``α`` from a state dict of this class or of a torch optimizer with one parameter group."""
        try:
            (group,) = state_dict["param_groups"]
            lr = float(group["lr"])
        except (KeyError, TypeError, ValueError) as error:
            message = f"a tabular policy's optimizer state needs one parameter group with an 'lr': {error}"
            raise ValueError(message) from None
        if not np.isfinite(lr) or lr < 0:
            raise ValueError(f"a tabular policy's learning rate must be a finite number >= 0, got {lr}")
        self.param_groups[0]["lr"] = lr


class TabularPolicy(SFDQNPolicy):
    """
    Tabular successor features: multi-objective Q-learning with experience replay.

    Each sampled transition moves its entry by ``α · (target − ψ)`` with ``α`` the learning rate: the SGD step
    on ``0.5 · Σ_batch ||target − ψ(s, a)||²``, exactly the tabular update of the paper (Table 1: α = 0.1).
    By default there is no separate target network (``target_network=False``): targets read the table itself,
    as in Q-learning.

    The table starts at zero, so every action of a state not learned yet ties: the behaviour policy breaks ties at
    random (``masked_actions``), which keeps its greedy steps exploring there; the learned policy
    (TD target, ``predict(deterministic=True)``) takes the first of tied actions.

    :param observation_space: a small integer observation space
    :param action_space: Action space (Discrete)
    :param lr_schedule: Learning rate schedule (``α``)
    :param reward_dim: Number of objectives ``d``
    :param target_network: Keep a separate, periodically copied target table
    :param optimizer_class: What holds the learning rate ``α`` (:class:`StepSize` by default; a torch optimizer
        class also serves, never stepped: :meth:`td_update` updates the table in place)
    :param optimizer_kwargs: Keyword arguments of the optimizer, excluding the learning rate
    """

    sf_net: TabularSFNetwork
    sf_net_target: TabularSFNetwork

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        reward_dim: int,
        target_network: bool = False,
        optimizer_class: type[th.optim.Optimizer] | type[StepSize] = StepSize,
        optimizer_kwargs: dict[str, Any] | None = None,
    ):
        self.target_network = target_network
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            reward_dim,
            net_arch=[],
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )
        self._weights_view, self._weights_address = np.empty(0, dtype=np.float32), -1  # made by weights_array()

    def _build(self, lr_schedule: Schedule) -> None:
        self.sf_net = self.make_sf_net()
        if self.target_network:
            self.sf_net_target = self.make_sf_net()
            self.sf_net_target.load_state_dict(self.sf_net.state_dict())
        else:
            self.sf_net_target = self.sf_net
        # The optimizer only holds α, which SB3's schedules set in its param groups; the table (numpy) has no torch
        # parameters and a torch optimizer refuses an empty list, so it gets an empty placeholder, never stepped.
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            [th.empty(0, requires_grad=True)], lr=lr_schedule(1), **self.optimizer_kwargs
        )

    def make_sf_net(self) -> TabularSFNetwork:  # type: ignore[override]
        """A new zero-initialised SF table."""
        return TabularSFNetwork(self.observation_space, self.action_space, self.reward_dim).to(self.device)  # type: ignore[arg-type]

    def greedy(self, observation: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, bool]:
        """``argmax_a w · ψ(s, a)`` read from the table (see :meth:`SFDQNPolicy.greedy`)."""
        q_values, vectorized = self.q_values(observation, weights)
        return q_values.argmax(axis=1), vectorized

    def weights_array(self) -> np.ndarray:
        """
        ``w``: a numpy view of the ``weights`` buffer, made again only where the buffer's memory is another (a copy
        of the policy); torch's ``numpy()`` costs more than a tabular update's arithmetic.
        """
        weights = self.weights
        if self._weights_address != weights.data_ptr():
            self._weights_view, self._weights_address = weights.numpy(), weights.data_ptr()
        return self._weights_view

    def q_values(self, observation: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, bool]:
        """``w · ψ(s, a)`` read from the table with numpy (see :meth:`SFDQNPolicy.q_values`)."""
        obs, vectorized = self._observation_rows(observation)
        return self.sf_net.action_values(obs, weights), vectorized

    def _observation_rows(self, observation: np.ndarray) -> tuple[np.ndarray, bool]:
        """The observation(s) as a batch, and whether they were one."""
        # SB3's is_vectorized_observation, without its image-transpose step (integer spaces are never images).
        vectorized = is_vectorized_observation(observation, self.observation_space)
        return np.asarray(observation).reshape(-1, *self.observation_space.shape), vectorized

    def masked_actions(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        weights: np.ndarray,
        action_masks: np.ndarray | None,
        exploration_rate: float | None,
    ) -> tuple[np.ndarray, bool]:
        """
        :meth:`SFDQNPolicy.masked_actions`, the ε-greedy choice read and drawn by one compiled call
        (:meth:`TabularSFNetwork.epsilon_greedy <sb3_sfgpi.tabular.network.TabularSFNetwork.epsilon_greedy>`): the
        same actions from the same draws.
        """
        from sb3_sfgpi.tabular.numpy_random import global_stream  # numba loads with the first tabular read

        stream = None if exploration_rate is None else global_stream()
        if stream is None:  # the greedy choice draws nothing; another global generator only numpy reads
            return super().masked_actions(observation, weights, action_masks, exploration_rate)
        obs, vectorized = self._observation_rows(observation)  # type: ignore[arg-type]
        masks = checked_masks(action_masks, len(obs), int(self.action_space.n))  # type: ignore[attr-defined]
        actions = self.sf_net.epsilon_greedy(obs, weights, masks, exploration_rate, stream)
        for i in np.flatnonzero(actions < 0):
            actions[i] = sample_allowed(self.action_space, None if masks is None else masks[i])
        return actions, vectorized

    def fill(self, value: float) -> None:
        """
        Set every entry of the table (and of its target) to ``value``: optimistic initial values when ``value`` is
        above what the policy can get.

        :param value: the value of every component of ``ψ(s, a)``, for every pair
        """
        self.sf_net.table.fill(value)
        if self.sf_net_target is not self.sf_net:
            self.sf_net_target.table.fill(value)

    def experience(self, replay_buffer: MOReplayBuffer) -> Experience:
        """
        The transitions of ``replay_buffer``, condensed for planning (see :class:`Experience`).

        :raises ValueError: the buffer holds action masks: planning backs up every action's value
        """
        if replay_buffer.next_forbidden is not None:
            raise ValueError(
                "planning (planning_sweeps, pool_replay) does not take action masks (the env gives "
                "info['action_mask']): turn it off"
            )
        net = self.sf_net
        obs, actions, next_obs, dones, rewards = replay_buffer.stored_arrays()
        rows, next_rows = net.rows(obs, check=False), net.rows(next_obs, check=False)
        return Experience.from_transitions(rows, actions, next_rows, dones, rewards, net.table.n_rows, net.n_actions)

    def plan(
        self, replay_buffer: MOReplayBuffer, gamma: float, max_sweeps: int, untried_value: float | None = None
    ) -> int:
        """
        Dyna-style planning: sweeps of the SF backup over every pair recorded in the replay buffer (see
        :class:`~sb3_sfgpi.tabular.planning.EmpiricalModel`); a separate target table is then set to the result.

        :param replay_buffer: the transitions that make the model
        :param gamma: discount factor
        :param max_sweeps: most sweeps to do
        :param untried_value: if given, every pair not recorded in the buffer first gets ``ψ`` of this value in
            each component (0: what a fresh table holds), so that the sweeps back up no other value for them
        :return: the number of sweeps done
        """
        model = self.experience(replay_buffer).model()
        sweeps = plan_table(self.sf_net.table, model, self.weights_array(), gamma, max_sweeps, untried_value)
        self.update_target()
        return sweeps

    def update_target(self, tau: float = 1.0) -> None:
        """
        Move the target table (if separate) towards the online one, every row: ``(1 − τ) · target + τ · online``
        (``τ = 1``: a copy).
        """
        online, target = self.sf_net.table, self.sf_net_target.table
        if target is online:
            return
        target.store(online.stored_rows())
        values, rows = target.values, target.stored_rows()
        values[: len(rows)] = (1 - tau) * values[: len(rows)] + tau * online.lookup(rows)
        values[-1] = (1 - tau) * values[-1] + tau * online.default

    def td_update(
        self,
        replay_buffer: MOReplayBuffer,
        batch_size: int,
        gamma: float,
        max_grad_norm: float,
        vec_normalize_env: VecNormalize | None = None,
    ) -> float:
        """
        ``ψ(s, a) ← ψ(s, a) + α (target − ψ(s, a))`` for every sampled transition (repeats add up), with the
        target of :meth:`SFDQNPolicy.td_update`.

        This is the SGD step on ``0.5 · Σ ||target − ψ(s, a)||²`` with learning rate ``α``, done in place on the
        table's memory by compiled code that reads the sampled transitions from the buffer's storage
        (:func:`~sb3_sfgpi.tabular.kernels.sampled_td_update`: numpy's arithmetic, the same bits). ``α`` is the
        optimizer's current learning rate, so SB3's learning-rate schedules apply. ``max_grad_norm`` is unused:
        the tabular update is exact.

        :return: the loss before the step
        :raises ValueError: the update diverged: a value overflowed float32 (a learning rate too large for the batch)
        """
        if vec_normalize_env is not None and vec_normalize_env.norm_obs:
            raise ValueError("TabularPolicy indexes raw integer observations: do not normalise them with VecNormalize")
        # numba (its memory and start-up time) loads with the first tabular update: deep learners never import it
        from sb3_sfgpi.tabular.kernels import DIVERGED, STORE_ROWS, sampled_td_update

        flat, next_flat = self.minibatch_rows(replay_buffer, batch_size)
        lr = self.optimizer.param_groups[0]["lr"]
        net, target_net, storage = self.sf_net, self.sf_net_target, replay_buffer.flat_storage()
        rows, td_error = np.empty(batch_size, dtype=np.int64), np.empty((batch_size, self.reward_dim), dtype=np.float32)
        outcome = STORE_ROWS
        while outcome == STORE_ROWS:  # at most twice: the second time every row is stored
            outcome = sampled_td_update(
                net.table_storage(), target_net.table_storage(), storage, flat, next_flat,
                *net.row_strides(), self.weights_array(), np.float32(gamma), np.float32(lr), rows, td_error,
            )  # fmt: skip
            if outcome == STORE_ROWS:
                net.table.store(rows)
        if outcome == DIVERGED:
            raise diverged_error(lr, batch_size)
        with np.errstate(over="raise", invalid="raise"):  # a loss beyond float32 is divergence too
            try:
                return float(0.5 * np.square(td_error).sum())
            except FloatingPointError:
                raise diverged_error(lr, batch_size) from None

    @staticmethod
    def minibatch_rows(replay_buffer: MOReplayBuffer, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """
        The flat rows of a minibatch and of its next observations, drawn as
        :meth:`MOReplayBuffer.sample_rows <sb3_sfgpi.common.buffers.MOReplayBuffer.sample_rows>` draws them: by
        compiled code from numpy's global generator where it can read it
        (:func:`~sb3_sfgpi.tabular.kernels.sample_rows`), by numpy otherwise; the same numbers either way.
        """
        from sb3_sfgpi.tabular.kernels import sample_rows
        from sb3_sfgpi.tabular.numpy_random import global_stream

        stream, positions = global_stream(), replay_buffer.valid_positions()
        if stream is None or positions[1] <= positions[0]:  # numpy's draws (an empty buffer: numpy's error)
            flat = replay_buffer.sample_rows(batch_size)
            return flat, replay_buffer.next_rows(flat)
        flat, next_flat = np.empty(batch_size, dtype=np.int64), np.empty(batch_size, dtype=np.int64)
        n_envs = replay_buffer.n_envs
        next_offset = n_envs if replay_buffer.optimize_memory_usage else 0
        sample_rows(*stream, positions, replay_buffer.buffer_size, n_envs, next_offset, flat, next_flat)
        return flat, next_flat

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return dict(
            observation_space=self.observation_space,
            action_space=self.action_space,
            reward_dim=self.reward_dim,
            target_network=self.target_network,
            lr_schedule=self._dummy_schedule,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )


def diverged_error(lr: float, batch_size: int) -> ValueError:
    """The error of a tabular TD update whose values overflowed float32."""
    return ValueError(
        f"the tabular TD update diverged (its values overflowed float32) with learning_rate {lr:g} and batch_size "
        f"{batch_size}: an entry sampled k times in one batch moves k · learning_rate of the way to its target, and "
        "beyond twice the way it grows instead of converging; lower learning_rate"
    )
