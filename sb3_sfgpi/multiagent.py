"""Independent SFDQN learners stepping one PettingZoo ParallelEnv in lockstep.

Each agent has its own :class:`~sb3_sfgpi.sfdqn.SFDQN` (own network, own replay buffer), fed its transitions as its
own ``learn()`` would (:mod:`sb3_sfgpi.learners`): its logger, callbacks and save/load work as there. The runner
behaves like an SB3 algorithm towards a runner-level callback (e.g. :class:`~sb3_sfgpi.callbacks.OLSCallback`):
``learn(total_timesteps, callback)`` calls ``callback.on_step()`` after every joint step; False stops it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.type_aliases import MaybeCallback, TrainFrequencyUnit
from tqdm.auto import tqdm

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask, stacked_masks
from sb3_sfgpi.common.agent_views import AgentVecEnv, Transitions, folderless_logger, replaced
from sb3_sfgpi.common.checks import (
    check_homogeneous,
    check_parallel_reset,
    check_parallel_step,
    warn_of_swapped_flags,
)
from sb3_sfgpi.common.env_copies import EnvCopies, SideBySide, SingleCopy
from sb3_sfgpi.common.parallel_wrappers import as_parallel_env, time_limit
from sb3_sfgpi.common.rollouts import (
    EpisodeReturns,
    JointPolicy,
    RowPolicy,
    batched_episodes,
    run_episodes,
    run_lockstep,
)
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import SAME_WEIGHT
from sb3_sfgpi.compiled_episodes import PackedStarts, compiled_gpi_episodes
from sb3_sfgpi.compiled_steps import CompiledSteps, PendingStep, compiled_steps
from sb3_sfgpi.episode_weights import EpisodeWeights
from sb3_sfgpi.learners import (
    EpisodeMonitor,
    LearnerFactory,
    default_learner_factory,
    end_learning,
    greedy_joint_policy,
    learner_step,
    start_learning,
    stored_rows,
)
from sb3_sfgpi.ols import unique_points
from sb3_sfgpi.run_settings import EPISODE_WEIGHTS, SHARED, SHARINGS
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.training_state import restore_training_state

if TYPE_CHECKING:
    from sb3_sfgpi.gpi import GPIPolicy
    from sb3_sfgpi.tabular.gpi_episodes import GPIEpisodes


class MultiAgentRunner:
    """
    Learners trained in lockstep on a shared PettingZoo ParallelEnv: one per agent (independent learners, the
    paper's), or one that every agent acts with and feeds (parameter sharing).

    Agents whose episode ended (terminated or truncated) store no further transitions until the shared
    env is reset, which happens when no agent is left. A time-limit truncation is stored as such
    (it bootstraps), a termination is not.

    With ``sharing="shared"`` the agents are the slots of their learner's view (SB3's ``n_envs``): one batched
    forward pass picks every agent's action, every live agent's transition goes to the one replay buffer, and the
    learner trains as an SB3 algorithm on ``n_envs`` envs does (``train_freq`` and ``gradient_steps`` per joint
    step, ``learning_starts`` and ``target_update_interval`` in transitions). Learners are named by
    :attr:`learner_names`: the agents' names, or :data:`SHARED`.

    :param env: a ParallelEnv with vector rewards (``reward_space(agent)``) and homogeneous agents, or a single-agent
        Gymnasium env with a ``reward_space`` (one agent, see
        :class:`~sb3_sfgpi.common.single_agent.SingleAgentParallelEnv`); composite observation spaces (``Tuple``,
        ``Dict``) are flattened (:class:`~sb3_sfgpi.common.parallel_wrappers.FlattenObservations`)
    :param learner_factory: builds a learner; see :func:`default_learner_factory`
    :param seed: seed of the run (learners and resets derive theirs from it)
    :param gamma: discount of the Monte-Carlo evaluation (default: the learners')
    :param learner_callback: builds a callback for each new learner (e.g. a checkpoint callback)
    :param tensorboard_log: directory of the TensorBoard logs (runner and learners), or None
    :param verbose: verbosity of the runner-level logger
    :param log_interval: a learner writes its logs (TensorBoard, stdout) every ``log_interval`` of its episodes, as
        in SB3's ``learn(log_interval=...)``, and at the end of its iteration
    :param sharing: ``"independent"``: one learner per agent; ``"shared"``: one learner for all agents
    :param n_envs: copies of the env to train on, each in its own process (``env_fn``), all stepped at every joint
        step: a learner has a slot per agent and copy (SB3's ``n_envs``). 1: train on ``env`` itself. Evaluations and
        value estimates always run on ``env``
    :param env_fn: picklable constructor of the copies (required when ``n_envs > 1``)
    :param env_kwargs: its keyword arguments (they should build the same env as ``env``)
    :param episode_weights: what learners conditioned on the weights act and train for in each episode: ``"own"``
        (their iteration's weight) or ``"support"`` (one drawn from their support at every reset of the env; see
        :class:`~sb3_sfgpi.episode_weights.EpisodeWeights`)
    """

    def __init__(
        self,
        env: ParallelEnv | gym.Env,
        learner_factory: LearnerFactory | None = None,
        seed: int = 0,
        gamma: float | None = None,
        learner_callback: Callable[[str], BaseCallback] | None = None,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        log_interval: int = 4,
        sharing: str = "independent",
        n_envs: int = 1,
        env_fn: Callable[..., ParallelEnv | gym.Env] | None = None,
        env_kwargs: Mapping[str, Any] | None = None,
        episode_weights: str = EPISODE_WEIGHTS[0],
    ):
        if isinstance(log_interval, bool) or not isinstance(log_interval, int) or log_interval < 1:
            raise ValueError(f"log_interval must be a positive integer, got {log_interval!r}")
        if sharing not in SHARINGS:
            raise ValueError(f"sharing must be one of {SHARINGS}, got {sharing!r}")
        if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
            raise ValueError(f"n_envs must be a positive integer, got {n_envs!r}")
        if n_envs > 1 and env_fn is None:
            raise ValueError("n_envs > 1 needs env_fn (and env_kwargs) to build the env's copies")
        self.log_interval, self.sharing = log_interval, sharing
        self.env = env = as_parallel_env(env)
        self.agents: list[str] = list(env.possible_agents)
        self._time_limit = time_limit(env)
        self._warned_swap = False
        self.learner_factory = learner_factory or default_learner_factory()
        self.seed = seed
        self.learner_callback, self.tensorboard_log = learner_callback, tensorboard_log
        self.verbose = verbose
        check_homogeneous(env, self.agents)
        self._reward_dim = int(env.reward_space(self.agents[0]).shape[0])  # type: ignore[attr-defined]
        #: learner name -> the agents it acts for, in the order of its slots
        self.groups: dict[str, list[str]] = (
            {SHARED: self.agents} if sharing == "shared" else {agent: [agent] for agent in self.agents}
        )
        self.n_envs = n_envs
        #: learner name -> its slots: ``(copy, agent)``, copy by copy
        self.slots = {name: [(c, a) for c in range(n_envs) for a in agents] for name, agents in self.groups.items()}
        #: agent -> the name of the learner it trains
        self._learner_of = {agent: name for name, agents in self.groups.items() for agent in agents}
        self.views = {name: AgentVecEnv(env, agents, n_envs) for name, agents in self.groups.items()}
        self.copies: SingleCopy | EnvCopies = (
            SingleCopy(env) if n_envs == 1 else EnvCopies(env_fn, env_kwargs or {}, n_envs)  # type: ignore[arg-type]
        )
        self._live: list[set[str]] = [set() for _ in range(n_envs)]  # per copy, the agents still in its episode
        self._n_actions = int(env.action_space(self.agents[0]).n)  # type: ignore[attr-defined]
        #: ``(copy, agent)`` -> the action mask of its last observation (None: every action)
        self._masks: dict[tuple[int, str], np.ndarray | None] = {}
        self._episode_steps = [0] * n_envs
        self._side_by_side = SideBySide(env, env_fn, env_kwargs)  # copies for :meth:`lockstep`
        self._packed_starts: PackedStarts | None = None  # episode starts for :meth:`gpi_episodes`
        self.learners: dict[str, SFDQN] = {}
        self._learner_callbacks: dict[str, BaseCallback] = {}
        self._gamma = gamma
        self.num_timesteps = 0
        self.iteration = 0
        self.logger: Logger = folderless_logger(verbose)
        self._monitor = EpisodeMonitor(self._reward_dim)
        self.episode_weights = EpisodeWeights(episode_weights)

    @property
    def learner_names(self) -> list[str]:
        """The names of the learners of an iteration (the keys of the weights it trains)."""
        return list(self.groups)

    @property
    def conditioned_learners(self) -> dict[str, SFDQN]:
        """The learners conditioned on the weights, by name: they go on across iterations."""
        return {name: learner for name, learner in self.learners.items() if learner.conditioned}

    @property
    def reward_dim(self) -> int:
        return self._reward_dim

    @property
    def gamma(self) -> float:
        if self._gamma is not None:
            return self._gamma
        if not self.learners:
            raise ValueError("gamma is known once learners exist; pass gamma= to the runner")
        return next(iter(self.learners.values())).gamma

    def get_env(self) -> ParallelEnv:
        """The shared env (what SB3 callbacks see as ``training_env``)."""
        return self.env

    def set_logger(self, logger: Logger) -> None:
        """Use ``logger`` for the runner-level records (e.g. OLS progress and evaluations)."""
        self.logger = logger

    def check_learner(self) -> None:
        """
        Build one learner (the first one's, for uniform weights) and drop it, so that bad learner options are
        refused before any training.

        :raises ValueError: an option the learners do not take, or one out of range
        """
        name = self.learner_names[0]
        try:
            learner = self.learner_factory(name, self.views[name], np.full(self.reward_dim, 1 / self.reward_dim), 0)
        except TypeError as error:  # an unknown keyword argument
            raise ValueError(f"bad learner options: {error}") from error
        if learner.optimize_memory_usage and learner.n_envs > 1:
            raise ValueError(
                "a learner whose buffer takes several agents' rows (one shared learner, or n_envs > 1) needs "
                "optimize_memory_usage=False"
            )

    def start_iteration(
        self,
        weights: dict[str, np.ndarray],
        iteration: int,
        total_timesteps: int,
        support: list[np.ndarray] | None = None,
    ) -> None:
        """
        Give every learner name a new learner for its weights and reset the shared env. A learner conditioned on the
        weights (``ConditionedMlpPolicy``) is not replaced: it goes on learning, for its new weights and the support.

        Everything an iteration of fresh learners does depends only on ``(seed, iteration, learner name)`` and the
        weights, so a resumed run repeats an interrupted iteration exactly.

        :param weights: learner name (:attr:`learner_names`) -> preference weights
        :param iteration: index of the iteration (for seeds and log names)
        :param total_timesteps: joint env steps the iteration will run (for the learners' schedules)
        :param support: the weights trained before (OLS's), which conditioned learners also train for and act over
        """
        self.iteration = iteration
        self._close_learners()
        this_iteration = list(weights.values())
        for name in self.learner_names:
            learner = self.learners.get(name)
            if learner is not None and learner.conditioned:
                learner.set_weights(weights[name])
            else:
                learner = self.learner_factory(
                    name, self.views[name], weights[name], derive_seed(self.seed, iteration, name)
                )
            if learner.train_freq.unit != TrainFrequencyUnit.STEP:  # type: ignore[union-attr]
                raise ValueError("the multi-agent runner supports train_freq in steps only")
            if learner.conditioned:  # seeded by iteration, as a new learner is: a resumed run goes on the same
                learner.set_random_seed(derive_seed(self.seed, iteration, name))
                support_weights = np.array([*(support or []), *this_iteration], dtype=np.float64)
                learner.set_weight_support(np.array(unique_points(support_weights, SAME_WEIGHT)))
            self.learners[name] = learner
        self.episode_weights.start(self.conditioned_learners, self.seed, iteration)
        self.reset_env(derive_seed(self.seed, iteration, "reset"))
        for name, learner in self.learners.items():
            callback = self.learner_callback(name) if self.learner_callback else None
            self._learner_callbacks[name] = start_learning(
                learner, f"{name}_iter{iteration + 1:03d}", total_timesteps, callback, self.tensorboard_log
            )  # iterations are named from 1

    def restore_learners(self, states: Mapping[str, Any]) -> None:
        """
        Rebuild the learners that go on across iterations from their saved states (a resumed run's).

        :param states: learner name -> :func:`~sb3_sfgpi.sfdqn.training_state.training_state`
        :raises ValueError: an unknown learner name, or a state that does not fit the learner
        """
        for name, state in states.items():
            if name not in self.groups:
                raise ValueError(f"saved state of an unknown learner {name!r} (the learners: {self.learner_names})")
            learner = self.learner_factory(name, self.views[name], np.full(self.reward_dim, 1 / self.reward_dim), 0)
            restore_training_state(learner, state)
            self.learners[name] = learner

    def reset_env(self, seed: int | None = None, copies: list[int] | None = None) -> None:
        """
        Reset the env's copies and hand every learner its first observations (training continues from there).

        :param seed: the seed of the first copy (the others derive theirs from it), or None
        :param copies: the copies to reset (default: all)
        """
        copies = list(range(self.n_envs)) if copies is None else copies
        seeds = [seed if seed is None or copy == 0 else derive_seed(seed, "copy", copy) for copy in copies]
        observations = {}
        for copy, (obs, infos, agents) in zip(copies, self.copies.reset(seeds, copies), strict=True):
            check_parallel_reset(self.env, copy, obs, self.agents)  # known agents, finite observations
            self._live[copy], self._episode_steps[copy] = set(agents), 0
            observations.update({(copy, agent): obs[agent] for agent in obs})
            self._note_masks(copy, infos)
        for name, slots in self.slots.items():
            rows = [i for i, key in enumerate(slots) if key in observations]
            batched = np.stack([np.asarray(observations[slots[i]]) for i in rows])
            whole = len(rows) == len(slots)
            if whole:
                self.views[name].current_obs = batched
            if name in self.learners:
                learner = self.learners[name]
                last = batched.copy() if whole else replaced(learner._last_obs, rows, batched)  # type: ignore[arg-type]
                learner._last_obs = learner._last_original_obs = last  # type: ignore[assignment]
        self.episode_weights.draw()  # episodes start: the weights their conditioned learners act for

    def step(self, chosen: PendingStep | None = None) -> bool:
        """
        One joint step: every live agent of every copy acts, its learner stores the transition and trains when due.

        :param chosen: the step's actions, already chosen for the learners (by
            :class:`~sb3_sfgpi.compiled_steps.CompiledSteps`), or None: they choose them now
        :return: False if a learner's callback asked to stop
        """
        actions, sampled = self._behaviour_actions() if chosen is None else chosen
        results = self.copies.step(actions)
        self.num_timesteps += 1
        merged: list[dict] = [{}, {}, {}, {}, {}]  # observations, rewards, terminations, truncations, infos
        for copy, (*returned, agents) in enumerate(results):
            check_parallel_step(self.env, copy, actions[copy], returned, agents, self.num_timesteps)  # before storing
            self._episode_steps[copy] += 1
            self._live[copy] = set(agents)
            if not (self._warned_swap or self._live[copy] or self._time_limit is None):  # an episode ended early?
                steps = self._episode_steps[copy]
                self._warned_swap = warn_of_swapped_flags(returned[2], returned[3], steps, self._time_limit)
            for values, by_key in zip(returned, merged, strict=True):
                by_key.update({(copy, agent): value for agent, value in values.items()})
        for copy, (*_, infos, _agents) in enumerate(results):
            self._note_masks(copy, infos)
        keep_going = True
        for name, (live, buffer_action) in sampled.items():
            keys = [self.slots[name][i] for i in live]
            step = Transitions(keys, live, buffer_action[live], *merged)
            rows, infos = stored_rows(self.learners[name], step, self._monitor, self._slot_masks(keys))
            keep_going &= learner_step(
                self.learners[name], self._learner_callbacks[name], rows, infos, self.log_interval
            )
        finished = [copy for copy in range(self.n_envs) if not self._live[copy]]
        if finished:
            self.reset_env(copies=finished)
        return keep_going

    def _behaviour_actions(self) -> PendingStep:
        """Every live slot's behaviour action (SB3's ``_sample_action``), and each learner's sampled slots, actions."""
        actions: list[dict[str, int]] = [{} for _ in range(self.n_envs)]
        sampled = {}
        for name, slots in self.slots.items():
            live = [i for i, (copy, agent) in enumerate(slots) if agent in self._live[copy]]
            if live:
                learner = self.learners[name]
                learner._last_action_masks = self._slot_masks(slots)
                action, buffer_action = learner._sample_action(learner.learning_starts, None, learner.n_envs)
                for i in live:
                    copy, agent = slots[i]
                    actions[copy][agent] = int(action[i])
                sampled[name] = (live, buffer_action)
        return actions, sampled

    def _note_masks(self, copy: int, infos: Mapping[str, Mapping[str, Any]]) -> None:
        """Keep the action masks (``info["action_mask"]``) of copy ``copy``'s agents' new observations."""
        for agent, info in infos.items():
            if self._masks or ACTION_MASK in info:  # nothing kept for an env that gives no masks
                self._masks[(copy, agent)] = info_mask(info, self._n_actions, f"agent {agent!r}")

    def _slot_masks(self, keys: list[tuple[int, str]]) -> np.ndarray | None:
        """The masks of the ``(copy, agent)`` keys' last observations, shape ``(len(keys), n_actions)``, or None."""
        return stacked_masks([self._masks.get(key) for key in keys], self._n_actions) if self._masks else None

    def end_iteration(self) -> None:
        """
        Give the learners their own weights back (:class:`~sb3_sfgpi.episode_weights.EpisodeWeights`), remove their
        optimism (:meth:`~sb3_sfgpi.sfdqn.SFDQN.remove_optimism`), close their callbacks and logs.
        """
        self.episode_weights.end()
        for name, callback in self._learner_callbacks.items():
            end_learning(self.learners[name], callback)
        self._learner_callbacks = {}

    def _close_learners(self) -> None:
        if self._learner_callbacks:
            self.end_iteration()
        self._monitor.clear()

    def learner_policy(self, learner: str | None = None) -> JointPolicy:
        """
        The joint policy of the learners' greedy policies (:func:`~sb3_sfgpi.learners.greedy_joint_policy`).

        :param learner: None: every agent acts with the learner it trains; a learner's name: every agent acts with
            that learner (the value of its policy as a shared one)
        """
        acting = self.learners if learner is None else {learner: self.learners[learner]}
        return greedy_joint_policy(acting, self._learner_of if learner is None else None)

    def rollout(self, policy: JointPolicy, n_episodes: int, seed: int) -> EpisodeReturns:
        """
        Monte-Carlo returns of a joint policy on the shared env (episode ``i`` resets with ``seed + i``).

        Where training runs on the same env (``n_envs=1``), it is reset afterwards, so training resumes on a fresh
        episode; the copies of ``n_envs > 1`` go on where they were.
        """
        returns = run_episodes(self.env, policy, n_episodes, self.gamma, seed=seed)
        self._after_rollout()
        return returns

    def lockstep(
        self,
        policy: RowPolicy,
        weights: np.ndarray,
        seeds: list[int],
        per_result: int = 1,
        decided: Callable[[list[int]], None] | None = None,
    ) -> list[EpisodeReturns] | None:
        """
        :func:`~sb3_sfgpi.common.rollouts.run_lockstep`'s episodes: the returns :meth:`rollout` gives one after
        another. They run as the env's batched episodes where its class offers them (Four-Room; the shared env is
        then reset with the last seed, its action spaces seeded as that episode leaves them), else the last on the
        shared env and the others on copies built by ``env_fn`` (:class:`~sb3_sfgpi.common.env_copies.SideBySide`);
        None where there are neither (then :meth:`rollout` runs the episodes).

        :param per_result: consecutive episodes whose returns form one result
        :param decided: called after every decision with each row's episode (see ``run_lockstep``)
        """
        batch = batched_episodes(self.env, len(seeds))
        envs = batch if batch is not None else self._side_by_side.envs(len(seeds))
        if not envs:
            return None
        returns = run_lockstep(envs, policy, weights, seeds, self.gamma, per_result, decided)
        if batch is not None:
            self.env.reset(seed=seeds[-1])  # seeded as the last episode would have left it (its action spaces)
        self._after_rollout()
        return returns

    def gpi_episodes(
        self, policy_set: GPIPolicy, weights: np.ndarray, left_out: np.ndarray, seeds: list[int], per_result: int = 1
    ) -> tuple[list[EpisodeReturns], GPIEpisodes] | None:
        """
        GPI's episodes over a set of tables in one compiled call where the env allows it
        (:func:`~sb3_sfgpi.compiled_episodes.compiled_gpi_episodes`): the returns :meth:`lockstep` gives for GPI over
        ``policy_set`` (each episode for its weights, without its member ``left_out``, ``-1``: none) and every
        decision; else None. The shared env is left as :meth:`lockstep` leaves it.
        """
        if self._packed_starts is None:
            self._packed_starts = PackedStarts(self.env)
        ran = compiled_gpi_episodes(self._packed_starts, policy_set, weights, left_out, seeds, self.gamma, per_result)
        if ran is not None:
            self.env.reset(seed=seeds[-1])
            self._after_rollout()
        return ran

    def _after_rollout(self) -> None:
        """Where training runs on the shared env (``n_envs=1``), start it on a fresh episode."""
        if self.n_envs == 1:
            self.reset_env()
            self._monitor.clear()

    def close(self) -> None:
        """
        Stop the processes of the env's copies (``n_envs > 1``) and close the copies :meth:`lockstep` built; the env
        itself is the caller's.
        """
        self.copies.close()
        self._side_by_side.close()

    def learn(
        self, total_timesteps: int, callback: MaybeCallback = None, progress_bar: bool = False
    ) -> MultiAgentRunner:
        """
        Step the shared env for ``total_timesteps`` more joint steps (one iteration of Algorithm 1: see
        :func:`~sb3_sfgpi.callbacks.learn_iterations`), or until a callback returns False.

        The runner-level callback decides the learners' weights (see :class:`~sb3_sfgpi.callbacks.OLSCallback`);
        it must call :meth:`start_iteration` in its ``_on_training_start``.

        :param total_timesteps: joint env steps of this call
        :param callback: runner-level callback(s)
        :param progress_bar: show a progress bar over the steps
        """
        if isinstance(callback, list):
            callback = CallbackList(callback)
        if callback is None or callable(callback) and not isinstance(callback, BaseCallback):
            raise ValueError("MultiAgentRunner.learn needs a runner-level callback such as OLSCallback")
        callback.init_callback(self)  # type: ignore[arg-type]
        callback.on_training_start(locals(), globals())
        if not self._learner_callbacks:  # no callback started an iteration: nothing to train
            callback.on_training_end()
            return self
        end = self.num_timesteps + total_timesteps
        compiled = self._compiled_steps(callback, total_timesteps)
        bar = tqdm(total=total_timesteps, desc="training", unit="step", disable=not progress_bar)
        try:
            keep_going = True
            while self.num_timesteps < end and keep_going:
                if compiled is not None:
                    done = compiled.run(end - self.num_timesteps, self._live[0])
                    self._episode_steps[0] += done
                    keep_going = self._show_compiled_steps(done, callback, bar)
                    if self.num_timesteps == end or not keep_going:
                        break
                keep_going = self.step(None if compiled is None else compiled.pending)
                bar.update(1)
                callback.update_locals(locals())
                keep_going = callback.on_step() and keep_going
        finally:
            bar.close()
        callback.on_training_end()
        callback.locals.clear()  # this frame's locals hold the callback itself: a cycle that would keep the learners
        return self

    def _compiled_steps(self, callback: BaseCallback, steps: int) -> CompiledSteps | None:
        """The iteration's joint steps in compiled batches where they give what :meth:`step` gives (else None)."""
        if self.n_envs != 1 or self._masks or self.sharing == SHARED:
            return None
        learners = {agent: self.learners[agent] for agent in self.agents}  # in the env's order of agents
        return compiled_steps(self.env, learners, self._learner_callbacks, self._monitor, callback, steps)

    def _show_compiled_steps(self, steps: int, callback: BaseCallback, bar: tqdm) -> bool:
        """Count ``steps`` joint steps done by compiled code and show each to the runner-level callback."""
        bar.update(steps)
        callback.update_locals({"steps": steps})
        for _ in range(steps):
            self.num_timesteps += 1
            if not callback.on_step():
                return False
        return True
