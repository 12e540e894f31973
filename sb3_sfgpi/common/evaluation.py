"""Monte-Carlo evaluation in multi-agent envs (in-process or in worker processes), expected utility and hypervolume.

* :func:`run_episodes` runs full episodes of a PettingZoo ParallelEnv with vector rewards under a joint policy
  and collects every agent's vector returns, last infos and (optionally) per-step infos.
* :func:`gpi_joint_policy` makes the joint policy of agents acting by GPI over a policy set (all agents over the
  whole set, or each over the policies it learned itself).
* :class:`EvaluationJob`, :func:`run_job`, :class:`ParallelEvaluator` and :func:`evaluate_gpi_parallel` run such
  evaluations in a pool of spawned worker processes. Each worker builds its own env from a picklable constructor
  and keyword arguments (simulators such as libsumo hold one simulation per process) and loads the policy set
  from a policy-set directory (:meth:`~sb3_sfgpi.gpi.GPIPolicy.load`). Results equal those of the same job run
  in-process (:func:`run_job`) with the same policy set and seeds.
"""

from __future__ import annotations

import multiprocessing
import numbers
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pettingzoo import ParallelEnv

if TYPE_CHECKING:
    from sb3_sfgpi.gpi import GPIPolicy

#: Maps the observations of the live agents to their actions.
JointPolicy = Callable[[dict[str, Any]], dict[str, Any]]


@dataclass
class EpisodeReturns:
    """
    Vector returns of every agent over several episodes.

    :param discounted: agent -> array ``(n_episodes, d)`` of discounted returns
    :param undiscounted: agent -> array ``(n_episodes, d)`` of plain sums of rewards
    :param final_infos: per episode, the last info dict of every agent
    :param step_infos: per episode (when recorded), agent -> info key -> its value after every step; only the
        numeric entries of the infos are kept
    """

    discounted: dict[str, np.ndarray]
    undiscounted: dict[str, np.ndarray]
    final_infos: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    step_infos: list[dict[str, dict[str, list[float]]]] = field(default_factory=list)

    def mean_discounted(self, agent: str) -> np.ndarray:
        """Mean discounted vector return of ``agent``: the Monte-Carlo estimate of ``V^π``."""
        return self.discounted[agent].mean(axis=0)

    def mean_undiscounted(self, agent: str) -> np.ndarray:
        """Mean undiscounted vector return of ``agent``."""
        return self.undiscounted[agent].mean(axis=0)


