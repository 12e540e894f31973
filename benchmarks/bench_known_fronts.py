"""SFOLS + GPI on MO-Gymnasium problems with known fronts: expected utility against the exact optimum (EU/EU*).

For each problem and seed, :class:`~sb3_sfgpi.masfols.MASFOLS` trains on the single-agent env with the learners the
command line's preset picks for it (:mod:`sb3_sfgpi.cli.gym_domains`: tables for small integer observations, planned
on the run's pooled replay, else MLPs), validation on 50 weights, and the budget below. Then GPI over the final Π is
scored on 50 Dirichlet(1) test weights (``random_weights(d, 50, rng=0)``):

* **EU** = mean over the test weights of ``w · V^GPI`` (discounted with the learners' γ). For the tabular problems it
  is exact: GPI's action in every state of the env's model (:mod:`sfgpi_envs.tabular_optimum`) and the policy's
  value computed from the model, so the stochastic resource-gathering has no Monte-Carlo noise. The run's own
  Monte-Carlo score (its last ``mean_return``) is in the notes. Minecart has no model: its EU is that score.
* **EU*** = mean of ``max_π w · V^π(s0)``: finite-horizon value iteration on the scalarised reward (deep-sea-treasure
  and fruit-tree: equal to the env's ``pareto_front(γ)``, see ``tests/test_known_fronts.py``; resource-gathering:
  above it, the env's front being too low). Minecart: the front of trips searched in the env itself
  (:mod:`benchmarks.minecart_reference`: every point driven, so EU* is at most the true one; a run exceeds it only
  with a trip outside the search), not MO-Gymnasium's modelled ``convex_coverage_set(γ)``, which promises trips the
  env does not drive and misses faster ones; the row names MO-Gymnasium's EU* as well. Lunar lander has no known
  front: its rows give EU alone, beside its peer's at the same env steps.

Rows: per problem, EU/EU* mean ± std over the seeds with the per-seed values, then one row per seed (wall time of
training with its per-iteration evaluations, env steps of training, |Π|). Where ``morl_baselines`` imports, a peer
of it trains with the same env steps per problem (``peer_steps`` / ``--peer-steps`` sets its own) and its GPI is
scored the same way: MPMOQLearning (OLS weights, GPI, Dyna) on the tabular problems, GPI-LS (its minecart example's
settings without PER and Dyna, :data:`GPI_LS_SETTINGS`, at our gradient updates per step) on the deep problems,
whose EU is then Monte Carlo by the
protocol of our test evaluation (:func:`rollout_expected_utility`: the same episodes' seeds per test weight).
The deep problems (minecart, minecart-deterministic, lunar lander) are slow and run only when named (``deep-fronts``, or
``--envs``).
"""

from __future__ import annotations

import functools
import importlib
import json
import random
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mo_gymnasium as mo
import numpy as np
import torch as th
from sfgpi_envs.resource_gathering_optimum import resource_gathering_mdp
from sfgpi_envs.tabular_optimum import TabularMDP, deep_sea_treasure_mdp, fruit_tree_mdp

from benchmarks._common import MORL_MISSING, Row
from benchmarks.gpi_ls_runs import train_gpi_ls
from benchmarks.minecart_reference import searched_front as minecart_front
from sb3_sfgpi import MASFOLS
from sb3_sfgpi.cli.gym_domains import (
    MLP_LEARNER,
    MLP_RUN,
    TABULAR_LEARNER,
    TABULAR_POOL_REPLAY,
    TABULAR_RUN,
    gym_preset,
)
from sb3_sfgpi.common.parallel_wrappers import as_parallel_env
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.seeded_draws import with_seeded_draws
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import summarize_test_episodes
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_settings import RunSettings

NAME = "known fronts"
N_TEST_WEIGHTS = 50
SEEDS = (0, 1, 2)


@dataclass(frozen=True)
class Problem:
    """One env and its budget: ``iterations × steps_per_iteration`` env steps of training (``quick``: the smoke run)."""

    env_id: str
    steps_per_iteration: int
    iterations: int
    quick: tuple[int, int]  # (steps_per_iteration, iterations) of --quick
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    tabular: bool = True
    eval_episodes: int = 5  # the preset's
    model: Callable[[Any, float], TabularMDP] | None = None  # its exact model's builder (env, γ); None: none
    front: Callable[[Any, float], np.ndarray] | None = None  # its reference front (env, γ) without a model; None: env's
    known_front: bool = True  # False: no optimum to score against (EU alone)

    def budget(self, quick: bool) -> tuple[int, int]:
        return self.quick if quick else (self.steps_per_iteration, self.iterations)


