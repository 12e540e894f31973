"""GPI's decisions over a set of successor-feature networks, computed in one batched pass.

``π(s) = argmax_a max_{π ∈ Π} w · ψ^π(s, a)``, for one preference ``w`` or for one per observation. The networks
share one architecture, so the ``ψ`` of all of them is one batched pass (:mod:`sb3_sfgpi.stacking`) over a batched
copy, built once after the networks change; weights used for many decisions in a row are validated once. A decision
can also name the members GPI followed: those that attain the value of the action it took.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.utils import is_vectorized_observation
from torch import nn

from sb3_sfgpi.common.action_masks import checked_masks, masked
from sb3_sfgpi.common.observations import numeric_array
from sb3_sfgpi.common.weights import validate_weight_rows, validate_weights, weighted_sum
from sb3_sfgpi.stacking import Stacked, StackedTables, numpy_tables, stack_networks


class BatchedGPI(ABC):
    """
    GPI's action values and actions over ``networks``, the SF networks of a set of policies that share one
    architecture, spaces and reward dimension (:class:`~sb3_sfgpi.gpi.GPIPolicy` is such a set).

    The set keeps the networks and says where they live (:attr:`device`); what is derived here from them, their
    batched copy and the last validated weights, lasts until :meth:`networks_changed`.
    """

    networks: list[nn.Module]
    _stacked: Stacked | None = None
    _weights_cache: tuple[Any, tuple[np.ndarray, th.Tensor, np.ndarray]] | None = None

    @property
    @abstractmethod
    def device(self) -> th.device:
        """Where the networks live."""

    def networks_changed(self) -> None:
        """Drop what the set derived from its networks (stacked copies): call it after changing them in place."""
        self._stacked = None
        self._weights_cache = None

    @property
    def reward_dim(self) -> int:
        return self._first().reward_dim

    @property
    def observation_space(self) -> spaces.Space:
        return self._first().observation_space

    @property
    def action_space(self) -> spaces.Discrete:
        return self._first().action_space

    def _first(self) -> Any:
        if not self.networks:
            raise ValueError("the policy set is empty")
        return self.networks[0]

    def _stack(self) -> Stacked:
        if self._stacked is None:
            self._stacked = stack_networks(self.networks)
        return self._stacked

    def stacked_tables(self) -> StackedTables | None:
        """The set's tables stacked, where it is a set of tables on the CPU (what compiled GPI reads), else None."""
        stacked = self._stack()
        return stacked if isinstance(stacked, StackedTables) and self.device.type == "cpu" else None

    def _psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        """``ψ`` of every policy, shape ``(n_policies, batch, n_actions, d)``, in one batched pass."""
        with th.no_grad():
            return self._stack().psi(obs_tensor)

    def _psi_each(self, obs_tensor: th.Tensor) -> th.Tensor:
        """``ψ`` of each network by its own forward pass, stacked (a reference for tests and benchmarks)."""
        with th.no_grad():
            return th.stack([net(obs_tensor) for net in self.networks])

    def _obs_to_tensor(self, observation: np.ndarray) -> tuple[th.Tensor, bool]:
        return self._first().obs_to_tensor(observation)

    def _obs_to_array(self, observation: np.ndarray) -> tuple[np.ndarray, bool]:
        """The observation as a batch array and whether it was one (as SB3's ``obs_to_tensor``, without torch)."""
        space = self.observation_space
        if isinstance(observation, dict) or is_image_space(space):
            obs_tensor, vectorized = self._obs_to_tensor(observation)
            return obs_tensor.cpu().numpy(), vectorized
        array = numeric_array(observation)
        vectorized = is_vectorized_observation(array, space)
        return array.reshape((-1, *space.shape)), vectorized  # type: ignore[misc]

    def _validated_weights(
        self, w: np.ndarray | list[float], per_row: bool = False
    ) -> tuple[np.ndarray, th.Tensor, np.ndarray]:
        """
        ``w`` checked and normalised: float64 array, float32 tensor on the set's device, float32 array.

        The last weights are remembered, so acting many times for one ``w`` validates it once.

        :param per_row: ``w`` holds one weight per observation, shape ``(batch, d)``: each row checked
        :raises ValueError: bad weights (with ``per_row``, also weights that are not a 2-D array)
        """
        if isinstance(w, th.Tensor):  # one that requires grad too
            w = w.detach().cpu().numpy()
        try:
            raw = np.asarray(w, dtype=np.float64)
        except (TypeError, ValueError):
            raw = None
        key = None if raw is None else (per_row, raw.shape, raw.tobytes())
        cached = self._weights_cache
        if key is not None and cached is not None and cached[0] == key:
            return cached[1]
        if not per_row:
            weights = validate_weights(w if raw is None else raw, self.reward_dim)
        elif raw is None or raw.ndim != 2:
            raise ValueError(f"weights must have shape (batch, {self.reward_dim}), got {np.shape(w)}")
        else:
            weights = validate_weight_rows(raw, self.reward_dim)
        # float32 like the networks: Q = ψ · w is computed in single precision on every path.
        result = (weights, th.as_tensor(weights, dtype=th.float32, device=self.device), weights.astype(np.float32))
        self._weights_cache = (key, result)
        return result

    def successor_features(self, observation: np.ndarray) -> np.ndarray:
        """
        ``ψ^π(s, ·)`` of every policy in the set.

        :param observation: one observation or a batch
        :return: shape ``(n_policies, batch, n_actions, d)``
        """
        obs_tensor, _ = self._obs_to_tensor(observation)
        return self._psi(obs_tensor).cpu().numpy()

    def q_values(self, observation: np.ndarray, w: np.ndarray | list[float]) -> np.ndarray:
        """
        GPI action values ``max_π w · ψ^π(s, a)``.

        :param observation: one observation or a batch
        :param w: preference weights of length ``d``
        :return: shape ``(batch, n_actions)``
        """
        weights = self._validated_weights(w)
        obs, _ = self._obs_to_array(observation)
        return self._gpi_q(obs, weights)

    def _gpi_q(self, obs: np.ndarray, weights: tuple[np.ndarray, th.Tensor, np.ndarray]) -> np.ndarray:
        """GPI's action values of a batch for one weight (shape ``(d,)``) or one per observation (``(batch, d)``)."""
        stacked = self._stack()
        if numpy_tables(stacked) and self.device.type == "cpu":
            return stacked.q_values_numpy(obs, weights[2])
        obs_tensor = th.as_tensor(obs, device=self.device)
        each = weights[1] if weights[1].dim() == 1 else weights[1][:, None, :]
        with th.no_grad():
            return th.amax(weighted_sum(stacked.psi(obs_tensor), each), dim=0).cpu().numpy()

    def _policy_q(self, obs: np.ndarray, weights: tuple[np.ndarray, th.Tensor, np.ndarray]) -> np.ndarray:
        """Every policy's action values ``w · ψ^π(s, a)``, shape ``(n_policies, batch, n_actions)``."""
        stacked = self._stack()
        if numpy_tables(stacked) and self.device.type == "cpu":
            return stacked.policy_q_numpy(obs, weights[2]).transpose(1, 0, 2)
        obs_tensor = th.as_tensor(obs, device=self.device)
        each = weights[1] if weights[1].dim() == 1 else weights[1][:, None, :]
        with th.no_grad():
            return weighted_sum(stacked.psi(obs_tensor), each).cpu().numpy()

    def predict_followed(
        self,
        observation: np.ndarray,
        w: np.ndarray | Sequence[float],
        action_masks: np.ndarray | None = None,
        per_row: bool = False,
    ) -> tuple[np.ndarray, list[frozenset[int]]]:
        """
        GPI actions of a batch, the same as :meth:`predict`'s, and for each observation the members GPI followed: those
        that attain GPI's value of the action taken, ``max_π w · ψ^π(s, a*)``.

        Without a member, GPI takes the same action wherever another member attains that value too: the action's value
        is unchanged, no other action's grew, and ties still go to the first action. Each policy's values are computed
        on their own (:func:`~sb3_sfgpi.common.weights.weighted_sum`), whatever the other members.

        :param observation: a batch of observations
        :param w: preference weights of length ``d``
        :param action_masks: the actions each observation has (see :meth:`predict`)
        :param per_row: ``w`` holds one weight per observation, shape ``(batch, d)`` (as :meth:`predict_rows`)
        :return: the actions, shape ``(batch,)``, and the members followed, one set of indices per observation
        """
        actions, attaining = self.predict_attaining(observation, w, action_masks, per_row)
        patterns, pattern_of = distinct_columns(attaining)
        return actions, [patterns[i] for i in pattern_of.tolist()]

    def predict_attaining(
        self,
        observation: np.ndarray,
        w: np.ndarray | Sequence[float],
        action_masks: np.ndarray | None = None,
        per_row: bool = False,
        left_out: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        :meth:`predict_followed` with the members followed as a boolean matrix, shape ``(n_policies, batch)``: True
        where a member attains GPI's value of the action taken.

        :param left_out: for each observation a member GPI acts without there (``-1``: none), or None: GPI over the
            set without that member, as :meth:`~sb3_sfgpi.gpi.GPIPolicy.without` acts (each member's values are its
            own; the member left out attains nothing)
        """
        weights = self._validated_weights(w, per_row=per_row)
        obs, _ = self._obs_to_array(observation)
        if per_row:
            _check_one_weight_per_row(weights[0], obs)
        stacked = self.stacked_tables()
        if stacked is not None:  # one compiled call
            index = stacked.rows(obs)  # raises ValueError for an observation outside the space
            return stacked.attaining(
                index, weights[2], left_out, checked_masks(action_masks, len(obs), self.action_space.n)
            )
        q = self._policy_q(obs, weights)
        if left_out is not None:
            rows = np.flatnonzero(left_out >= 0)
            q[left_out[rows], rows] = -np.inf
        q = masked(q, checked_masks(action_masks, len(obs), self.action_space.n))
        best = q.max(axis=0)
        actions = best.argmax(axis=1)
        rows = np.arange(len(actions))
        return actions, q[:, rows, actions] == best[rows, actions]

    def predict(
        self,
        observation: np.ndarray,
        w: np.ndarray | list[float],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
        action_masks: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        GPI action ``argmax_a max_π w · ψ^π(s, a)`` (ties go to the first action), as SB3's ``predict``, over the
        actions ``action_masks`` allows.

        :param observation: one observation or a batch
        :param w: preference weights of length ``d``
        :param state: unused, returned as is
        :param episode_start: unused
        :param deterministic: GPI is deterministic; kept for SB3 compatibility
        :param action_masks: the actions each observation has, 0/1 of shape ``(batch, n_actions)`` (the envs'
            ``info["action_mask"]``, as sb3-contrib's maskable algorithms take them); None: every action
        :return: the actions (a scalar array for one observation) and ``state``
        :raises ValueError: bad weights, bad masks or an empty set
        """
        weights = self._validated_weights(w)
        obs, vectorized = self._obs_to_array(observation)
        masks = checked_masks(action_masks, len(obs), self.action_space.n)
        actions = masked(self._gpi_q(obs, weights), masks).argmax(axis=1)
        return (actions if vectorized else actions[0]), state

    def predict_rows(
        self, observations: np.ndarray, weights: np.ndarray, action_masks: np.ndarray | None = None
    ) -> np.ndarray:
        """
        GPI actions of a batch in which every observation has its own preference weights (episodes for several
        weights stepped together): row ``i`` gets :meth:`predict`'s action for ``observations[i]`` and
        ``weights[i]``, computed the same way.

        :param observations: a batch of observations
        :param weights: shape ``(batch, d)``
        :param action_masks: as :meth:`predict`'s
        :return: the actions, shape ``(batch,)``
        :raises ValueError: bad weights or masks, or a weight per observation missing
        """
        rows = self._validated_weights(weights, per_row=True)
        obs, _ = self._obs_to_array(observations)
        _check_one_weight_per_row(rows[0], obs)
        masks = checked_masks(action_masks, len(obs), self.action_space.n)
        return masked(self._gpi_q(obs, rows), masks).argmax(axis=1)


def _check_one_weight_per_row(weights: np.ndarray, obs: np.ndarray) -> None:
    """Refuse per-row weights that are not one per observation."""
    if len(weights) != len(obs):
        raise ValueError(f"one weight per observation: got {len(weights)} weights for {len(obs)} observations")


def distinct_columns(attaining: np.ndarray) -> tuple[list[frozenset[int]], np.ndarray]:
    """
    The distinct columns of a boolean matrix as sets of their True rows, and each column's index among them (a batch
    of decisions has few distinct sets of members followed: one set is built per pattern, keyed by its packed bits).

    :param attaining: shape ``(n_policies, batch)``
    :return: the sets, and for each column the index of its set, shape ``(batch,)``
    """
    packed = np.ascontiguousarray(np.packbits(attaining, axis=0).T)  # (batch, bytes): at least one member
    keys = packed.view(np.dtype((np.void, packed.shape[1]))).reshape(-1)
    _, first, pattern_of = np.unique(keys, return_index=True, return_inverse=True)
    sets = [frozenset(np.flatnonzero(attaining[:, column]).tolist()) for column in first.tolist()]
    return sets, pattern_of.reshape(-1)
