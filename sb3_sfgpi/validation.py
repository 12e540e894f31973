"""GPI scored on validation weights, with the members it followed: leave-one-out scores without most rollouts.

GPI's actions are a deterministic function of the observation, ``w`` and the set, and the episodes of validation
weight ``i`` start from the same seed for every set scored. So where a member was never the only one to attain GPI's
value of an action taken (:meth:`~sb3_sfgpi.gpi.GPIPolicy.predict_followed`), GPI without it takes the same actions:
its episodes, hence its returns, are those of the whole set. :meth:`ValidationScorer.without` runs again only the
weights where the member left out decided something, and reuses the rest: the scores are those of full rollouts,
bit for bit, for a small part of their cost (:class:`~sb3_sfgpi.admission.Admission`'s pruning scores every
leave-one-out subset of Π). Likewise :meth:`ValidationScorer.replayed` scores Π with new policies from Π's recorded
decisions: GPI over the larger set acts on their observations in one batch, and only the weights where it acts
otherwise are rolled out. The per-policy values must not depend on the other members, as those of
:func:`~sb3_sfgpi.common.weights.weighted_sum` do not; and ``reset(seed)`` must determine the env's episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from sb3_sfgpi.common.rollouts import EpisodeReturns
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.evaluation import GPIEpisodesRunner, Lockstep, Rollout, mean_return
from sb3_sfgpi.gpi import Decisions, GPIPolicy
from sb3_sfgpi.gpi_decisions import distinct_columns
from sb3_sfgpi.tabular.network import TabularSFNetwork

#: One weight's decisions, every agent, decision and episode in order: observations, action masks (None: the env
#: gives none), actions.
Decided = tuple[np.ndarray, np.ndarray | None, np.ndarray]
#: The decisions of a weight whose episodes ended at reset: none.
NO_DECISIONS: Decided = (np.empty((0,)), None, np.empty((0,), dtype=np.int64))
#: One weight's episodes: the returns, the members followed, and the decisions.
Run = tuple[EpisodeReturns, frozenset[frozenset[int]], Decided]


@dataclass(frozen=True)
class Scored:
    """
    GPI's episodes over a policy set at every validation weight.

    :param score: the mean over weights and agents of the discounted w·return (what validation compares)
    :param returns: per weight, every agent's returns
    :param followed: per weight, the sets of members that attained GPI's value of an action taken (every agent,
        every decision, every episode), as indices into the set
    :param decisions: per weight, the observations GPI acted on (every agent, decision and episode, in order), their
        action masks and its actions
    """

    score: float
    returns: tuple[EpisodeReturns, ...]
    followed: tuple[frozenset[frozenset[int]], ...]
    decisions: tuple[Decided, ...]

    def decisive(self, member: int) -> list[int]:
        """
        The weights at which GPI without ``member`` may act otherwise: it alone attained a value GPI acted on (or no
        member did: a value that is not a number, where every member counts as decisive).
        """
        alone, empty = frozenset({member}), frozenset[int]()
        return [i for i, sets in enumerate(self.followed) if alone in sets or empty in sets]

    def decisive_members(self) -> set[int]:
        """The members without which GPI acts otherwise at some weight (the others' removal changes nothing)."""
        return {m for sets in self.followed for members in sets if len(members) == 1 for m in members}


def _masks_of(trace: Sequence[Decisions], n_actions: int) -> np.ndarray | None:
    """The decisions' action masks in one array (rows without a mask allow every action), or None without masks."""
    if all(step.masks is None for step in trace):
        return None
    return np.concatenate(
        [np.ones((len(step.actions), n_actions), dtype=bool) if step.masks is None else step.masks for step in trace]
    )


def _runs_decisions(
    steps: Sequence[tuple[Any, ...]], n_runs: int, episodes: int, n_actions: int
) -> list[tuple[frozenset[frozenset[int]], Decided]]:
    """
    Each run's members followed and decisions from the steps of episodes stepped together: run ``j`` holds episodes
    ``j * episodes`` to ``(j + 1) * episodes - 1``, its decisions in episode order, each episode's in step order (as
    one weight's episodes one after another give them).

    :param steps: per step: the observations, action masks (or None), actions, members attaining GPI's value (shape
        ``(n_policies, rows)``) and each row's episode
    """
    if not steps:  # no decision (episodes that end at reset)
        return [(frozenset(), NO_DECISIONS)] * n_runs
    observations, actions = np.concatenate([s[0] for s in steps]), np.concatenate([s[2] for s in steps])
    masks = _masks_of([Decisions(s[0], s[1], s[2], []) for s in steps], n_actions)
    patterns, pattern_of = distinct_columns(np.concatenate([s[3] for s in steps], axis=1))
    episode_of = np.concatenate([s[4] for s in steps])
    followed = _followed_by_group(patterns, pattern_of, episode_of // episodes, n_runs)
    order = np.argsort(episode_of, kind="stable")  # episode by episode, each in step order
    bounds = np.searchsorted(episode_of[order], np.arange(n_runs + 1) * episodes).tolist()
    runs = []
    for run, start, stop in zip(followed, bounds[:-1], bounds[1:], strict=True):
        rows = order[start:stop]
        if not len(rows):
            runs.append((frozenset(), NO_DECISIONS))
            continue
        runs.append((run, (observations[rows], None if masks is None else masks[rows], actions[rows])))
    return runs


def _followed_by_group(
    patterns: list[frozenset[int]], pattern_of: np.ndarray, group_of: np.ndarray, n_groups: int
) -> list[frozenset[frozenset[int]]]:
    """
    The sets of members followed in each group of decisions, from :func:`~sb3_sfgpi.gpi_decisions.distinct_columns`'
    sets and each decision's set (``pattern_of``) and group (``group_of``, in ``0..n_groups-1``): one pass for all.
    """
    pairs = np.unique(group_of * len(patterns) + pattern_of)  # each (group, set) once
    followed: list[list[frozenset[int]]] = [[] for _ in range(n_groups)]
    for group, k in zip((pairs // len(patterns)).tolist(), (pairs % len(patterns)).tolist(), strict=True):
        followed[group].append(patterns[k])
    return [frozenset(sets) for sets in followed]


@lru_cache(maxsize=1 << 14)
def _without(sets: frozenset[frozenset[int]], member: int) -> frozenset[frozenset[int]]:
    """
    The followed sets of a set's episodes, in the indices of the set without ``member`` (episodes unchanged); cached:
    most weights follow the same few sets, and pruning asks for every member of every weight.
    """
    return frozenset(frozenset(j - (j > member) for j in members if j != member) for members in sets)


class ValidationScorer:
    """
    GPI over a policy set on validation weights, every agent acting by it; the episodes of weight ``i`` start from
    ``derive_seed(seed, purpose, i)`` (the score of :func:`~sb3_sfgpi.evaluation.gpi_score`).

    :param weights: the validation weights, shape ``(n, d)``
    :param rollout: runs a joint policy for some episodes from a seed
    :param episodes: episodes per weight
    :param seed: the run's seed
    :param purpose: what the episodes are for (a part of their seeds)
    :param lockstep: runs the episodes of several weights together, one batched GPI decision a step, where it can
        (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.lockstep`): the same episodes and decisions as one weight after
        another
    :param gpi_episodes: runs GPI's episodes over a set of tables in one compiled call where it can
        (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.gpi_episodes`): the same episodes and decisions again
    """

    def __init__(
        self,
        weights: np.ndarray,
        rollout: Rollout,
        episodes: int,
        seed: int,
        purpose: str = "validation",
        lockstep: Lockstep | None = None,
        gpi_episodes: GPIEpisodesRunner | None = None,
    ):
        self.weights = np.asarray(weights, dtype=np.float64)
        self.rollout, self.episodes, self.lockstep, self.gpi_episodes = rollout, episodes, lockstep, gpi_episodes
        self.seeds = [derive_seed(seed, purpose, i) for i in range(len(self.weights))]
        #: weights rolled out so far (one call of ``rollout`` each)
        self.rollouts = 0

    def __call__(self, policy_set: GPIPolicy) -> Scored:
        """GPI's episodes over ``policy_set`` at every weight."""
        return self._scored(self._runs(policy_set, list(range(len(self.weights)))))

    def replayed(self, policy_set: GPIPolicy, scored: Scored) -> Scored:
        """
        What ``policy_set`` scores, from another set's episodes ``scored`` (e.g. Π's, for Π and new policies): GPI over
        ``policy_set`` acts on every weight's decisions' observations in one batch (each row with its weight); at a
        weight where it takes the same actions, its episodes are those ones; elsewhere they are rolled out. Tables
        only (their values of a batch are those of each observation alone); other sets are rolled out at every weight.
        """
        if not isinstance(policy_set.networks[0], TabularSFNetwork):
            return self(policy_set)
        decided = [i for i, (_, _, actions) in enumerate(scored.decisions) if len(actions)]
        runs: list[Run | None] = [(r, frozenset(), d) for r, d in zip(scored.returns, scored.decisions, strict=True)]
        if decided:
            again, members = self._decided_again(policy_set, scored, decided)
            for i in decided:
                same = np.array_equal(again[i], scored.decisions[i][2])
                runs[i] = (scored.returns[i], members[i], scored.decisions[i]) if same else None
        redo = [i for i, run in enumerate(runs) if run is None]
        for i, run in zip(redo, self._runs(policy_set, redo), strict=True):
            runs[i] = run
        return self._scored(runs)  # type: ignore[arg-type]

    def _decided_again(
        self, policy_set: GPIPolicy, scored: Scored, decided: list[int]
    ) -> tuple[dict[int, np.ndarray], dict[int, frozenset[frozenset[int]]]]:
        """GPI over ``policy_set`` on the decisions of the weights ``decided``, in one batch: its actions and the
        members it followed, per weight."""
        trace = [Decisions(*scored.decisions[i], []) for i in decided]
        lengths = [len(step.actions) for step in trace]
        masks = _masks_of(trace, policy_set.action_space.n)
        rows = np.repeat(self.weights[decided], lengths, axis=0)
        observations = np.concatenate([step.observations for step in trace])
        again, attaining = policy_set.predict_attaining(observations, rows, masks, per_row=True)
        patterns, pattern_of = distinct_columns(attaining)
        followed = _followed_by_group(patterns, pattern_of, np.repeat(np.arange(len(decided)), lengths), len(decided))
        bounds = np.cumsum([0, *lengths]).tolist()
        actions_of = {i: again[start:stop] for i, start, stop in zip(decided, bounds[:-1], bounds[1:], strict=True)}
        return actions_of, dict(zip(decided, followed, strict=True))

    def without(self, policy_set: GPIPolicy, scored: Scored, member: int) -> Scored:
        """
        What ``policy_set`` without its ``member`` scores, from ``scored`` (``policy_set``'s own): only the weights
        at which the member was decisive (:meth:`Scored.decisive`) are rolled out again.
        """
        again = scored.decisive(member)
        rolled = self._runs(policy_set.without(member), again) if again else []
        return self._replaced(scored, member, dict(zip(again, rolled, strict=True)))

    def without_each(self, policy_set: GPIPolicy, scored: Scored) -> list[Scored]:
        """
        :meth:`without` of every member of ``policy_set``, the weights at which any member was decisive rolled out
        together in one lockstep where the runner can (each row acting by GPI without its member): the same scores.
        """
        pairs = [(member, i) for member in range(len(policy_set)) for i in scored.decisive(member)]
        together = None
        if self._runs_together and len(pairs) > 1:
            together = self._together(policy_set, [i for _, i in pairs], [member for member, _ in pairs])
        if together is None:
            return [self.without(policy_set, scored, member) for member in range(len(policy_set))]
        rolled: list[dict[int, Run]] = [{} for _ in range(len(policy_set))]
        for (member, i), (returns, followed, decided) in zip(pairs, together, strict=True):
            rolled[member][i] = (returns, _without(followed, member), decided)  # in the indices of the set without it
        return [self._replaced(scored, member, runs) for member, runs in enumerate(rolled)]

    def _replaced(self, scored: Scored, member: int, rolled: dict[int, Run]) -> Scored:
        """
        ``scored`` without ``member``: its members followed in the indices of the set without it, and the runs of the
        weights in ``rolled`` (those at which the member was decisive, rolled out again) in place of its own.
        """
        followed = tuple(_without(sets, member) for sets in scored.followed)
        if not rolled:
            return Scored(scored.score, scored.returns, followed, scored.decisions)
        runs = list(zip(scored.returns, followed, scored.decisions, strict=True))
        for i, run in rolled.items():
            runs[i] = run
        return self._scored(runs)

    def _runs(self, policy_set: GPIPolicy, indices: list[int]) -> list[Run]:
        """The episodes of the weights ``indices``: together where the runner can, else one weight after another."""
        together = self._together(policy_set, indices) if self._runs_together and len(indices) > 1 else None
        return together if together is not None else [self._episodes(policy_set, i) for i in indices]

    @property
    def _runs_together(self) -> bool:
        """Whether the runner can run several weights' episodes together (compiled or in lockstep)."""
        return self.lockstep is not None or self.gpi_episodes is not None

    def _together(
        self, policy_set: GPIPolicy, indices: list[int], left_out: list[int] | None = None
    ) -> list[Run] | None:
        """
        Every weight's episodes run together, each decision traced to its episode: in one compiled call where the
        runner can (:data:`~sb3_sfgpi.evaluation.GPIEpisodesRunner`), else stepped in lockstep; None: neither.

        :param left_out: for each weight of ``indices``, a member GPI acts without in its episodes (their members
            followed in the set's indices, the member left out never among them), or None: the whole set
        """
        n = self.episodes
        seeds = [self.seeds[i] + episode for i in indices for episode in range(n)]
        weights = np.repeat(self.weights[indices], n, axis=0)
        without = np.repeat(np.asarray([-1] * len(indices) if left_out is None else left_out, dtype=np.int64), n)
        ran = None if self.gpi_episodes is None else self.gpi_episodes(policy_set, weights, without, seeds, n)
        if ran is not None:
            returns, episodes = ran
            steps = [(episodes.observations, None, episodes.actions, episodes.attaining, episodes.episodes)]
        else:
            stepped, steps = self._stepped_together(policy_set, weights, without, seeds)
            if stepped is None:
                return None
            returns = stepped
        self.rollouts += len(indices)
        decisions = _runs_decisions(steps, len(indices), n, policy_set.action_space.n)
        return [(result, *decided) for result, decided in zip(returns, decisions, strict=True)]

    def _stepped_together(
        self, policy_set: GPIPolicy, weights: np.ndarray, left_out: np.ndarray, seeds: list[int]
    ) -> tuple[list[EpisodeReturns] | None, list[tuple[Any, ...]]]:
        """The episodes in the runner's lockstep, one batched GPI decision a step: the returns and the decision steps
        (observations, masks, actions, members attaining GPI's value and each row's episode)."""
        steps: list[tuple[Any, ...]] = []
        last: list[Any] = []
        if self.lockstep is None:
            return None, steps

        def act(obs: np.ndarray, rows: np.ndarray, masks: np.ndarray | None, _: list[str]) -> np.ndarray:
            # each row's weights, then the member it acts without as a last column
            without = rows[:, -1].astype(np.int64)
            actions, attaining = policy_set.predict_attaining(obs, rows[:, :-1], masks, per_row=True, left_out=without)
            last[:] = [obs, masks, actions, attaining]
            return actions

        def decided(episodes: list[int]) -> None:
            steps.append((*last, np.asarray(episodes, dtype=np.int64)))

        rows = np.column_stack([weights, left_out.astype(np.float64)])
        returns = self.lockstep(act, rows, seeds, self.episodes, decided)  # type: ignore[misc]
        return returns, steps

    def _episodes(self, policy_set: GPIPolicy, i: int) -> Run:
        trace: list[Decisions] = []
        self.rollouts += 1
        policy = policy_set.joint_policy(self.weights[i], trace=trace)
        return self._run(self.rollout(policy, self.episodes, self.seeds[i]), trace, policy_set)

    def _run(self, returns: EpisodeReturns, trace: list[Decisions], policy_set: GPIPolicy) -> Run:
        """One weight's run from its episodes' returns and decisions."""
        if not trace:  # no decision (episodes that end at reset)
            return returns, frozenset(), NO_DECISIONS
        observations = np.concatenate([step.observations for step in trace])
        actions = np.concatenate([step.actions for step in trace])
        followed = frozenset(m for step in trace for m in step.followed)
        return returns, followed, (observations, _masks_of(trace, policy_set.action_space.n), actions)

    def _scored(self, runs: Sequence[Run]) -> Scored:
        returns = tuple(r for r, _, _ in runs)
        score = mean_return(self.weights, returns)
        return Scored(score, returns, tuple(f for _, f, _ in runs), tuple(d for _, _, d in runs))
