"""MA-SFOLS (the paper's Algorithm 1) and the random-weights baseline, as an SB3 callback.

:class:`OLSCallback` drives a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` iteration by iteration:
it hands every agent a weight (highest OLS priority first, Dirichlet(1) random weights for the agents
beyond the queue), and after ``steps_per_iteration`` joint steps it evaluates each agent's new policy
(Monte-Carlo vector return in the multi-agent env), adds new value vectors and their SFs to the shared
set Π, updates OLS, evaluates GPI over Π on fixed test weights, writes a checkpoint and starts the next
iteration. It stops when the OLS queue is empty (Π is a CCS) or after ``max_iterations``.

Run directory (written atomically after every iteration; ``resume=True`` continues from it)::

    policy_set/        Π in the policy-set format of :class:`~sb3_sfgpi.gpi.GPIPolicy`
    checkpoint.json    OLS state, next iteration and its weights, number of policies in Π
    evaluation.json    per iteration: per test weight and agent, vector returns (discounted and not)
    evaluation.csv     per iteration: the summary row (also logged to the runner's logger)
"""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

from sb3_sfgpi.common.evaluation import expected_utility, hypervolume, run_episodes
from sb3_sfgpi.common.serialization import atomic_write_bytes, atomic_write_json, read_json
from sb3_sfgpi.common.weights import random_weights, validate_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import MultiAgentRunner, derive_seed
from sb3_sfgpi.ols import OLS

ALGORITHMS = ("ma-sfols", "random")
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
)


class OLSCallback(BaseCallback):
    """
    MA-SFOLS over a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` (or Random + GPI).

    :param steps_per_iteration: joint env steps every agent trains for its weight in one iteration
    :param test_weights: weights GPI is evaluated on after every iteration, shape ``(n, d)``
    :param algorithm: ``"ma-sfols"`` (corner weights by OLS priority) or ``"random"`` (Dirichlet(1) weights)
    :param max_iterations: stop after this many iterations (None: only when OLS ends)
    :param value_episodes: episodes of the Monte-Carlo estimate of each new policy's value ``V^π``
    :param eval_episodes: episodes per test weight of the GPI evaluation
    :param transfer: start each new learner from the policy in Π that is best for its weight
    :param hypervolume_reference: reference point of the hypervolume of Π's values (None: not computed)
    :param run_dir: where checkpoints and evaluations go (None: nowhere)
    :param resume: continue from the checkpoint in ``run_dir`` if there is one
    :param tolerance: the OLS tolerance
    :param progress_bar: show progress bars for the iteration and the evaluation
    :param verbose: 1 prints a line per iteration
    """

    model: MultiAgentRunner  # type: ignore[assignment]

    def __init__(
        self,
        steps_per_iteration: int,
        test_weights: np.ndarray,
        algorithm: str = "ma-sfols",
        max_iterations: int | None = None,
        value_episodes: int = 1,
        eval_episodes: int = 1,
        transfer: bool = False,
        hypervolume_reference: np.ndarray | None = None,
        run_dir: str | Path | None = None,
        resume: bool = False,
        tolerance: float = 1e-6,
        progress_bar: bool = False,
        verbose: int = 0,
    ):
        super().__init__(verbose)
        if algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
        if resume and run_dir is None:
            raise ValueError("resume=True needs the run_dir to resume from")
        if steps_per_iteration < 1:
            raise ValueError(f"steps_per_iteration must be positive, got {steps_per_iteration}")
        self.steps_per_iteration = steps_per_iteration
        self.test_weights = np.asarray(test_weights, dtype=np.float64)
        self.algorithm = algorithm
        self.max_iterations = max_iterations
        self.value_episodes = value_episodes
        self.eval_episodes = eval_episodes
        self.transfer = transfer
        self.hypervolume_reference = hypervolume_reference
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.resume = resume
        self.tolerance = tolerance
        self.progress_bar = progress_bar
        self.history: list[dict[str, Any]] = []
        self.finished = False
        self._iteration_bar: Any = None

    # --- set-up -------------------------------------------------------------------------------------
    def _on_training_start(self) -> None:
        d = self.model.reward_dim
        self.test_weights = np.array([validate_weights(w, d, "test weight") for w in self.test_weights])
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
        returns = runner.evaluate_learners(self.value_episodes, seed=derive_seed(runner.seed, "value", self.iteration))
        for agent in runner.agents:
            value = returns.mean_discounted(agent)
            n_values = len(self.ols.values)
            self.ols.add_solution(value, self.weights[agent])
            if len(self.ols.values) > n_values:
                self.policy_set.add(runner.learners[agent], value=value, agent=agent, iteration=self.iteration)
        self._evaluate_gpi()
        self.iteration += 1
        next_weights = self._next_weights()  # saved even at the iteration cap, so a resume can go further
        self._save_checkpoint(next_weights)
        if next_weights is None or self._reached_max_iterations():
            self.finished = True
        else:
            self._start(next_weights)

    def _evaluate_gpi(self) -> None:
        runner = self.model
        discounted, undiscounted, details = [], [], []
        weights = self.test_weights
        for i, w in enumerate(tqdm(weights, desc="evaluating GPI", unit="w", leave=False, disable=not self.progress_bar)):

            def act(observations: dict[str, Any], w: np.ndarray = w) -> dict[str, int]:
                agents = list(observations)
                actions, _ = self.policy_set.predict(np.stack([observations[a] for a in agents]), w)
                return dict(zip(agents, actions.tolist()))

            result = run_episodes(runner.env, act, self.eval_episodes, runner.gamma, seed=derive_seed(runner.seed, "eval", i))
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
        }
        runner._reset_env()
        for key, value in summary.items():
            if value is not None:
                self.logger.record(f"ols/{key}", value)
        self.logger.dump(step=self.iteration)
        if self.verbose:
            print(
                f"iteration {summary['iteration']}: |Π|={summary['n_policies']} CCS={summary['ccs_size']} "
                f"mean w·return={summary['mean_return']:.4f} ({summary['wall_time']:.1f}s)"
            )
        self.history.append({**summary, "weights_trained": {a: w.tolist() for a, w in self.weights.items()}, "test": details})

    # --- checkpoints ---------------------------------------------------------------------------------------
    def _save_checkpoint(self, next_weights: dict[str, np.ndarray] | None) -> None:
        if self.run_dir is None:
            return
        self.policy_set.save(self.run_dir / "policy_set")
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
        self.ols = OLS.from_state_dict(state["ols"])
        full_set = GPIPolicy.load(self.run_dir / "policy_set")
        self.policy_set = GPIPolicy()
        for net, info in list(zip(full_set.networks, full_set.infos))[: state["n_policies"]]:
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
