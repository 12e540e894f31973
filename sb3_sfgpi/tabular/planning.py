"""Dyna-style planning for tabular successor features: sweeps of the SF Bellman backup on the replay buffer's model.

The replay buffer of a tabular learner is an empirical model of its environment: for each state-action pair
``(s, a)`` it holds the next states seen, how often, and the rewards and terminations that came with them.
:class:`Experience` counts each distinct ``(s, a, s')``, and :class:`EmpiricalModel` condenses that into one row
per outcome with its empirical probability ``P̂(s' | s, a)`` and mean reward and termination, and
:meth:`EmpiricalModel.sweep` applies

``ψ(s, a) ← Σ_s' P̂(s' | s, a) · (r̄(s, a, s') + γ (1 − d̄(s, a, s')) ψ(s', a*(s')))``,  ``a*(s') = argmax_a w · ψ(s', a)``

to every recorded pair at once (Jacobi sweeps), until no entry moves by more than ``TOLERANCE`` or the number of
sweeps is reached: value iteration of the policy greedy in ``w · ψ`` on the model (Sutton and Barto, Sec. 8.2, for
successor features).
In a deterministic environment the model is exact where it has been seen. Pairs never tried keep their entries.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from sb3_sfgpi.tabular.kernels import planning_sweeps
from sb3_sfgpi.tabular.sparse import SparseTable

#: Sweeps stop once no entry of ψ moves by more than this.
TOLERANCE = 1e-6
#: Most sweeps a table is settled with (SFDQN's ``remove_optimism``, pooled replay): far more than planning needs to
#: reach :data:`TOLERANCE` at γ = 0.99.
SETTLE_SWEEPS = 10_000


@dataclass(frozen=True)
class EmpiricalModel:
    """
    One row per distinct recorded ``(s, a, s')``, grouped by ``(s, a)``.

    :param entries: the row ``s * n_actions + a`` of each recorded pair, shape ``(P,)``, sorted and distinct
    :param pair: for each outcome, the index into ``entries`` of its pair, shape ``(O,)``
    :param next_first: ``s' * n_actions`` of each outcome, shape ``(O,)``
    :param probability: ``P̂(s' | s, a)`` of each outcome, shape ``(O,)``
    :param continues: mean ``1 − terminated`` of each outcome, shape ``(O,)``
    :param reward: mean vector reward of each outcome, shape ``(O, d)``
    :param n_actions: number of actions
    """

    entries: np.ndarray
    pair: np.ndarray
    next_first: np.ndarray
    probability: np.ndarray
    continues: np.ndarray
    reward: np.ndarray
    n_actions: int

    def sweep(
        self, table: SparseTable, weights: np.ndarray, gamma: float, max_sweeps: int, dtype: type = np.float32
    ) -> int:
        """
        Back up every recorded pair of ``table`` in place, ``max_sweeps`` times or until no entry moves by more than
        :data:`TOLERANCE`.

        The sweeps work on a contiguous copy of the rows they read or write (every action of the states recorded
        and of their next states, which the table then stores), written back at the end: the same arithmetic as on
        the table, without indexing the whole table at every sweep (``python -m benchmarks planning``).

        :param table: ψ, one row per state of ``n_actions * d`` values
        :param weights: ``w``, shape ``(d,)``
        :param gamma: discount factor
        :param max_sweeps: most sweeps to do
        :param dtype: the precision of the sweeps (the table keeps its own)
        :return: the number of sweeps done
        """
        n_actions, n_pairs = self.n_actions, len(self.entries)
        states, local_state = np.unique(
            np.concatenate([self.entries, self.next_first]) // n_actions, return_inverse=True
        )
        slots = table.store(states)
        entries = table.values.reshape(-1, self.reward.shape[1])
        rows = (slots[:, None] * n_actions + np.arange(n_actions)).ravel()
        psi = entries[rows].astype(dtype, copy=False)
        own = local_state[:n_pairs] * n_actions + self.entries % n_actions
        following_state = local_state[n_pairs:]
        scale = gamma * self.continues * self.probability
        expected_reward = self.reward * self.probability[:, None]
        summed = len(self.pair) != n_pairs  # a deterministic environment (one outcome a pair): no sums
        sweeps = planning_sweeps(
            psi, np.asarray(weights, dtype=psi.dtype), n_actions, own,
            following_state, self.pair, summed, scale, expected_reward, max_sweeps, TOLERANCE,
        )  # fmt: skip
        entries[rows] = psi
        return sweeps


@dataclass(frozen=True)
class Experience:
    """
    Everything recorded, condensed: how often each distinct ``(s, a, s')`` was seen, with the sums of its
    terminations and vector rewards; :meth:`model` condenses it into an :class:`EmpiricalModel` (probabilities
    and means) for planning.

    :param keys: ``(s * n_actions + a) * n_rows * n_actions + s' * n_actions`` of each outcome, sorted and distinct,
        shape ``(O,)``
    :param counts: how often each outcome was recorded, shape ``(O,)``
    :param dones: the number of its recordings that terminated the episode, shape ``(O,)``
    :param rewards: the sum of its recorded vector rewards, shape ``(O, d)``
    :param n_rows: number of rows (states) of the table
    :param n_actions: number of actions
    """

    keys: np.ndarray
    counts: np.ndarray
    dones: np.ndarray
    rewards: np.ndarray
    n_rows: int
    n_actions: int

    @classmethod
    def from_transitions(
        cls,
        rows: np.ndarray,
        actions: np.ndarray,
        next_rows: np.ndarray,
        dones: np.ndarray,
        rewards: np.ndarray,
        n_rows: int,
        n_actions: int,
    ) -> Experience:
        """
        The experience of recorded transitions.

        :param rows: table row of each transition's state, shape ``(N,)``
        :param actions: shape ``(N,)``
        :param next_rows: table row of each next state, shape ``(N,)``
        :param dones: 1 where the transition terminated the episode (truncations are 0), shape ``(N,)``
        :param rewards: vector rewards, shape ``(N, d)``
        :param n_rows: number of rows of the table
        :param n_actions: number of actions
        """
        n_entries = n_rows * n_actions
        entry = rows.astype(np.int64) * n_actions + actions.astype(np.int64)
        keys, outcome, counts = np.unique(
            entry * n_entries + next_rows.astype(np.int64) * n_actions, return_inverse=True, return_counts=True
        )
        return cls._summed(keys, outcome, counts, np.asarray(dones, dtype=np.float64), rewards, n_rows, n_actions)

    @classmethod
    def _summed(
        cls,
        keys: np.ndarray,
        outcome: np.ndarray,
        counts: np.ndarray,
        dones: np.ndarray,
        rewards: np.ndarray,
        n_rows: int,
        n_actions: int,
    ) -> Experience:
        def total(values: np.ndarray) -> np.ndarray:
            return np.bincount(outcome, weights=values, minlength=len(keys))

        summed_rewards = np.stack([total(rewards[:, i]) for i in range(rewards.shape[1])], axis=1)
        return cls(keys, counts.astype(np.int64), total(dones), summed_rewards, n_rows, n_actions)

    def merged(self, other: Experience) -> Experience:
        """
        This experience and ``other`` together: the counts, terminations and reward sums of each outcome added.

        :raises ValueError: experiences of tables of other sizes or reward dimensions
        """
        if (self.n_rows, self.n_actions, self.reward_dim) != (other.n_rows, other.n_actions, other.reward_dim):
            raise ValueError("cannot merge the experiences of tables of different sizes or reward dimensions")
        keys, outcome = np.unique(np.concatenate([self.keys, other.keys]), return_inverse=True)
        counts = np.bincount(outcome, weights=np.concatenate([self.counts, other.counts]), minlength=len(keys))
        dones = np.concatenate([self.dones, other.dones])
        rewards = np.concatenate([self.rewards, other.rewards])
        return self._summed(keys, outcome, counts, dones, rewards, self.n_rows, self.n_actions)

    def arrays(self) -> dict[str, np.ndarray]:
        """The experience as plain arrays (for a file; :meth:`from_arrays` reads them back)."""
        return {"keys": self.keys, "counts": self.counts, "dones": self.dones, "rewards": self.rewards}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], n_rows: int, n_actions: int, reward_dim: int) -> Experience:
        """
        The experience in ``arrays`` (:meth:`arrays`) of a table of ``n_rows`` rows and ``n_actions`` actions, checked.

        :raises ValueError: a missing array, or arrays that no transitions of such a table make (keys not sorted,
            distinct and in range; counts below 1; terminations outside ``[0, counts]``; non-finite rewards; shapes)
        """
        missing = {"keys", "counts", "dones", "rewards"} - set(arrays)
        if missing:
            raise ValueError(f"experience lacks {sorted(missing)}")
        keys, counts = np.asarray(arrays["keys"]), np.asarray(arrays["counts"])
        dones, rewards = np.asarray(arrays["dones"], dtype=np.float64), np.asarray(arrays["rewards"], dtype=np.float64)
        n_entries = n_rows * n_actions
        checks = {
            "keys must be sorted, distinct outcomes of the table's pairs": keys.dtype.kind in "iu"
            and keys.ndim == 1
            and bool(np.all(np.diff(keys) > 0) and np.all(keys % n_actions == 0))
            and (len(keys) == 0 or (keys[0] >= 0 and keys[-1] < n_entries * n_entries)),
            "counts must be integers >= 1, one per key": counts.dtype.kind in "iu"
            and counts.shape == keys.shape
            and bool(np.all(counts >= 1)),
            "dones must be between 0 and the counts": dones.shape == counts.shape == keys.shape
            and bool(np.all((dones >= 0) & (dones <= counts))),
            f"rewards must be finite, shape (keys, {reward_dim})": rewards.shape == (len(keys), reward_dim)
            and bool(np.isfinite(rewards).all()),
        }
        for problem, holds in checks.items():
            if not holds:
                raise ValueError(f"experience: {problem}")
        return cls(keys.astype(np.int64), counts.astype(np.int64), dones, rewards, n_rows, n_actions)

    @property
    def reward_dim(self) -> int:
        return self.rewards.shape[1]

    def __len__(self) -> int:
        """The number of transitions recorded."""
        return int(self.counts.sum())

    def model(self) -> EmpiricalModel:
        """The empirical model of this experience: ``P̂(s' | s, a)``, mean rewards and terminations."""
        n_entries = self.n_rows * self.n_actions
        entries, pair = np.unique(self.keys // n_entries, return_inverse=True)
        pair_total = np.bincount(pair, weights=self.counts)
        return EmpiricalModel(
            entries=entries,
            pair=pair,
            next_first=self.keys % n_entries,
            probability=self.counts / pair_total[pair],
            continues=1.0 - self.dones / self.counts,
            reward=self.rewards / self.counts[:, None],
            n_actions=self.n_actions,
        )


def plan_table(
    table: SparseTable,
    model: EmpiricalModel,
    weights: np.ndarray,
    gamma: float,
    max_sweeps: int,
    untried_value: float | None = None,
    dtype: type = np.float32,
) -> int:
    """
    Plan a table on a model: :meth:`EmpiricalModel.sweep`, after giving the pairs the model has not recorded
    ``untried_value`` in every component of ψ (if given).

    :param table: ψ, one row per state of ``n_actions * d`` values, updated in place
    :param dtype: the precision of the sweeps (the table keeps its own)
    :return: the number of sweeps done
    """
    if untried_value is not None:
        n_actions = model.n_actions
        tried = table.store(model.entries // n_actions) * n_actions + model.entries % n_actions
        entries = table.values.reshape(len(table.values) * n_actions, -1)
        untried = np.ones(len(entries), dtype=bool)
        untried[tried] = False
        entries[untried] = untried_value  # the default row's too: every pair of a row not stored is untried
    return model.sweep(table, weights, gamma, max_sweeps, dtype) if len(model.entries) else 0
