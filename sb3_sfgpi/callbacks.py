"""MA-SFOLS (the paper's Algorithm 1), the random-weights baseline and fixed-weight learners, as an SB3 callback.

:class:`OLSCallback` drives a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` iteration by iteration:
it hands every agent a weight (highest OLS priority first, Dirichlet(1) random weights for the agents
beyond the queue), and after ``steps_per_iteration`` joint steps it evaluates each agent's new policy
(Monte-Carlo vector return in the multi-agent env), adds new value vectors and their SFs to the shared
set Π, updates OLS, evaluates GPI over Π on fixed test weights, writes a checkpoint and starts the next
iteration. It stops when the OLS queue is empty (Π is a CCS) or after ``max_iterations``.

With ``algorithm="fixed"`` every agent trains for the same ``fixed_weights`` in every iteration and all
their policies go into Π: the a priori scalarised baseline (independent learners on one fixed preference).
Evaluate them with ``eval_policies="own"`` (each agent acts with the policies it learned itself).

The GPI evaluation on the test weights runs in this process on the training env (``eval_workers=0``) or in
``eval_workers`` spawned processes, each with its own env built by ``eval_env_fn(**eval_env_kwargs)``
(simulators such as libsumo hold one simulation per process); the workers load Π from ``policy_set/``, so Π
is saved before it is evaluated. Both give the same numbers.

After each iteration the run directory is written in this order (each file atomically; ``resume=True``
continues from it)::

    policy_set/        Π in the policy-set format of :class:`~sb3_sfgpi.gpi.GPIPolicy`
    evaluation.json    per iteration: per test weight and agent, vector returns (discounted and not), last infos
    evaluation.csv     per iteration: the summary row (also logged to the runner's logger)
    checkpoint.json    OLS state, next iteration and its weights, number of policies in Π -- written last: it
                       is what a resume trusts (extra policies in policy_set/ and extra rows are ignored)
"""

from __future__ import annotations

import csv
import io
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

from sb3_sfgpi.common.evaluation import (
    EpisodeReturns,
    EvaluationJob,
    ParallelEvaluator,
    agent_policy_sets,
    ccs_subset,
    expected_utility,
    gpi_joint_policy,
    hypervolume,
    run_episodes,
)
from sb3_sfgpi.common.serialization import atomic_write_bytes, atomic_write_json, read_json
from sb3_sfgpi.common.weights import random_weights, validate_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import MultiAgentRunner, derive_seed
from sb3_sfgpi.ols import OLS

ALGORITHMS = ("ma-sfols", "random", "fixed")
EVAL_POLICIES = ("shared", "own")
GPI_SETS = ("all", "ccs")
VALUE_MODES = ("joint", "shared")
CHECKPOINT = "checkpoint.json"
SUMMARY_FIELDS = (
    "iteration",
    "timesteps",
    "n_policies",
    "ccs_size",
    "mean_return",
    "mean_return_undiscounted",
    "expected_utility",
    "hypervolume",
    "wall_time",
    "eval_time",
)