PROBLEMS = {
    "deep-sea-treasure": Problem("deep-sea-treasure-v0", 10_000, 15, (1_500, 2), model=deep_sea_treasure_mdp),
    "resource-gathering": Problem("resource-gathering-v0", 10_000, 12, (1_500, 2), model=resource_gathering_mdp),
    "fruit-tree": Problem("fruit-tree-v0", 5_000, 25, (1_000, 2), {"depth": 6}, model=fruit_tree_mdp),
    # GPI-PD's published budget (15 × 10,000); scored with the deep preset's γ, 0.98, as its minecart example
    "minecart": Problem("minecart-v0", 10_000, 15, (1_500, 2), tabular=False, eval_episodes=1, front=minecart_front),
    "minecart-deterministic": Problem(
        "minecart-deterministic-v0", 10_000, 15, (1_500, 2), tabular=False, eval_episodes=1, front=minecart_front
    ),  # fmt: skip
    # the tabular problem with the deep preset's MLP SFs: exact EU by the model, 10 × 10,000 steps
    "deep-sea-treasure-mlp": Problem(
        "deep-sea-treasure-v0", 10_000, 10, (1_500, 2), tabular=False, eval_episodes=1, model=deep_sea_treasure_mdp
    ),  # fmt: skip
    # no known front (MO-Gymnasium gives none): EU beside the peer's, at minecart's budget
    "lunar-lander": Problem(
        "mo-lunar-lander-v3", 10_000, 15, (1_500, 2), tabular=False, eval_episodes=1, known_front=False
    ),  # fmt: skip
}
DEEP = ("minecart", "minecart-deterministic", "deep-sea-treasure-mlp", "lunar-lander")
DEFAULT = ("deep-sea-treasure", "resource-gathering", "fruit-tree")


@dataclass
class Outcome:
    """What one training run (one seed) measured."""

    expected_utility: float  # exact where the problem has a model, else Monte Carlo
    monte_carlo: float | None  # the run's own last mean_return (None: not a MASFOLS run)
    wall_time: float
    env_steps: int
    n_policies: int
    iterations: int
    by_iteration: tuple[float, ...] = ()  # GPI's Monte-Carlo EU after each iteration (MASFOLS runs)


def run(
    quick: bool = False,
    seeds: Sequence[int] | None = None,
    envs: Sequence[str] | None = None,
    peer_steps: int | None = None,
    runs: Path | None = None,
) -> list[Row]:
    """
    EU/EU* of SFOLS + GPI (and of morl-baselines where installed) on the known-front problems.

    :param quick: the smoke run's tiny budgets
    :param seeds: the seeds (default 0, 1, 2)
    :param envs: problem names or Gymnasium ids (default: all but minecart)
    :param peer_steps: the morl-baselines peers' env steps (default: ours)
    :param runs: where our runs keep their run directories, ``<problem>-s<seed>``, and go on from them (None: no
        files; see :func:`learned`)
    """
    names = [_problem_name(env) for env in envs or DEFAULT]
    seeds = list(SEEDS if seeds is None else seeds)
    rows: list[Row] = []
    for name in names:
        rows.extend(_problem_rows(name, seeds, quick, runs))
    rows.extend(_morl_rows([PROBLEMS[name] for name in names], seeds, quick, peer_steps, runs))
    return rows


def run_deep(
    quick: bool = False,
    seeds: Sequence[int] | None = None,
    envs: Sequence[str] | None = None,
    peer_steps: int | None = None,
    runs: Path | None = None,
) -> list[Row]:
    """Minecart, minecart-deterministic (MLP learners, approximate fronts) and lunar lander (no known front); slow:
    ``python -m benchmarks deep-fronts`` (``--runs DIR``: resumable)."""
    return run(quick, seeds, envs or list(DEEP), peer_steps, runs)


