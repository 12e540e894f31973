"""Which new policies join Π: every one (the paper), or those that GPI does no worse with on validation weights.

:class:`Admission` sits beside the :mod:`weight schedules <sb3_sfgpi.schedules>`: after every iteration the
schedule takes the new policies' values (OLS), and the admission decides which of the policies join Π. With
validation a new policy joins only if GPI over Π does at least as well with it as without it on validation weights;
an iteration's policies left out one by one can then be tried together, and Π can be pruned of policies without
which GPI does better. Why each rule exists, and what it was measured to do, is on the docs' levers page.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import format_weights, random_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_settings import RunSettings
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.validation import Scored, ValidationScorer


@dataclass(frozen=True)
class Candidate:
    """A policy learned in an iteration, with what Π records of it (``weights``: those it joins bound to, where a
    learner conditioned on the weights offers its network for another weight than its own; None: its own)."""

    learner: SFDQN
    value: np.ndarray
    agent: str
    weights: np.ndarray | None = None


class Admission:
    """
    Which new policies join Π.

    With ``validation_weights > 0`` a new policy joins only if GPI over Π does at least as well with it as without
    it on validation weights: the simplex extrema and ``validation_weights`` Dirichlet(1) weights drawn from the
    run's seed (not the test weights), every agent acting by GPI. A policy left out is one whose SFs promise more
    than it returns where GPI would follow it (in a multi-agent env, typically objects its partner takes first). Its
    value still goes to the schedule, so the weights trained, and the learners, are the same with and without
    validation.

    :param validation_weights: Dirichlet(1) validation weights besides the extrema; 0: every new policy joins Π, as
        in the paper
    :param episodes: episodes per validation weight
    :param prune: after every iteration, while GPI does strictly better without one of Π's policies, retire the one
        without which it does best (backward elimination: a policy admitted early can mislead GPI once its
        partners' policies changed). Retired policies stay in the run's record
    :param together: the policies of an iteration left out one by one (two or more) are then tried together, and
        join together if GPI does at least as well with all of them: two agents' policies can each mislead GPI
        alone and help it together
    :param verbose: 1 prints a line for every policy left out or retired
    :raises ValueError: a negative number of weights, or ``prune``/``together`` without validation weights
    """

    def __init__(
        self,
        validation_weights: int = RunSettings.validation_weights,
        episodes: int = 1,
        prune: bool = RunSettings.prune,
        together: bool = RunSettings.admit_together,
        verbose: int = 0,
    ):
        if isinstance(validation_weights, bool) or not isinstance(validation_weights, int) or validation_weights < 0:
            raise ValueError(f"validation_weights must be a non-negative integer, got {validation_weights!r}")
        if episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {episodes}")
        if prune and not validation_weights:
            raise ValueError("pruning Π needs validation weights: validation_weights must be positive")
        if together and not validation_weights:
            raise ValueError("admitting together needs validation weights: validation_weights must be positive")
        self.validation_weights = validation_weights
        self.episodes = episodes
        self.prune = prune
        self.together = together
        self.verbose = verbose
        self._scorer: ValidationScorer | None = None
        self._cached: Scored | None = None  # GPI's episodes over Π as it stands

    def weights(self, reward_dim: int, seed: int) -> np.ndarray:
        """The validation weights of a run with ``seed``, shape ``(reward_dim + validation_weights, reward_dim)``."""
        drawn = random_weights(reward_dim, self.validation_weights, rng=derive_seed(seed, "validation-weights"))
        return np.vstack([np.eye(reward_dim), drawn])

    def start(self, scorer: ValidationScorer) -> None:
        """Score policy sets with ``scorer`` (GPI on :meth:`weights`, ``episodes`` each) from now on."""
        self._scorer, self._cached = scorer, None

    def forget(self) -> None:
        """Forget GPI's score over Π (kept between iterations): call it after Π's SFs were changed in place."""
        self._cached = None

    def admit(self, record: GPIPolicy, candidates: Sequence[Candidate], iteration: int) -> GPIPolicy:
        """
        Add the candidates that pass to ``record`` (every policy ever admitted), retire what pruning retires.

        :param record: the run's record; its members (:meth:`~sb3_sfgpi.gpi.GPIPolicy.members`) are Π
        :param candidates: the iteration's new policies, in the order they are tried
        :param iteration: the iteration they were learned in (numbered from 1)
        :return: Π afterwards
        """
        policy_set = record.members()
        left_out = [c for c in candidates if not self._try(policy_set, record, [c], iteration)]
        if self.together and len(left_out) > 1:
            self._try(policy_set, record, left_out, iteration)
        if self.prune:
            policy_set = self._pruned(policy_set, record, iteration)
        return policy_set

    def _try(self, policy_set: GPIPolicy, record: GPIPolicy, group: list[Candidate], iteration: int) -> bool:
        """
        Add ``group`` to Π and the record, unless GPI does worse with it on the validation weights: all or none. Π with
        the group is rolled out only where it acts otherwise on Π's decisions (:meth:`ValidationScorer.replayed`).
        """
        validate = self.validation_weights > 0 and len(policy_set) > 0
        kept = self._episodes(policy_set) if validate else None
        before = 0.0 if kept is None else kept.score
        for c in group:
            policy_set.add(c.learner, c.weights, value=c.value, agent=c.agent, iteration=iteration)
        self._cached = None if kept is None else self._started().replayed(policy_set, kept)
        if validate and (after := self._current(policy_set)) < before:
            for _ in group:
                policy_set.pop()
            self._cached = kept
            policies = "policy" if len(group) == 1 else "policies together"
            self._print(f"{' and '.join(c.agent for c in group)}'s {policies}{_offered_for(group)} left out of Π: "
                      f"GPI on the validation weights {after:.4f} with, {before:.4f} without")  # fmt: skip
            return False
        for c in group:
            record.add(c.learner, c.weights, value=c.value, agent=c.agent, iteration=iteration)
        return True

    def _pruned(self, policy_set: GPIPolicy, record: GPIPolicy, iteration: int) -> GPIPolicy:
        """
        Retire, one at a time, the policy without which GPI does best, while it does better without it.

        Each round rolls out again only the weights at which a member was decisive (:meth:`ValidationScorer.without`):
        the scores of full rollouts of every leave-one-out subset, at the cost of those weights.
        """
        while len(policy_set) > 1:
            current, scorer = self._episodes(policy_set), self._started()
            without = scorer.without_each(policy_set, current)
            scores = [s.score for s in without]
            worst = int(np.argmax(scores))
            if scores[worst] <= current.score:
                break
            info = policy_set.infos[worst]
            self._print(f"{info.agent}'s policy of iteration {info.iteration} for w = {format_weights(info.weights)} "
                      f"retired from Π: GPI on the validation weights {scores[worst]:.4f} without it, "
                      f"{self._current(policy_set):.4f} with")  # fmt: skip
            members = [i for i, member in enumerate(record.infos) if member.retired is None]
            record.retire(members[worst], iteration)
            policy_set = policy_set.subset(j for j in range(len(policy_set)) if j != worst)
            self._cached = without[worst]
        return policy_set

    def _current(self, policy_set: GPIPolicy) -> float:
        """GPI's score over Π (cached until Π changes)."""
        return self._episodes(policy_set).score

    def _episodes(self, policy_set: GPIPolicy) -> Scored:
        """GPI's episodes over Π on the validation weights (cached until Π changes)."""
        if self._cached is None:
            self._cached = self._started()(policy_set)
        return self._cached

    def _started(self) -> ValidationScorer:
        if self._scorer is None:
            raise RuntimeError("Admission.start(scorer) must be called before policies are validated")
        return self._scorer

    def _print(self, message: str) -> None:
        if self.verbose:
            print(message)


def _offered_for(group: Sequence[Candidate]) -> str:
    """The weights that candidates offered for other weights than their learners' own were offered for, as words."""
    offered = [format_weights(c.weights) for c in group if c.weights is not None]
    return f" for w = {' and '.join(offered)}" if offered else ""
