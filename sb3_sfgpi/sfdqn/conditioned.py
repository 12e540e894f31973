"""Weight-conditioned successor features: one network ``ψ(s, a, w)`` learned for every weight of a support at once.

A per-weight SF network learns only from the transitions scalarised by its own ``w``: on a sparse problem such as
minecart a learner for an ore-only weight needs 40,000-90,000 steps before its first ore, and OLS gives it one
iteration. :class:`ConditionedSFNetwork` takes the weight as an input (the state's features times the weight's
features, as in Alegre et al.'s GPI-LS), so that every minibatch trains it for the iteration's weight and for the
weights OLS already holds (its *support*), and :class:`ConditionedPolicy` acts by GPI over that support: what was
learned for one weight is there for every other one.

As a member of Π a conditioned network is bound to one weight (its ``member_weights`` buffer, saved with it):
called without a weight, it gives ``ψ(s, ·, w_member)``, so GPI over Π treats it as any other SF network.
"""

from __future__ import annotations

import copy
import itertools
import numbers
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn
from torch.nn import functional as F

from sb3_sfgpi.common.buffers import MOReplayBuffer, MOReplayBufferSamples
from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.sfdqn.networks import SFNetwork, greedy_actions, scalarize
from sb3_sfgpi.sfdqn.policies import SFDQNPolicy

#: The hidden layers of a conditioned network unless told otherwise (GPI-LS's on minecart).
CONDITIONED_NET_ARCH = [256, 256, 256, 256]
#: The heads of a conditioned network unless told otherwise: two, whose lower estimate is bootstrapped (GPI-LS's
#: pessimism; measured against one head on minecart: docs, experiments/levers).
CONDITIONED_HEADS = 2


class ConditionedHead(nn.Module):
    """
    One estimate of ``ψ(s, ·, w)`` from the state's features: a feature layer for the state and one for the weight
    (``net_arch[0]`` units each), their element-wise product, then ``net_arch[1:]`` with layer normalisation.

    :param features_dim: Number of state features
    :param reward_dim: Number of objectives ``d``
    :param n_outputs: ``n_actions × d``
    :param net_arch: Hidden layer sizes (at least one)
    :param activation_fn: Activation function
    """

    def __init__(
        self, features_dim: int, reward_dim: int, n_outputs: int, net_arch: list[int], activation_fn: type[nn.Module]
    ):
        super().__init__()
        self.state_features = nn.Sequential(nn.Linear(features_dim, net_arch[0]), activation_fn())
        self.weight_features = nn.Sequential(nn.Linear(reward_dim, net_arch[0]), activation_fn())
        layers: list[nn.Module] = []
        for n_in, n_out in itertools.pairwise(net_arch):
            layers += [nn.Linear(n_in, n_out), nn.LayerNorm(n_out), activation_fn()]
        layers.append(nn.Linear(net_arch[-1], n_outputs))
        self.layers = nn.Sequential(*layers)

    def forward(self, features: th.Tensor, weights: th.Tensor) -> th.Tensor:
        """
        :param features: shape ``(batch, features_dim)``
        :param weights: shape ``(batch, d)``
        :return: shape ``(batch, n_outputs)``
        """
        return self.layers(self.state_features(features) * self.weight_features(weights))


class ConditionedSFNetwork(SFNetwork):
    """
    ``ψ(s, ·, w)`` from ``n_heads`` :class:`ConditionedHead` estimates learned side by side: it is their mean, and a
    TD target bootstraps from the lowest of them (see :class:`ConditionedPolicy`).

    Its constructor's arguments are :class:`~sb3_sfgpi.sfdqn.networks.SFNetwork`'s (``net_arch``: at least one
    layer, :data:`CONDITIONED_NET_ARCH` by default) and ``n_heads``.

    :param n_heads: Number of heads (at least one; :data:`CONDITIONED_HEADS` by default)
    """

    default_net_arch = tuple(CONDITIONED_NET_ARCH)

    def __init__(self, *args: Any, n_heads: int = CONDITIONED_HEADS, **kwargs: Any):
        if n_heads < 1:
            raise ValueError(f"a conditioned SF network needs at least one head, got n_heads={n_heads}")
        self.n_heads = n_heads
        super().__init__(*args, **kwargs)
        self.register_buffer("member_weights", th.full((self.reward_dim,), 1.0 / self.reward_dim))

    def _make_layers(self) -> nn.ModuleList:  # type: ignore[override]
        """The heads."""
        if not self.net_arch:
            raise ValueError("a conditioned SF network needs at least one hidden layer (net_arch)")
        n_outputs = self.n_actions * self.reward_dim
        return nn.ModuleList(
            ConditionedHead(self.features_dim, self.reward_dim, n_outputs, self.net_arch, self.activation_fn)
            for _ in range(self.n_heads)
        )

    def heads(self, obs: PyTorchObs, weights: th.Tensor | None = None) -> th.Tensor:
        """
        :param obs: Observation batch
        :param weights: the weights to condition on, shape ``(d,)`` or ``(batch, d)``; None: ``member_weights``
        :return: each head's ``ψ(s, ·, w)``, shape ``(n_heads, batch, n_actions, d)``
        """
        features = self.extract_features(obs, self.features_extractor)
        weights = (self.member_weights if weights is None else weights).expand(len(features), -1)
        psi = [head(features, weights) for head in self.sf_net]
        return th.stack(psi).view(self.n_heads, -1, self.n_actions, self.reward_dim)

    def forward(self, obs: PyTorchObs, weights: th.Tensor | None = None) -> th.Tensor:
        """
        :param obs: Observation batch
        :param weights: the weights to condition on, shape ``(d,)`` or ``(batch, d)``; None: ``member_weights``
        :return: ``ψ(s, ·, w)``, the heads' mean, shape ``(batch, n_actions, d)``
        """
        heads = self.heads(obs, weights)
        return heads[0] if self.n_heads == 1 else heads.mean(dim=0)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "n_heads": self.n_heads}

    def bound_to(self, weights: np.ndarray) -> ConditionedSFNetwork:
        """
        A copy of this network bound to ``weights``: a policy of Π, ``ψ(s, ·, weights)`` when called without one.

        :param weights: the member's weights, shape ``(d,)``
        """
        member = copy.deepcopy(self)
        member.member_weights.copy_(th.as_tensor(weights, dtype=th.float32))
        member.set_training_mode(False)
        return member