def _problem_name(env: str) -> str:
    for name, problem in PROBLEMS.items():
        if env in (name, problem.env_id):
            return name
    raise ValueError(f"unknown env {env!r}: one of {', '.join(PROBLEMS)} (or their Gymnasium ids)")


def _make_env(problem: Problem) -> Any:
    return with_seeded_draws(mo.make(problem.env_id, **problem.env_kwargs))


def _learner_of(problem: Problem) -> tuple[str, dict[str, Any]]:
    """The SFDQN policy and learner arguments of the command line's preset for the problem's observations, with its
    default device: a run of ``sb3-sfgpi train <env id>`` is one of the benchmark's (``--runs``)."""
    kwargs = dict(TABULAR_LEARNER if problem.tabular else MLP_LEARNER) | {"device": "auto"}
    return kwargs.pop("policy"), kwargs


def _model(problem: Problem, env: Any, gamma: float) -> TabularMDP | None:
    """The env's exact model, or None."""
    return None if problem.model is None else problem.model(env, gamma)


def _best(problem: Problem, env: Any, model: Any, weights: np.ndarray, gamma: float) -> float | None:
    """EU*, the mean of ``max_π w · V^π(s0)`` over the test weights: exact by the model, else from the env's
    (approximate) CCS or the problem's own; None where the problem has no known front."""
    if model is not None:
        return float(np.mean([model.value(w) for w in weights]))
    if not problem.known_front:
        return None
    front = (problem.front or _env_ccs)(env, gamma)
    return float((weights @ front.T).max(axis=1).mean())


def _env_ccs(env: Any, gamma: float) -> np.ndarray:
    return np.array(env.unwrapped.convex_coverage_set(gamma))


# --- SFOLS + GPI ------------------------------------------------------------------------------------------------------
def _problem_rows(name: str, seeds: list[int], quick: bool, runs: Path | None = None) -> list[Row]:
    """The summary row of the problem ``name`` and a row per seed."""
    problem = PROBLEMS[name]
    env = _make_env(problem)
    policy, learner = _learner_of(problem)
    gamma = learner["gamma"]
    d = env.unwrapped.reward_space.shape[0]
    weights = random_weights(d, N_TEST_WEIGHTS, rng=0)
    model = _model(problem, env, gamma)
    best = _best(problem, env, model, weights, gamma)
    outcomes = [_train_sfols(name, policy, learner, weights, model, seed, quick, runs) for seed in seeds]
    steps, iterations = problem.budget(quick)
    case = f"{problem.env_id} (d={d}), SFOLS + GPI, {iterations} × {steps:,} steps"
    reference = "exact (value iteration)" if model is not None else "MO-Gymnasium's approximate CCS"
    reference = reference if problem.front is None else f"the trips {problem.front.__module__} drives in the env"
    front = _front_expected_utility(env, weights, gamma)
    baseline = _reference(best) + ("" if best is None else f", {reference}")
    baseline += "" if front is None else f"; MO-Gymnasium's front: {front:.4f}"
    return [summary_row(NAME, case, outcomes, best, baseline, seeds)] + [
        seed_row(NAME, f"{problem.env_id} seed {seed}", outcome, best)
        for seed, outcome in zip(seeds, outcomes, strict=True)
    ]


def _train_sfols(
    name: str, policy: str, learner: dict[str, Any], weights: np.ndarray, model: Any, seed: int, quick: bool,
    runs: Path | None,
) -> Outcome:  # fmt: skip
    """One MASFOLS run on the problem ``name`` with the preset's evaluation and admission (in ``runs/<name>-s<seed>``
    where given), and GPI's EU over its final Π."""
    problem = PROBLEMS[name]
    steps, iterations = problem.budget(quick)
    preset = gym_preset(problem.env_id)
    assert preset is not None, f"{problem.env_id} is not a registered Gymnasium id"
    verbose = 0 if problem.tabular else 1  # a line per iteration of the hour-long deep runs

    def build(run_dir: Path | None) -> MASFOLS:
        return MASFOLS(
            _make_env(problem), policy=policy, steps_per_iteration=steps, learner_kwargs=learner,
            value_episodes=preset["value_episodes"],
            **(TABULAR_RUN if problem.tabular else MLP_RUN),
            pool_replay=problem.tabular and TABULAR_POOL_REPLAY,
            test_weights=weights, eval_episodes=problem.eval_episodes, seed=seed, run_dir=run_dir, verbose=verbose,
        )  # fmt: skip

    masfols = learned(build, lambda: _make_env(problem), runs, f"{name}-s{seed}", iterations)
    last = masfols.history[-1]
    policy_set = masfols.policy_set
    exact = None if model is None else model.expected_utility(lambda o, w: policy_set.predict(o, w)[0], weights)
    return Outcome(
        expected_utility=last["mean_return"] if exact is None else exact,
        monte_carlo=last["mean_return"],
        wall_time=last["wall_time"],
        env_steps=int(last["timesteps"]),
        n_policies=len(policy_set),
        iterations=len(masfols.history),
        by_iteration=tuple(entry["mean_return"] for entry in masfols.history),
    )


