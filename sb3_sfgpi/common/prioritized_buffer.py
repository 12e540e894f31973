"""Prioritised replay for vector rewards: transitions drawn in proportion to their last TD error for the weights.

A transition that a learner rarely sees and still predicts badly (the first cart that brings a rare ore home) is
drawn as often as any other from a uniform buffer, once in about ``buffer_size / batch_size`` updates.
:class:`PrioritizedMOReplayBuffer` draws each stored transition with probability ``p_i / Σ p``, where ``p_i =
max(|w · δ_i|, min_priority) ** alpha`` and ``δ_i`` is the transition's TD error (a vector of ``d`` objectives) when
it was last learned for the learner's weights ``w`` (Schaul et al., 2016; GPI-PD's replay in Alegre et al., 2023:
no importance-sampling correction of the loss). A new transition gets the highest priority stored, so it is drawn
soon; at the start of each ``learn()`` the learner scores every stored transition again for its weights
(:meth:`~sb3_sfgpi.sfdqn.policies.SFDQNPolicy.score_replay`), since errors for other weights say nothing of them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sfgpi.common.buffers import MOReplayBuffer, MOReplayBufferSamples


class SumTree:
    """
    Sums and maxima of ``n`` non-negative leaves in two complete binary trees (arrays of ``2 · 2^k`` entries; the
    root at 1): a leaf changes in ``O(log n)`` and a draw in proportion to the leaves costs ``O(log n)``.

    :param n: Number of leaves
    """

    def __init__(self, n: int):
        self.size = 1 << max(n - 1, 1).bit_length()
        self.sums = np.zeros(2 * self.size)
        self.maxima = np.zeros(2 * self.size)

    @property
    def total(self) -> float:
        """The sum of the leaves."""
        return float(self.sums[1])

    @property
    def max(self) -> float:
        """The largest leaf."""
        return float(self.maxima[1])

    def leaves(self, rows: np.ndarray | slice) -> np.ndarray:
        """The leaves at ``rows`` (a copy)."""
        return self.sums[self.size :][rows].copy()

    def set(self, rows: np.ndarray, values: np.ndarray) -> None:
        """
        Set the leaves at ``rows`` (distinct or not: the last value of a row stays) and their ancestors.

        :param rows: leaf indices, shape ``(k,)``
        :param values: non-negative numbers, shape ``(k,)``
        """
        nodes = np.asarray(rows, dtype=np.int64) + self.size
        self.sums[nodes] = values
        self.maxima[nodes] = values
        while nodes[0] > 1:  # every node is at the same depth; a parent named twice gets the same value twice
            nodes = nodes // 2
            self.sums[nodes] = self.sums[2 * nodes] + self.sums[2 * nodes + 1]
            self.maxima[nodes] = np.maximum(self.maxima[2 * nodes], self.maxima[2 * nodes + 1])

    def find(self, masses: np.ndarray) -> np.ndarray:
        """
        The leaves at which the cumulative sum of the leaves first exceeds each of ``masses``.

        :param masses: numbers in ``[0, total)``, shape ``(k,)``
        :return: leaf indices, shape ``(k,)``; only leaves above zero are found
        """
        nodes = np.ones(len(masses), dtype=np.int64)
        masses = np.array(masses, dtype=np.float64)
        while nodes[0] < self.size:
            left = self.sums[2 * nodes]
            right = masses >= left
            masses -= left * right
            nodes = 2 * nodes + right
        # Rounding can step past the last positive leaf (a mass within an ulp of the total): take the nearest before.
        found = nodes - self.size
        empty = self.sums[nodes] <= 0
        if empty.any():
            found[empty] = [self._positive_before(row) for row in found[empty]]
        return found

    def _positive_before(self, row: int) -> int:
        positive = np.flatnonzero(self.sums[self.size : self.size + row + 1] > 0)
        return int(positive[-1]) if len(positive) else int(np.flatnonzero(self.sums[self.size :] > 0)[0])


class PrioritizedMOReplayBuffer(MOReplayBuffer):
    """
    :class:`~sb3_sfgpi.common.buffers.MOReplayBuffer` whose transitions are drawn in proportion to their priority
    (see the module); pass it as SFDQN's ``replay_buffer_class`` with a network policy (its
    ``replay_buffer_kwargs`` set ``alpha`` and ``min_priority``).

    :param alpha: How much the priorities count: 0 draws uniformly, 1 in proportion to the errors (0.6, GPI-PD's)
    :param min_priority: The least ``|w · δ|`` a transition counts with, so that none is never drawn again (0.01)
    :param kwargs: :class:`~sb3_sfgpi.common.buffers.MOReplayBuffer`'s arguments (``optimize_memory_usage`` is
        refused: a transition's next observation would be another one's)
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        *args: Any,
        alpha: float = 0.6,
        min_priority: float = 0.01,
        **kwargs: Any,
    ):
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
        if not min_priority > 0.0:
            raise ValueError(f"min_priority must be above zero, got {min_priority!r}")
        super().__init__(buffer_size, observation_space, action_space, *args, **kwargs)
        if self.optimize_memory_usage:
            raise ValueError("a prioritized replay buffer does not take optimize_memory_usage")
        self.alpha, self.min_priority = float(alpha), float(min_priority)
        self.tree = SumTree(self.buffer_size * self.n_envs)

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        rows = self._next_rows(self.n_envs)
        super().add(obs, next_obs, action, reward, done, infos)
        self._prioritize_new(rows)

    def add_rows(self, obs: np.ndarray, *args: Any, **kwargs: Any) -> None:
        rows = self._next_rows(len(obs))
        super().add_rows(obs, *args, **kwargs)
        self._prioritize_new(rows)

    def _next_rows(self, k: int) -> np.ndarray:
        """The flat rows the next ``k`` transitions go to."""
        first = self.pos * self.n_envs + self._rows_at_pos
        return (first + np.arange(k)) % (self.buffer_size * self.n_envs)

    def _prioritize_new(self, rows: np.ndarray) -> None:
        """New transitions: the highest priority stored (1 in an empty buffer), so that each is drawn soon."""
        self.tree.set(rows, np.full(len(rows), self.tree.max or 1.0))

    def _sample_indices(self, batch_size: int) -> np.ndarray:
        """
        Flat rows ``transition * n_envs + env`` (not positions: see :meth:`_flat_rows`), one from each of
        ``batch_size`` equal slices of the priorities' total (stratified), drawn from numpy's global generator.
        """
        bounds = np.arange(batch_size) + np.random.uniform(size=batch_size)
        return self.tree.find(bounds * (self.tree.total / batch_size))

    def _flat_rows(self, batch_inds: np.ndarray) -> np.ndarray:
        return batch_inds  # already flat rows, with their envs (see _sample_indices)

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> MOReplayBufferSamples:
        """As :meth:`MOReplayBuffer.sample`, drawn by priority; the samples' ``rows`` are the flat rows drawn."""
        return self.samples_at(self._sample_indices(batch_size), env)

    def samples_at(self, rows: np.ndarray, env: VecNormalize | None = None) -> MOReplayBufferSamples:
        """The transitions at the flat rows ``rows``, as :meth:`sample` gives them."""
        return self._get_samples(rows, env=env)._replace(rows=rows)

    def update_priorities(self, rows: np.ndarray, errors: th.Tensor | np.ndarray) -> None:
        """
        :param rows: flat rows (a sample's ``rows``)
        :param errors: each row's TD error for the learner's weights, ``w · δ``, shape ``(len(rows),)``
        """
        errors = np.abs(errors.detach().cpu().numpy() if isinstance(errors, th.Tensor) else np.asarray(errors))
        self.tree.set(rows, np.maximum(errors.astype(np.float64), self.min_priority) ** self.alpha)

    def stored_rows(self) -> np.ndarray:
        """The flat rows that hold a transition (those of a step whose rows are not all written yet included)."""
        return np.arange(self.buffer_size * self.n_envs if self.full else self.pos * self.n_envs + self._rows_at_pos)


#: The replay buffers a learner's arguments may name (a run file holds names, not classes).
REPLAY_BUFFERS: dict[str, type[MOReplayBuffer]] = {
    "MOReplayBuffer": MOReplayBuffer,
    "PrioritizedMOReplayBuffer": PrioritizedMOReplayBuffer,
}


def replay_buffer_class_named(name: str | type[ReplayBuffer] | None) -> type[ReplayBuffer]:
    """
    The class of a replay buffer given by name (:data:`REPLAY_BUFFERS`), by class, or None (``MOReplayBuffer``).

    :raises ValueError: an unknown name
    """
    if name is None:
        return MOReplayBuffer
    if not isinstance(name, str):
        return name
    if name not in REPLAY_BUFFERS:
        raise ValueError(f"unknown replay_buffer_class {name!r}: one of {', '.join(REPLAY_BUFFERS)}, or a class")
    return REPLAY_BUFFERS[name]