def run_episodes(
    env: ParallelEnv,
    policy: JointPolicy,
    n_episodes: int,
    gamma: float,
    seed: int | None = None,
    record_infos: bool = False,
) -> EpisodeReturns:
    """
    Run full episodes of a PettingZoo ParallelEnv with vector rewards and collect each agent's returns.

    :param env: the env (it is reset, once per episode)
    :param policy: maps the live agents' observations to their actions
    :param n_episodes: number of episodes
    :param gamma: discount factor of the discounted returns
    :param seed: seed of the first reset (episode ``i`` uses ``seed + i``)
    :param record_infos: also keep the numeric entries of every agent's info after every step
        (:attr:`EpisodeReturns.step_infos`), e.g. waiting times over a traffic episode
    :return: the returns of every agent that was present at reset
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be at least 1, got {n_episodes}")
    discounted: dict[str, list[np.ndarray]] = {}
    undiscounted: dict[str, list[np.ndarray]] = {}
    final_infos = []
    step_infos: list[dict[str, dict[str, list[float]]]] = []
    for episode in range(n_episodes):
        obs, infos = env.reset(seed=None if seed is None else seed + episode)
        agents = list(env.agents)
        dims = {agent: env.reward_space(agent).shape[0] for agent in agents}  # type: ignore[attr-defined]
        disc = {agent: np.zeros(dims[agent]) for agent in agents}
        total = {agent: np.zeros(dims[agent]) for agent in agents}
        last_infos = dict(infos)
        trace: dict[str, dict[str, list[float]]] = {}
        discount = 1.0
        while env.agents:
            actions = policy({agent: obs[agent] for agent in env.agents})
            obs, rewards, _, _, infos = env.step(actions)
            for agent, reward in rewards.items():
                disc[agent] += discount * np.asarray(reward, dtype=np.float64)
                total[agent] += reward
            last_infos.update(infos)
            if record_infos:
                _record_step(trace, infos)
            discount *= gamma
        for agent in agents:
            discounted.setdefault(agent, []).append(disc[agent])
            undiscounted.setdefault(agent, []).append(total[agent])
        final_infos.append(last_infos)
        if record_infos:
            step_infos.append(trace)
    return EpisodeReturns(
        {agent: np.array(values) for agent, values in discounted.items()},
        {agent: np.array(values) for agent, values in undiscounted.items()},
        final_infos,
        step_infos,
    )


def _record_step(trace: dict[str, dict[str, list[float]]], infos: Mapping[str, Mapping[str, Any]]) -> None:
    for agent, info in infos.items():
        columns = trace.setdefault(agent, {})
        for key, value in info.items():
            if isinstance(value, (numbers.Real, np.bool_)):  # bool and numpy scalars included
                columns.setdefault(key, []).append(float(value))


def expected_utility(weights: np.ndarray, returns: np.ndarray) -> float:
    """
    Mean scalarised return ``mean_i w_i · G_i`` over test weights.

    :param weights: shape ``(n, d)``
    :param returns: the vector return obtained for each weight, shape ``(n, d)``
    """
    weights, returns = np.asarray(weights, dtype=np.float64), np.asarray(returns, dtype=np.float64)
    if weights.shape != returns.shape:
        raise ValueError(f"weights {weights.shape} and returns {returns.shape} must have the same shape")
    return float(np.mean(np.sum(weights * returns, axis=1)))


def hypervolume(points: Sequence[np.ndarray] | np.ndarray, reference: Sequence[float] | np.ndarray) -> float:
    """
    Volume dominated by ``points`` (maximisation) and bounded below by ``reference``.

    Exact, by slicing along the last objective; meant for the few dozen points of a coverage set.

    :param points: shape ``(n, d)``
    :param reference: shape ``(d,)``; points not strictly above it in every objective add nothing
    """
    ref = np.asarray(reference, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, ref.shape[0])
    pts = pts[np.all(pts > ref, axis=1)]
    return _hypervolume(pts - ref)


def _hypervolume(pts: np.ndarray) -> float:
    # Points are relative to the reference (all coordinates > 0).
    if len(pts) == 0:
        return 0.0
    if pts.shape[1] == 1:
        return float(pts.max())
    order = np.argsort(-pts[:, -1])
    pts = pts[order]
    volume = 0.0
    for i in range(len(pts)):
        lower = pts[i + 1, -1] if i + 1 < len(pts) else 0.0
        height = pts[i, -1] - lower
        if height > 0:
            volume += height * _hypervolume(pts[: i + 1, :-1])
    return volume


# --- GPI joint policies ------------------------------------------------------------------------------------
def agent_policy_sets(policy_set: GPIPolicy, agents: Sequence[str]) -> dict[str, GPIPolicy]:
    """
    For each agent, the sub-set of the policies it learned itself (e.g. an a priori scalarised learner).

    :raises ValueError: an agent without any policy in the set
    """
    from sb3_sfgpi.gpi import GPIPolicy

    subsets = {}
    for agent in agents:
        subset = GPIPolicy(device=policy_set.device)
        for net, info in zip(policy_set.networks, policy_set.infos, strict=True):
            if info.agent == agent:
                subset.add(net, info.weights, info.value, info.agent, info.iteration)
        if not len(subset):
            raise ValueError(f"the policy set has no policy learned by agent {agent!r}")
        subsets[agent] = subset
    return subsets


def ccs_subset(policy_set: GPIPolicy, tolerance: float = 1e-6) -> GPIPolicy:
    """
    The policies of the set whose value vectors ``V^π`` form its convex coverage set (CCS): those that are the
    best of the set, by more than ``tolerance``, for some weight (computed by :class:`~sb3_sfgpi.ols.OLS` from
    the values stored in the set; of policies with the same value the first is kept). GPI over this subset
    ignores dominated policies, whose learned SFs can only mislead it where they overestimate.

    :param policy_set: a set whose policies carry their values (policies without one are left out)
    :return: a new set holding the CCS policies, in their order in ``policy_set``
    :raises ValueError: no policy of the set has a value
    """
    from sb3_sfgpi.gpi import GPIPolicy
    from sb3_sfgpi.ols import OLS

    with_values = [i for i, info in enumerate(policy_set.infos) if info.value is not None]
    if not with_values:
        raise ValueError("the policies of the set carry no value vectors: their CCS is unknown")
    ols = OLS(policy_set.reward_dim, tolerance=tolerance)
    for i in with_values:
        ols.add_solution(policy_set.infos[i].value, policy_set.infos[i].weights)
    subset = GPIPolicy(device=policy_set.device)
    kept: list[np.ndarray] = []
    for i in with_values:
        info = policy_set.infos[i]
        value = np.asarray(info.value)
        in_ccs = any(np.max(np.abs(value - v)) <= tolerance for v in ols.ccs)
        if in_ccs and not any(np.max(np.abs(value - v)) <= tolerance for v in kept):
            kept.append(value)
            subset.add(policy_set.networks[i], info.weights, info.value, info.agent, info.iteration)
    return subset


def gpi_joint_policy(
    policy_set: GPIPolicy, w: np.ndarray | Sequence[float], own_sets: Mapping[str, GPIPolicy] | None = None
) -> JointPolicy:
    """
    The joint policy of agents acting by GPI for the preference ``w``.

    :param policy_set: the shared set: every agent acts by GPI over all of it (one batched call per step)
    :param w: preference weights
    :param own_sets: agent -> its own policies (see :func:`agent_policy_sets`); when given, each agent acts by
        GPI over its own policies only
    """
    w = np.asarray(w, dtype=np.float64)

    def act(observations: dict[str, Any]) -> dict[str, int]:
        agents = list(observations)
        if own_sets is None:
            actions, _ = policy_set.predict(np.stack([observations[a] for a in agents]), w)
            return dict(zip(agents, actions.tolist(), strict=True))
        return {a: int(own_sets[a].predict(observations[a], w)[0]) for a in agents}

    return act


def _no_actions(observations: dict[str, Any]) -> dict[str, Any]:
    """No action for anyone: the env's own controller acts (e.g. SUMO's fixed-time or actuated programs)."""
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
    :param policy_dir: the policy-set directory to act with (required with ``weights``; a worker loads it)
    :param own_policies: each agent acts by GPI over the policies it learned itself only
    :param ccs_only: act by GPI over the policies of the set's CCS only (:func:`ccs_subset`)
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


def run_job(
    env: ParallelEnv, job: EvaluationJob, gamma: float, policy_set: GPIPolicy | None = None
) -> EpisodeReturns:
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
            from sb3_sfgpi.gpi import GPIPolicy

            policy_set = GPIPolicy.load(job.policy_dir)  # type: ignore[arg-type]
        if job.ccs_only:
            policy_set = ccs_subset(policy_set)
        own = agent_policy_sets(policy_set, env.possible_agents) if job.own_policies else None
        policy = gpi_joint_policy(policy_set, job.weights, own)
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
        _worker["env"] = _worker["env_fn"](**{**_worker["env_kwargs"], **dict(overrides)})
        _worker["env_key"] = overrides
    return _worker["env"]


def _worker_policy_set(policy_dir: str) -> GPIPolicy:
    from sb3_sfgpi.gpi import MANIFEST, GPIPolicy

    manifest = (Path(policy_dir) / MANIFEST).read_bytes()  # the manifest names every file of the set
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
        gamma: float = 0.99,
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