def learned(
    build: Callable[[Path | None], MASFOLS], make_env: Callable[[], Any], runs: Path | None, name: str, iterations: int
) -> MASFOLS:
    """
    A run of ours trained for ``iterations`` iterations in all, its logs closed. With ``runs`` it keeps its run
    directory there, ``runs/name`` (a checkpoint after every iteration): a run found there goes on from its last
    checkpoint, or is only read once finished, so that a benchmark of hours survives an interruption. Its
    ``history[-1]["wall_time"]`` is that of all its sessions.

    :param build: a new run of the benchmark's settings, in the given run directory (None: none)
    :param make_env: the run's env, as ``build`` makes it (a continued run is as verbose as ``build``'s)
    :raises ValueError: ``runs/name`` holds a run of other settings
    """
    path = None if runs is None else Path(runs) / name
    masfols = build(path)
    if path is not None and RunDirectory(path).has_checkpoint():
        stored = RunSettings.stored(RunDirectory(path).read_config(), str(path / RunDirectory.RUN))
        masfols.close()
        if _as_json(stored.to_json()) != _as_json(masfols.settings.to_json()):
            raise ValueError(f"{path} holds a run of other settings than this benchmark's: move it away")
        masfols = MASFOLS.load(path, make_env(), verbose=masfols.callback.verbose)
    try:
        masfols.learn(max_iterations=iterations)
    finally:
        masfols.close()
    return masfols


def _as_json(settings: dict[str, Any]) -> Any:
    """Settings as ``run.json`` reads them back (arrays as lists)."""
    return json.loads(json.dumps(settings, default=lambda value: np.asarray(value).tolist()))


def _front_expected_utility(env: Any, weights: np.ndarray, gamma: float) -> float | None:
    """EU* by the env's own ``pareto_front(γ)`` (None where it has none)."""
    pareto_front = getattr(env.unwrapped, "pareto_front", None)
    if pareto_front is None:
        return None
    return float((weights @ np.array(pareto_front(gamma)).T).max(axis=1).mean())


# --- rows -------------------------------------------------------------------------------------------------------------
def _mean_std(values: Sequence[float], digits: int = 3) -> str:
    """``mean ± std`` over the seeds (the sample standard deviation; the value alone for one seed)."""
    mean = f"{statistics.mean(values):,.{digits}f}"
    return f"{mean} ± {statistics.stdev(values):,.{digits}f}" if len(values) > 1 else mean


def _score(expected_utility: float, best: float | None) -> float:
    """What a row reports: EU/EU* where the optimum is known, else EU (named by :func:`_score_name`)."""
    return expected_utility if best is None else expected_utility / best


def _score_name(best: float | None) -> str:
    return "EU" if best is None else "EU/EU*"


def _reference(best: float | None) -> str:
    """What a row's scores are measured against: EU*, or nothing where the problem has no known front."""
    return "no known front: EU alone" if best is None else f"EU* {best:.4f}"


