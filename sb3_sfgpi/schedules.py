"""Where the weights of the next iteration come from (the paper's Algorithm 1, lines 6-14, and its baselines).

Every schedule records the value vectors of the policies trained so far in an :class:`~sb3_sfgpi.ols.OLS`: the
rule that a policy joins Π only when its value is new, and the CCS reported after every iteration, are the same
for all of them. They differ in the weights they hand out:

* :class:`OLSSchedule` (MA-SFOLS): the corner weights of highest optimistic priority, simplex extrema first, one
  per agent (``batch="top"``, Algorithm 1), with Dirichlet(1) random weights for the agents beyond the queue; or,
  once the simplex extrema are handed out, the one corner weight of highest priority for every agent
  (``batch="same-after-extrema"``); None (stop) when the queue is empty.
* :class:`RandomSchedule` (Random + GPI): Dirichlet(1) random weights for every agent, never stops by itself.
* :class:`FixedSchedule` (a priori scalarised learners): the same weights for every agent in every iteration;
  every policy joins Π.

A schedule's state (kind, its own settings and the OLS) goes into the run's checkpoint; restoring it checks that
the checkpoint was written by the same kind of schedule with the same settings.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np

from sb3_sfgpi.common.weights import random_weights, validate_weights
from sb3_sfgpi.ols import OLS, TOLERANCE
from sb3_sfgpi.run_settings import OLS_BATCHES

#: agent -> the weights it trains for in the next iteration
AgentWeights = dict[str, np.ndarray]


class WeightSchedule(ABC):
    """
    Base class: hands every agent its weights and records the values of the policies trained.

    :param tolerance: the tolerance of the OLS that records the values (equal values, CCS membership)
    """

    #: the name stored in checkpoints
    kind: str = ""
    #: whether every trained policy joins Π, or only those whose value is new
    keeps_every_policy: bool = False

    def __init__(self, tolerance: float = TOLERANCE):
        self.tolerance = tolerance
        self._ols: OLS | None = None

    @property
    def ols(self) -> OLS:
        """The OLS holding the values recorded so far (created by :meth:`start`)."""
        if self._ols is None:
            raise ValueError(f"{type(self).__name__} has not been started: call start(reward_dim) first")
        return self._ols

    def start(self, reward_dim: int) -> None:
        """
        Begin a run with ``reward_dim`` objectives (forgets what was recorded before).

        :raises ValueError: settings that do not fit ``reward_dim``
        """
        self._ols = OLS(reward_dim, tolerance=self.tolerance)

    @abstractmethod
    def next_weights(self, agents: Sequence[str], rng: np.random.Generator) -> AgentWeights | None:
        """
        The weights of the next iteration.

        :param agents: the agents, in order (the first gets the weight of highest priority)
        :param rng: source of the random weights
        :return: agent -> weights, or None when the schedule has ended
        """

    def add(self, value: np.ndarray, weights: np.ndarray) -> bool:
        """
        Record the value vector ``V^π`` of a policy trained for ``weights`` (Algorithm 1, line 20).

        :return: whether the policy joins Π (its value is new, or the schedule keeps every policy)
        """
        n_values = len(self.ols.values)
        self.ols.add_solution(value, weights)
        return len(self.ols.values) > n_values or self.keeps_every_policy

    def state_dict(self) -> dict[str, Any]:
        """JSON-compatible state: the kind, the settings and the recorded values (OLS)."""
        return {"kind": self.kind, **self._settings(), "ols": self.ols.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        Restore what :meth:`state_dict` returned.

        :raises ValueError: a state of another kind of schedule or with other settings
        """
        if not isinstance(state, dict) or state.get("kind") != self.kind:
            kind = state.get("kind") if isinstance(state, dict) else state
            raise ValueError(f"the checkpoint holds a {kind!r} schedule, not {self.kind!r}")
        for key, mine in self._settings().items():
            saved = state.get(key)
            if not _same_setting(saved, mine):
                raise ValueError(f"the checkpoint's schedule has {key}={saved}, not {mine}")
        try:
            ols = OLS.from_state_dict(state["ols"])
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"the checkpoint's OLS state is malformed: {error!r}") from error
        if ols.reward_dim != self.ols.reward_dim:
            raise ValueError(f"the checkpoint's OLS has {ols.reward_dim} objectives, the env {self.ols.reward_dim}")
        self._ols = ols

    def _settings(self) -> dict[str, Any]:
        return {}


