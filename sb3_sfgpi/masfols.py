"""MASFOLS: MA-SFOLS + GPI in one object, built from the runner and the callback (no logic of its own).

``MASFOLS(env, ...)`` makes a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` (one SFDQN per agent) and an
:class:`~sb3_sfgpi.callbacks.OLSCallback` with a :mod:`schedule <sb3_sfgpi.schedules>`; :meth:`MASFOLS.learn`
runs them; :attr:`MASFOLS.policy_set` is Π as a :class:`~sb3_sfgpi.gpi.GPIPolicy`. With a ``run_dir`` the run
writes its settings to ``run.json`` and continues from its directory with :meth:`MASFOLS.load`.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv
from stable_baselines3.common.type_aliases import MaybeCallback

from sb3_sfgpi.callbacks import EvaluationConfig, OLSCallback, PolicyValidation, ValueEstimation
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import SHARED, MultiAgentRunner, default_learner_factory
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.schedules import make_schedule

#: The settings stored in ``run.json`` (the arguments of :class:`MASFOLS` that are plain data).
SETTINGS = (
    "policy",
    "weights",
    "ols_batch",
    "steps_per_iteration",
    "learner_kwargs",
    "test_weights",
    "seed",
    "value_mode",
    "value_episodes",
    "eval_episodes",
    "gpi_set",
    "transfer",
    "gpi_behaviour",
    "validation_weights",
    "prune",
    "admit_together",
    "replan",
    "sharing",
    "n_envs",
)
#: Settings that runs written before they existed lack, with the value that reproduces those runs.
SETTING_DEFAULTS = {
    "validation_weights": 0,
    "prune": False,
    "admit_together": False,
    "sharing": "independent",
    "n_envs": 1,
    "ols_batch": "top",
    "gpi_behaviour": False,
    "replan": False,
}


def acts_by_own_policies(fixed: bool, sharing: str) -> bool:
    """
    Whether each agent of a run is evaluated by GPI over the policies it learned itself: fixed weights (a priori
    scalarised learners) with one learner per agent. Otherwise every agent acts by GPI over the whole set.
    """
    return fixed and sharing != SHARED


class MASFOLS:
    """
    MA-SFOLS + GPI over a PettingZoo ParallelEnv with vector rewards: one SFDQN per agent (or one that all agents
    share), OLS over the weights.

    :param env: the env (homogeneous agents, Discrete actions, ``reward_space(agent)``)
    :param policy: the learners' SFDQN policy, ``"TabularPolicy"`` or ``"MlpPolicy"``
    :param weights: ``"ols"`` (MA-SFOLS), ``"random"`` (Random + GPI: Dirichlet(1) weights) or array-like fixed
        weights (a priori scalarised learners: every agent trains for them; each agent is evaluated by GPI over
        its own policies, at these weights unless ``test_weights`` says otherwise)
    :param ols_batch: how an MA-SFOLS iteration takes its agents' weights from the OLS queue: ``"top"``, the
        highest priorities (Algorithm 1); ``"spread"``, each agent's weight ranked as if the weights handed out
        before it in the iteration brought no improvement; ``"same"``, the highest one for every agent;
        ``"same-after-extrema"``, ``"top"`` while simplex extrema are queued, ``"same"`` after (see
        :class:`~sb3_sfgpi.schedules.OLSSchedule`; only with ``weights="ols"``)
    :param steps_per_iteration: joint env steps every agent trains for its weights in one iteration
    :param learner_kwargs: further SFDQN arguments of the learners (learning rate, γ, exploration, ...)
    :param test_weights: the weights GPI is evaluated on after every iteration: an array ``(n, d)``, or a number
        ``n`` of Dirichlet(1) weights drawn with seed 0 (default 12)
    :param seed: the run's seed (learners, resets and random weights derive theirs from it)
    :param run_dir: where Π, evaluations, checkpoints and logs go (None: nowhere)
    :param value_mode: see :class:`~sb3_sfgpi.callbacks.ValueEstimation`
    :param value_episodes: episodes of each value estimate
    :param eval_episodes: episodes per test weight of the GPI evaluation
    :param gpi_set: GPI over ``"all"`` of Π or over its CCS (``"ccs"``)
    :param transfer: start each new learner from the policy of Π best for its weights
    :param gpi_behaviour: each new learner acts ε-greedily by GPI over Π and itself (SFOLS's behaviour; see
        :class:`~sb3_sfgpi.callbacks.OLSCallback`)
    :param validation_weights: a new policy joins Π only if GPI does at least as well with it on the simplex
        extrema and this many Dirichlet(1) validation weights (see :class:`~sb3_sfgpi.callbacks.PolicyValidation`;
        0: every new policy joins, as in the paper; not for fixed weights)
    :param prune: after every iteration, also retire from Π the policies without which GPI does better on the
        validation weights (needs ``validation_weights > 0``; see :class:`~sb3_sfgpi.callbacks.PolicyValidation`)
    :param admit_together: after the one-by-one admission of an iteration, also try its policies left out together:
        they join Π together if GPI does no worse with them all (needs ``validation_weights > 0``; nothing to do with
        ``sharing="shared"``: one policy per iteration)
    :param replan: old policies keep learning (``TabularPolicy`` only): after every iteration, every policy of Π and
        every new one is planned afresh, for its own weights, on the run's experience, every transition recorded by
        every learner so far (see :meth:`~sb3_sfgpi.callbacks.OLSCallback._replan`)
    :param sharing: ``"independent"``: one learner per agent, each trained for its own weights (every iteration
        trains as many weights as there are agents: the paper's setting); ``"shared"``: parameter sharing, one
        learner per iteration that every agent acts with and feeds (one weight per iteration, trained on all the
        agents' transitions; for many homogeneous agents); ``"experience"``: one learner per agent, for its own
        weights, that also stores the transitions of the other agents training for the same weights (experience
        sharing: in the rounds where several agents train for one weight, e.g. ``ols_batch="same"``, and with fixed
        weights). See :class:`~sb3_sfgpi.multiagent.MultiAgentRunner`
    :param n_envs: train on this many copies of the env, each in its own process (``env_fn``), stepped together: a
        learner has a slot per agent and copy. An iteration's ``steps_per_iteration`` joint steps then give
        ``n_envs`` times as many transitions. 1: train on ``env`` (evaluations always run on ``env``)
    :param env_fn: picklable env constructor of the copies (required when ``n_envs > 1``), and of the evaluation
        workers unless ``eval_env_fn`` is given
    :param env_kwargs: its keyword arguments
    :param eval_workers: evaluate GPI in this many worker processes (0: in this process)
    :param eval_env_fn: picklable env constructor of the workers (default: ``env_fn``; required when
        ``eval_workers > 0`` and there is no ``env_fn``)
    :param eval_env_kwargs: its keyword arguments (default: ``env_kwargs``)
    :param run_info: more plain data to store in ``run.json`` (e.g. the CLI's domain and env arguments)
    :param verbose: 1 prints a line per iteration
    :raises ValueError: learner options the learners refuse (a learner is built and dropped to check them)
    """

    def __init__(
        self,
        env: ParallelEnv,
        policy: str = "TabularPolicy",
        weights: str | np.ndarray | Sequence[float] = "ols",
        ols_batch: str = "top",
        steps_per_iteration: int = 10_000,
        learner_kwargs: Mapping[str, Any] | None = None,
        test_weights: int | np.ndarray | Sequence[Sequence[float]] | None = None,
        seed: int = 0,
        run_dir: str | Path | None = None,
        value_mode: str = "joint",
        value_episodes: int = 1,
        eval_episodes: int = 1,
        gpi_set: str = "all",
        transfer: bool = False,
        gpi_behaviour: bool = False,
        validation_weights: int = 0,
        prune: bool = False,
        admit_together: bool = False,
        replan: bool = False,
        sharing: str = "independent",
        n_envs: int = 1,
        env_fn: Callable[..., ParallelEnv] | None = None,
        env_kwargs: Mapping[str, Any] | None = None,
        eval_workers: int = 0,
        eval_env_fn: Callable[..., ParallelEnv] | None = None,
        eval_env_kwargs: Mapping[str, Any] | None = None,
        run_info: Mapping[str, Any] | None = None,
        verbose: int = 0,
    ):
        learner_kwargs = dict(learner_kwargs or {})
        if replan and policy != "TabularPolicy":
            raise ValueError(f"replan plans tables: it needs policy='TabularPolicy', not {policy!r}")
        self.runner = MultiAgentRunner(
            env,
            default_learner_factory(policy=policy, **learner_kwargs),
            seed=seed,
            gamma=learner_kwargs.get("gamma", 0.99),
            tensorboard_log=None if run_dir is None else str(RunDirectory(run_dir).tensorboard_dir),
            sharing=sharing,
            n_envs=n_envs,
            env_fn=env_fn,
            env_kwargs=env_kwargs,
        )
        self.runner.check_learner()
        fixed = not isinstance(weights, str)
        test_weights = self._test_weights(test_weights, weights if fixed else None)
        self.run_dir = None if run_dir is None else RunDirectory(run_dir)
        self.settings = {
            "policy": policy,
            "weights": weights if isinstance(weights, str) else np.asarray(weights, dtype=np.float64).tolist(),
            "ols_batch": ols_batch,
            "steps_per_iteration": steps_per_iteration,
            "learner_kwargs": learner_kwargs,
            "test_weights": test_weights.tolist(),
            "seed": seed,
            "value_mode": value_mode,
            "value_episodes": value_episodes,
            "eval_episodes": eval_episodes,
            "gpi_set": gpi_set,
            "transfer": transfer,
            "gpi_behaviour": gpi_behaviour,
            "validation_weights": validation_weights,
            "prune": prune,
            "admit_together": admit_together,
            "replan": replan,
            "sharing": sharing,
            "n_envs": n_envs,
        }
        policies = "own" if acts_by_own_policies(fixed, sharing) else "shared"
        evaluation = EvaluationConfig(
            test_weights, eval_episodes, policies, gpi_set, eval_workers,
            eval_env_fn or env_fn, dict(eval_env_kwargs or env_kwargs or {}),
        )  # fmt: skip
        self.callback = OLSCallback(
            make_schedule(weights, ols_batch),
            steps_per_iteration,
            evaluation,
            ValueEstimation(value_mode, value_episodes),
            PolicyValidation(validation_weights, prune=prune, together=admit_together),
            run_dir=self.run_dir,
            transfer=transfer,
            gpi_behaviour=gpi_behaviour,
            replan=replan,
            verbose=verbose,
        )
        self.run_info = {**dict(run_info or {}), **self.settings}
        if self.run_dir is not None:
            self.runner.set_logger(self.run_dir.make_logger())

    def _test_weights(self, test_weights: Any, fixed: Any) -> np.ndarray:
        if test_weights is None and fixed is not None:
            return np.array([fixed], dtype=np.float64)
        if test_weights is None or isinstance(test_weights, (int, np.integer)):
            n = 12 if test_weights is None else int(test_weights)
            if n < 1:
                raise ValueError(f"test_weights must be a positive number of weights or an array, got {n}")
            return random_weights(self.runner.reward_dim, n, rng=0)
        return np.asarray(test_weights, dtype=np.float64)

    @classmethod
    def load(cls, run_dir: str | Path, env: ParallelEnv, **kwargs: Any) -> MASFOLS:
        """
        Continue the run in ``run_dir`` from its last checkpoint, with the settings stored in its ``run.json``.

        :param run_dir: the run directory (written by a :class:`MASFOLS` with ``run_dir``)
        :param env: the env, built as for the run
        :param kwargs: arguments that are not stored: ``env_fn``, ``env_kwargs``, ``eval_workers``, ``eval_env_fn``,
            ``eval_env_kwargs``, ``verbose``
        :raises ValueError: not a run directory, or a stored setting missing
        """
        config = {**SETTING_DEFAULTS, **RunDirectory(run_dir).read_config()}
        missing = [key for key in SETTINGS if key not in config]
        if missing:
            raise ValueError(f"{run_dir}/run.json lacks the settings {missing}: not a run of MASFOLS")
        model = cls(env, **{key: config[key] for key in SETTINGS}, run_dir=run_dir, run_info=config, **kwargs)
        model.callback.resume = True
        return model

    def learn(
        self, max_iterations: int | None = None, callback: MaybeCallback = None, progress_bar: bool = False
    ) -> MASFOLS:
        """
        Run Algorithm 1 until the schedule ends (OLS: Π is a CCS) or for ``max_iterations`` iterations in all.

        :param max_iterations: iterations in all, those of a continued run included (None: until OLS ends)
        :param callback: more runner-level callbacks (they see every joint step)
        :param progress_bar: show progress bars (all steps, the iteration, the evaluation)
        :return: self
        """
        if self.run_dir is not None and not self.callback.resume:
            if self.run_dir.has_checkpoint():
                raise ValueError(f"{self.run_dir} already holds a run: continue it with MASFOLS.load")
            self.run_dir.write_config(self.run_info)
        self.callback.max_iterations = max_iterations
        self.callback.progress_bar = progress_bar
        steps = self.callback.steps_per_iteration
        total = sys.maxsize if max_iterations is None else max_iterations * steps
        extra = [] if callback is None else callback if isinstance(callback, list) else [callback]
        self.runner.learn(total, [self.callback, *extra], progress_bar=progress_bar and max_iterations is not None)
        return self

    @property
    def policy_set(self) -> GPIPolicy:
        """Π: every policy kept so far, acting by GPI for any weights."""
        return self.callback.policy_set

    @property
    def history(self) -> list[dict[str, Any]]:
        """Per finished iteration: the summary row, the weights trained and GPI's returns on the test weights."""
        return self.callback.history

    def close(self) -> None:
        """Stop evaluation workers and the env's copies, and close the env."""
        self.callback.close()
        self.runner.close()
        self.runner.env.close()
