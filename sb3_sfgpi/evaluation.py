"""GPI (and controller) episodes as jobs, run in this process or in a pool of worker processes.

:class:`EvaluationJob`, :func:`run_job`, :class:`ParallelEvaluator` and :func:`evaluate_gpi_parallel` run
evaluations in a pool of spawned worker processes. Each worker builds its own env from a picklable constructor and
keyword arguments (simulators such as libsumo hold one simulation per process) and loads the policy set from a
policy-set directory (:meth:`~sb3_sfgpi.gpi.GPIPolicy.load`). Results equal those of the same job run in-process
(:func:`run_job`) with the same policy set and seeds.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv
from tqdm.auto import tqdm

from sb3_sfgpi.common.metrics import expected_utility
from sb3_sfgpi.common.parallel_wrappers import as_parallel_env
from sb3_sfgpi.common.rollouts import EpisodeReturns, JointPolicy, RowPolicy, run_episodes
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.serialization import jsonable
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.policy_set_files import manifest_path
from sb3_sfgpi.run_settings import GAMMA, RunSettings

#: Runs a joint policy for some episodes from a seed (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.rollout`).
Rollout = Callable[[JointPolicy, int, int], EpisodeReturns]
#: Runs episodes for many weights together, one batched decision a step, where it can (else None): ``lockstep(policy,
#: weights, seeds, per_result)`` (:meth:`~sb3_sfgpi.multiagent.MultiAgentRunner.lockstep`).
Lockstep = Callable[[RowPolicy, np.ndarray, list[int], int], list[EpisodeReturns] | None]


def _no_actions(observations: dict[str, Any], action_masks: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """No action for anyone, whatever the masks: the env's own controller acts (e.g. SUMO's programs)."""
    return {}


# --- evaluation jobs, in-process or in worker processes ---------------------------------------------------
@dataclass(frozen=True)
class EvaluationJob:
    """
    One evaluation: ``n_episodes`` episodes from ``seed`` (episode ``i`` resets with ``seed + i``).

    :param seed: seed of the first episode
    :param weights: preference weights GPI acts for; None: no policy, every agent sends no action (for envs whose
        own controller then acts, such as the traffic env's fixed-time and actuated programs)
    :param n_episodes: number of episodes
    :param policy_dir: the policy set to act with, its directory or manifest (required with ``weights``; a worker
        loads it)
    :param own_policies: each agent acts by GPI over the policies it learned itself only
    :param ccs_only: act by GPI over the policies of the set's CCS only (:meth:`~sb3_sfgpi.gpi.GPIPolicy.ccs_policies`)
    :param env_overrides: keyword arguments of the env replacing the evaluator's for this job
    :param record_infos: keep the per-step infos (:attr:`EpisodeReturns.step_infos`)
    """

    seed: int
    weights: tuple[float, ...] | None = None
    n_episodes: int = 1
    policy_dir: str | None = None
    own_policies: bool = False
    env_overrides: tuple[tuple[str, Any], ...] = ()
    record_infos: bool = False
    ccs_only: bool = False

    def __post_init__(self) -> None:
        if self.n_episodes < 1:
            raise ValueError(f"n_episodes must be at least 1, got {self.n_episodes}")
        if self.weights is not None and self.policy_dir is None:
            raise ValueError("an evaluation job with weights needs the policy_dir of the policy set to act with")
        if self.weights is not None:
            object.__setattr__(self, "weights", tuple(float(x) for x in self.weights))
        if isinstance(self.env_overrides, Mapping):
            object.__setattr__(self, "env_overrides", tuple(sorted(self.env_overrides.items())))


def run_job(env: ParallelEnv, job: EvaluationJob, gamma: float, policy_set: GPIPolicy | None = None) -> EpisodeReturns:
    """
    Run an evaluation job in this process, on ``env`` (which must already carry ``job.env_overrides``).

    :param env: the env
    :param job: the job
    :param gamma: discount of the discounted returns
    :param policy_set: the policy set to act with (default: loaded from ``job.policy_dir``)
    """
    if job.weights is None:
        policy: JointPolicy = _no_actions
    else:
        if policy_set is None:
            policy_set = GPIPolicy.load(job.policy_dir)  # type: ignore[arg-type]
        if job.ccs_only:
            policy_set = policy_set.ccs_policies()
        policy = policy_set.joint_policy(job.weights, list(env.possible_agents) if job.own_policies else None)
    return run_episodes(env, policy, job.n_episodes, gamma, seed=job.seed, record_infos=job.record_infos)


# State of a worker process: its env (one at a time: libsumo holds one simulation per process) and the last
# policy set it loaded.
_worker: dict[str, Any] = {}


def _exit_with_parent(parent: int) -> None:
    """Leave as soon as the parent process is gone (a killed parent would otherwise leave idle workers behind)."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(0)


def _init_worker(
    env_fn: Callable[..., ParallelEnv], env_kwargs: dict[str, Any], gamma: float, threads: int, parent: int
) -> None:
    import torch as th

    th.set_num_threads(threads)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True, name="exit-with-parent").start()
    _worker.clear()
    _worker.update(env_fn=env_fn, env_kwargs=dict(env_kwargs), gamma=gamma, env=None, env_key=None, sets={})


