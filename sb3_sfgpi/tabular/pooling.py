"""Replay pooled across iterations: one empirical model of everything the run's learners saw, and Π's SFs on it.

In a single-agent env the dynamics do not depend on the policy, so the transitions of every learner of every
iteration are samples of one model. :class:`PooledReplay` adds each iteration's transitions to it (counts per
``(s, a, s')`` with their reward and termination sums: :class:`~sb3_sfgpi.tabular.planning.Experience`) and plans
the SF table of every policy, old and new, on it for the policy's own weights: value iteration of the SF Bellman
backup (:meth:`~sb3_sfgpi.tabular.planning.EmpiricalModel.sweep`) until no entry moves by more than
:data:`~sb3_sfgpi.tabular.planning.TOLERANCE`. Each table is then the SFs of its own greedy policy on the pooled model,
including in states that policy's learner seldom visited, where its own replay held few samples (an enemy's attack
that comes with probability 0.1 per visit). GPI follows a member's SFs exactly there. Pairs no learner tried keep
their entries. With several agents an agent's transitions depend on the others' policies: pooling is refused there.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.tabular.planning import SETTLE_SWEEPS, Experience, plan_table


class PooledReplay:
    """
    The transitions of every learner of a run so far, condensed into one empirical model, and SF tables planned on it.

    :param gamma: the learners' discount factor
    """

    def __init__(self, gamma: float):
        self.gamma = gamma
        self.experience: Experience | None = None  # None: nothing pooled yet

    def add(self, experience: Experience) -> None:
        """Pool ``experience`` (one iteration's, for example) with what is pooled already."""
        self.experience = experience if self.experience is None else self.experience.merged(experience)

    def add_saved(self, arrays: Mapping[str, np.ndarray], table: TabularSFNetwork) -> None:
        """
        Pool the experience :meth:`Experience.arrays <sb3_sfgpi.tabular.planning.Experience.arrays>` wrote (a run
        directory's), checked against the tables it is for (``table``: one of them).

        :raises ValueError: arrays that no transitions of such a table make
        """
        n_rows, n_actions = table.table.n_rows, table.n_actions
        self.add(Experience.from_arrays(arrays, n_rows, n_actions, table.reward_dim))

    def add_experiences(self, experiences: Iterable[Experience]) -> Experience:
        """
        Pool the transitions of a run's learners (each tabular learner's ``policy.experience(replay_buffer)``).

        :return: what they add, together (what a run directory keeps of the iteration)
        """
        added: Experience | None = None
        for experience in experiences:
            added = experience if added is None else added.merged(experience)
        if added is None:
            raise ValueError("no learners to pool the transitions of")
        self.add(added)
        return added

    def plan(self, tables: Iterable[tuple[TabularSFNetwork, np.ndarray]]) -> None:
        """
        Plan each SF table on the pooled model for its weights, in place, in double precision (stored in the
        table's): value iteration until no entry moves by more than
        :data:`~sb3_sfgpi.tabular.planning.TOLERANCE` or :data:`~sb3_sfgpi.tabular.planning.SETTLE_SWEEPS` sweeps.

        :param tables: (SF table, the weights of its policy) pairs
        :raises ValueError: nothing pooled yet
        """
        if self.experience is None:
            raise ValueError("nothing pooled yet: add transitions before planning on them")
        model = self.experience.model()
        for net, weights in tables:
            plan_table(net.table, model, np.asarray(weights, np.float64), self.gamma, SETTLE_SWEEPS, dtype=np.float64)
