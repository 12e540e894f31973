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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from sb3_sfgpi.common.parallel_wrappers import as_parallel_env
from sb3_sfgpi.common.rollouts import EpisodeReturns, JointPolicy, run_episodes
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.policy_set_files import manifest_path
from sb3_sfgpi.run_settings import GAMMA


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