def summary_row(
    name: str, case: str, outcomes: list[Outcome], best: float | None, baseline: str, seeds: list[int]
) -> Row:
    """The row of a method on a problem: its score over the seeds (mean ± std and each), EU, wall, steps, |Π|."""
    scores = [_score(o.expected_utility, best) for o in outcomes]
    notes = [
        f"per seed ({', '.join(map(str, seeds))}): {', '.join(f'{r:.3f}' for r in scores)}",
        f"EU {_mean_std([o.expected_utility for o in outcomes], 4)}",
        f"wall {_mean_std([o.wall_time for o in outcomes], 0)} s",
        f"env steps {_mean_std([o.env_steps for o in outcomes], 0)}",
        f"|Π| {_mean_std([o.n_policies for o in outcomes], 1)}",
    ]
    if all(o.monte_carlo is not None for o in outcomes):
        notes.insert(2, f"run's Monte-Carlo EU {_mean_std([o.monte_carlo for o in outcomes], 4)}")
    return Row(name, case, f"{_score_name(best)} {_mean_std(scores)}", baseline, note="; ".join(notes))


def seed_row(name: str, case: str, outcome: Outcome, best: float | None) -> Row:
    """The row of one seed's run: its score, EU, wall, steps, iterations, |Π| and its score after each iteration."""
    notes = f"{outcome.wall_time:.0f} s, {outcome.env_steps:,} env steps, {outcome.iterations} iterations"
    if outcome.n_policies:
        notes += f", |Π| = {outcome.n_policies}"
    if outcome.by_iteration:
        trace = ", ".join(f"{_score(value, best):.2f}" for value in outcome.by_iteration)
        notes += f"; {_score_name(best)} by iteration (Monte Carlo): {trace}"
    score = f"{_score_name(best)} {_score(outcome.expected_utility, best):.3f}"
    return Row(name, case, score, f"EU {outcome.expected_utility:.4f}", note=notes)


# --- morl-baselines (optional: pip install morl-baselines) ------------------------------------------------------------
@dataclass(frozen=True)
class Peer:
    """
    A morl-baselines algorithm run beside ours at the same env steps and scored the same way.

    :param module: the module of its class (imported only when the peer runs)
    :param name: its class's name
    :param label: how the rows name it
    :param train: builds and trains it: ``(class, problem, learner preset, seed, steps per iteration, iterations,
        checkpoint file or None)`` -> ``(agent, wall time of training)``
    :param policies: how many policies its GPI acts over, once trained
    :param steps_per_iteration: its own iteration length (None: ours); the smoke run always takes ours
    """

    module: str
    name: str
    label: str
    train: Callable[[Any, Problem, dict[str, Any], int, int, int, Path | None], tuple[Any, float]]
    policies: Callable[[Any], int]
    steps_per_iteration: int | None = None

    def load(self) -> Any:
        """The algorithm's class (:raises ImportError: morl-baselines is not installed)."""
        return getattr(importlib.import_module(self.module), self.name)

    def budget(self, problem: Problem, quick: bool, total: int | None) -> tuple[int, int]:
        """``(steps per iteration, iterations)``: ``total`` env steps (default: ours) in its iterations."""
        steps, iterations = problem.budget(quick)
        per_iteration = steps if quick or self.steps_per_iteration is None else self.steps_per_iteration
        return per_iteration, (total or steps * iterations) // per_iteration


def _train_mpmoq(
    algorithm: Any, problem: Problem, learner: dict[str, Any], seed: int, steps: int, iterations: int,
    checkpoint: Path | None,
) -> tuple[Any, float]:  # fmt: skip
    """MPMOQLearning (OLS weights, GPI, Dyna) with the preset's learning rate, γ and final ε; the agent and its wall
    time of training. Its runs take seconds: each starts anew, ``checkpoint`` is not written."""
    agent = algorithm(
        _seeded_env(problem, seed), learning_rate=learner["learning_rate"], gamma=learner["gamma"],
        initial_epsilon=1.0, final_epsilon=learner["exploration_final_eps"],
        epsilon_decay_steps=int(learner["exploration_fraction"] * steps * iterations),  # its ε decays over all steps
        weight_selection_algo="ols", epsilon_ols=0.0, use_gpi_policy=True, dyna=True, seed=seed, log=False,
    )  # fmt: skip
    d = agent.reward_dim
    start = time.perf_counter()
    agent.train(
        total_timesteps=steps * iterations, eval_env=_seeded_env(problem, derive_seed(seed, "peer eval")),
        ref_point=np.full(d, -100.0), timesteps_per_iteration=steps,
    )  # fmt: skip
    return agent, time.perf_counter() - start


