"""MA-SFOLS (the paper's Algorithm 1) as an SB3 callback orchestrating the learners of a multi-agent runner.

:class:`OLSCallback` is given to :meth:`MultiAgentRunner.learn <sb3_sfgpi.multiagent.MultiAgentRunner.learn>`.
The runner owns the step loop (every agent's SFDQN acts, stores and trains); the callback decides the weights.
An iteration is: every learner (one per agent, or one that all agents share) starts afresh for the weights the
schedule gave it and trains for
``steps_per_iteration`` joint steps; then :meth:`OLSCallback._end_iteration` runs the rest of Algorithm 1 —
the values of the new policies, OLS and Π updated, GPI evaluated on the test weights, the checkpoint written, the
next weights taken from the schedule. The run stops when the schedule ends (OLS: Π is a CCS) or after
``max_iterations``. Where the weights come from is a :mod:`schedule <sb3_sfgpi.schedules>` (MA-SFOLS, Random +
GPI or fixed weights); what is written where is the :class:`~sb3_sfgpi.run_directory.RunDirectory`'s business.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

from sb3_sfgpi.common.metrics import hypervolume
from sb3_sfgpi.common.rollouts import EpisodeReturns
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights, validate_weights
from sb3_sfgpi.evaluation import EvaluationJob, ParallelEvaluator, gpi_score, summarize_test_episodes
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.run_directory import RunDirectory, summary_scalars
from sb3_sfgpi.schedules import AgentWeights, WeightSchedule
from sb3_sfgpi.sfdqn.planning import EmpiricalModel, Experience, plan_afresh
from sb3_sfgpi.sfdqn.sfdqn import SETTLE_SWEEPS

#: How the values of new policies can be estimated (see :class:`ValueEstimation`)
VALUE_MODES = ("joint", "shared", "gpi")


@dataclass(frozen=True)
class EvaluationConfig:
    """
    How GPI over Π is evaluated after every iteration.

    :param test_weights: the weights GPI acts for, shape ``(n, d)``
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

    test_weights: np.ndarray
    episodes: int = 1
    policies: str = "shared"
    gpi_set: str = "all"
    workers: int = 0
    env_fn: Callable[..., Any] | None = None
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    hypervolume_reference: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "test_weights", np.asarray(self.test_weights, dtype=np.float64))
        if self.policies not in ("shared", "own"):
            raise ValueError(f"policies must be 'shared' or 'own', got {self.policies!r}")
        if self.gpi_set not in ("all", "ccs"):
            raise ValueError(f"gpi_set must be 'all' or 'ccs', got {self.gpi_set!r}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ValueError(f"workers must be a non-negative integer, got {self.workers!r}")
        if self.workers > 0 and self.env_fn is None:
            raise ValueError("workers > 0 needs env_fn (and env_kwargs) to build the workers' envs")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")


@dataclass(frozen=True)
class ValueEstimation:
    """
    How the value vector ``V^π`` of each new policy is estimated (Monte Carlo in the multi-agent env).

    :param mode: ``"joint"``: the new learners act together and the discounted return of a learner's agents (its
        mean over them, when agents share a learner) is the value of its policy; ``"shared"``: each new policy is
        run by every agent at once and its value is the mean discounted return over the agents (comparable between
        policies learned at different places of a heterogeneous env, e.g. different intersections); ``"gpi"``:
        the value of the GPI agent at the learner's weights (SFOLS, GPI-LS), every agent acting by GPI over Π and
        the iteration's new policies, its mean discounted return over the agents (GPI over all of Π: not with
        ``gpi_set="ccs"``, whose members are chosen by these values)
    :param episodes: episodes of the estimate (per policy in ``"shared"`` mode, per learner in ``"gpi"`` mode)
    """

    mode: str = "joint"
    episodes: int = 1

    def __post_init__(self) -> None:
        if self.mode not in VALUE_MODES:
            raise ValueError(f"mode must be one of {VALUE_MODES}, got {self.mode!r}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")


@dataclass(frozen=True)
class PolicyValidation:
    """
    Which new policies join Π. With ``n_weights > 0`` a new policy joins only if GPI over Π does at least as well
    with it as without it on validation weights: the simplex extrema and ``n_weights`` Dirichlet(1) weights drawn
    from the run's seed (not the test weights), scored by the mean over weights and agents of the discounted
    w·return, every agent acting by GPI. A policy left out is one whose SFs promise more than it returns where GPI
    would follow it (in a multi-agent env, typically objects its partner takes first). Its value still goes to the
    schedule, so the weights trained, and the learners, are the same with and without validation.

    With ``together``, the new policies of an iteration that were left out one by one are then tried together: they
    join Π together if GPI does at least as well with all of them. Two agents' policies can each mislead GPI alone
    and help it together (one knows the states the other's SFs lead GPI to; measured in README "Four-Room"). Only
    the whole group is tried, and only when two or more were left out: one policy left out before a later one of its
    iteration joined is not tried again. With a shared learner an iteration has one policy, and this does nothing.

    With ``prune``, validation also looks back after every iteration: as long as GPI does strictly better on the
    validation weights without one of Π's policies, the policy without which it does best is retired from Π
    (backward elimination). A policy admitted early can mislead GPI later, once the policies its partner acts
    by have changed. Retired policies stay in the run's record (see :meth:`~sb3_sfgpi.gpi.GPIPolicy.retire`).

    :param n_weights: Dirichlet(1) validation weights besides the extrema; 0: every new policy joins Π (the paper)
    :param episodes: episodes per validation weight
    :param prune: also retire policies without which GPI does better (needs ``n_weights > 0``)
    :param together: also try an iteration's policies left out one by one together (needs ``n_weights > 0``)
    """

    n_weights: int = 0
    episodes: int = 1
    prune: bool = False
    together: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.n_weights, bool) or not isinstance(self.n_weights, int) or self.n_weights < 0:
            raise ValueError(f"n_weights must be a non-negative integer, got {self.n_weights!r}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")
        if self.prune and not self.n_weights:
            raise ValueError("pruning Π needs validation weights: n_weights must be positive")
        if self.together and not self.n_weights:
            raise ValueError("admitting policies together needs validation weights: n_weights must be positive")

    def weights(self, reward_dim: int, seed: int) -> np.ndarray:
        """The validation weights of a run with ``seed``, shape ``(reward_dim + n_weights, reward_dim)``."""
        drawn = random_weights(reward_dim, self.n_weights, rng=derive_seed(seed, "validation-weights"))
        return np.vstack([np.eye(reward_dim), drawn])