class OLSSchedule(WeightSchedule):
    """
    MA-SFOLS: corner weights by OLS priority, one per agent; random weights for the agents beyond the queue.

    :param batch: how a round's weights are taken from the queue: ``"top"``, the highest stored priorities
        (Algorithm 1); ``"same-after-extrema"``, ``"top"`` while a simplex extremum heads the queue (the first
        rounds cover the simplex as Algorithm 1's do), after that the weight of highest priority for every agent, so
        that a round's policies are learned beside partners acting for their weight, as all agents act for one
        weight at execution
    :param tolerance: see :class:`WeightSchedule`
    """

    kind = "ols"

    def __init__(self, batch: str = "top", tolerance: float = TOLERANCE):
        if batch not in OLS_BATCHES:
            raise ValueError(f"batch must be one of {OLS_BATCHES}, got {batch!r}")
        super().__init__(tolerance)
        self.batch = batch

    def next_weights(self, agents: Sequence[str], rng: np.random.Generator) -> AgentWeights | None:
        queue = self.ols.queue
        if not queue:
            return None
        if self.batch == "same-after-extrema" and not math.isinf(queue[0][0]):
            first = self.ols.next_weight()
            return {agent: first.copy() for agent in agents}
        weights = {agents[0]: self.ols.next_weight()}
        for agent in agents[1:]:
            w = self.ols.next_weight()
            weights[agent] = random_weights(self.ols.reward_dim, rng=rng) if w is None else w
        return weights

    def _settings(self) -> dict[str, Any]:
        return {"batch": self.batch}


class RandomSchedule(WeightSchedule):
    """Random + GPI: Dirichlet(1) weights for every agent in every iteration."""

    kind = "random"

    def next_weights(self, agents: Sequence[str], rng: np.random.Generator) -> AgentWeights | None:
        return {agent: random_weights(self.ols.reward_dim, rng=rng) for agent in agents}


class FixedSchedule(WeightSchedule):
    """
    A priori scalarisation: every agent trains for the same ``weights`` in every iteration; every policy joins Π.

    :param weights: the preference weights (validated against the env's number of objectives at :meth:`start`)
    """

    kind = "fixed"
    keeps_every_policy = True

    def __init__(self, weights: np.ndarray | Sequence[float], tolerance: float = TOLERANCE):
        super().__init__(tolerance)
        self.weights = np.asarray(weights, dtype=np.float64)

    def start(self, reward_dim: int) -> None:
        self.weights = validate_weights(self.weights, reward_dim, "fixed weights")
        super().start(reward_dim)

    def next_weights(self, agents: Sequence[str], rng: np.random.Generator) -> AgentWeights | None:
        self.ols  # noqa: B018 -- raises before start(): the weights are validated there
        return {agent: self.weights.copy() for agent in agents}

    def _settings(self) -> dict[str, Any]:
        return {"weights": self.weights.tolist()}


def _same_setting(saved: Any, mine: Any) -> bool:
    if isinstance(mine, str):
        return saved == mine
    try:
        return np.shape(saved) == np.shape(mine) and bool(np.allclose(np.asarray(saved, dtype=np.float64), mine))
    except (TypeError, ValueError):
        return False


def make_schedule(
    weights: str | np.ndarray | Sequence[float], ols_batch: str = "top", tolerance: float = TOLERANCE
) -> WeightSchedule:
    """
    A schedule from its short description.

    :param weights: ``"ols"`` (MA-SFOLS), ``"random"`` (Random + GPI) or the weights of a :class:`FixedSchedule`
    :param ols_batch: the ``batch`` of an :class:`OLSSchedule` (only for ``"ols"``)
    :raises ValueError: an unknown name; ``ols_batch`` other than ``"top"`` for a schedule without OLS weights
    """
    if isinstance(weights, str) and weights == "ols":
        return OLSSchedule(ols_batch, tolerance)
    if ols_batch != "top":
        raise ValueError(f"ols_batch={ols_batch!r} is only for OLS weights (weights='ols'), not {weights!r}")
    if isinstance(weights, str):
        if weights != "random":
            raise ValueError(f"weights must be 'ols', 'random' or array-like weights, got {weights!r}")
        return RandomSchedule(tolerance)
    return FixedSchedule(weights, tolerance)