class ConditionedPolicy(SFDQNPolicy):
    """
    SFDQN's policy over a :class:`ConditionedSFNetwork`: trained for its weights and its support, acting by GPI.

    Each gradient step samples one batch of transitions and learns it twice in one pass: for the policy's weights
    ``w`` and, where the support holds other weights, for support weights drawn uniformly (one per transition).
    The target of a transition for weight ``w'`` is ``r + γ (1 − terminated) ψ_target(s', a*, w')`` with
    ``a* = argmax_a w' · ψ(s', a, w')`` (online network picks, target network evaluates) and, with several heads,
    ``ψ_target`` the target head of lowest ``w' · ψ`` there (an overestimate of one head is not bootstrapped).

    With prioritised replay a transition's priority is its error for ``w`` (the head that errs most).

    Acting for weights ``w`` is GPI over the support and ``w`` itself:
    ``argmax_a max_{w' ∈ support ∪ {w}} w · ψ(s, a, w')``: what the network learned for the other weights of
    the support serves ``w`` too.

    :param observation_space: Observation space
    :param action_space: Action space (Discrete)
    :param lr_schedule: Learning rate schedule
    :param reward_dim: Number of objectives ``d``
    :param net_arch: Hidden layer sizes (default :data:`CONDITIONED_NET_ARCH`)
    :param n_heads: Number of heads of the network (:data:`CONDITIONED_HEADS` by default)
    :param member_average: 0: a member of Π copies the network as it is; else it copies a running average of the
        network, moved that fraction of the way to the network after every gradient step (an exponential moving
        average over about ``1 / member_average`` steps: a member is not the network of one noisy step)
    :param optimizer_kwargs: Keyword arguments of the optimizer, excluding the learning rate (default: ``foreach``)
    :param kwargs: further :class:`~sb3_sfgpi.sfdqn.policies.SFDQNPolicy` arguments
    """

    sf_net: ConditionedSFNetwork
    sf_net_target: ConditionedSFNetwork
    sf_network_class = ConditionedSFNetwork

    def __init__(
        self,
        *args: Any,
        net_arch: list[int] | None = None,
        n_heads: int = CONDITIONED_HEADS,
        member_average: float = 0.0,
        optimizer_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ):
        if (
            isinstance(member_average, bool)
            or not isinstance(member_average, numbers.Real)
            or not 0 <= member_average < 1
        ):
            raise ValueError(f"member_average must be a number in [0, 1), got {member_average!r}")
        self.member_average = member_average
        # foreach: the optimizer updates all parameters with a few batched kernels instead of a loop over them (unless
        # told otherwise, or to fuse them)
        optimizer_kwargs = dict(optimizer_kwargs or {})
        if not optimizer_kwargs.get("fused"):
            optimizer_kwargs.setdefault("foreach", True)
        net_arch = list(CONDITIONED_NET_ARCH if net_arch is None else net_arch)
        self.n_heads = n_heads
        super().__init__(*args, net_arch=net_arch, optimizer_kwargs=optimizer_kwargs, **kwargs)
        #: the weights trained beside ``weights`` and acted over by GPI, shape ``(k, d)`` (set by SFDQN)
        self.support = self.weights.reshape(1, -1).clone()

    @property
    def sf_network_kwargs(self) -> dict[str, Any]:
        return {"n_heads": self.n_heads}

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        self.sf_net_average = copy.deepcopy(self.sf_net).requires_grad_(False) if self.member_average else None

    @property
    def member_net(self) -> nn.Module:
        """The network members of Π copy: the running average of the SF network, where there is one."""
        return self.sf_net if self.sf_net_average is None else self.sf_net_average

    def gradient_step(self, loss: th.Tensor, max_grad_norm: float) -> float:
        """One optimizer step (:meth:`SFDQNPolicy.gradient_step`), then the running average moves toward the network."""
        value = super().gradient_step(loss, max_grad_norm)
        if self.sf_net_average is not None:
            with th.no_grad():
                averaged, online = list(self.sf_net_average.parameters()), list(self.sf_net.parameters())
                th._foreach_lerp_(averaged, online, self.member_average)
        return value

    def set_support(self, support: np.ndarray) -> None:
        """
        :param support: the weights to train beside the policy's own and to act over by GPI, shape ``(k, d)``
        """
        self.support = th.as_tensor(np.asarray(support, dtype=np.float32).reshape(-1, self.reward_dim)).to(self.device)

    def action_values(self, obs: PyTorchObs, weights: th.Tensor) -> th.Tensor:
        """
        GPI's action values for ``w`` over the support: ``max_{w' ∈ support ∪ {w}} w · ψ(s, a, w')``.

        :param weights: ``w``, shape ``(d,)``, or ``(batch, d)``: each observation's own
        """
        assert isinstance(obs, th.Tensor), "a conditioned network takes flat (Box) observations"
        batch, support = len(obs), self.support.to(weights.device)
        rows = weights.expand(batch, -1)  # (d,) or (batch, d): each row's own
        obs_each = obs.repeat(len(support) + 1, *([1] * (obs.dim() - 1)))
        members = th.cat([support.repeat_interleave(batch, dim=0), rows])  # every support weight, then each row's
        psi = self.sf_net(obs_each, members)
        return scalarize(psi, rows.repeat(len(support) + 1, 1)).view(len(support) + 1, batch, -1).max(dim=0).values

    def td_update(
        self,
        replay_buffer: MOReplayBuffer,
        batch_size: int,
        gamma: float,
        max_grad_norm: float,
        vec_normalize_env: VecNormalize | None = None,
    ) -> float:
        """
        One gradient step on a sampled batch, for the policy's weights and for support weights (see the class), Huber
        loss averaged over batch and objectives and summed over heads, gradient norm clipped.

        :return: the loss before the step
        """
        batch = replay_buffer.sample(batch_size, env=vec_normalize_env)
        weights = self.weights.expand(batch_size, -1)
        if len(self.support) > 1:
            drawn = th.randint(len(self.support), (batch_size,), device=self.support.device)
            weights = th.cat([weights, self.support[drawn].to(weights.device)])
        current_heads, target_psi = self._heads_and_target(batch, weights, gamma)
        own = slice(0, batch_size)  # the rows learned for the policy's weights: their errors are the priorities
        self.give_back_errors(replay_buffer, batch, current_heads[:, own].detach(), target_psi[own])
        loss = F.smooth_l1_loss(current_heads, target_psi.expand_as(current_heads), reduction="none")
        return self.gradient_step(loss.mean(dim=(1, 2)).sum(), max_grad_norm)

    def current_and_target(self, batch: MOReplayBufferSamples, gamma: float) -> tuple[th.Tensor, th.Tensor]:
        """
        Each head's ``ψ(s, a, w)`` of the sampled transitions for the policy's weights ``w`` (with its gradient),
        shape ``(n_heads, batch, d)``, and their TD target, shape ``(batch, d)``.
        """
        return self._heads_and_target(batch, self.weights.expand(len(batch.rewards), -1), gamma)

    def weighted_errors(self, current_psi: th.Tensor, target_psi: th.Tensor) -> th.Tensor:
        """``|w · (ψ(s, a, w) − target)|`` of the head that errs most, shape ``(batch,)``."""
        return weighted_sum(current_psi - target_psi, self.weights).abs().max(dim=0).values

    def _heads_and_target(
        self, batch: MOReplayBufferSamples, weights: th.Tensor, gamma: float
    ) -> tuple[th.Tensor, th.Tensor]:
        """
        The heads' ``ψ(s, a, w')`` and the TD targets of the batch learned once for each block of ``len(batch)``
        rows of ``weights`` (one weight per row, shape ``(k · batch, d)``).
        """
        copies = len(weights) // len(batch.rewards)

        def repeated(x: th.Tensor) -> th.Tensor:
            return x.repeat(copies, *([1] * (x.dim() - 1)))

        observations, next_observations = repeated(batch.observations), repeated(batch.next_observations)  # type: ignore[arg-type]
        masks = None if batch.next_action_masks is None else repeated(batch.next_action_masks)
        rows = th.arange(len(weights), device=weights.device)
        with th.no_grad():
            next_actions = greedy_actions(self.sf_net(next_observations, weights), weights, masks)
            target_heads = self.sf_net_target.heads(next_observations, weights)[:, rows, next_actions]
            next_psi = target_heads[weighted_sum(target_heads, weights).argmin(dim=0), rows]
            target_psi = repeated(batch.rewards) + (1 - repeated(batch.dones)) * gamma * next_psi
        current_heads = self.sf_net.heads(observations, weights)[:, rows, repeated(batch.actions).long().flatten()]
        return current_heads, target_psi

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "n_heads": self.n_heads, "member_average": self.member_average}