#: GPI-LS's settings: morl-baselines' ``GPIPD`` with the settings of its minecart example
#: (``examples/gpi_pd_minecart.py``: two 4 × 256 SF networks conditioned on w with a min target, replay 200,000, ε
#: from 1 to 0.05 over 50,000 steps, target networks every 200 steps) and GPI-PD's own parts off (no prioritised
#: replay, no learned model), as the GPI-PD paper's GPI-LS; γ is ours (the deep preset's 0.98, the example's) and so
#: are its gradient updates per step.
GPI_LS_SETTINGS = {
    "num_nets": 2,
    "max_grad_norm": None,
    "learning_rate": 3e-4,
    "batch_size": 128,
    "net_arch": [256, 256, 256, 256],
    "buffer_size": 200_000,
    "initial_epsilon": 1.0,
    "final_epsilon": 0.05,
    "epsilon_decay_steps": 50_000,
    "learning_starts": 100,
    "target_net_update_freq": 200,
    "tau": 1,
    "per": False,
    "gpi_pd": False,
    "dyna": False,
    "use_gpi": True,
}


def _train_gpi_ls(
    algorithm: Any, problem: Problem, learner: dict[str, Any], seed: int, steps: int, iterations: int,
    checkpoint: Path | None,
) -> tuple[Any, float]:  # fmt: skip
    """GPI-LS at our gradient updates per step, no wandb, continued from ``checkpoint`` where a run is stored there
    (:func:`~benchmarks.gpi_ls_runs.train_gpi_ls`); the agent and its wall time of training."""
    updates = learner.get("gradient_steps", 1)

    def agent() -> Any:
        made = algorithm(
            _seeded_env(problem, seed), gamma=learner["gamma"], gradient_updates=updates, seed=seed, log=False,
            device=peer_device(), **GPI_LS_SETTINGS,
        )  # fmt: skip
        drop_sampled_indices(made)
        return made

    settings = {"env": problem.env_id, "seed": seed, "gamma": learner["gamma"], "gradient_updates": updates,
                "steps_per_iteration": steps, **GPI_LS_SETTINGS}  # fmt: skip
    eval_env = functools.partial(_seeded_env, problem, derive_seed(seed, "peer eval"))
    run = train_gpi_ls(agent, eval_env, settings, steps, iterations, checkpoint)
    return run.agent, run.wall_time


def drop_sampled_indices(agent: Any) -> None:
    """A GPI-PD agent without PER samples 5 arrays, as it unpacks them (morl-baselines 1.4 also returns indices)."""
    sample = agent._sample_batch_experiences
    agent._sample_batch_experiences = lambda: tuple(sample())[:5]


#: morl-baselines' peer by the kind of the problem's learners: tabular (True) or MLP (False).
PEERS = {
    True: Peer(  # tabular problems
        "morl_baselines.multi_policy.multi_policy_moqlearning.mp_mo_q_learning", "MPMOQLearning",
        "MPMOQLearning (OLS, GPI, Dyna)", _train_mpmoq, lambda agent: len(agent.policies),
    ),
    False: Peer(  # deep problems
        "morl_baselines.multi_policy.gpi_pd.gpi_pd", "GPIPD", "GPI-LS (GPIPD without PER and Dyna)", _train_gpi_ls,
        lambda agent: len(agent.weight_support), steps_per_iteration=10_000,  # its minecart example's
    ),
}  # fmt: skip


def _seeded_env(problem: Problem, seed: int) -> Any:
    """A fresh env of the problem, seeded for a peer (:func:`seeded`)."""
    return seeded(_make_env(problem), seed)


def seeded(env: Any, seed: int) -> Any:
    """``env`` with its first reset and its action sampling seeded (the peers reset without a seed)."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    return env


def seed_peer_generators(seed: int) -> None:
    """Seed the global generators a morl-baselines peer draws weights, minibatches and networks from."""
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 - theirs, not ours
    th.manual_seed(seed)


def peer_device() -> str:
    """A peer's torch device: CUDA where there is one, as ours (``device="auto"``), else the CPU."""
    return "auto" if th.cuda.is_available() else "cpu"


