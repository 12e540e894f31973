"""Replay buffer for vector rewards (and integer observations stored in the smallest dtype that holds them).

SB3's :class:`~stable_baselines3.common.buffers.ReplayBuffer` stores one float per transition and, handed
vector rewards, either fails or (when sampling) flattens them silently into shape ``(batch * d, 1)``.
:class:`MOReplayBuffer` stores rewards of shape ``(buffer_size, n_envs, reward_dim)`` and samples
``(batch, reward_dim)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sfgpi.common.action_masks import info_mask, stacked_masks

#: A sampled batch as numpy arrays: observations, actions ``(B,)``, next observations, dones ``(B,)`` (truncations
#: count as not done), rewards ``(B, d)``, and the next observations' action masks ``(B, n_actions)`` (None: every
#: action exists).
Arrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, "np.ndarray | None"]


class FlatStorage(NamedTuple):
    """
    A buffer's arrays seen as one row per ``transition * n_envs + env`` (views of its storage, for compiled
    learners that read the sampled rows themselves; timeouts are time-limit truncations, which bootstrap).
    """

    observations: np.ndarray  #: ``(rows, obs_size)``, in the stored dtype
    next_observations: np.ndarray  #: ``(rows, obs_size)``: read at :meth:`MOReplayBuffer.next_rows`
    actions: np.ndarray  #: ``(rows,)``
    rewards: np.ndarray  #: ``(rows, d)``, float32
    dones: np.ndarray  #: ``(rows,)``, float32
    timeouts: np.ndarray  #: ``(rows,)``, float32
    next_forbidden: np.ndarray  #: ``(rows, n_actions)``: True where the next observation's mask forbids the action;
    #: ``(0, 0)`` while no mask was stored


class MOReplayBufferSamples(NamedTuple):
    """
    SB3's ``ReplayBufferSamples`` (rewards of shape ``(batch, d)``) with the next observations' action masks and,
    from a buffer that takes priorities back (:class:`~sb3_sfgpi.common.prioritized_buffer.PrioritizedMOReplayBuffer`),
    the rows drawn.
    """

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    next_action_masks: th.Tensor | None = None
    rows: np.ndarray | None = None


class MOReplayBuffer(ReplayBuffer):
    """
    Replay buffer whose rewards are vectors of length ``reward_dim``.

    Time-limit truncations are stored apart from terminations (``handle_timeout_termination``) so that
    truncated transitions bootstrap. With ``optimize_memory_usage=True`` the next observation of a
    truncated transition is lost, so, as in SB3, truncations are then treated as terminations.

    Where the env gives action masks (``info["action_mask"]``, :mod:`~sb3_sfgpi.common.action_masks`), the mask of
    each next observation is stored with its transition, so that the TD target bootstraps only on allowed actions;
    the storage is made when the first mask arrives (rows stored before count as allowing every action).

    Observations of an integer space are stored in the smallest integer dtype that holds the space
    (:func:`compact_dtype`: a byte for the Four-Room's cells and flags, instead of SB3's ``int64``); they are read
    back as the same values in the space's dtype.

    :param buffer_size: Max number of transitions in the buffer
    :param observation_space: Observation space
    :param action_space: Action space
    :param device: PyTorch device
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: Store each observation once (about half the memory for observations)
    :param handle_timeout_termination: Bootstrap on time-limit truncation (forced off with
        ``optimize_memory_usage``)
    :param reward_dim: Number of objectives ``d``
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        reward_dim: int = 1,
    ):
        if reward_dim < 1:
            raise ValueError(f"reward_dim must be at least 1, got {reward_dim}")
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=optimize_memory_usage,
            handle_timeout_termination=handle_timeout_termination and not optimize_memory_usage,
        )
        self.reward_dim = reward_dim
        self.rewards = np.zeros((self.buffer_size, self.n_envs, reward_dim), dtype=np.float32)
        compact = compact_dtype(observation_space)
        if compact is not None:  # the same values in fewer bytes; np.zeros, not zeros_like: no page is touched yet
            self.observations = np.zeros(self.observations.shape, dtype=compact)
            if not optimize_memory_usage:
                self.next_observations = np.zeros(self.next_observations.shape, dtype=compact)
        self._rows_at_pos = 0  # rows of the step at ``pos`` written by add_rows (it is sampled once complete)
        #: True where a next observation's mask forbids the action, shape ``(buffer_size, n_envs, n_actions)``;
        #: None while no mask was stored (zeros: untouched pages cost no memory)
        self.next_forbidden: np.ndarray | None = None

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Add one step of ``n_envs`` transitions.

        :raises ValueError: if ``reward`` is not of shape ``(n_envs, reward_dim)``
        """
        reward = np.asarray(reward)
        if reward.shape != (self.n_envs, self.reward_dim):
            raise ValueError(
                f"MOReplayBuffer expects rewards of shape (n_envs, reward_dim) = {(self.n_envs, self.reward_dim)}, "
                f"got {reward.shape}"
            )
        masks = stacked_masks([info_mask(info, self._n_actions(), "the env") for info in infos], self._n_actions())
        self._store_masks(slice(self.pos * self.n_envs, (self.pos + 1) * self.n_envs), masks)
        super().add(obs, next_obs, action, reward, done, infos)
        self._rows_at_pos = 0

    def _n_actions(self) -> int:
        return int(self.action_space.n)  # type: ignore[attr-defined]

    def _store_masks(self, rows: slice | np.ndarray, masks: np.ndarray | None) -> None:
        """Store the next observations' masks (None: every action) at the flat rows ``transition * n_envs + env``."""
        if masks is None and self.next_forbidden is None:
            return
        n_actions = self._n_actions()
        if self.next_forbidden is None:
            self.next_forbidden = np.zeros((self.buffer_size, self.n_envs, n_actions), dtype=bool)
        self.next_forbidden.reshape(-1, n_actions)[rows] = False if masks is None else ~masks

    def add_rows(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        dones: np.ndarray,
        timeouts: np.ndarray,
        next_masks: np.ndarray | None = None,
    ) -> None:
        """
        Add ``k`` transitions (any ``k``, e.g. those of the agents still alive among the ``n_envs`` that share one
        learner) as the next ``k`` of the buffer's ``buffer_size * n_envs`` rows, in order.

        A step of ``n_envs`` rows is sampled once all its rows are written, so sampling sees only complete steps;
        with ``n_envs = 1`` and ``k = 1`` this is :meth:`add`.

        :param obs: observations, shape ``(k, *obs_shape)``
        :param next_obs: next observations (the terminal one where the episode ended)
        :param actions: actions, shape ``(k,)`` or ``(k, action_dim)``
        :param rewards: vector rewards, shape ``(k, reward_dim)``
        :param dones: whether each transition ended its episode, shape ``(k,)``
        :param timeouts: whether that end was a time-limit truncation, shape ``(k,)``
        :param next_masks: the next observations' action masks, shape ``(k, n_actions)``, or None (every action)
        :raises ValueError: with ``optimize_memory_usage`` (its next observation is the same env's next row), or
            rewards of the wrong shape
        """
        if self.optimize_memory_usage:
            raise ValueError("add_rows needs a buffer without optimize_memory_usage")
        k = len(rewards)
        if np.shape(rewards) != (k, self.reward_dim):
            raise ValueError(f"add_rows expects rewards of shape (k, {self.reward_dim}), got {np.shape(rewards)}")
        capacity = self.buffer_size * self.n_envs
        first = self.pos * self.n_envs + self._rows_at_pos
        whole_step = self._rows_at_pos == 0 and k == self.n_envs  # exactly the rows at ``pos``: written as one
        # A slice writes in place without an index array; only a write that wraps around needs one.
        rows = slice(first, first + k) if first + k <= capacity else (first + np.arange(k)) % capacity
        for storage, values in (
            (self.observations, obs),
            (self.next_observations, next_obs),
            (self.actions, actions),
            (self.rewards, rewards),
            (self.dones, dones),
            (self.timeouts, timeouts if self.handle_timeout_termination else np.zeros(k)),
        ):
            if whole_step:
                storage[self.pos] = np.asarray(values).reshape(storage.shape[1:])
            else:  # the flat rows of a view of shape (buffer_size * n_envs, ...): the storage is contiguous
                storage.reshape(capacity, *storage.shape[2:])[rows] = np.asarray(values).reshape(k, *storage.shape[2:])
        self._store_masks(rows, next_masks)
        end = first + k
        self.full = self.full or end >= capacity
        self.pos, self._rows_at_pos = divmod(end % capacity, self.n_envs)

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> MOReplayBufferSamples:
        """
        Sample a batch of transitions as tensors; rewards have shape ``(batch_size, reward_dim)``.

        :param batch_size: Number of transitions
        :param env: A VecNormalize to normalise observations with (reward normalisation is refused)
        """
        return self._get_samples(self._sample_indices(batch_size), env=env)

    def sample_arrays(self, batch_size: int) -> Arrays:
        """
        Sample a batch as numpy arrays, without tensors (for numpy learners such as the tabular policy).

        :param batch_size: Number of transitions
        :return: see :data:`Arrays`
        """
        obs, actions, next_obs, dones, rewards, next_masks = self._arrays(self._sample_indices(batch_size))
        return obs, actions.reshape(-1), next_obs, dones, rewards, next_masks

    def stored_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """
        Every stored transition of every env, as numpy arrays in the layout of :meth:`sample_arrays`.

        :return: observations, actions ``(N,)``, next observations, dones ``(N,)`` (truncations count as not done),
            rewards ``(N, d)``
        """
        start, stop, shift = self.valid_positions()
        indices = (np.arange(start, stop) + shift) % self.buffer_size
        flat = (indices[:, None] * self.n_envs + np.arange(self.n_envs)).reshape(-1)
        obs, actions, next_obs, dones, rewards, _ = self._gather(flat)
        return obs, actions.reshape(-1), next_obs, dones, rewards

    def valid_positions(self) -> tuple[int, int, int]:
        """The stored transitions are at ``(i + shift) % buffer_size`` for ``start <= i < stop``."""
        if not self.optimize_memory_usage:
            return 0, self.buffer_size if self.full else self.pos, 0
        # With one array for obs and next obs, the transition at ``pos`` is not valid.
        return (1, self.buffer_size, self.pos) if self.full else (0, self.pos, 0)

    def _sample_indices(self, batch_size: int) -> np.ndarray:
        start, stop, shift = self.valid_positions()
        indices = np.random.randint(start, stop, size=batch_size)
        return (indices + shift) % self.buffer_size if shift else indices  # without a shift, all in [0, buffer_size)

    def sample_rows(self, batch_size: int) -> np.ndarray:
        """
        The flat rows ``transition * n_envs + env`` of a sampled batch (of :meth:`flat_storage`), drawn as
        :meth:`sample` and :meth:`sample_arrays` draw theirs.
        """
        return self._flat_rows(self._sample_indices(batch_size))

    def next_rows(self, flat: np.ndarray) -> np.ndarray:
        """The flat rows of the next observations of the transitions at ``flat`` in :meth:`flat_storage`."""
        # With one array for obs and next obs, the next observation is the same env's one step later.
        return (flat + self.n_envs) % (self.buffer_size * self.n_envs) if self.optimize_memory_usage else flat

    def flat_storage(self) -> FlatStorage:
        """The stored transitions, one row per ``transition * n_envs + env`` (views, see :class:`FlatStorage`)."""
        n_rows = self.buffer_size * self.n_envs
        forbidden = self.next_forbidden
        return FlatStorage(
            self.observations.reshape(n_rows, -1),
            (self.observations if self.optimize_memory_usage else self.next_observations).reshape(n_rows, -1),
            self.actions.reshape(n_rows),
            self.rewards.reshape(n_rows, self.reward_dim),
            self.dones.reshape(n_rows),
            self.timeouts.reshape(n_rows),
            np.zeros((0, 0), dtype=bool) if forbidden is None else forbidden.reshape(n_rows, -1),
        )

    def _flat_rows(self, batch_inds: np.ndarray) -> np.ndarray:
        # Each array is read as (buffer_size * n_envs, ...) at the flat rows ``transition * n_envs + env``: one
        # ``take`` per array is several times cheaper than indexing with two index arrays, for the same elements.
        if self.n_envs == 1:
            # randint over a single value draws nothing from the generator: skipping it changes no sample.
            return batch_inds
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        return batch_inds * self.n_envs + env_indices

    def _arrays(self, batch_inds: np.ndarray) -> Arrays:
        return self._gather(self._flat_rows(batch_inds))

    def _gather(self, flat: np.ndarray) -> Arrays:
        """The transitions at the flat rows ``transition * n_envs + env`` (:data:`Arrays`, actions not flattened)."""
        next_flat = self.next_rows(flat)
        next_source = self.observations if self.optimize_memory_usage else self.next_observations
        dones, timeouts = self.dones.reshape(-1).take(flat), self.timeouts.reshape(-1).take(flat)
        return (
            _rows(self.observations, flat).astype(self.observation_space.dtype, copy=False),
            _rows(self.actions, flat),
            _rows(next_source, next_flat).astype(self.observation_space.dtype, copy=False),
            # A time-limit truncation is not a termination: it bootstraps.
            dones * (1 - timeouts),
            _rows(self.rewards, flat),
            None if self.next_forbidden is None else ~_rows(self.next_forbidden, flat),  # stored with the transition
        )

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> MOReplayBufferSamples:
        if env is not None and env.norm_reward:
            raise ValueError(
                "Reward normalisation (VecNormalize(norm_reward=True)) is not supported for vector rewards"
            )
        obs, actions, next_obs, dones, rewards, next_masks = self._arrays(batch_inds)
        data = (self._normalize_obs(obs, env), actions, self._normalize_obs(next_obs, env), dones[:, None], rewards)
        return MOReplayBufferSamples(
            *map(self.to_torch, data), next_action_masks=None if next_masks is None else self.to_torch(next_masks)
        )


