"""GPI's evaluation after every iteration: the test weights' episodes and their summary, and validation's score.

:class:`EvaluationConfig` says how GPI over Π is evaluated; :class:`TestEvaluation` runs it (in this process, with
every weight's episodes in lockstep where it can, or as jobs in worker processes: :mod:`sb3_sfgpi.evaluation_jobs`)
and :func:`summarize_test_episodes` gives its metrics (:func:`mean_return` the one validation compares).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from sb3_sfgpi.common.metrics import expected_utility
from sb3_sfgpi.common.rollouts import EpisodeReturns, JointPolicy
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.serialization import jsonable
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.evaluation_jobs import EvaluationJob, ParallelEvaluator
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_settings import RunSettings

if TYPE_CHECKING:
    from sb3_sfgpi.tabular.gpi_episodes import GPIEpisodes

#: Runs a joint policy for some episodes from a seed (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.rollout`).
Rollout = Callable[[JointPolicy, int, int], EpisodeReturns]
#: Runs episodes for many weights together, one batched decision a step, where it can (else None): ``lockstep(policy,
#: weights, seeds, per_result, decided=None)`` (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.lockstep`).
Lockstep = Callable[..., list[EpisodeReturns] | None]
#: Runs GPI's episodes over a set of tables in one compiled call where it can (else None): ``gpi_episodes(policy_set,
#: weights, left_out, seeds, per_result)`` (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.gpi_episodes`).
GPIEpisodesRunner = Callable[..., "tuple[list[EpisodeReturns], GPIEpisodes] | None"]


def summarize_test_episodes(
    weights: np.ndarray, results: Sequence[EpisodeReturns]
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """
    What GPI reached on the test weights: the summary metrics and, per weight and agent, the vector returns.

    :param weights: the test weights, shape ``(n, d)``
    :param results: the episodes of agents acting by GPI for each weight
    :return: ``mean_return`` (mean over weights and agents of w · discounted return),
        ``mean_return_undiscounted`` (the same with plain sums of rewards) and ``expected_utility`` (of the
        agents' mean return); and the JSON-compatible details, one entry per weight
    """
    disc, undisc = _agents_means(results, discounted=True), _agents_means(results, discounted=False)
    details = [
        {
            "weights": w.tolist(),
            "agents": {
                a: {"discounted": d.tolist(), "undiscounted": u.tolist()}
                for a, d, u in zip(r.discounted, dw, uw, strict=True)
            },
            "final_infos": jsonable(r.final_infos),
        }
        for w, r, dw, uw in zip(weights, results, disc, undisc, strict=True)
    ]
    metrics = {
        "mean_return": _mean_return(weights, disc),
        "mean_return_undiscounted": _mean_return(weights, undisc),
        "expected_utility": expected_utility(weights, disc.mean(axis=1)),
    }
    return metrics, details


def mean_return(weights: np.ndarray, results: Sequence[EpisodeReturns]) -> float:
    """
    ``mean_return`` of :func:`summarize_test_episodes` alone (what policy validation compares), without the details.
    """
    return _mean_return(weights, _agents_means(results, discounted=True))


def _agents_means(results: Sequence[EpisodeReturns], discounted: bool) -> np.ndarray:
    """Each weight's agents' mean (discounted) vector returns, shape ``(n_weights, n_agents, d)``."""
    return np.array(
        [[r.mean_discounted(a) if discounted else r.mean_undiscounted(a) for a in r.discounted] for r in results]
    )


def _mean_return(weights: np.ndarray, returns: np.ndarray) -> float:
    """The mean over weights and agents of ``w · return``, from returns of shape ``(n_weights, n_agents, d)``."""
    d = weights.shape[1]
    per_agent_w = np.repeat(weights[:, None, :], returns.shape[1], axis=1).reshape(-1, d)
    return expected_utility(per_agent_w, returns.reshape(-1, d))


def gpi_score(
    policy_set: GPIPolicy,
    weights: np.ndarray,
    rollout: Rollout,
    episodes: int,
    seed: int,
    purpose: str,
) -> float:
    """
    GPI over ``policy_set`` at every weight, all agents acting by it: the mean over weights and agents of the
    discounted w·return (``mean_return`` of :func:`summarize_test_episodes`; what policy validation compares).

    :param rollout: runs a joint policy for some episodes from a seed (:meth:`MultiAgentRunner.rollout`)
    :param episodes: episodes per weight
    :param seed: the run's seed: the episodes of weight ``i`` start from ``derive_seed(seed, purpose, i)``
    :param purpose: what the episodes are for (``"validation"``, ``"eval"``)
    """
    returns = [
        rollout(policy_set.joint_policy(w), episodes, derive_seed(seed, purpose, i)) for i, w in enumerate(weights)
    ]
    return mean_return(weights, returns)


# --- GPI on the test weights after every iteration -------------------------------------------------------
@dataclass(frozen=True)
class EvaluationConfig:
    """
    How GPI over Π is evaluated after every iteration.

    :param test_weights: the weights GPI acts for, shape ``(n, d)`` (:class:`~sb3_sfgpi.masfols.MASFOLS` also takes
        a number of Dirichlet(1) weights, or None for its default)
    :param episodes: episodes per test weight
    :param policies: ``"shared"``: every agent acts by GPI over the whole Π; ``"own"``: each agent over the
        policies it learned itself (the evaluation of independent fixed-weight learners)
    :param gpi_set: ``"all"`` of Π, or only the policies whose values form Π's CCS (``"ccs"``)
    :param workers: 0: in this process on the training env; ``n > 0``: in ``n`` worker processes (kept for the
        whole run), each with its own env ``env_fn(**env_kwargs)``; they load Π from the run directory
    :param env_fn: picklable env constructor of the workers (required when ``workers > 0``)
    :param env_kwargs: its keyword arguments (they should build the same env as the training one)
    :param hypervolume_reference: reference point of the hypervolume of Π's CCS (None: not computed)
    """

    test_weights: Any = None
    episodes: int = RunSettings.eval_episodes
    policies: str = "shared"
    gpi_set: str = RunSettings.gpi_set
    workers: int = 0
    env_fn: Callable[..., Any] | None = None
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    hypervolume_reference: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.test_weights is not None and np.ndim(self.test_weights) > 0:
            object.__setattr__(self, "test_weights", np.asarray(self.test_weights, dtype=np.float64))
        if self.policies not in ("shared", "own"):
            raise ValueError(f"policies must be 'shared' or 'own', got {self.policies!r}")
        if self.gpi_set not in ("all", "ccs"):
            raise ValueError(f"gpi_set must be 'all' or 'ccs', got {self.gpi_set!r}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ValueError(f"workers must be a non-negative integer, got {self.workers!r}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")

    @property
    def ccs_only(self) -> bool:
        """Whether GPI acts over Π's CCS only (never for ``policies="own"``)."""
        return self.gpi_set == "ccs" and self.policies != "own"


class TestEvaluation:
    """
    GPI over Π on the test weights (the curve of the paper's Figs. 4 and 7): for each test weight every agent
    acts by GPI, in this process or in worker processes kept for the whole run.

    :param config: what to evaluate and where
    :param rollout: runs a joint policy on the training env (the in-process evaluation)
    :param reward_dim: the number of objectives (the test weights are checked against it)
    :param seed: the run's seed: the episodes of test weight ``i`` start from ``derive_seed(seed, "eval", i)``
    :param agents: the env's agents (for ``policies="own"``)
    :param lockstep: where given, the in-process episodes of every test weight run together by it (the same
        returns, one batched GPI decision a step)
    :raises ValueError: a test weight of the wrong length, negative or all zero
    """

    __test__ = False  # not a pytest test class

    def __init__(
        self,
        config: EvaluationConfig,
        rollout: Rollout,
        reward_dim: int,
        seed: int,
        agents: list[str],
        lockstep: Lockstep | None = None,
    ):
        if config.workers > 0 and config.env_fn is None:
            raise ValueError("an evaluation with workers > 0 needs env_fn (and env_kwargs) to build the workers' envs")
        if config.test_weights is None or np.ndim(config.test_weights) != 2:
            raise ValueError(f"test_weights must be an array of shape (n, d), got {config.test_weights!r}")
        self.config = config
        self.weights = np.array([validate_weights(w, reward_dim, "test weight") for w in config.test_weights])
        self.seeds = [derive_seed(seed, "eval", i) for i in range(len(self.weights))]
        self._rollout, self._agents, self._lockstep = rollout, agents, lockstep
        self._pool: ParallelEvaluator | None = None

    def policies(self, policy_set: GPIPolicy) -> GPIPolicy:
        """The policies GPI acts over: Π, or its CCS (``gpi_set="ccs"``)."""
        return policy_set.ccs_policies() if self.config.ccs_only else policy_set

    def run(
        self, policy_set: GPIPolicy, policy_dir: Path | None, gamma: float, progress_bar: bool = False
    ) -> tuple[dict[str, float], list[dict[str, Any]]]:
        """
        Evaluate GPI over ``policy_set`` (saved in ``policy_dir`` for the workers).

        :param gamma: discount of the returns (the workers')
        :return: the summary metrics and the per-weight details (:func:`summarize_test_episodes`)
        """
        return summarize_test_episodes(self.weights, self._episodes(policy_set, policy_dir, gamma, progress_bar))

    def _episodes(
        self, policy_set: GPIPolicy, policy_dir: Path | None, gamma: float, progress_bar: bool
    ) -> list[EpisodeReturns]:
        config, own = self.config, self.config.policies == "own"
        if config.workers > 0:
            assert policy_dir is not None and config.env_fn is not None
            if self._pool is None:
                self._pool = ParallelEvaluator(config.env_fn, config.env_kwargs, config.workers, gamma)
            jobs = [
                EvaluationJob(seed, tuple(w), config.episodes, str(policy_dir), own, ccs_only=config.ccs_only)
                for w, seed in zip(self.weights, self.seeds, strict=True)
            ]
            return self._pool.run(jobs)
        acting, agents = self.policies(policy_set), self._agents if own else None
        if self._lockstep is not None and not own:
            episodes = config.episodes
            seeds = [seed + episode for seed in self.seeds for episode in range(episodes)]
            weights = np.repeat(self.weights, episodes, axis=0)
            together = self._lockstep(lambda o, w, m, _: acting.predict_rows(o, w, m), weights, seeds, episodes)
            if together is not None:
                return together
        bar = tqdm(self.weights, desc="evaluating GPI", unit="w", leave=False, disable=not progress_bar)
        return [
            self._rollout(acting.joint_policy(w, agents), config.episodes, seed)
            for w, seed in zip(bar, self.seeds, strict=True)
        ]

    def close(self) -> None:
        """Stop the worker processes, if any (a later :meth:`run` starts new ones)."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None