def _morl_rows(
    problems: list[Problem], seeds: list[int], quick: bool, peer_steps: int | None = None, runs: Path | None = None
) -> list[Row]:
    """Per problem, its morl-baselines peer (:data:`PEERS`) at the same env steps (or ``peer_steps``); with ``runs``,
    a resumable peer keeps its checkpoint there, ``<env id>-<peer>-s<seed>.pkl``."""
    peers = [(PEERS[problem.tabular], problem) for problem in problems]
    return [row for peer, problem in peers for row in _peer_rows(peer, problem, seeds, quick, peer_steps, runs)]


def _peer_rows(
    peer: Peer, problem: Problem, seeds: list[int], quick: bool, peer_steps: int | None, runs: Path | None = None
) -> list[Row]:
    """The summary row of one peer on one problem and a row per seed; one row where it is missing or fails."""
    steps, iterations = peer.budget(problem, quick, peer_steps)
    case = f"{problem.env_id}, morl-baselines {peer.label}, {iterations} × {steps:,} steps"
    try:
        algorithm = peer.load()
    except ImportError:
        return [Row(NAME, case, MORL_MISSING)]
    env = _make_env(problem)
    _, learner = _learner_of(problem)
    weights = random_weights(env.unwrapped.reward_space.shape[0], N_TEST_WEIGHTS, rng=0)
    model = _model(problem, env, learner["gamma"])
    best = _best(problem, env, model, weights, learner["gamma"])
    try:
        outcomes = [_train_peer(peer, algorithm, problem, learner, weights, model, seed, steps, iterations, runs)
                    for seed in seeds]  # fmt: skip
    except Exception as error:  # noqa: BLE001 - another version's API: say so in the table, go on
        return [Row(NAME, case, f"failed: {type(error).__name__}: {error}")]
    label = f"{problem.env_id} morl-baselines {peer.name}"
    return [summary_row(NAME, case, outcomes, best, _reference(best), seeds)] + [
        seed_row(NAME, f"{label} seed {seed}", outcome, best) for seed, outcome in zip(seeds, outcomes, strict=True)
    ]


def _train_peer(
    peer: Peer, algorithm: Any, problem: Problem, learner: dict[str, Any], weights: np.ndarray, model: Any,
    seed: int, steps: int, iterations: int, runs: Path | None,
) -> Outcome:  # fmt: skip
    """One seeded run of a peer, its GPI scored like ours: exactly by the model, else by rollouts."""
    seed_peer_generators(seed)
    checkpoint = None if runs is None else Path(runs) / f"{problem.env_id}-{peer.name}-s{seed}.pkl"
    agent, wall_time = peer.train(algorithm, problem, learner, seed, steps, iterations, checkpoint)
    if model is None:
        eu = rollout_expected_utility(problem, agent.eval, weights, learner["gamma"], seed)
    else:
        eu = model.expected_utility(lambda obs, w: [agent.eval(o, w) for o in obs], weights)
    return Outcome(eu, None, wall_time, int(agent.global_step), peer.policies(agent), iterations)


def rollout_expected_utility(
    problem: Problem, act: Callable[[Any, np.ndarray], int], weights: np.ndarray, gamma: float, seed: int
) -> float:
    """
    Monte-Carlo EU of a policy asked for one action at a time, by the protocol of our runs' test evaluation
    (:class:`~sb3_sfgpi.evaluation.TestEvaluation`): ``problem.eval_episodes`` episodes per test weight on a fresh
    env, those of weight ``i`` from ``derive_seed(seed, "eval", i)``; the mean over weights of w · discounted return.

    :param act: ``act(observation, w)`` -> action (a morl-baselines agent's ``eval``)
    :param seed: the run's seed
    """
    env = as_parallel_env(_make_env(problem))
    returns = [
        run_episodes(env, functools.partial(_joint_action, act, w), problem.eval_episodes, gamma,
                     seed=derive_seed(seed, "eval", i))
        for i, w in enumerate(weights)
    ]  # fmt: skip
    return summarize_test_episodes(weights, returns)[0]["mean_return"]


def _joint_action(act: Callable[[Any, np.ndarray], int], w: np.ndarray, observations: dict[str, Any]) -> dict:
    """Every live agent's action by ``act`` for the weight ``w``."""
    return {agent: act(observation, w) for agent, observation in observations.items()}