#: The dtypes :func:`compact_dtype` chooses from, smallest first.
COMPACT_DTYPES = (np.uint8, np.int8, np.int16, np.int32)  # the integer dtypes torch supports in full


def compact_dtype(space: spaces.Space) -> np.dtype | None:
    """
    The smallest integer dtype that holds every value of an integer observation space (Discrete, MultiDiscrete,
    MultiBinary, bounded integer Box), where it is smaller than the space's own; None for any other space.
    """
    if isinstance(space, spaces.Discrete):
        low, high = np.array(space.start), np.array(space.start + space.n - 1)
    elif isinstance(space, spaces.MultiDiscrete):
        low, high = np.asarray(space.start), np.asarray(space.start) + space.nvec - 1
    elif isinstance(space, spaces.MultiBinary):
        low, high = np.array(0), np.array(1)
    elif isinstance(space, spaces.Box) and np.issubdtype(space.dtype, np.integer) and space.is_bounded():
        low, high = space.low, space.high
    else:
        return None
    own = np.dtype(space.dtype)
    for dtype in COMPACT_DTYPES:
        info = np.iinfo(dtype)
        if info.min <= low.min() and high.max() <= info.max:
            return np.dtype(dtype) if np.dtype(dtype).itemsize < own.itemsize else None
    return None


def _rows(array: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``array[i, j]`` for the flat row indices ``i * n_envs + j`` of an array of shape ``(N, n_envs, ...)``."""
    return array.reshape(-1, *array.shape[2:]).take(flat, axis=0)
