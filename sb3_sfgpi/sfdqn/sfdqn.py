"""SFDQN: deep (or tabular) Q-learning of successor features from vector rewards."""

from __future__ import annotations

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import LinearSchedule

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.cpu_arithmetic import warn_unless_pinned
from sb3_sfgpi.common.device import resolve_device
from sb3_sfgpi.common.mo_off_policy import MOOffPolicyAlgorithm
from sb3_sfgpi.common.observations import numeric_array
from sb3_sfgpi.common.prioritized_buffer import PrioritizedMOReplayBuffer, replay_buffer_class_named
from sb3_sfgpi.common.vec_env import make_mo_vec_env, vec_env_reward_dim
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.run_settings import GAMMA
from sb3_sfgpi.sfdqn.conditioned import ConditionedPolicy
from sb3_sfgpi.sfdqn.options import check_arguments, learning_rate_schedule, optimistic_value
from sb3_sfgpi.sfdqn.policies import MlpPolicy, SFDQNPolicy
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy
from sb3_sfgpi.tabular.planning import SETTLE_SWEEPS

SelfSFDQN = TypeVar("SelfSFDQN", bound="SFDQN")


class SFDQN(MOOffPolicyAlgorithm):
    """
    Successor-feature DQN: learns ``ψ(s, a) ∈ R^d`` for the policy that is greedy in ``w · ψ``.

    The TD target of a transition ``(s, a, r, s')`` with vector reward ``r`` is
    ``r + γ (1 − terminated) ψ_target(s', a*)`` with ``a* = argmax_a w · ψ(s', a)`` (the online network
    picks, the target network evaluates). Time-limit truncation bootstraps.

    The env must follow the MO-Gymnasium convention (vector reward of shape ``(d,)``, ``reward_space``);
    it is wrapped in :class:`~sb3_sfgpi.common.vec_env.MOMonitor` and
    :class:`~sb3_sfgpi.common.vec_env.MODummyVecEnv`. Episode returns are logged scalarised
    (``rollout/ep_rew_mean`` = ``w · return``) and per objective (``rollout/ep_rew_mean_<i>``).

    :param policy: The policy model to use (``"MlpPolicy"``, ``"TabularPolicy"``, or a class)
    :param env: The environment to learn from (a registered id, MO-Gymnasium's included, is made by
        :func:`~sb3_sfgpi.common.vec_env.make_mo_vec_env`)
    :param weights: Preference weights ``w`` (length ``d``); ``None`` for equal weights
    :param learning_rate: The learning rate (``α`` of the tabular policy), constant or a schedule; ``"lin_X"``: from
        ``X`` linearly down to 0 over each call of :meth:`learn` (:func:`learning_rate_schedule`)
    :param buffer_size: Size of the replay buffer
    :param learning_starts: How many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: The soft update coefficient ("Polyak update", between 0 and 1), 1 for hard update
    :param gamma: The discount factor
    :param train_freq: Update the model every ``train_freq`` steps, or a tuple ``(n, "step" | "episode")``
    :param gradient_steps: How many gradient steps to do after each rollout (-1: as many as env steps)
    :param replay_buffer_class: Replay buffer class, a subclass of ``MOReplayBuffer``, or the name of one of
        :data:`~sb3_sfgpi.common.prioritized_buffer.REPLAY_BUFFERS` (what a run file may name):
        ``"PrioritizedMOReplayBuffer"`` draws transitions by their TD errors (network policies); None:
        ``MOReplayBuffer``
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation (the prioritised
        buffer's ``alpha`` and ``min_priority``)
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param n_steps: Must be 1 (n-step returns are not implemented for vector rewards)
    :param target_update_interval: Update the target network every ``target_update_interval`` env steps
    :param exploration_fraction: Fraction of training over which the exploration rate is reduced
    :param exploration_initial_eps: Initial value of random action probability
    :param exploration_final_eps: Final value of random action probability
    :param exploration_steps: where given, ε falls from its initial to its final value over the learner's first
        ``exploration_steps`` env steps, counted across calls of :meth:`learn` (a learner that goes on learning
        over OLS's iterations explores once, as GPI-LS's), instead of over ``exploration_fraction`` of each call
    :param max_grad_norm: The maximum value for the gradient clipping (not used by the tabular policy)
    :param planning_sweeps: Dyna-style planning (``TabularPolicy`` only): every ``planning_interval`` env steps,
        up to this many sweeps of the SF backup over every pair recorded in the replay buffer
        (:meth:`~sb3_sfgpi.sfdqn.tabular_policy.TabularPolicy.plan`); 0 for none
    :param planning_interval: Env steps between two plannings
    :param optimistic_init: optimistic initial values (``TabularPolicy`` with planning only; 0 for none): every
        entry of the table starts at this value, so the greedy behaviour tries the pairs it has not tried yet, and
        planning carries their promise to the states that lead to them (directed exploration, as R-max). At the end
        of :meth:`learn`, :meth:`remove_optimism` removes it: the pairs never tried get 0 and the table is planned
        until it converges, so the trained policy never counts on an action it has not tried. ``"rmax_X"``: ``X``
        times the largest reward one step can give (read from the bounds of the env's ``reward_space``), one setting
        for every scale of rewards; the higher, the more of the state space is explored (docs: experiments/single_agent)
    :param stats_window_size: Window size for the rollout logging
    :param tensorboard_log: The log location for tensorboard (if None, no logging)
    :param policy_kwargs: Additional arguments to be passed to the policy on creation (``MlpPolicy``: ``net_arch``,
        ``activation_fn``, ...)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run. ``"auto"``: the CPU for
        ``TabularPolicy``, else CUDA where available; ``TabularPolicy`` refuses any other device than the CPU
        (see :func:`~sb3_sfgpi.common.device.resolve_device`)
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "TabularPolicy": TabularPolicy,
        "ConditionedMlpPolicy": ConditionedPolicy,
    }
    policy: SFDQNPolicy
    replay_buffer: MOReplayBuffer

    def __init__(
        self,
        policy: str | type[SFDQNPolicy],
        env: GymEnv | str | None,
        weights: np.ndarray | list[float] | None = None,
        learning_rate: float | str | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = GAMMA,
        train_freq: int | tuple[int, str] = 4,
        gradient_steps: int = 1,
        replay_buffer_class: str | type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        target_update_interval: int = 10_000,
        exploration_fraction: float = 0.1,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.05,
        exploration_steps: int | None = None,
        max_grad_norm: float = 10,
        planning_sweeps: int = 0,
        planning_interval: int = 5_000,
        optimistic_init: float | str = 0.0,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        policy_class = self._get_policy_from_name(policy) if isinstance(policy, str) else policy
        learning_rate = learning_rate_schedule(learning_rate)
        replay_buffer_class = replay_buffer_class_named(replay_buffer_class)
        check_arguments(locals(), policy_class)
        device = resolve_device(device, tabular=issubclass(policy_class, TabularPolicy))
        env = make_mo_vec_env(env) if isinstance(env, str) else env  # SB3's gym.make would wrap a scalar Monitor
        super().__init__(
            policy, env, learning_rate, buffer_size, learning_starts, batch_size, tau, gamma, train_freq,
            gradient_steps, action_noise=None, replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs, optimize_memory_usage=optimize_memory_usage, n_steps=1,
            policy_kwargs=policy_kwargs, stats_window_size=stats_window_size, tensorboard_log=tensorboard_log,
            verbose=verbose, device=device, seed=seed, sde_support=False, supported_action_spaces=(spaces.Discrete,),
            support_multi_env=True,
        )  # fmt: skip
        self.exploration_initial_eps = exploration_initial_eps
        self.exploration_final_eps = exploration_final_eps
        self.exploration_fraction = exploration_fraction
        self.exploration_steps = exploration_steps
        #: the weights a ConditionedMlpPolicy trains beside its own and acts over by GPI, shape ``(k, d)`` (None: none)
        self.weight_support: np.ndarray | None = None
        self.target_update_interval = target_update_interval
        self._n_calls = 0
        self.max_grad_norm = max_grad_norm
        self.planning_sweeps = planning_sweeps
        self.planning_interval = planning_interval
        self.optimistic_init = optimistic_init if isinstance(optimistic_init, str) else float(optimistic_init)
        self._plannings = 0  # plannings done: one each time num_timesteps passes a multiple of planning_interval
        self.exploration_rate = 0.0
        if self.env is not None:
            self.reward_dim = vec_env_reward_dim(self.env)
            self._weights = validate_weights(
                np.full(self.reward_dim, 1.0 / self.reward_dim) if weights is None else weights, self.reward_dim
            )
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        self.replay_buffer_kwargs = {**self.replay_buffer_kwargs, "reward_dim": self.reward_dim}
        self.policy_kwargs = {**self.policy_kwargs, "reward_dim": self.reward_dim}
        super()._setup_model()
        prioritised = isinstance(self.replay_buffer, PrioritizedMOReplayBuffer)
        if prioritised and isinstance(self.policy, TabularPolicy):
            raise ValueError("prioritised replay is for network policies: a table learns every sampled row exactly")
        if self.device.type == "cpu" and not isinstance(self.policy, TabularPolicy):
            warn_unless_pinned()
        fraction = self.exploration_fraction if self.exploration_steps is None else 1.0  # of exploration_steps
        self.exploration_schedule = LinearSchedule(self.exploration_initial_eps, self.exploration_final_eps, fraction)
        self.set_weights(self._weights)
        if self.weight_support is not None:
            self.set_weight_support(self.weight_support)
        reward_space = self.env.get_attr("reward_space", indices=[0])[0] if self.env is not None else None
        bounds = (reward_space.low, reward_space.high) if reward_space is not None else ([np.inf], [np.inf])
        self.optimistic_value = optimistic_value(self.optimistic_init, *bounds)
        if self.optimistic_value:
            self.policy.fill(self.optimistic_value)  # type: ignore[attr-defined]

    @property
    def conditioned(self) -> bool:
        """Whether the policy is conditioned on the weights (``ConditionedMlpPolicy``): one learner for every weight."""
        return isinstance(self.policy, ConditionedPolicy)

    @property
    def weights(self) -> np.ndarray:
        """The preference weights ``w`` the policy is trained for and acts with (a copy)."""
        return self._weights.copy()

    def set_weights(self, weights: np.ndarray | list[float]) -> None:
        """
        Set the preference weights to train for and act with.

        :param weights: ``d`` non-negative numbers, not all zero (normalised to sum to one)
        :raises ValueError: wrong length, negative, NaN or all zero
        """
        self._weights = validate_weights(weights, self.reward_dim)
        self.policy.weights.copy_(th.as_tensor(self._weights, dtype=th.float32))

    def set_weight_support(self, support: np.ndarray | list[list[float]]) -> None:
        """
        The weights a ``ConditionedMlpPolicy`` learns beside its own and acts over by GPI (OLS's support).

        :param support: weights, shape ``(k, d)``, each validated as :meth:`set_weights` does
        :raises ValueError: a policy that is not conditioned on the weights, or bad weights
        """
        if not self.conditioned:
            raise ValueError(f"a weight support is for ConditionedMlpPolicy, not {type(self.policy).__name__}")
        rows = [validate_weights(w, self.reward_dim, "support weights") for w in np.asarray(support, dtype=np.float64)]
        if not rows:
            raise ValueError("the weight support must hold at least one weight")
        self.weight_support = np.array(rows)
        self.policy.set_support(self.weight_support)

    def successor_features(self, observation: np.ndarray) -> np.ndarray:
        """
        ``ψ(s, ·)`` of the online network.

        :param observation: one observation or a batch
        :return: shape ``(batch, n_actions, d)``
        :raises ValueError: an observation that is not finite numbers, or outside a table's observation space
        """
        if not isinstance(observation, dict):
            observation = numeric_array(observation)  # finite numbers
            if isinstance(self.policy, TabularPolicy):  # refuse what would index another state's row, as predict
                self.policy.sf_net.rows(observation.reshape(-1, *self.observation_space.shape))  # type: ignore[misc]
        obs_tensor, _ = self.policy.obs_to_tensor(observation)
        with th.no_grad():
            return self.policy.sf_net(obs_tensor).cpu().numpy()

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if reset_num_timesteps:
            self._plannings = 0
        if isinstance(self.replay_buffer, PrioritizedMOReplayBuffer):  # errors for earlier weights say nothing of these
            self.policy.score_replay(self.replay_buffer, self.gamma)
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _on_step(self) -> None:
        """Update the exploration rate and, every ``target_update_interval`` steps, the target network."""
        self._n_calls += 1
        if self._n_calls % max(self.target_update_interval // self.n_envs, 1) == 0:
            self.policy.update_target(self.tau)
        self.exploration_rate = self.exploration_rate_at(self.num_timesteps, self._current_progress_remaining)
        self.logger.record("rollout/exploration_rate", self.exploration_rate)

    def exploration_rate_at(self, num_timesteps: int, progress_remaining: float) -> float:
        """
        ε after the step that brings the learner to ``num_timesteps`` steps, ``progress_remaining`` of its
        ``learn()`` left: over ``exploration_steps`` steps where given, else over ``exploration_fraction`` of the call.
        """
        if self.exploration_steps is None:
            return self.exploration_schedule(progress_remaining)
        return self.exploration_schedule(1.0 - num_timesteps / self.exploration_steps)

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = [
            self.policy.td_update(
                self.replay_buffer, batch_size, self.gamma, self.max_grad_norm, self._vec_normalize_env
            )
            for _ in range(gradient_steps)
        ]
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", sum(losses) / len(losses))
        if self.planning_sweeps and self.num_timesteps // self.planning_interval > self._plannings:
            self._plannings = self.num_timesteps // self.planning_interval
            sweeps = self.policy.plan(self.replay_buffer, self.gamma, self.planning_sweeps)  # type: ignore[attr-defined]
            self.logger.record("train/planning_sweeps", sweeps)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
        w: np.ndarray | list[float] | None = None,
        action_masks: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        ε-greedy action in ``w · ψ(s, ·)`` (greedy if ``deterministic``), among the actions ``action_masks`` allows.

        In a batch (several envs, or the agents sharing a learner) each row explores with probability ε on its own;
        SB3's DQN draws once for the whole batch.

        The greedy choice of the ε-greedy (behaviour) policy breaks ties between actions of equal value at random:
        a tabular policy ties in every state it has not learned yet, and taking the first action there would
        explore nothing. The deterministic policy, whose successor features are learned, takes the first.

        :param observation: the input observation (one or a batch)
        :param state: unused (no recurrent policy), returned as is
        :param episode_start: unused
        :param deterministic: act greedily, without exploration
        :param w: weights to act for in this call only; ``None`` for the model's weights
        :param action_masks: the actions each observation has, 0/1 of shape ``(batch, n_actions)`` (the envs'
            ``info["action_mask"]``, as sb3-contrib's maskable algorithms take them); None: every action
        :return: the actions and ``state``
        """
        # Validate w and the observation first: an exploratory action must not hide bad input.
        weights = self._weights if w is None else validate_weights(w, self.reward_dim)
        if not isinstance(observation, dict):
            observation = numeric_array(observation)
        if deterministic and action_masks is None:
            actions, vectorized = self.policy.greedy(observation, weights)
        else:
            exploration_rate = None if deterministic else self.exploration_rate
            actions, vectorized = self.policy.masked_actions(observation, weights, action_masks, exploration_rate)
        return (actions if vectorized else actions[0]), state

    def _update_info_buffer(self, infos: list[dict[str, Any]], dones: np.ndarray | None = None) -> None:
        # MOMonitor reports vector returns; the scalar return SB3 logs is w · return for the current w.
        scalarized = []
        for info in infos:
            episode = info.get("episode")
            if episode is not None and "r_vec" in episode:
                info = {**info, "episode": {**episode, "r": float(np.dot(self._weights, episode["r_vec"]))}}
            scalarized.append(info)
        super()._update_info_buffer(scalarized, dones)

    def learn(
        self: SelfSFDQN,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "SFDQN",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfSFDQN:
        super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
        self.remove_optimism()
        return self

    def remove_optimism(self) -> None:
        """
        Remove the optimistic initial values (``optimistic_init``; nothing to do without): the pairs not in the
        replay buffer get ``ψ = 0``, and the recorded ones are planned until no entry moves by more than
        :data:`~sb3_sfgpi.tabular.planning.TOLERANCE` (at most :data:`~sb3_sfgpi.tabular.planning.SETTLE_SWEEPS`
        sweeps). Called at the end of :meth:`learn`; a later :meth:`learn` goes on from that table, without optimism.
        """
        if self.optimistic_value:
            self.policy.plan(self.replay_buffer, self.gamma, SETTLE_SWEEPS, untried_value=0.0)  # type: ignore[attr-defined]

    @classmethod
    def load(cls, path: Any, env: GymEnv | None = None, device: th.device | str = "auto", **kwargs: Any) -> Any:
        """
        SB3's :meth:`~stable_baselines3.common.base_class.BaseAlgorithm.load` (which unpickles: load only files you
        trust), refusing in one line a file another algorithm saved.

        :raises ValueError: the file is not an SFDQN model (e.g. SB3's DQN: it has no ``reward_dim``), or its
            parameters do not fit the policy it names
        """
        try:
            return super().load(path, env=env, device=device, **kwargs)
        except (AttributeError, KeyError) as error:
            raise ValueError(f"{path} is not an SFDQN model (saved by another algorithm?): {error!r}") from None
        except RuntimeError as error:
            if "loading state_dict" not in str(error):
                raise
            raise ValueError(
                f"{path}: its parameters do not fit the policy its policy_kwargs build ({str(error).splitlines()[0]}); "
                "a ConditionedMlpPolicy saved with one head before two became the default loads with "
                'custom_objects={"policy_kwargs": {**its policy_kwargs, "n_heads": 1}}'
            ) from None

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "exploration_schedule"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "policy.optimizer"], []
