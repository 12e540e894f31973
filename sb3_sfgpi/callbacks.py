"""MA-SFOLS (the paper's Algorithm 1): a loop of iterations, each one the runner's training orchestrated by OLS.

:func:`learn_iterations` is the loop: one :meth:`MultiAgentRunner.learn <sb3_sfgpi.multiagent.MultiAgentRunner.learn>`
per iteration, with an :class:`OLSCallback`. The runner owns the step loop (every agent's SFDQN acts, stores and
trains); the callback gives every learner its weights when training starts, and when it ends runs the rest of
Algorithm 1 (:meth:`OLSCallback._end_iteration`: values, OLS, Π, GPI's evaluation, the checkpoint). Where
the weights come from is a :mod:`schedule <sb3_sfgpi.schedules>`, which new policies join Π an
:class:`~sb3_sfgpi.admission.Admission`, how GPI is evaluated a :class:`~sb3_sfgpi.evaluation.TestEvaluation`,
and what is written where the :class:`~sb3_sfgpi.run_directory.RunDirectory`'s business.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

from sb3_sfgpi.admission import Admission, Candidate
from sb3_sfgpi.common.metrics import hypervolume
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights, same_weight
from sb3_sfgpi.evaluation import EvaluationConfig, TestEvaluation
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.run_directory import RunDirectory, summary_scalars
from sb3_sfgpi.run_policy_set import commit_policy_set, load_policy_set, stage_policy_set, staged_digest
from sb3_sfgpi.run_settings import VALUE_MODES, RunSettings
from sb3_sfgpi.schedules import AgentWeights, WeightSchedule
from sb3_sfgpi.sfdqn.training_state import training_state
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.tabular.pooling import PooledReplay
from sb3_sfgpi.validation import ValidationScorer


@dataclass(frozen=True)
class ValueEstimation:
    """
    How the value vector ``V^π`` of each new policy is estimated (Monte Carlo in the multi-agent env).

    :param mode: ``"joint"``: the new learners act together and the discounted return of a learner's agents (its
        mean over them, when agents share a learner) is the value of its policy; ``"shared"``: each new policy is
        run by every agent at once and its value is the mean discounted return over the agents (comparable between
        policies learned at different places of a heterogeneous env, e.g. different intersections)
    :param episodes: episodes of the estimate (per policy in ``"shared"`` mode)
    """

    mode: str = RunSettings.value_mode
    episodes: int = RunSettings.value_episodes

    def __post_init__(self) -> None:
        if self.mode not in VALUE_MODES:
            raise ValueError(f"mode must be one of {VALUE_MODES}, got {self.mode!r}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")


class OLSCallback(BaseCallback):
    """
    Algorithm 1 over a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner`: the weights of every iteration, Π, and the
    GPI evaluation.

    :param schedule: where the weights come from (:class:`~sb3_sfgpi.schedules.OLSSchedule` for MA-SFOLS)
    :param steps_per_iteration: joint env steps every learner trains for its weights in one iteration
    :param evaluation: how GPI is evaluated after every iteration
    :param values: how the values of new policies are estimated
    :param admission: which new policies join Π (default: all of them, as in the paper)
    :param run_dir: where Π, evaluations and checkpoints go (None: nowhere, or a temporary directory when the
        evaluation runs in worker processes)
    :param resume: continue from the checkpoint in ``run_dir`` if there is one
    :param verbose: 1 prints a line per iteration
    :param pooled: where given, every iteration's transitions are pooled and the SFs of the new policies and of every
        recorded one planned on the pool before the values are estimated (single-agent tabular runs; see
        :mod:`sb3_sfgpi.tabular.pooling`); the run directory keeps what each iteration added
    :param rebind_support: after every iteration each learner conditioned on the weights also offers Π its latest
        network bound to every earlier weight of OLS's support, for validation to admit (it needs validation weights)
    """

    model: MultiAgentRunner  # type: ignore[assignment]
    #: its ``on_step`` counts steps and reads nothing of them: the runner may show it compiled steps in batches
    takes_steps_in_batches = True

    def __init__(
        self,
        schedule: WeightSchedule,
        steps_per_iteration: int,
        evaluation: EvaluationConfig,
        values: ValueEstimation = ValueEstimation(),
        admission: Admission | None = None,
        run_dir: RunDirectory | str | Path | None = None,
        resume: bool = False,
        verbose: int = 0,
        pooled: PooledReplay | None = None,
        rebind_support: bool = False,
    ):
        super().__init__(verbose)
        if steps_per_iteration < 1:
            raise ValueError(f"steps_per_iteration must be positive, got {steps_per_iteration}")
        if resume and run_dir is None:
            raise ValueError("resume=True needs the run_dir to resume from")
        self.admission = admission or Admission(verbose=verbose)
        if rebind_support and not self.admission.validation_weights:
            raise ValueError("rebind_support offers Π networks for validation to admit: it needs validation weights")
        self.rebind_support = rebind_support
        if self.admission.validation_weights and evaluation.policies == "own":
            raise ValueError("policy validation scores GPI over the shared Π: not for policies='own' evaluations")
        self.schedule = schedule
        self.steps_per_iteration = steps_per_iteration
        self.evaluation = evaluation
        self.values = values
        self.pooled = pooled
        self.run_dir = run_dir if run_dir is None or isinstance(run_dir, RunDirectory) else RunDirectory(run_dir)
        self.resume = resume
        self.max_iterations: int | None = None  # set by learn_iterations, as is progress_bar
        self.progress_bar = False
        self.policy_set = GPIPolicy()  # Π: what GPI acts over
        self.record = GPIPolicy()  # every policy admitted to Π, those retired since included (what is saved)
        self.history: list[dict[str, Any]] = []
        self.iteration = 0
        self.weights: AgentWeights = {}
        #: the weights of the next iteration (None: the schedule ended; for OLS, Π's values form a CCS)
        self.next_weights: AgentWeights | None = None
        #: whether the last training the callback saw ran its iteration to the end (not stopped by a callback)
        self.iteration_ended = False
        self._iteration_bar: Any = None
        self._tests: TestEvaluation | None = None
        self._policy_dir: RunDirectory | None = self.run_dir
        self._staged_policy_set: Path | None = None  # the manifest of Π as the evaluation workers load it

    @property
    def reached_max_iterations(self) -> bool:
        """Whether the run has done its ``max_iterations``."""
        return self.max_iterations is not None and self.iteration >= self.max_iterations

    @property
    def ended_by_schedule(self) -> bool:
        """Whether the schedule has no more weights (for OLS: Π's values form a CCS) before the iteration cap."""
        return self.next_weights is None and not self.reached_max_iterations

    @property
    def started(self) -> bool:
        """Whether :meth:`start` ran."""
        return self._tests is not None

    # --- Algorithm 1 ----------------------------------------------------------------------------------------------
    def start(self, runner: MultiAgentRunner) -> None:
        """
        Lines 1-4 (the evaluation, validation and the schedule set up, the first weights), or the state of a resumed
        run's checkpoint. Once: a later call does nothing.
        """
        if self.started:
            return
        self.init_callback(runner)  # type: ignore[arg-type]
        self._tests = TestEvaluation(
            self.evaluation, runner.rollout, runner.reward_dim, runner.seed, runner.agents, runner.lockstep
        )
        validation_weights = self.admission.weights(runner.reward_dim, runner.seed)
        self.admission.start(
            ValidationScorer(
                validation_weights,
                runner.rollout,
                self.admission.episodes,
                runner.seed,
                "validation",
                runner.lockstep,
                runner.gpi_episodes,
            )
        )
        self.schedule.start(runner.reward_dim)
        if self.resume and self.run_dir is not None and self.run_dir.has_checkpoint():
            self.next_weights = self._restore()
        else:
            runner.num_timesteps = 0
            self.next_weights = self._next_weights()
        self._elapsed_before = self.history[-1]["wall_time"] if self.history else 0.0
        self._start_time = time.time()

    def _on_training_start(self) -> None:
        """Lines 6-14: every learner gets its weights (a fresh learner, or the conditioned one going on)."""
        assert self.next_weights is not None, "start() first, and no iteration once the schedule ended"
        self.iteration_ended = False
        self._start_iteration(self.next_weights)

    def _on_step(self) -> bool:
        if self._iteration_bar is not None:
            self._iteration_bar.update(1)
        return True

    def _on_training_end(self) -> None:
        """The rest of the iteration, if it ran all its steps (a callback may have stopped it, as a kill would)."""
        if self._iteration_bar is not None:
            self._iteration_bar.close()
        if self.model.num_timesteps - self._iteration_start >= self.steps_per_iteration:
            self._end_iteration()
            self.iteration_ended = True

    def _end_iteration(self) -> None:
        """Algorithm 1, lines 16-30: values, OLS and Π; then GPI evaluated, the checkpoint and the next weights."""
        self.model.end_iteration()  # line 15: the agents learned their policies and SFs
        self._pool_replay()  # with pooled replay: every policy's SFs planned on all that was seen so far
        candidates = [
            Candidate(self.model.learners[name], value, name)
            for name, value in self._estimate_values().items()  # lines 17-19: V^π of each agent's new policy
            if self.schedule.add(value, self.weights[name])  # lines 20-21, 23-28: a new value: OLS's corner weights
        ]
        if self.rebind_support:
            candidates += self._rebound()
        self.policy_set = self.admission.admit(self.record, candidates, self.iteration + 1)  # line 22: Π
        self._stage_policy_set()  # before the evaluation: its worker processes load Π
        self.history.append(self._evaluate_gpi())
        self.iteration += 1
        self.next_weights = self._next_weights()  # lines 6-14 of the next round (None, line 5: the queue is empty)
        self._write_checkpoint(self.next_weights)  # last: a resumed run starts here (even at the iteration cap)

    def _pool_replay(self) -> None:
        """With pooled replay: pool the iteration's transitions, plan the new and the recorded policies' SFs on them."""
        if self.pooled is None:
            return
        added = self.pooled.add_experiences(
            learner.policy.experience(learner.replay_buffer)
            for learner in self.model.learners.values()  # type: ignore[attr-defined, operator]
        )
        if self.run_dir is not None:
            self.run_dir.write_experience(self.iteration + 1, added.arrays())
        learners = list(self.model.learners.values())
        tables = cast("list[TabularSFNetwork]", [learner.policy.sf_net for learner in learners] + self.record.networks)
        weights = [learner.weights for learner in learners] + [info.weights for info in self.record.infos]
        self.pooled.plan(zip(tables, weights, strict=True))
        self.record.networks_changed()
        self.admission.forget()  # Π's SFs changed, and with them GPI's score over Π

    def _next_weights(self) -> AgentWeights | None:
        """
        The next weights from the schedule (top of the OLS queue, Dirichlet(1) beyond it), None when it ended.

        Learners conditioned on the weights are still learning every weight when OLS's queue empties (on minecart,
        every extremum's first value is the same cart that brings no ore: one CCS point, no corner left): a run with
        ``max_iterations`` then spends its budget on Dirichlet(1) weights, whose new values can queue corner weights
        again.
        """
        rng = np.random.default_rng(derive_seed(self.model.seed, "random-weights", self.iteration))
        weights = self.schedule.next_weights(self.model.learner_names, rng)
        if weights is None and self.model.conditioned_learners and self.max_iterations is not None:
            return {name: random_weights(self.model.reward_dim, rng=rng) for name in self.model.learner_names}
        return weights

    def _start_iteration(self, weights: AgentWeights) -> None:
        self.weights = weights
        self._iteration_start = self.model.num_timesteps
        self.model.start_iteration(weights, self.iteration, self.steps_per_iteration, support=self.schedule.ols.weights)
        if self.progress_bar:
            self._iteration_bar = tqdm(
                total=self.steps_per_iteration, desc=f"iteration {self.iteration + 1}", unit="step", leave=False
            )

    def _estimate_values(self) -> dict[str, np.ndarray]:
        """Monte-Carlo estimate of ``V^π`` of every new policy (see :class:`ValueEstimation`), by learner name."""
        runner, episodes, seed = self.model, self.values.episodes, self._value_seed()
        if self.values.mode == "joint":  # the learners act together; a policy's value is its agents' mean return
            returns = runner.rollout(runner.learner_policy(), episodes, seed)
            return {name: returns.mean_discounted_over(agents) for name, agents in runner.groups.items()}
        return {  # "shared": each new policy run by every agent
            name: runner.rollout(runner.learner_policy(name), episodes, seed).mean_discounted_over()
            for name in runner.learner_names
        }

    def _rebound(self) -> list[Candidate]:
        """
        Each conditioned learner's latest network bound to every earlier weight of OLS's support (not its iteration's
        own), with the value of that member acting alone for its weight, on the episodes of :meth:`_estimate_values`.
        """
        runner, seed = self.model, self._value_seed()
        offered = []
        for name, learner in runner.conditioned_learners.items():
            for w in (np.asarray(w, dtype=np.float64) for w in self.schedule.ols.weights):
                if same_weight(w, self.weights[name]):
                    continue
                alone = GPIPolicy()
                alone.add(learner, w)
                returns = runner.rollout(alone.joint_policy(w), self.values.episodes, seed)
                offered.append(Candidate(learner, returns.mean_discounted_over(runner.groups[name]), name, w))
        return offered

    def _value_seed(self) -> int:
        """The seed of the iteration's value episodes: the same episodes for every policy valued in it."""
        return derive_seed(self.model.seed, "value", self.iteration)

    # --- GPI evaluation ---------------------------------------------------------------------------------------------
    def _evaluate_gpi(self) -> dict[str, Any]:
        """GPI over Π on the test weights: the iteration's summary row (logged) with the per-weight details."""
        assert self._tests is not None
        eval_start = time.time()
        policy_dir = self._staged_policy_set
        metrics, details = self._tests.run(self.policy_set, policy_dir, self.model.gamma, self.progress_bar)
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
    def _stage_policy_set(self) -> None:
        """Stage Π in the run directory (its checkpoint commits it), or a temporary one for evaluation workers."""
        if self._policy_dir is None and self.evaluation.workers > 0:
            self._policy_dir = RunDirectory.temporary()  # the workers load Π from disk
        if self._policy_dir is not None and len(self.record):
            self._staged_policy_set = stage_policy_set(self._policy_dir, self.record, self.iteration + 1)

    def _write_checkpoint(self, next_weights: AgentWeights | None) -> None:
        if self.run_dir is None:
            return
        going_on = self.model.conditioned_learners
        if going_on:  # before the checkpoint that names them
            states = {name: training_state(learner) for name, learner in going_on.items()}
            self.run_dir.write_learners(self.iteration, states)
        checkpoint = {
            "iteration": self.iteration,
            "timesteps": self.model.num_timesteps,
            "n_policies": len(self.record),  # the record's: Π is its members as of "iteration"
            "schedule": self.schedule.state_dict(),
            "next_weights": None if next_weights is None else {a: w.tolist() for a, w in next_weights.items()},
            "learners": bool(going_on),  # learners that go on across iterations: their state in learners/
            "policy_set": staged_digest(self.run_dir),  # Π: the set this iteration staged
        }
        self.run_dir.write_iteration(self.history, checkpoint)
        commit_policy_set(self.run_dir)
        if going_on:
            self.run_dir.remove_learners_before(self.iteration)

    def _restore(self) -> AgentWeights | None:
        """Restore the state of the last finished iteration; return the next weights (None if the schedule ended)."""
        assert self.run_dir is not None
        commit_policy_set(self.run_dir)  # a set the checkpoint named but a killed writer did not commit
        state = self.run_dir.read_checkpoint()
        self.schedule.load_state_dict(state["schedule"])
        self.record = load_policy_set(self.run_dir, state["n_policies"], iteration=state["iteration"], record=True)
        self.policy_set = self.record.members()
        self.history = self.run_dir.read_history(state["iteration"])
        self.iteration = state["iteration"]
        if self.pooled is not None:
            table = cast(TabularSFNetwork, self.record.networks[0])  # the size of every table of the run
            for iteration in range(1, self.iteration + 1):
                self.pooled.add_saved(self.run_dir.read_experience(iteration), table)
        self.model.num_timesteps = state["timesteps"]
        if state.get("learners"):
            self.model.restore_learners(self.run_dir.read_learners(self.iteration))
        if state["next_weights"] is None:
            return None
        if set(state["next_weights"]) != set(self.model.learner_names):
            raise ValueError(
                f"checkpoint of {self.run_dir}: 'next_weights' is not for the learners {self.model.learner_names}"
            )
        return {agent: np.asarray(w, dtype=np.float64) for agent, w in state["next_weights"].items()}

    def close(self) -> None:
        """Stop the evaluation workers (if any) and delete a temporary copy of Π. Safe to call several times."""
        if self._tests is not None:
            self._tests.close()
        if self._policy_dir is not None and self._policy_dir is not self.run_dir:
            self._policy_dir.remove_temporary()
            self._policy_dir = None


def learn_iterations(
    runner: MultiAgentRunner,
    ols: OLSCallback,
    max_iterations: int | None = None,
    callbacks: Sequence[BaseCallback] = (),
    progress_bar: bool = False,
) -> None:
    """
    Algorithm 1 as a loop: from the first weights (or a checkpoint's), every iteration is one training of the runner
    for ``steps_per_iteration`` joint steps (line 15), which ``ols`` opens by giving the learners their weights and
    closes with values, OLS, Π, GPI's evaluation and the checkpoint; until the schedule ends (OLS: Π is a CCS),
    ``max_iterations`` iterations in all, or a callback stops the training.

    :param runner: the learners and the env
    :param ols: the run's OLS callback
    :param max_iterations: iterations in all, those of a resumed run included (None: until the schedule ends)
    :param callbacks: more runner-level callbacks (they see every joint step of every iteration)
    :param progress_bar: show progress bars (the iterations, each iteration's steps, the evaluation)
    """
    if max_iterations is not None and max_iterations < 1:
        raise ValueError(f"max_iterations must be positive or None, got {max_iterations}")
    ols.max_iterations, ols.progress_bar = max_iterations, progress_bar
    ols.start(runner)  # lines 1-4, or the checkpoint of a resumed run
    bar = tqdm(total=max_iterations, initial=ols.iteration, desc="iterations", disable=not progress_bar)
    try:
        while ols.next_weights is not None and not ols.reached_max_iterations:
            runner.learn(ols.steps_per_iteration, [ols, *callbacks])
            if not ols.iteration_ended:  # a callback stopped it, as a kill would: the checkpoint before stays
                break
            bar.update(1)
    finally:
        bar.close()
        ols.close()