class OLSCallback(BaseCallback):
    """
    Algorithm 1 over a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner`: the weights of every iteration, Π, and the
    GPI evaluation.

    :param schedule: where the weights come from (:class:`~sb3_sfgpi.schedules.OLSSchedule` for MA-SFOLS)
    :param steps_per_iteration: joint env steps every learner trains for its weights in one iteration
    :param evaluation: how GPI is evaluated after every iteration
    :param values: how the values of new policies are estimated
    :param validation: which new policies join Π (default: all of them)
    :param run_dir: where Π, evaluations and checkpoints go (None: nowhere, or a temporary directory when the
        evaluation runs in worker processes)
    :param resume: continue from the checkpoint in ``run_dir`` if there is one
    :param max_iterations: stop after this many iterations (None: only when the schedule ends)
    :param transfer: start each new learner from the policy of Π that is best for its weights
    :param gpi_behaviour: each new learner acts ε-greedily by GPI over Π (as GPI acts at execution) and itself
        (SFOLS's behaviour), instead of by itself alone; what it learns stays its own policy's SFs
    :param replan: old policies keep learning (tabular learners only): after every iteration its transitions join
        the run's experience (every transition every learner recorded, pooled), and every policy of Π and every new
        one is planned from ψ = 0 on that experience's model for its own weights, until it converges (see
        :meth:`_replan`)
    :param progress_bar: show progress bars for the iteration and the evaluation
    :param verbose: 1 prints a line per iteration
    """

    model: MultiAgentRunner  # type: ignore[assignment]

    def __init__(
        self,
        schedule: WeightSchedule,
        steps_per_iteration: int,
        evaluation: EvaluationConfig,
        values: ValueEstimation = ValueEstimation(),
        validation: PolicyValidation = PolicyValidation(),
        run_dir: RunDirectory | str | Path | None = None,
        resume: bool = False,
        max_iterations: int | None = None,
        transfer: bool = False,
        gpi_behaviour: bool = False,
        replan: bool = False,
        progress_bar: bool = False,
        verbose: int = 0,
    ):
        super().__init__(verbose)
        if steps_per_iteration < 1:
            raise ValueError(f"steps_per_iteration must be positive, got {steps_per_iteration}")
        if resume and run_dir is None:
            raise ValueError("resume=True needs the run_dir to resume from")
        if max_iterations is not None and max_iterations < 1:
            raise ValueError(f"max_iterations must be positive or None, got {max_iterations}")
        self.schedule = schedule
        self.steps_per_iteration = steps_per_iteration
        self.evaluation = evaluation
        self.values = values
        self.validation = validation
        if validation.n_weights and evaluation.policies == "own":
            raise ValueError("policy validation scores GPI over the shared Π: not for policies='own' evaluations")
        if gpi_behaviour and evaluation.policies == "own":
            raise ValueError("GPI behaviour acts over the shared Π: not for policies='own' evaluations")
        if values.mode == "gpi" and evaluation.gpi_set == "ccs":
            raise ValueError("value mode 'gpi' takes GPI over all of Π: not with gpi_set='ccs' (chosen by the values)")
        self.run_dir = run_dir if run_dir is None or isinstance(run_dir, RunDirectory) else RunDirectory(run_dir)
        self.resume = resume
        self.max_iterations = max_iterations
        self.transfer = transfer
        self.gpi_behaviour = gpi_behaviour
        self.replan = replan
        self.experience: Experience | None = None  # with replan: every transition recorded so far, pooled
        self.progress_bar = progress_bar
        self.policy_set = GPIPolicy()  # Π: what GPI acts over
        self.record = GPIPolicy()  # every policy admitted to Π, those retired since included (what is saved)
        self.history: list[dict[str, Any]] = []
        self.iteration = 0
        self.weights: AgentWeights = {}
        self.finished = False
        self._iteration_bar: Any = None
        self._evaluator: ParallelEvaluator | None = None
        self._policy_dir: RunDirectory | None = self.run_dir
        self._started = False
        self._pending: AgentWeights | None = None  # the next weights, when a call of learn() stopped at its cap
        self._validation_score: float | None = None  # GPI's score over Π on the validation weights (cache)

    @property
    def reached_max_iterations(self) -> bool:
        """Whether the run has done its ``max_iterations``."""
        return self.max_iterations is not None and self.iteration >= self.max_iterations

    @property
    def ended_by_schedule(self) -> bool:
        """Whether the schedule has no more weights (for OLS: Π's values form a CCS)."""
        return self.finished and not self.reached_max_iterations

    # --- Algorithm 1 ----------------------------------------------------------------------------------------------
    def _on_training_start(self) -> None:
        if self._started:  # learn() called again: continue where the last call stopped
            self.finished = self._pending is None or self.reached_max_iterations
            if not self.finished:
                self._start_iteration(self._pending)  # type: ignore[arg-type]
            return
        self._started = True
        reward_dim = self.model.reward_dim
        test_weights = np.array([validate_weights(w, reward_dim, "test weight") for w in self.evaluation.test_weights])
        self._test_weights = test_weights
        self.schedule.start(reward_dim)
        if self.resume and self.run_dir is not None and self.run_dir.has_checkpoint():
            weights = self._restore()
        else:
            self.model.num_timesteps = 0
            weights = self._next_weights()
        self._elapsed_before = self.history[-1]["wall_time"] if self.history else 0.0
        self._start_time = time.time()
        self._pending = weights
        if weights is None or self.reached_max_iterations:
            self.finished = True
        else:
            self._start_iteration(weights)

    def _on_step(self) -> bool:
        if self.finished:
            return False
        if self._iteration_bar is not None:
            self._iteration_bar.update(1)
        if self.model.num_timesteps - self._iteration_start >= self.steps_per_iteration:
            self._end_iteration()
        return not self.finished

    def _end_iteration(self) -> None:
        """Algorithm 1 after training: values → OLS and Π → GPI evaluated → checkpoint → next weights."""
        if self._iteration_bar is not None:
            self._iteration_bar.close()
        self.model.end_iteration()
        if self.replan:
            self._replan()
        left_out: dict[str, np.ndarray] = {}
        for name, value in self._estimate_values().items():
            # a new value: the policy is a candidate for Π
            if self.schedule.add(value, self.weights[name]) and not self._admit({name: value}):
                left_out[name] = value
        if self.validation.together and len(left_out) > 1:
            self._admit(left_out)
        if self.validation.prune:
            self._prune()
        self._save_policy_set()  # before the evaluation: its worker processes load Π
        self.history.append(self._evaluate_gpi())
        self.iteration += 1
        next_weights = self._next_weights()  # saved even at the iteration cap, so that a resume can go further
        self._write_checkpoint(next_weights)
        self._pending = next_weights
        if next_weights is None or self.reached_max_iterations:
            self.finished = True
        else:
            self._start_iteration(next_weights)

    def _replan(self) -> None:
        """
        Old policies keep learning: the iteration's transitions join the run's experience, on which every policy of Π
        and every new one is then planned afresh for its own weights (GPI-PD's old policies trained on the replayed
        data, done exactly for tables). A policy's table becomes a function of the experience and its weights alone,
        so a resumed run plans Π again from the checkpoint's experience and goes on exactly.
        """
        for learner in self.model.learners.values():
            recorded = learner.policy.experience(learner.replay_buffer)
            self.experience = recorded if self.experience is None else self.experience.merge(recorded)
        model = self.experience.model()
        for learner in self.model.learners.values():
            learner.policy.plan_afresh(model, self.model.gamma, SETTLE_SWEEPS)
        self._plan_policy_set(model)

    def _plan_policy_set(self, model: EmpiricalModel) -> None:
        """Plan every policy of Π afresh on ``model``, the run's experience's (see :meth:`_replan`)."""
        for net, info in zip(self.record.networks, self.record.infos, strict=True):
            if info.retired is None:
                plan_afresh(net.entries(), model, info.weights, self.model.gamma, SETTLE_SWEEPS)
        self.record.networks_changed()
        self.policy_set = self.record.members()
        self._validation_score = None

    def _next_weights(self) -> AgentWeights | None:
        """The next weights from the schedule (top of the OLS queue, Dirichlet(1) beyond it), None when it ended."""
        rng = np.random.default_rng(derive_seed(self.model.seed, "random-weights", self.iteration))
        return self.schedule.next_weights(self.model.learner_names, rng)

    def _start_iteration(self, weights: AgentWeights) -> None:
        self.weights = weights
        self._iteration_start = self.model.num_timesteps
        init = None
        if self.transfer and len(self.policy_set):
            init = {name: self._best_network(w) for name, w in weights.items()}
        self.model.start_iteration(weights, self.iteration, self.steps_per_iteration, init_networks=init)
        if self.gpi_behaviour and len(self.policy_set):
            behaviour_set = self._gpi_policies()
            for learner in self.model.learners.values():
                learner.behaviour_set = behaviour_set
        if self.progress_bar:
            self._iteration_bar = tqdm(
                total=self.steps_per_iteration, desc=f"iteration {self.iteration + 1}", unit="step", leave=False
            )

    def _best_network(self, w: np.ndarray) -> Any:
        values = [info.value if info.value is not None else np.full_like(w, -np.inf) for info in self.policy_set.infos]
        return self.policy_set.networks[int(np.argmax([np.dot(w, v) for v in values]))]

    def _estimate_values(self) -> dict[str, np.ndarray]:
        """Monte-Carlo estimate of ``V^π`` of every new policy (see :class:`ValueEstimation`), by learner name."""
        runner, episodes = self.model, self.values.episodes
        seed = derive_seed(runner.seed, "value", self.iteration)  # the same episodes for every policy
        if self.values.mode == "joint":  # the learners act together; a policy's value is its agents' mean return
            returns = runner.rollout(runner.learner_policy(), episodes, seed)
            return {name: returns.mean_discounted_over(agents) for name, agents in runner.groups.items()}
        if self.values.mode == "gpi":  # GPI over Π and the new policies, at each learner's weights
            candidates = self.policy_set.subset(range(len(self.policy_set)))
            for name in runner.learner_names:
                candidates.add(runner.learners[name], agent=name)
            policies = {name: candidates.joint_policy(w) for name, w in self.weights.items()}
        else:  # "shared": each new policy run by every agent
            policies = {name: runner.learner_policy(name) for name in runner.learner_names}
        return {
            name: runner.rollout(policy, episodes, seed).mean_discounted_over() for name, policy in policies.items()
        }

    def _admit(self, values: dict[str, np.ndarray]) -> bool:
        """
        Add the new policies of the learners named in ``values`` (name -> value) to Π, unless GPI does worse with
        them on the validation weights: all of them or none.

        :return: whether they joined Π
        """
        validate = self.validation.n_weights > 0 and len(self.policy_set) > 0
        before = self._gpi_validation_score() if validate else 0.0
        for name, value in values.items():
            self.policy_set.add(self.model.learners[name], value=value, agent=name, iteration=self.iteration + 1)
        self._validation_score = None  # Π changed
        if validate and (after := self._gpi_validation_score()) < before:
            for _ in values:
                self.policy_set.pop()
            self._validation_score = before
            if self.verbose:
                policies = "policy" if len(values) == 1 else "policies together"
                print(f"{' and '.join(values)}'s {policies} left out of Π: GPI on the validation weights {after:.4f} "
                      f"with, {before:.4f} without")  # fmt: skip
            return False
        for name, value in values.items():
            self.record.add(self.model.learners[name], value=value, agent=name, iteration=self.iteration + 1)
        return True

    def _prune(self) -> None:
        """Retire from Π, one at a time, the policy without which GPI does best, while it does better without it."""
        while len(self.policy_set) > 1:
            others = [[j for j in range(len(self.policy_set)) if j != i] for i in range(len(self.policy_set))]
            scores = [self._validation_score_of(self.policy_set.subset(rest)) for rest in others]
            worst = int(np.argmax(scores))
            if scores[worst] <= self._gpi_validation_score():
                return
            if self.verbose:
                info = self.policy_set.infos[worst]
                print(f"{info.agent}'s policy of iteration {info.iteration} retired from Π: GPI on the validation "
                      f"weights {scores[worst]:.4f} without it, {self._gpi_validation_score():.4f} with")  # fmt: skip
            members = [i for i, info in enumerate(self.record.infos) if info.retired is None]
            self.record.retire(members[worst], self.iteration + 1)
            self.policy_set = self.policy_set.subset(others[worst])
            self._validation_score = scores[worst]

    def _gpi_validation_score(self) -> float:
        """GPI over Π on the validation weights (cached until Π changes)."""
        if self._validation_score is None:
            self._validation_score = self._validation_score_of(self.policy_set)
        return self._validation_score

    def _validation_score_of(self, policy_set: GPIPolicy) -> float:
        """GPI over ``policy_set`` on the validation weights: mean over weights and agents of the discounted return."""
        runner, validation = self.model, self.validation
        weights = validation.weights(runner.reward_dim, runner.seed)
        return gpi_score(policy_set, weights, runner.rollout, validation.episodes, runner.seed, "validation")

    # --- GPI evaluation ---------------------------------------------------------------------------------------------
    def _evaluate_gpi(self) -> dict[str, Any]:
        """GPI over Π on the test weights: the iteration's summary row (logged) with the per-weight details."""
        eval_start = time.time()
        metrics, details = summarize_test_episodes(self._test_weights, self._run_test_episodes())
        reference = self.evaluation.hypervolume_reference
        summary = {
            "iteration": self.iteration + 1,  # iterations are numbered from 1 wherever they are named
            "timesteps": self.model.num_timesteps,
            "n_policies": len(self.policy_set),
            "ccs_size": len(self.schedule.ols.ccs),
            **metrics,
            "hypervolume": None if reference is None else hypervolume(np.array(self.schedule.ols.ccs), reference),
            "wall_time": self._elapsed_before + time.time() - self._start_time,
            "eval_time": time.time() - eval_start,
        }
        self._log(summary)
        trained = {agent: w.tolist() for agent, w in self.weights.items()}
        return {**summary, "weights_trained": trained, "test": details}

    def _run_test_episodes(self) -> list[EpisodeReturns]:
        """Per test weight, the episodes of the agents acting by GPI (in this process or in the workers)."""
        runner, config = self.model, self.evaluation
        seeds = [derive_seed(runner.seed, "eval", i) for i in range(len(self._test_weights))]
        own = config.policies == "own"
        ccs_only = config.gpi_set == "ccs" and not own
        if config.workers > 0:
            assert self._policy_dir is not None and config.env_fn is not None
            if self._evaluator is None:
                self._evaluator = ParallelEvaluator(config.env_fn, config.env_kwargs, config.workers, runner.gamma)
            policy_dir = str(self._policy_dir.policy_set_dir)
            jobs = [
                EvaluationJob(seed, tuple(w), config.episodes, policy_dir, own_policies=own, ccs_only=ccs_only)
                for w, seed in zip(self._test_weights, seeds, strict=True)
            ]
            return self._evaluator.run(jobs)
        policy_set = self._gpi_policies()
        agents = runner.agents if own else None
        bar = tqdm(self._test_weights, desc="evaluating GPI", unit="w", leave=False, disable=not self.progress_bar)
        return [
            runner.rollout(policy_set.joint_policy(w, agents), config.episodes, seed)
            for w, seed in zip(bar, seeds, strict=True)
        ]

    def _gpi_policies(self) -> GPIPolicy:
        """The policies GPI acts over: Π, or its CCS (``gpi_set="ccs"``, not with ``policies="own"``)."""
        ccs_only = self.evaluation.gpi_set == "ccs" and self.evaluation.policies != "own"
        return self.policy_set.ccs_policies() if ccs_only else self.policy_set

    def _log(self, summary: dict[str, Any]) -> None:
        for key, value in summary_scalars(summary).items():
            self.logger.record(key, value)
        self.logger.dump(step=summary["iteration"])
        if self.verbose:
            print(
                f"iteration {summary['iteration']}: |Π|={summary['n_policies']} CCS={summary['ccs_size']} "
                f"mean w·return (discounted)={summary['mean_return']:.4f} ({summary['wall_time']:.1f}s, "
                f"GPI evaluation {summary['eval_time']:.1f}s)"
            )

    # --- run directory --------------------------------------------------------------------------------------------
    def _save_policy_set(self) -> None:
        if self._policy_dir is None and self.evaluation.workers > 0:
            self._policy_dir = RunDirectory.temporary()  # the workers load Π from disk
        if self._policy_dir is not None and len(self.record):
            self._policy_dir.save_policy_set(self.record)

    def _write_checkpoint(self, next_weights: AgentWeights | None) -> None:
        if self.run_dir is None:
            return
        checkpoint = {
            "iteration": self.iteration,
            "timesteps": self.model.num_timesteps,
            "n_policies": len(self.record),  # the record's: Π is its members as of "iteration"
            "schedule": self.schedule.state_dict(),
            "next_weights": None if next_weights is None else {a: w.tolist() for a, w in next_weights.items()},
        }
        if self.experience is not None:
            self.run_dir.save_experience(self.experience, self.iteration)
        self.run_dir.write_iteration(self.history, checkpoint)
        if self.experience is not None:
            self.run_dir.remove_older_experience(self.iteration)

    def _restore(self) -> AgentWeights | None:
        """Restore the state of the last finished iteration; return the next weights (None if the schedule ended)."""
        assert self.run_dir is not None
        state = self.run_dir.read_checkpoint()
        self.schedule.load_state_dict(state["schedule"])
        self.record = self.run_dir.load_policy_set(state["n_policies"], iteration=state["iteration"], record=True)
        self.policy_set = self.record.members()
        if self.replan:  # Π as the checkpoint's iteration planned it (Π's files may be from a later one)
            self.experience = self.run_dir.load_experience(state["iteration"])
            self._plan_policy_set(self.experience.model())
        self.history = self.run_dir.read_history(state["iteration"])
        self.iteration = state["iteration"]
        self.model.num_timesteps = state["timesteps"]
        if state["next_weights"] is None:
            return None
        if set(state["next_weights"]) != set(self.model.learner_names):
            raise ValueError(
                f"checkpoint of {self.run_dir}: 'next_weights' is not for the learners {self.model.learner_names}"
            )
        return {agent: np.asarray(w, dtype=np.float64) for agent, w in state["next_weights"].items()}

    def _on_training_end(self) -> None:
        self.close()

    def close(self) -> None:
        """Stop the evaluation workers (if any) and delete a temporary copy of Π. Safe to call several times."""
        if self._evaluator is not None:
            self._evaluator.close()
            self._evaluator = None
        if self._policy_dir is not None and self._policy_dir is not self.run_dir:
            self._policy_dir.remove_temporary()
            self._policy_dir = None