def _worker_env(overrides: tuple[tuple[str, Any], ...]) -> ParallelEnv:
    if _worker["env"] is None or _worker["env_key"] != overrides:
        if _worker["env"] is not None:
            _worker["env"].close()
            _worker["env"] = None
        _worker["env"] = as_parallel_env(_worker["env_fn"](**{**_worker["env_kwargs"], **dict(overrides)}))
        _worker["env_key"] = overrides
    return _worker["env"]


def _worker_policy_set(policy_dir: str) -> GPIPolicy:
    manifest = manifest_path(Path(policy_dir)).read_bytes()  # the manifest names every file of the set
    cached = _worker["sets"].get(policy_dir)
    if cached is None or cached[0] != manifest:
        cached = (manifest, GPIPolicy.load(policy_dir))
        _worker["sets"] = {policy_dir: cached}
    return cached[1]


def _run_job_in_worker(job: EvaluationJob) -> EpisodeReturns:
    env = _worker_env(job.env_overrides)
    policy_set = None if job.weights is None else _worker_policy_set(job.policy_dir)  # type: ignore[arg-type]
    return run_job(env, job, _worker["gamma"], policy_set)


class ParallelEvaluator:
    """
    A pool of ``workers`` spawned processes running :class:`EvaluationJob` s, each on its own env.

    Each worker builds its env once from ``env_fn(**env_kwargs, **job.env_overrides)`` (a job with other
    overrides closes it and builds a new one) and caches the last policy set it loaded (reloaded when the
    directory's manifest changes), so the pool can be kept across many evaluations. If a worker dies (e.g. the
    simulator crashes the process), the pool is restarted and the evaluation retried once.

    :param env_fn: a picklable env constructor (a class or a module-level function)
    :param env_kwargs: its keyword arguments (picklable)
    :param workers: number of processes
    :param gamma: discount of the discounted returns
    :param threads: torch threads per worker
    """

    def __init__(
        self,
        env_fn: Callable[..., ParallelEnv],
        env_kwargs: Mapping[str, Any] | None = None,
        workers: int = 2,
        gamma: float = GAMMA,
        threads: int = 1,
    ):
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.env_fn = env_fn
        self.env_kwargs = dict(env_kwargs or {})
        self.workers = workers
        self.gamma = gamma
        self.threads = threads
        self._executor: ProcessPoolExecutor | None = None

    def _pool(self) -> ProcessPoolExecutor:
        if self._executor is None:
            self._executor = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker,
                initargs=(self.env_fn, self.env_kwargs, self.gamma, self.threads, os.getpid()),
            )
        return self._executor

    def run(self, jobs: Sequence[EvaluationJob]) -> list[EpisodeReturns]:
        """
        Run the jobs on the workers.

        :return: the results, in the order of ``jobs``
        :raises RuntimeError: a worker died twice in a row; any exception a job raised is re-raised as is
        """
        jobs = list(jobs)
        for attempt in range(2):
            try:
                futures = [self._pool().submit(_run_job_in_worker, job) for job in jobs]
                return [future.result() for future in futures]
            except BrokenProcessPool as error:
                self.close()
                if attempt == 1:
                    raise RuntimeError(f"an evaluation worker process died twice in a row: {error}") from error
        raise AssertionError("unreachable")

    def close(self) -> None:
        """Stop the workers (their envs are closed as the processes exit). The next :meth:`run` starts new ones."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> ParallelEvaluator:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def evaluate_gpi_parallel(
    env_fn: Callable[..., ParallelEnv],
    env_kwargs: Mapping[str, Any] | None,
    policy_dir: str | Path,
    weights: Sequence[Sequence[float]] | np.ndarray,
    gamma: float,
    seeds: Sequence[int],
    n_episodes: int = 1,
    workers: int = 2,
    own_policies: bool = False,
    record_infos: bool = False,
    evaluator: ParallelEvaluator | None = None,
    ccs_only: bool = False,
) -> list[EpisodeReturns]:
    """
    GPI episodes for a list of weights, in parallel worker processes.

    Every worker builds its env with ``env_fn(**env_kwargs)`` and loads the policy set from ``policy_dir``; the
    result for ``weights[i]`` is what :func:`run_job` gives in-process for the same set and seed.

    :param env_fn: a picklable env constructor
    :param env_kwargs: its keyword arguments
    :param policy_dir: a policy-set directory (:meth:`~sb3_sfgpi.gpi.GPIPolicy.save`)
    :param weights: the preference weights, shape ``(n, d)``
    :param gamma: discount of the discounted returns
    :param seeds: seed of the first episode for each weight
    :param n_episodes: episodes per weight
    :param workers: number of processes (ignored when ``evaluator`` is given)
    :param own_policies: each agent acts by GPI over its own policies only
    :param record_infos: keep the per-step infos
    :param ccs_only: act by GPI over the policies of the set's CCS only
    :param evaluator: an open evaluator to use (its env must be ``env_fn(**env_kwargs)``); default: a new pool,
        closed at the end
    :return: per weight, every agent's vector returns and final infos
    """
    if len(seeds) != len(weights):
        raise ValueError(f"one seed per weight: got {len(seeds)} seeds for {len(weights)} weights")
    jobs = [
        EvaluationJob(int(seed), tuple(w), n_episodes, str(policy_dir), own_policies, (), record_infos, ccs_only)
        for w, seed in zip(weights, seeds, strict=True)
    ]
    if evaluator is not None:
        return evaluator.run(jobs)
    with ParallelEvaluator(env_fn, env_kwargs, workers, gamma) as pool:
        return pool.run(jobs)


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
    discounted, undiscounted, details = [], [], []
    for w, result in zip(weights, results, strict=True):
        agents = list(result.discounted)
        discounted.append([result.mean_discounted(a) for a in agents])
        undiscounted.append([result.mean_undiscounted(a) for a in agents])
        per_agent = {
            a: {"discounted": result.mean_discounted(a).tolist(), "undiscounted": result.mean_undiscounted(a).tolist()}
            for a in agents
        }
        details.append({"weights": w.tolist(), "agents": per_agent, "final_infos": jsonable(result.final_infos)})
    disc, undisc = np.array(discounted), np.array(undiscounted)  # (n_weights, n_agents, d)
    d = weights.shape[1]
    per_agent_w = np.repeat(weights[:, None, :], disc.shape[1], axis=1).reshape(-1, d)
    metrics = {
        "mean_return": expected_utility(per_agent_w, disc.reshape(-1, d)),
        "mean_return_undiscounted": expected_utility(per_agent_w, undisc.reshape(-1, d)),
        "expected_utility": expected_utility(weights, disc.mean(axis=1)),
    }
    return metrics, details


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
    return summarize_test_episodes(weights, returns)[0]["mean_return"]


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
