"""Dyna-style planning for tabular successor features: sweeps of the SF Bellman backup on the replay buffer's model.

The replay buffer of a tabular learner is an empirical model of its environment: for each state-action pair
``(s, a)`` it holds the next states seen, how often, and the rewards and terminations that came with them.
:class:`EmpiricalModel` condenses it into one row per distinct ``(s, a, s')`` with its empirical probability
``P̂(s' | s, a)`` and mean reward and termination, and :meth:`EmpiricalModel.sweep` applies

``ψ(s, a) ← Σ_s' P̂(s' | s, a) · (r̄(s, a, s') + γ (1 − d̄(s, a, s')) ψ(s', a*(s')))``,  ``a*(s') = argmax_a w · ψ(s', a)``

to every recorded pair at once (Jacobi sweeps), until no entry moves by more than ``TOLERANCE`` or the number of
sweeps is reached: value iteration of the policy greedy in ``w · ψ`` on the model (Sutton and Barto, Sec. 8.2, for
successor features).
In a deterministic environment the model is exact where it has been seen. Pairs never tried keep their entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sb3_sfgpi.sfdqn.networks import greedy_entries

#: Sweeps stop once no entry of ψ moves by more than this.
TOLERANCE = 1e-6


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
    ) -> EmpiricalModel:
        """
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
        entries, pair = np.unique(keys // n_entries, return_inverse=True)
        pair_total = np.bincount(pair, weights=counts)

        def mean(values: np.ndarray) -> np.ndarray:
            return np.bincount(outcome, weights=values, minlength=len(keys)) / counts

        return cls(
            entries=entries,
            pair=pair,
            next_first=keys % n_entries,
            probability=counts / pair_total[pair],
            continues=1.0 - mean(np.asarray(dones, dtype=np.float64)),
            reward=np.stack([mean(rewards[:, i]) for i in range(rewards.shape[1])], axis=1),
            n_actions=n_actions,
        )

    def sweep(self, table: np.ndarray, weights: np.ndarray, gamma: float, max_sweeps: int) -> int:
        """
        Back up every recorded pair of ``table`` in place, ``max_sweeps`` times or until no entry moves by more than
        :data:`TOLERANCE`.

        :param table: ψ, one row per ``(state, action)``: shape ``(n_rows * n_actions, d)``
        :param weights: ``w``, shape ``(d,)``
        :param gamma: discount factor
        :param max_sweeps: most sweeps to do
        :return: the number of sweeps done
        """
        scale = (gamma * self.continues * self.probability)[:, None]
        expected_reward = self.reward * self.probability[:, None]
        for sweep in range(1, max_sweeps + 1):
            following = table[greedy_entries(table, self.next_first, self.n_actions, weights)]
            contributions = expected_reward + scale * following
            backed_up = np.stack(
                [
                    np.bincount(self.pair, weights=contributions[:, i], minlength=len(self.entries))
                    for i in range(table.shape[1])
                ],
                axis=1,
            )
            change = np.abs(table[self.entries] - backed_up).max(initial=0.0)
            table[self.entries] = backed_up
            if change <= TOLERANCE:
                return sweep
        return max_sweeps
