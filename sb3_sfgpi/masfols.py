"""MASFOLS: MA-SFOLS + GPI in one object, built from the runner and the callback (no logic of its own).

``MASFOLS(env, ...)`` makes a :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` (one SFDQN per agent) and an
:class:`~sb3_sfgpi.callbacks.OLSCallback` with a :mod:`schedule <sb3_sfgpi.schedules>` and an
:class:`~sb3_sfgpi.admission.Admission`; :meth:`MASFOLS.learn` runs them; :attr:`MASFOLS.policy_set` is Π as a
:class:`~sb3_sfgpi.gpi.GPIPolicy`. With a ``run_dir`` the run writes its settings to ``run.json`` and continues
from its directory with :meth:`MASFOLS.load`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv
from stable_baselines3.common.type_aliases import MaybeCallback

from sb3_sfgpi.admission import Admission
from sb3_sfgpi.callbacks import OLSCallback, ValueEstimation, learn_iterations
from sb3_sfgpi.common.software import software_versions
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import EvaluationConfig
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.learners import default_learner_factory, replay_sized
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_logger import run_logger
from sb3_sfgpi.run_settings import GAMMA, RunSettings, acts_by_own_policies
from sb3_sfgpi.schedules import make_schedule
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.conditioned import ConditionedPolicy
from sb3_sfgpi.tabular.pooling import PooledReplay
from sb3_sfgpi.trust import check_learner_kwargs


class MASFOLS:
    """
    MA-SFOLS + GPI over a PettingZoo ParallelEnv with vector rewards: one SFDQN per agent (or one that all agents
    share), OLS over the weights. Given a single-agent Gymnasium env (MO-Gymnasium's), it is SFOLS + GPI: the same
    algorithm with one agent.

    :param env: the env: a ParallelEnv (homogeneous agents, Discrete actions, ``reward_space(agent)``) or a
        Gymnasium env with a ``reward_space`` (``mo_gymnasium.make(...)``)
    :param policy: the learners' SFDQN policy, ``"TabularPolicy"``, ``"MlpPolicy"`` (a new learner per iteration) or
        ``"ConditionedMlpPolicy"`` (one learner per agent for the whole run, ``ψ(s, a, w)`` trained for every weight
        of OLS's support and acting by GPI over it; its replay buffer is not cut to one iteration)
    :param weights: ``"ols"`` (MA-SFOLS), ``"random"`` (Random + GPI: Dirichlet(1) weights) or array-like fixed
        weights (a priori scalarised learners: every agent trains for them; each agent is evaluated by GPI over
        its own policies, at these weights unless the evaluation's ``test_weights`` say otherwise)
    :param ols_batch: how an MA-SFOLS iteration takes its agents' weights from the OLS queue: ``"top"``, the
        highest priorities (Algorithm 1), or ``"same-after-extrema"`` (see
        :class:`~sb3_sfgpi.schedules.OLSSchedule`; only with ``weights="ols"``)
    :param steps_per_iteration: joint env steps every agent trains for its weights in one iteration
    :param learner_kwargs: further SFDQN arguments of the learners (learning rate, γ, exploration, ...)
    :param sharing: ``"independent"``: one learner per agent, each trained for its own weights (the paper's
        setting); ``"shared"``: parameter sharing, one learner per iteration that every agent acts with and feeds
        (one weight per iteration, trained on all the agents' transitions; for many homogeneous agents)
    :param pool_replay: pool the transitions of every iteration into one empirical model and, after every iteration,
        plan the SF tables of the new policies and of Π's on it for their own weights, before the values are
        estimated and validation scores GPI (see :mod:`sb3_sfgpi.tabular.pooling`). Single-agent envs (one agent: its
        dynamics do not depend on the policy) and ``TabularPolicy`` only; the run directory keeps what each
        iteration added, so that a resumed run is the same
    :param episode_weights: what learners conditioned on the weights (``"ConditionedMlpPolicy"``) act and train for in
        each episode: ``"own"``, their iteration's weight, or ``"support"``, one drawn from their support at every
        episode start (GPI-LS's behaviour; :mod:`~sb3_sfgpi.episode_weights`)
    :param rebind_support: at the end of every iteration, each learner conditioned on the weights also offers Π its
        latest network bound to every earlier weight of OLS's support (what it learned for that weight since its
        member joined); validation admits each only where GPI does no worse, and pruning retires what it supersedes
    :param test_weights: the weights GPI is evaluated at after every iteration: an array ``(n, d)``, a number ``n`` of
        Dirichlet(1) weights drawn with seed 0, or None (12 such weights; fixed weights: those)
    :param eval_episodes: episodes per test weight
    :param gpi_set: GPI's evaluation acts over ``"all"`` of Π or only the policies whose values form its CCS
        (``"ccs"``)
    :param value_mode: how the value vector of a new policy is estimated
        (:class:`~sb3_sfgpi.callbacks.ValueEstimation`): ``"joint"``, the new learners acting together, or ``"shared"``
    :param value_episodes: episodes of that estimate
    :param validation_weights: which new policies join Π (:class:`~sb3_sfgpi.admission.Admission`): 0, every one
        (the paper); ``n > 0``, those that raise GPI's score on ``n`` validation weights
    :param prune: also retire the members of Π whose removal does not lower that score
    :param admit_together: admit an iteration's new policies together, not one after another
    :param n_envs: train on this many copies of the env, each in its own process (``env_fn``), stepped together: a
        learner has a slot per agent and copy. 1: train on ``env`` (evaluations always run on ``env``)
    :param env_fn: picklable constructor of the env's copies and of the evaluation workers, called without
        arguments (e.g. ``functools.partial(MyEnv, **kwargs)``): required when ``n_envs > 1`` or ``eval_workers > 0``
    :param eval_workers: worker processes of GPI's evaluation (0: in this process; they do not change its results)
    :param seed: the run's seed (learners, resets and random weights derive theirs from it)
    :param run_dir: where Π, evaluations, checkpoints and logs go (None: nowhere). :attr:`run_info` is written to
        its ``run.json`` when :meth:`learn` starts; a resume builds the learners from it alone, so with a run
        directory ``learner_kwargs`` are those a run file takes (numbers, strings, ``policy_kwargs`` with
        ``net_arch`` and ``n_heads``: no classes)
    :param verbose: 1 prints a line per iteration, and the policies validation leaves out or retires
    :raises ValueError: learner options the learners refuse (a learner is built and dropped to check them);
        ``pool_replay`` with several agents or other learners than tables; ``episode_weights="support"`` or
        ``rebind_support`` with learners not conditioned on the weights; ``rebind_support`` without validation weights;
        with a ``run_dir``, learner arguments a run file does not take
    """

    def __init__(
        self,
        env: ParallelEnv | gym.Env,
        policy: str = RunSettings.policy,
        weights: str | np.ndarray | Sequence[float] = RunSettings.weights,
        ols_batch: str = RunSettings.ols_batch,
        steps_per_iteration: int = RunSettings.steps_per_iteration,
        learner_kwargs: Mapping[str, Any] | None = None,
        test_weights: Any = RunSettings.test_weights,
        seed: int = RunSettings.seed,
        value_mode: str = RunSettings.value_mode,
        value_episodes: int = RunSettings.value_episodes,
        eval_episodes: int = RunSettings.eval_episodes,
        gpi_set: str = RunSettings.gpi_set,
        validation_weights: int = RunSettings.validation_weights,
        prune: bool = RunSettings.prune,
        admit_together: bool = RunSettings.admit_together,
        sharing: str = RunSettings.sharing,
        n_envs: int = RunSettings.n_envs,
        pool_replay: bool = RunSettings.pool_replay,
        episode_weights: str = RunSettings.episode_weights,
        rebind_support: bool = RunSettings.rebind_support,
        env_fn: Callable[[], ParallelEnv | gym.Env] | None = None,
        run_dir: str | Path | None = None,
        eval_workers: int = 0,
        verbose: int = 0,
    ):
        learner_kwargs = dict(learner_kwargs or {})
        if rebind_support and not (_conditioned(policy) and validation_weights):
            raise ValueError(
                "rebind_support offers Π a conditioned learner's latest network at earlier weights, for validation to "
                f"admit: it needs policy='ConditionedMlpPolicy' and validation_weights > 0, got {policy!r} and "
                f"{validation_weights}"
            )
        if run_dir is not None:  # its run.json must describe the run to a resume, which takes nothing else
            check_learner_kwargs(learner_kwargs, "MASFOLS with a run_dir")
        self.runner = _runner(
            env,
            policy,
            steps_per_iteration,
            learner_kwargs,
            seed,
            sharing,
            n_envs,
            env_fn,
            run_dir,
            pool_replay,
            episode_weights,
        )
        fixed = None if isinstance(weights, str) else weights
        evaluation = self._evaluation(test_weights, eval_episodes, gpi_set, eval_workers, fixed, sharing, env_fn)
        self.run_dir = None if run_dir is None else RunDirectory(run_dir)
        self.settings = RunSettings(
            policy=policy,
            weights=weights if fixed is None else np.asarray(weights, dtype=np.float64).tolist(),
            ols_batch=ols_batch,
            steps_per_iteration=steps_per_iteration,
            learner_kwargs=learner_kwargs,
            test_weights=evaluation.test_weights.tolist(),
            seed=seed,
            value_mode=value_mode,
            value_episodes=value_episodes,
            eval_episodes=eval_episodes,
            gpi_set=gpi_set,
            validation_weights=validation_weights,
            prune=prune,
            admit_together=admit_together,
            sharing=sharing,
            n_envs=n_envs,
            pool_replay=pool_replay,
            episode_weights=episode_weights,
            rebind_support=rebind_support,
        )
        self.callback = OLSCallback(
            make_schedule(weights, ols_batch), steps_per_iteration, evaluation,
            ValueEstimation(value_mode, value_episodes),
            Admission(validation_weights, prune=prune, together=admit_together, verbose=verbose), self.run_dir,
            verbose=verbose, pooled=PooledReplay(self.runner.gamma) if pool_replay else None,
            rebind_support=rebind_support,
        )  # fmt: skip
        #: What :meth:`learn` writes to ``run.json``: the settings and plain data added here (the CLI: domain, env)
        self.run_info: dict[str, Any] = self.settings.to_json()
        self._logs_open = False  # logs/ is opened by the first learn(), under the run directory's lock

    def _evaluation(
        self,
        test_weights: Any,
        episodes: int,
        gpi_set: str,
        workers: int,
        fixed: Any,
        sharing: str,
        env_fn: Callable[[], ParallelEnv | gym.Env] | None,
    ) -> EvaluationConfig:
        """GPI's evaluation: its test weights drawn, its agents' policies chosen, its workers' env."""
        if test_weights is None and fixed is not None:
            test_weights = np.array([fixed], dtype=np.float64)
        elif test_weights is None or np.ndim(test_weights) == 0:
            n = 12 if test_weights is None else int(test_weights)
            if n < 1:
                raise ValueError(f"test_weights must be a positive number of weights or an array, got {n}")
            test_weights = random_weights(self.runner.reward_dim, n, rng=0)
        if workers > 0 and env_fn is None:
            raise ValueError("an evaluation with workers needs env_fn to build the workers' envs")
        policies = "own" if acts_by_own_policies(fixed is not None, sharing) else "shared"
        return EvaluationConfig(test_weights, episodes, policies, gpi_set=gpi_set, workers=workers, env_fn=env_fn)

    @classmethod
    def from_settings(
        cls,
        env: ParallelEnv | gym.Env,
        settings: RunSettings,
        env_fn: Callable[[], ParallelEnv | gym.Env] | None = None,
        run_dir: str | Path | None = None,
        eval_workers: int = 0,
        verbose: int = 0,
    ) -> MASFOLS:
        """
        A run of ``settings`` (what ``run.json`` stores; the constructor's arguments of the same names).

        :param eval_workers: worker processes of the GPI evaluation (they do not change its results)
        """
        fields = {name: getattr(settings, name) for name in RunSettings.names()}
        return cls(env, **fields, env_fn=env_fn, run_dir=run_dir, eval_workers=eval_workers, verbose=verbose)

    @classmethod
    def load(cls, run_dir: str | Path, env: ParallelEnv | gym.Env, **kwargs: Any) -> MASFOLS:
        """
        Continue the run in ``run_dir`` from its last checkpoint, with the settings stored in its ``run.json``.

        :param run_dir: the run directory (written by a :class:`MASFOLS` with ``run_dir``)
        :param env: the env, built as for the run
        :param kwargs: what is not stored: ``env_fn``, ``verbose``, and ``eval_workers`` (worker processes of the
            GPI evaluation)
        :raises ValueError: not a run directory, a run file of another format version, or a stored setting missing
        """
        config = RunDirectory(run_dir).read_config()
        unknown = set(kwargs) - {"env_fn", "verbose", "eval_workers"}
        if unknown:
            raise ValueError(f"MASFOLS.load takes env_fn, verbose and eval_workers, not {sorted(unknown)}")
        model = cls.from_settings(env, RunSettings.stored(config, f"{run_dir}/run.json"), run_dir=run_dir, **kwargs)
        model.run_info = {**config, **model.run_info}
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
        :raises ~sb3_sfgpi.run_directory.RunDirectoryBusy: another process writes the run directory
        """
        if self.run_dir is None:
            return self._learn(max_iterations, callback, progress_bar)
        with self.run_dir.lock(f"MASFOLS.learn (seed {self.settings.seed})"):  # one writer per run directory
            if not self.callback.resume:
                if self.run_dir.has_checkpoint():
                    raise ValueError(f"{self.run_dir} already holds a run: continue it with MASFOLS.load")
                self.run_dir.write_config(self.run_info)
            self.run_dir.record_software(software_versions())
            if not self._logs_open:  # once: a later learn() goes on writing to the same files
                self.runner.set_logger(run_logger(self.run_dir))  # continues logs/ where the checkpoint left it
                self._logs_open = True
            return self._learn(max_iterations, callback, progress_bar)

    def _learn(self, max_iterations: int | None, callback: MaybeCallback, progress_bar: bool) -> MASFOLS:
        extra = [] if callback is None else callback if isinstance(callback, list) else [callback]
        learn_iterations(self.runner, self.callback, max_iterations, extra, progress_bar)
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
        """Stop evaluation workers and the env's copies, close the run's logs (a later :meth:`learn` opens them again
        where the checkpoint left them) and the env."""
        self.callback.close()
        self.runner.close()
        if self._logs_open:
            self.runner.logger.close()
            self._logs_open = False
        self.runner.env.close()


def _check_poolable(runner: MultiAgentRunner, policy: str) -> None:
    """Refuse pooled replay where it is not sound (several agents) or has nothing to plan (no tables)."""
    if len(runner.agents) != 1:
        raise ValueError(
            f"pool_replay needs a single-agent env, not {len(runner.agents)} agents: an agent's transitions depend "
            "on the other agents' policies"
        )
    if policy != "TabularPolicy":
        raise ValueError(f"pool_replay plans SF tables: policy must be 'TabularPolicy', got {policy!r}")


def _conditioned(policy: str) -> bool:
    """Whether learners of ``policy`` are conditioned on the weights (one network going on over the iterations)."""
    return policy in SFDQN.policy_aliases and issubclass(SFDQN.policy_aliases[policy], ConditionedPolicy)


def _runner(
    env: ParallelEnv | gym.Env,
    policy: str,
    steps_per_iteration: int,
    learner_kwargs: dict[str, Any],
    seed: int,
    sharing: str,
    n_envs: int,
    env_fn: Callable[[], ParallelEnv | gym.Env] | None,
    run_dir: str | Path | None,
    pool_replay: bool,
    episode_weights: str,
) -> MultiAgentRunner:
    """The runner of the learners, its learner options checked on one learner built and dropped."""
    goes_on = _conditioned(policy)
    if episode_weights == "support" and not goes_on:  # refused before the env's copies start
        raise ValueError(
            f"episode_weights='support' draws the weights of learners conditioned on them: policy must be "
            f"'ConditionedMlpPolicy', got {policy!r}"
        )
    runner = MultiAgentRunner(
        env,
        seed=seed,
        gamma=learner_kwargs.get("gamma", GAMMA),
        tensorboard_log=None if run_dir is None else str(RunDirectory(run_dir).tensorboard_dir),
        sharing=sharing,
        n_envs=n_envs,
        env_fn=env_fn,
        episode_weights=episode_weights,
    )
    slots = max(len(slots) for slots in runner.slots.values())
    sized = learner_kwargs if goes_on else replay_sized(learner_kwargs, steps_per_iteration, slots)
    runner.learner_factory = default_learner_factory(policy=policy, **sized)
    runner.check_learner()
    if pool_replay:
        _check_poolable(runner, policy)
    return runner
