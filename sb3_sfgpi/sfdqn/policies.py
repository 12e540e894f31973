"""The SFDQN policies: an online and a target successor-feature network, acting greedily for weights ``w``."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn
from torch.nn import functional as F

from sb3_sfgpi.common.action_masks import checked_masks, masked, sample_allowed
from sb3_sfgpi.common.buffers import MOReplayBuffer, MOReplayBufferSamples
from sb3_sfgpi.common.prioritized_buffer import PrioritizedMOReplayBuffer
from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.sfdqn.networks import SFNetwork, argmax_random_ties, greedy_actions, scalarize


class SFDQNPolicy(BasePolicy):
    """
    Policy of SFDQN: an SF network, its target network, and the preference weights it acts for.

    Acting is greedy in ``w · ψ(s, ·)`` with ``w`` stored in the ``weights`` buffer.

    :param observation_space: Observation space
    :param action_space: Action space (Discrete)
    :param lr_schedule: Learning rate schedule
    :param reward_dim: Number of objectives ``d``
    :param net_arch: Hidden layer sizes of the SF network
    :param activation_fn: Activation function
    :param features_extractor_class: Features extractor to use
    :param features_extractor_kwargs: Keyword arguments for the features extractor
    :param normalize_images: Whether to divide images by 255
    :param optimizer_class: The optimizer, Adam by default
    :param optimizer_kwargs: Keyword arguments of the optimizer, excluding the learning rate
    """

    sf_net: nn.Module
    sf_net_target: nn.Module
    #: the class of the SF networks :meth:`make_sf_net` builds
    sf_network_class: type[SFNetwork] = SFNetwork

    @property
    def sf_network_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :attr:`sf_network_class` beside those every SF network takes."""
        return {}

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        reward_dim: int,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=normalize_images,
        )
        self.reward_dim = reward_dim
        self.net_arch = [64, 64] if net_arch is None else list(net_arch)
        self.activation_fn = activation_fn
        self.register_buffer("weights", th.full((reward_dim,), 1.0 / reward_dim))
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.sf_net = self.make_sf_net()
        self.sf_net_target = self.make_sf_net()
        self.sf_net_target.load_state_dict(self.sf_net.state_dict())
        self.sf_net_target.set_training_mode(False)
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.sf_net.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    @property
    def member_net(self) -> nn.Module:
        """The network a policy of Π copies from this policy: its SF network."""
        return self.sf_net

    def make_sf_net(self) -> SFNetwork:
        """A new SF network (:attr:`sf_network_class`) with its own features extractor."""
        features_extractor = self.make_features_extractor()
        return self.sf_network_class(
            self.observation_space,
            self.action_space,  # type: ignore[arg-type]
            features_extractor,
            features_extractor.features_dim,
            self.reward_dim,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            normalize_images=self.normalize_images,
            **self.sf_network_kwargs,
        ).to(self.device)

    def forward(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self.action_values(obs, self.weights).argmax(dim=1)

    def action_values(self, obs: PyTorchObs, weights: th.Tensor) -> th.Tensor:
        """
        What the policy acts on: ``w · ψ(s, a)`` of every action (ties: the first action wins the argmax).

        :param obs: a preprocessed batch
        :param weights: shape ``(d,)``
        :return: shape ``(batch, n_actions)``
        """
        return scalarize(self.sf_net(obs), weights)

    def greedy(self, observation: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, bool]:
        """
        ``argmax_a w · ψ(s, a)`` for one observation or a batch, ties to the first action.

        :param observation: raw observation(s), as given to ``predict``
        :param weights: shape ``(d,)``
        :return: the actions (shape ``(batch,)``) and whether the observation was a batch
        """
        self.set_training_mode(False)
        obs_tensor, vectorized = self.obs_to_tensor(observation)
        with th.no_grad():
            weights_tensor = th.as_tensor(weights, dtype=th.float32, device=self.weights.device)
            return self.action_values(obs_tensor, weights_tensor).argmax(dim=1).cpu().numpy(), vectorized

    def masked_actions(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        weights: np.ndarray,
        action_masks: np.ndarray | None,
        exploration_rate: float | None,
    ) -> tuple[np.ndarray, bool]:
        """
        Actions among those ``action_masks`` allows: greedy in ``w · ψ(s, ·)`` (ties to the first) where
        ``exploration_rate`` is None, else ε-greedy with ``ε = exploration_rate``.

        In a batch each row explores with probability ε on its own (SB3's DQN draws once for the whole batch). The
        greedy choice of the ε-greedy policy breaks ties at random
        (:func:`~sb3_sfgpi.sfdqn.networks.argmax_random_ties`).

        :param observation: raw observation(s), as given to ``predict``
        :param action_masks: 0/1 of shape ``(batch, n_actions)``, or None: every action
        :return: the actions (shape ``(batch,)``) and whether the observation was a batch
        """
        vectorized = self.is_vectorized_observation(observation)
        n_batch = len(observation) if vectorized else 1
        masks = checked_masks(action_masks, n_batch, int(self.action_space.n))  # type: ignore[attr-defined]
        if exploration_rate is None:
            return masked(self.q_values(observation, weights)[0], masks).argmax(axis=1), vectorized  # type: ignore[arg-type]
        explore = np.random.rand(n_batch) < exploration_rate
        rows = [None] * n_batch if masks is None else list(masks)
        if explore.all():
            return np.array([sample_allowed(self.action_space, rows[i]) for i in range(n_batch)]), vectorized
        actions = argmax_random_ties(masked(self.q_values(observation, weights)[0], masks))  # type: ignore[arg-type]
        for i in np.flatnonzero(explore):
            actions[i] = sample_allowed(self.action_space, rows[i])
        return actions, vectorized

    def q_values(self, observation: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, bool]:
        """
        ``w · ψ(s, a)`` of every action, for one observation or a batch.

        :param observation: raw observation(s), as given to ``predict``
        :param weights: shape ``(d,)``
        :return: the values (shape ``(batch, n_actions)``) and whether the observation was a batch
        """
        self.set_training_mode(False)
        obs_tensor, vectorized = self.obs_to_tensor(observation)
        with th.no_grad():
            weights_tensor = th.as_tensor(weights, dtype=th.float32, device=self.weights.device)
            return self.action_values(obs_tensor, weights_tensor).cpu().numpy(), vectorized

    def update_target(self, tau: float = 1.0) -> None:
        """Polyak update of the target network (if separate): ``(1 − τ) · target + τ · online`` (``τ = 1``: a copy)."""
        if self.sf_net_target is not self.sf_net:
            polyak_update(self.sf_net.parameters(), self.sf_net_target.parameters(), tau)

    def td_update(
        self,
        replay_buffer: MOReplayBuffer,
        batch_size: int,
        gamma: float,
        max_grad_norm: float,
        vec_normalize_env: VecNormalize | None = None,
    ) -> float:
        """
        One gradient step on a sampled batch, towards ``r + γ (1 − terminated) ψ_target(s', a*)`` with
        ``a* = argmax_a w · ψ(s', a)`` over the actions ``s'`` has (its action mask, where the env gives one; online
        network picks, target network evaluates), Huber loss averaged over batch and objectives, gradient norm
        clipped.

        :param replay_buffer: where to sample from
        :param batch_size: number of transitions
        :param gamma: discount factor
        :param max_grad_norm: gradient-norm clipping threshold
        :param vec_normalize_env: normalises the sampled observations, if given
        :return: the loss before the step
        """
        batch = replay_buffer.sample(batch_size, env=vec_normalize_env)
        current_psi, target_psi = self.current_and_target(batch, gamma)
        self.give_back_errors(replay_buffer, batch, current_psi.detach(), target_psi)
        return self.gradient_step(F.smooth_l1_loss(current_psi, target_psi), max_grad_norm)

    def current_and_target(self, batch: MOReplayBufferSamples, gamma: float) -> tuple[th.Tensor, th.Tensor]:
        """
        ``ψ(s, a)`` of the sampled transitions (with its gradient) and their TD target (see :meth:`td_update`).

        :return: both of shape ``(batch, d)``
        """
        rows = th.arange(len(batch.rewards), device=batch.rewards.device)
        with th.no_grad():
            next_online = self.sf_net(batch.next_observations)
            next_actions = greedy_actions(next_online, self.weights, batch.next_action_masks)
            next_psi = next_online if self.sf_net_target is self.sf_net else self.sf_net_target(batch.next_observations)
            target_psi = batch.rewards + (1 - batch.dones) * gamma * next_psi[rows, next_actions]
        return self.sf_net(batch.observations)[rows, batch.actions.long().flatten()], target_psi

    def weighted_errors(self, current_psi: th.Tensor, target_psi: th.Tensor) -> th.Tensor:
        """``|w · (ψ(s, a) − target)|`` for the policy's weights, shape ``(batch,)``."""
        return weighted_sum(current_psi - target_psi, self.weights).abs()

    def give_back_errors(
        self, replay_buffer: MOReplayBuffer, batch: MOReplayBufferSamples, current_psi: th.Tensor, target_psi: th.Tensor
    ) -> None:
        """The sampled rows' errors for the policy's weights to a buffer that draws by them (prioritised replay)."""
        if isinstance(replay_buffer, PrioritizedMOReplayBuffer):
            replay_buffer.update_priorities(batch.rows, self.weighted_errors(current_psi, target_psi))

    @th.no_grad()
    def score_replay(self, replay_buffer: PrioritizedMOReplayBuffer, gamma: float, chunk: int = 4096) -> None:
        """
        Give every stored transition of a prioritised buffer its error for the policy's weights (a learner that goes
        on with new weights does this before learning for them: the errors for other weights say nothing of them).
        """
        rows = replay_buffer.stored_rows()
        for start in range(0, len(rows), chunk):
            batch = replay_buffer.samples_at(rows[start : start + chunk])
            self.give_back_errors(replay_buffer, batch, *self.current_and_target(batch, gamma))

    def gradient_step(self, loss: th.Tensor, max_grad_norm: float) -> float:
        """
        One optimizer step on ``loss`` with the gradient norm of the SF network clipped at ``max_grad_norm``.

        :return: the loss before the step
        """
        self.optimizer.zero_grad()
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.sf_net.parameters(), max_grad_norm)
        self.optimizer.step()
        return loss.item()

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the SF network in training or evaluation mode, as SB3's ``set_training_mode``.

        SB3 flips the mode twice per step when training every step (evaluation to act, training to learn), and
        the recursive ``Module.train`` costs more than a tabular update. When no module of the SF network
        overrides ``train``, the same ``training`` flags are set directly on its modules, listed once per SF
        network object (SF networks do not gain submodules after they are built).
        """
        sf_net = self.sf_net
        if self.training is mode and sf_net.training is mode:
            return
        cached = self.__dict__.get("_mode_modules")
        if cached is None or cached[0] is not sf_net:
            modules = list(sf_net.modules())
            plain = all(type(module).train is nn.Module.train for module in modules)
            cached = (sf_net, modules if plain else None)
            self.__dict__["_mode_modules"] = cached
        if cached[1] is not None and isinstance(mode, bool):
            for module in cached[1]:
                object.__setattr__(module, "training", mode)  # what Module.train does, minus the recursion
        else:
            sf_net.set_training_mode(mode)
        object.__setattr__(self, "training", mode)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            reward_dim=self.reward_dim,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            lr_schedule=self._dummy_schedule,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
        )
        return data


MlpPolicy = SFDQNPolicy