class OLSCallback(BaseCallback):
    """
    MA-SFOLS over a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` (or Random + GPI, or fixed-weight learners).

    :param steps_per_iteration: joint env steps every agent trains for its weight in one iteration
    :param test_weights: weights GPI is evaluated on after every iteration, shape ``(n, d)``
    :param algorithm: ``"ma-sfols"`` (corner weights by OLS priority), ``"random"`` (Dirichlet(1) weights) or
        ``"fixed"`` (every agent trains for ``fixed_weights``; every policy joins Π)
    :param max_iterations: stop after this many iterations (None: only when OLS ends)
    :param value_episodes: episodes of the Monte-Carlo estimate of each new policy's value ``V^π``
    :param value_mode: how ``V^π`` is estimated. ``"joint"``: the new learners act together and an agent's
        own discounted return is the value of its policy. ``"shared"``: each new policy is run by every agent at
        once (``value_episodes`` episodes per policy) and its value is the mean discounted return over the
        agents: the value of the policy as a shared one, comparable between policies learned at different
        places of a heterogeneous env (e.g. different intersections)
    :param eval_episodes: episodes per test weight of the GPI evaluation
    :param transfer: start each new learner from the policy in Π that is best for its weight
    :param hypervolume_reference: reference point of the hypervolume of Π's values (None: not computed)
    :param run_dir: where checkpoints and evaluations go (None: nowhere)
    :param resume: continue from the checkpoint in ``run_dir`` if there is one
    :param tolerance: the OLS tolerance
    :param progress_bar: show progress bars for the iteration and the evaluation
    :param verbose: 1 prints a line per iteration
    :param fixed_weights: the weights of ``algorithm="fixed"`` (required by it, refused otherwise)
    :param eval_policies: ``"shared"``: every agent acts by GPI over the whole Π; ``"own"``: each agent over
        the policies it learned itself (the evaluation of independent fixed-weight learners)
    :param gpi_set: the policies GPI is evaluated over: ``"all"`` of Π, or only those whose values form Π's CCS
        (``"ccs"``, see :func:`~sb3_sfgpi.common.evaluation.ccs_subset`)
    :param eval_workers: 0: evaluate GPI in this process on the training env; ``n > 0``: in ``n`` worker
        processes (kept for the whole run), each with its own env
    :param eval_env_fn: picklable env constructor of the workers (required when ``eval_workers > 0``)
    :param eval_env_kwargs: its keyword arguments (they should build the same env as the training one)
    """

    model: MultiAgentRunner  # type: ignore[assignment]

    def __init__(
        self,
        steps_per_iteration: int,
        test_weights: np.ndarray,
        algorithm: str = "ma-sfols",
        max_iterations: int | None = None,
        value_episodes: int = 1,
        value_mode: str = "joint",
        eval_episodes: int = 1,
        transfer: bool = False,
        hypervolume_reference: np.ndarray | None = None,
        run_dir: str | Path | None = None,
        resume: bool = False,
        tolerance: float = 1e-6,
        progress_bar: bool = False,
        verbose: int = 0,
        fixed_weights: np.ndarray | list[float] | None = None,
        eval_policies: str = "shared",
        gpi_set: str = "all",
        eval_workers: int = 0,
        eval_env_fn: Callable[..., Any] | None = None,
        eval_env_kwargs: Mapping[str, Any] | None = None,
    ):
        super().__init__(verbose)
        if algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
        if (algorithm == "fixed") != (fixed_weights is not None):
            raise ValueError('fixed_weights are required by algorithm="fixed" and only by it')
        if value_mode not in VALUE_MODES:
            raise ValueError(f"value_mode must be one of {VALUE_MODES}, got {value_mode!r}")
        if gpi_set not in GPI_SETS:
            raise ValueError(f"gpi_set must be one of {GPI_SETS}, got {gpi_set!r}")
        if eval_policies not in EVAL_POLICIES:
            raise ValueError(f"eval_policies must be one of {EVAL_POLICIES}, got {eval_policies!r}")
        if isinstance(eval_workers, bool) or not isinstance(eval_workers, int) or eval_workers < 0:
            raise ValueError(f"eval_workers must be a non-negative integer, got {eval_workers!r}")
        if eval_workers > 0 and eval_env_fn is None:
            raise ValueError("eval_workers > 0 needs eval_env_fn (and eval_env_kwargs) to build the workers' envs")
        if resume and run_dir is None:
            raise ValueError("resume=True needs the run_dir to resume from")
        if steps_per_iteration < 1:
            raise ValueError(f"steps_per_iteration must be positive, got {steps_per_iteration}")
        self.steps_per_iteration = steps_per_iteration
        self.test_weights = np.asarray(test_weights, dtype=np.float64)
        self.algorithm = algorithm
        self.max_iterations = max_iterations
        self.value_episodes = value_episodes
        self.value_mode = value_mode
        self.eval_episodes = eval_episodes
        self.transfer = transfer
        self.hypervolume_reference = hypervolume_reference
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.resume = resume
        self.tolerance = tolerance
        self.progress_bar = progress_bar
        self.fixed_weights = None if fixed_weights is None else np.asarray(fixed_weights, dtype=np.float64)
        self.eval_policies = eval_policies
        self.gpi_set = gpi_set
        self.eval_workers = eval_workers
        self.eval_env_fn = eval_env_fn
        self.eval_env_kwargs = dict(eval_env_kwargs or {})
        self.history: list[dict[str, Any]] = []
        self.finished = False
        self._iteration_bar: Any = None
        self._evaluator: ParallelEvaluator | None = None
        self._scratch_dir: str | None = None

    # --- set-up -------------------------------------------------------------------------------------
    def _on_training_start(self) -> None:
        d = self.model.reward_dim
        self.test_weights = np.array([validate_weights(w, d, "test weight") for w in self.test_weights])
        if self.fixed_weights is not None:
            self.fixed_weights = validate_weights(self.fixed_weights, d, "fixed_weights")
        if self.resume and self.run_dir is not None and (self.run_dir / CHECKPOINT).exists():
            weights = self._load_checkpoint()
        else:
            self.ols = OLS(d, tolerance=self.tolerance)
            self.policy_set = GPIPolicy()
            self.iteration = 0
            self.model.num_timesteps = 0
            weights = self._next_weights()
        self._elapsed_before = self.history[-1]["wall_time"] if self.history else 0.0
        self._start_time = time.time()
        if weights is None or self._reached_max_iterations():
            self.finished = True
            return
        self._start(weights)

    def _reached_max_iterations(self) -> bool:
        return self.max_iterations is not None and self.iteration >= self.max_iterations

    def _next_weights(self) -> dict[str, np.ndarray] | None:
        """Weights of the next iteration (Algorithm 1, lines 6-14), or None when OLS has ended."""
        agents = self.model.agents
        if self.algorithm == "fixed":
            assert self.fixed_weights is not None
            return {agent: self.fixed_weights.copy() for agent in agents}
        rng = np.random.default_rng(derive_seed(self.model.seed, "random-weights", self.iteration))
        if self.algorithm == "random":
            return {agent: random_weights(self.model.reward_dim, rng=rng) for agent in agents}
        first = self.ols.next_weight()
        if first is None:
            return None
        weights = {agents[0]: first}
        for agent in agents[1:]:
            w = self.ols.next_weight()
            weights[agent] = random_weights(self.model.reward_dim, rng=rng) if w is None else w
        return weights

    def _start(self, weights: dict[str, np.ndarray]) -> None:
        self.weights = weights
        self._iteration_start = self.model.num_timesteps
        init = None
        if self.transfer and len(self.policy_set):
            init = {agent: self._best_network(w) for agent, w in weights.items()}
        self.model.start_iteration(weights, self.iteration, self.steps_per_iteration, init_networks=init)
        if self.progress_bar:
            self._iteration_bar = tqdm(
                total=self.steps_per_iteration, desc=f"iteration {self.iteration}", unit="step", leave=False
            )

    def _best_network(self, w: np.ndarray) -> Any:
        values = [info.value if info.value is not None else np.full_like(w, -np.inf) for info in self.policy_set.infos]
        return self.policy_set.networks[int(np.argmax([np.dot(w, v) for v in values]))]

    # --- the loop -------------------------------------------------------------------------------------
    def _on_step(self) -> bool:
        if self.finished:
            return False
        if self._iteration_bar is not None:
            self._iteration_bar.update(1)
        if self.model.num_timesteps - self._iteration_start < self.steps_per_iteration:
            return True
        self._finish_iteration()
        return not self.finished

    def _finish_iteration(self) -> None:
        if self._iteration_bar is not None:
            self._iteration_bar.close()
        runner = self.model
        runner.end_iteration()
        values = self._policy_values()
        for agent in runner.agents:
            value = values[agent]
            n_values = len(self.ols.values)
            self.ols.add_solution(value, self.weights[agent])
            if len(self.ols.values) > n_values or self.algorithm == "fixed":
                self.policy_set.add(runner.learners[agent], value=value, agent=agent, iteration=self.iteration)
        # Π is saved before it is evaluated (the evaluation workers load it); checkpoint.json comes last.
        self._save_policy_set()
        self._evaluate_gpi()
        self.iteration += 1
        next_weights = self._next_weights()  # saved even at the iteration cap, so a resume can go further
        self._save_checkpoint(next_weights)
        if next_weights is None or self._reached_max_iterations():
            self.finished = True
        else:
            self._start(next_weights)

    def _policy_values(self) -> dict[str, np.ndarray]:
        """Monte-Carlo estimate of ``V^π`` of every agent's new policy (see ``value_mode``)."""
        runner = self.model
        seed = derive_seed(runner.seed, "value", self.iteration)
        if self.value_mode == "joint":
            returns = runner.evaluate_learners(self.value_episodes, seed=seed)
            return {agent: returns.mean_discounted(agent) for agent in runner.agents}
        values = {}
        for agent in runner.agents:
            learner = runner.learners[agent]

            def act(observations: dict[str, Any], learner: Any = learner) -> dict[str, int]:
                agents = list(observations)
                actions, _ = learner.predict(np.stack([observations[a] for a in agents]), deterministic=True)
                return dict(zip(agents, actions.tolist(), strict=True))

            # the same episodes (seeds) for every policy
            returns = run_episodes(runner.env, act, self.value_episodes, runner.gamma, seed=seed)
            values[agent] = np.mean([returns.mean_discounted(a) for a in returns.discounted], axis=0)
        runner._reset_env()
        return values

    def _on_training_end(self) -> None:
        self.close()

    def close(self) -> None:
        """Stop the evaluation workers (if any) and delete the scratch copy of Π. Safe to call several times."""
        if self._evaluator is not None:
            self._evaluator.close()
            self._evaluator = None
        if self._scratch_dir is not None:
            shutil.rmtree(self._scratch_dir, ignore_errors=True)
            self._scratch_dir = None

    def _policy_dir(self) -> Path:
        """Where Π is saved: ``run_dir/policy_set``, or a scratch directory for the workers when there is no run_dir."""
        if self.run_dir is not None:
            return self.run_dir / "policy_set"
        if self._scratch_dir is None:
            self._scratch_dir = tempfile.mkdtemp(prefix="sfgpi_policy_set_")
        return Path(self._scratch_dir) / "policy_set"

    def _save_policy_set(self) -> None:
        if (self.run_dir is not None or self.eval_workers > 0) and len(self.policy_set):
            self.policy_set.save(self._policy_dir())

    def _run_test_episodes(self) -> list[EpisodeReturns]:
        """Per test weight, the episodes of the agents acting by GPI (in this process or in the workers)."""
        runner = self.model
        seeds = [derive_seed(runner.seed, "eval", i) for i in range(len(self.test_weights))]
        own = self.eval_policies == "own"
        ccs_only = self.gpi_set == "ccs" and not own
        if self.eval_workers > 0:
            if self._evaluator is None:
                assert self.eval_env_fn is not None
                self._evaluator = ParallelEvaluator(
                    self.eval_env_fn, self.eval_env_kwargs, self.eval_workers, runner.gamma
                )
            policy_dir = str(self._policy_dir())
            jobs = [
                EvaluationJob(seed, tuple(w), self.eval_episodes, policy_dir, own_policies=own, ccs_only=ccs_only)
                for w, seed in zip(self.test_weights, seeds, strict=True)
            ]
            return self._evaluator.run(jobs)
        policy_set = ccs_subset(self.policy_set) if ccs_only else self.policy_set
        own_sets = agent_policy_sets(policy_set, runner.agents) if own else None
        results = []
        bar = tqdm(self.test_weights, desc="evaluating GPI", unit="w", leave=False, disable=not self.progress_bar)
        for w, seed in zip(bar, seeds, strict=True):
            act = gpi_joint_policy(policy_set, w, own_sets)
            results.append(run_episodes(runner.env, act, self.eval_episodes, runner.gamma, seed=seed))
        return results

    def _evaluate_gpi(self) -> None:
        runner = self.model
        discounted, undiscounted, details = [], [], []
        weights = self.test_weights
        eval_start = time.time()
        results = self._run_test_episodes()
        eval_time = time.time() - eval_start
        for w, result in zip(weights, results, strict=True):
            agents = list(result.discounted)
            discounted.append([result.mean_discounted(a) for a in agents])
            undiscounted.append([result.mean_undiscounted(a) for a in agents])
            details.append(
                {
                    "weights": w.tolist(),
                    "agents": {
                        a: {
                            "discounted": result.mean_discounted(a).tolist(),
                            "undiscounted": result.mean_undiscounted(a).tolist(),
                        }
                        for a in agents
                    },
                    "final_infos": _jsonable(result.final_infos),
                }
            )
        disc, undisc = np.array(discounted), np.array(undiscounted)  # (n_weights, n_agents, d)
        per_agent_w = np.repeat(weights[:, None, :], disc.shape[1], axis=1).reshape(-1, weights.shape[1])
        summary = {
            "iteration": self.iteration,
            "timesteps": runner.num_timesteps,
            "n_policies": len(self.policy_set),
            "ccs_size": len(self.ols.ccs),
            "mean_return": expected_utility(per_agent_w, disc.reshape(-1, weights.shape[1])),
            "mean_return_undiscounted": expected_utility(per_agent_w, undisc.reshape(-1, weights.shape[1])),
            "expected_utility": expected_utility(weights, disc.mean(axis=1)),
            "hypervolume": None
            if self.hypervolume_reference is None
            else hypervolume(np.array(self.ols.ccs), self.hypervolume_reference),
            "wall_time": self._elapsed_before + time.time() - self._start_time,
            "eval_time": eval_time,
        }
        runner._reset_env()
        for key, value in summary.items():
            if value is not None:
                self.logger.record(f"ols/{key}", value)
        self.logger.dump(step=self.iteration)
        if self.verbose:
            print(
                f"iteration {summary['iteration']}: |Π|={summary['n_policies']} CCS={summary['ccs_size']} "
                f"mean w·return={summary['mean_return']:.4f} ({summary['wall_time']:.1f}s, "
                f"GPI evaluation {eval_time:.1f}s)"
            )
        trained = {a: w.tolist() for a, w in self.weights.items()}
        self.history.append({**summary, "weights_trained": trained, "test": details})

    # --- checkpoints ---------------------------------------------------------------------------------------
    def _save_checkpoint(self, next_weights: dict[str, np.ndarray] | None) -> None:
        """Evaluation files, then ``checkpoint.json`` (Π was saved before the evaluation)."""
        if self.run_dir is None:
            return
        atomic_write_json(self.run_dir / "evaluation.json", self.history)
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(self.history)
        atomic_write_bytes(self.run_dir / "evaluation.csv", out.getvalue().encode())
        atomic_write_json(  # written last: it is what a resume trusts
            self.run_dir / CHECKPOINT,
            {
                "algorithm": self.algorithm,
                "iteration": self.iteration,
                "timesteps": self.model.num_timesteps,
                "n_policies": len(self.policy_set),
                "fixed_weights": None if self.fixed_weights is None else self.fixed_weights.tolist(),
                "ols": self.ols.state_dict(),
                "next_weights": None if next_weights is None else {a: w.tolist() for a, w in next_weights.items()},
            },
        )

    def _load_checkpoint(self) -> dict[str, np.ndarray] | None:
        """Restore the state of the last finished iteration; return the next weights (None if OLS ended)."""
        assert self.run_dir is not None
        state = read_json(self.run_dir / CHECKPOINT, "checkpoint")
        if state.get("algorithm") != self.algorithm:
            raise ValueError(f"{self.run_dir} holds a {state.get('algorithm')!r} run, not {self.algorithm!r}")
        saved_fixed = state.get("fixed_weights")
        if self.fixed_weights is not None and (
            saved_fixed is None or not np.allclose(np.asarray(saved_fixed, dtype=np.float64), self.fixed_weights)
        ):
            raise ValueError(
                f"{self.run_dir} holds a fixed-weight run for {saved_fixed}, not for {self.fixed_weights.tolist()}"
            )
        self.ols = OLS.from_state_dict(state["ols"])
        full_set = GPIPolicy.load(self.run_dir / "policy_set")
        self.policy_set = GPIPolicy()
        for net, info in list(zip(full_set.networks, full_set.infos, strict=True))[: state["n_policies"]]:
            self.policy_set.add(net, info.weights, info.value, info.agent, info.iteration)
        self.history = read_json(self.run_dir / "evaluation.json", "evaluation")[: state["iteration"]]
        self.iteration = int(state["iteration"])
        self.model.num_timesteps = int(state["timesteps"])
        if state["next_weights"] is None:
            return None
        return {a: np.asarray(w) for a, w in state["next_weights"].items()}


def _jsonable(value: Any) -> Any:
    """Numbers, strings, lists and dicts only (numpy values become Python ones, NaN None; the rest is dropped)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items() if _jsonable(v) is not None}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None  # JSON has no NaN or infinity
    if isinstance(value, (int, float, str, bool)) or value is None:
        return value
    return None
