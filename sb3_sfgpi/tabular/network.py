"""The table of successor features: one row of ``ψ(s, ·)`` per observation value, and its greedy read."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs

from sb3_sfgpi.tabular.sparse import SparseTable

#: Largest table :class:`TabularSFNetwork` builds (number of observation values).
MAX_TABLE_STATES = 50_000_000
#: What a table's state dict may hold.
TABLE_KEYS = ("table.rows", "table.values", "table.shape", "table.default")


def observation_radices(observation_space: spaces.Space) -> tuple[np.ndarray, np.ndarray]:
    """
    Lower bounds and number of values of each component of a small integer observation space.

    :param observation_space: Discrete, MultiDiscrete, MultiBinary or integer 1-D Box with finite bounds
    :return: ``(low, n_values)``, integer arrays of equal length
    :raises ValueError: for any other space
    """
    if isinstance(observation_space, spaces.Discrete):
        return np.array([observation_space.start]), np.array([observation_space.n])
    if isinstance(observation_space, spaces.MultiDiscrete) and observation_space.nvec.ndim == 1:
        return np.asarray(observation_space.start).reshape(-1), observation_space.nvec.astype(np.int64)
    if isinstance(observation_space, spaces.MultiBinary) and np.ndim(observation_space.n) == 0:
        return np.zeros(int(observation_space.n), dtype=np.int64), np.full(int(observation_space.n), 2)
    if (
        isinstance(observation_space, spaces.Box)
        and len(observation_space.shape) == 1
        and np.issubdtype(observation_space.dtype, np.integer)
        and observation_space.is_bounded()
    ):
        low = observation_space.low.astype(np.int64)
        return low, observation_space.high.astype(np.int64) - low + 1
    raise ValueError(
        "TabularPolicy needs a small integer observation space (Discrete, MultiDiscrete, MultiBinary or a bounded "
        f"integer 1-D Box), got {observation_space}"
    )


class TabularSFNetwork(BasePolicy):
    """
    Table of successor features, one row per observation value, initialised to zero; it holds the rows it has stored
    (:class:`~sb3_sfgpi.tabular.sparse.SparseTable`), every other row reads the default row.

    The row of an observation is its mixed-radix index; ``TabularPolicy.td_update`` updates the sampled rows
    in place. The table lives in numpy on the CPU and has no torch parameters; its state dict holds
    ``table.rows`` (the stored rows), ``table.values``, ``table.shape`` (of the whole table) and, where it is not
    zero, ``table.default``.

    :param observation_space: a small integer observation space (see :func:`observation_radices`)
    :param action_space: Action space (Discrete)
    :param reward_dim: Number of objectives ``d``
    """

    action_space: spaces.Discrete

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Discrete, reward_dim: int):
        super().__init__(observation_space, action_space)
        low, n_values = observation_radices(observation_space)
        n_states = int(np.prod(n_values.astype(np.float64)))
        if n_states > MAX_TABLE_STATES:
            raise ValueError(
                f"the observation space has {n_states} values, more than a table holds ({MAX_TABLE_STATES}): "
                "use MlpPolicy"
            )
        strides = np.concatenate([np.cumprod(n_values[::-1])[::-1][1:], [1]]).astype(np.int64)
        self._low, self._strides, self._n_values = low.astype(np.int64), strides, n_values.astype(np.uint64)
        self._end = self._low + n_values.astype(np.int64)  # one past each component's highest value
        self._first_row = int(self._low @ strides)  # the row index of the lowest observation, before it is subtracted
        self._geometry = (self._low, self._end, self._strides, self._first_row)  # as the kernels read it
        self.reward_dim = reward_dim
        self.n_actions = int(action_space.n)
        self.table = SparseTable(n_states, self.n_actions * reward_dim)

    @property
    def geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """
        How compiled code finds an observation's row: each component's lowest value and one past its highest, the
        mixed-radix strides and the row of the lowest observation (:func:`~sb3_sfgpi.tabular.kernels.action_values`).
        """
        return self._geometry

    def table_storage(self) -> tuple[np.ndarray, np.ndarray]:
        """
        The table as compiled code reads it: its storage, shape ``(slots + 1, n_actions, d)`` (the default row last),
        and its slot map (views, until the table grows).
        """
        return self.table.values.reshape(-1, self.n_actions, self.reward_dim), self.table.slot_map()

    def action_values(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """
        ``w · ψ(s, a)`` of every action of raw observations, read by compiled code
        (:func:`~sb3_sfgpi.tabular.kernels.action_values`: the bits of
        :func:`~sb3_sfgpi.common.weights.weighted_sum`).

        :param obs: raw observations, shape ``(batch,)`` or ``(batch, n_components)``
        :param weights: ``w``, shape ``(d,)``
        :return: shape ``(batch, n_actions)``, float32
        :raises ValueError: an observation outside the observation space (it would read another state's row), or
            weights of another shape
        """
        from sb3_sfgpi.tabular.kernels import action_values  # numba loads with the first tabular read

        raw, observations, w, values = self._read_arguments(obs, weights)
        self._refuse_outside(raw, action_values(self.table_storage(), observations, *self._geometry, w, values))
        return values

    def epsilon_greedy(
        self, obs: np.ndarray, weights: np.ndarray, masks: np.ndarray | None, exploration_rate: float, stream: tuple
    ) -> np.ndarray:
        """
        ε-greedy actions in ``w · ψ(s, ·)`` drawn by compiled code from numpy's global generator
        (:func:`~sb3_sfgpi.tabular.kernels.epsilon_greedy`: the draws of
        :meth:`SFDQNPolicy.masked_actions <sb3_sfgpi.sfdqn.policies.SFDQNPolicy.masked_actions>`).

        :param masks: the actions each observation has, boolean ``(batch, n_actions)``, or None: all
        :param stream: :func:`~sb3_sfgpi.tabular.numpy_random.global_stream`
        :return: the actions, ``-1`` where the observation explores (its uniform action is the caller's to draw)
        :raises ValueError: as :meth:`action_values`
        """
        from sb3_sfgpi.tabular.kernels import epsilon_greedy

        raw, observations, w, values = self._read_arguments(obs, weights)
        actions = np.empty(len(raw), dtype=np.int64)
        allowed = np.zeros((0, 0), dtype=bool) if masks is None else masks
        outside = epsilon_greedy(
            self.table_storage(), observations, self._geometry, w, allowed, exploration_rate, stream, values, actions
        )
        self._refuse_outside(raw, outside)
        return actions

    def _read_arguments(self, obs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, ...]:
        """The raw observations, as rows of components, ``w`` as float32 and a values buffer, for the kernels."""
        raw = np.asarray(obs)
        w = np.asarray(weights, dtype=np.float32)
        if w.shape != (self.reward_dim,):
            raise ValueError(f"a table's values need weights of shape ({self.reward_dim},), got {w.shape}")
        values = np.empty((len(raw), self.n_actions), dtype=np.float32)
        return raw, raw.reshape(len(raw), self._low.size), w, values

    def _refuse_outside(self, raw: np.ndarray, outside: int) -> None:
        """Raise the error of observation ``outside`` (a kernel's answer) unless it is ``-1``."""
        if outside >= 0:
            raise self._outside(raw[outside])

    def row_strides(self) -> tuple[np.ndarray, int]:
        """The mixed-radix strides of an observation's components and the row of the lowest observation: an
        observation's row is ``observation @ strides - first_row`` (see :meth:`rows`)."""
        return self._strides, self._first_row

    def _save_to_state_dict(self, destination: dict[str, Any], prefix: str, keep_vars: bool) -> None:
        table = self.table
        destination[prefix + "table.rows"] = th.from_numpy(table.stored_rows().copy())
        destination[prefix + "table.values"] = th.from_numpy(table.stored_values().copy())
        destination[prefix + "table.shape"] = th.tensor([table.n_rows, table.width])
        if table.default.any():  # a settled or fresh table's file reads as before the key existed
            destination[prefix + "table.default"] = th.from_numpy(table.default.copy())

    def _load_from_state_dict(
        self,
        state_dict: dict[str, Any],
        prefix: str,
        local_metadata: dict[str, Any],
        strict: bool,
        missing_keys: list[str],
        unexpected_keys: list[str],
        error_msgs: list[str],
    ) -> None:
        ours = {key[len(prefix) :]: value for key, value in state_dict.items() if key.startswith(prefix)}
        unexpected_keys.extend(prefix + key for key in ours if key not in TABLE_KEYS)
        try:
            rows, values, default = _table_arrays(ours, (self.table.n_rows, self.table.width))
        except KeyError as error:
            missing_keys.append(prefix + str(error.args[0]))
        except ValueError as error:
            error_msgs.append(str(error))
        else:
            self.table.set_rows(rows, values, default)

    def rows(self, obs: np.ndarray, check: bool = True) -> np.ndarray:
        """
        Row indices of raw observations, shape ``(batch,)``.

        :param obs: raw observations, shape ``(batch,)`` or ``(batch, n_components)``
        :param check: refuse observations outside the observation space (they would index another state's row);
            ``False`` for transitions read back from a replay buffer, which recorded observations of the space
        :raises ValueError: an observation outside the observation space
        """
        raw = np.asarray(obs)
        values = raw.astype(np.int64, copy=False).reshape(len(raw), self._low.size)
        if check:
            self._check_inside(raw, values)
        return values @ self._strides - self._first_row  # (values - low) @ strides, exactly: integers

    def _check_inside(self, raw: np.ndarray, values: np.ndarray) -> None:
        """Refuse raw observations (``values``: as integers, one row each) outside the observation space."""
        # Below ``low``, a component wraps around to a huge unsigned value: one comparison checks both bounds.
        outside = (values - self._low).view(np.uint64) >= self._n_values
        if raw.dtype.kind == "f":
            outside |= (raw != np.floor(raw)).reshape(values.shape)
        if outside.any():
            raise self._outside(raw[int(np.argmax(outside.any(axis=1)))])

    def _outside(self, observation: np.ndarray) -> ValueError:
        """The error of a raw observation outside the observation space."""
        return ValueError(
            f"observation {observation.tolist()} is outside the observation space {self.observation_space}"
        )

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """
        :param obs: Observation batch (not preprocessed)
        :return: ``ψ(s, ·)``, shape ``(batch, n_actions, d)``
        """
        assert isinstance(obs, th.Tensor)
        psi = self.table.lookup(self.rows(obs.cpu().numpy(), check=False))
        return th.from_numpy(psi).view(-1, self.n_actions, self.reward_dim)

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        raise NotImplementedError("an SF network has no weights: use SFDQNPolicy or GPIPolicy to act")

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return dict(
            observation_space=self.observation_space, action_space=self.action_space, reward_dim=self.reward_dim
        )


def _table_arrays(state: dict[str, th.Tensor], shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    The stored rows, their values and the default row of a table's state dict (keys without prefix), checked against
    the table's ``shape``.

    :raises KeyError: a key it needs is missing
    :raises ValueError: shapes, types or rows that do not fit the table
    """
    state = {key: value.detach().cpu() for key, value in state.items()}  # SB3 loads onto its device: tables are numpy
    rows, values, stored_shape = state["table.rows"], state["table.values"], state["table.shape"]
    default = state.get("table.default", th.zeros(shape[1]))
    if tuple(stored_shape.tolist()) != shape:
        raise ValueError(f"the stored table has shape {tuple(stored_shape.tolist())}, the network's is {shape}")
    if rows.dtype != th.long or rows.ndim != 1 or values.shape != (len(rows), shape[1]):
        raise ValueError(f"stored table rows {tuple(rows.shape)} and values {tuple(values.shape)} do not match")
    if default.shape != (shape[1],) or not values.is_floating_point() or not default.is_floating_point():
        raise ValueError(f"stored table values {values.dtype} and default {tuple(default.shape)} do not fit")
    if len(rows) and (rows.min() < 0 or rows.max() >= shape[0]):
        raise ValueError(f"stored table rows outside 0..{shape[0] - 1}")
    if len(th.unique(rows)) != len(rows):
        raise ValueError("stored table rows repeat: each row may be stored once")
    return rows.numpy(), values.numpy(), default.numpy()
