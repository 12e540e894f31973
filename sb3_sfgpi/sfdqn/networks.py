"""Successor-feature networks: ``ψ(s, ·)`` from an MLP, and the ``ψ → Q`` helpers (tables: :mod:`sb3_sfgpi.tabular`).

A successor-feature network maps an observation to ``ψ(s, ·)`` of shape ``(batch, n_actions, d)``;
the Q-values for preference weights ``w`` are ``ψ · w``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_sfgpi.common.weights import weighted_sum


def scalarize(psi: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """
    ``Q_w(s, a) = w · ψ(s, a)``, summed in the order of the objectives (:func:`~sb3_sfgpi.common.weights.weighted_sum`:
    no matrix product, so the same bits, and the same argmax, on every CPU).

    :param psi: successor features, shape ``(batch, n_actions, d)``
    :param weights: shape ``(d,)`` or ``(batch, d)``
    :return: shape ``(batch, n_actions)``
    """
    return weighted_sum(psi, weights.reshape(-1, 1, psi.shape[-1]))


def greedy_actions(psi: th.Tensor, weights: th.Tensor, masks: th.Tensor | None = None) -> th.Tensor:
    """
    ``argmax_a w · ψ(s, a)`` (ties, exactly equal :func:`scalarize` values, go to the first action).

    :param psi: successor features, shape ``(batch, n_actions, d)``
    :param weights: shape ``(d,)`` or ``(batch, d)``
    :param masks: where given, True for the actions each state has, shape ``(batch, n_actions)``: the argmax is over
        those only
    :return: actions, shape ``(batch,)``
    """
    q_values = scalarize(psi, weights)
    if masks is not None:
        q_values = q_values.masked_fill(~masks, -th.inf)
    return q_values.argmax(dim=1)


def argmax_random_ties(q_values: np.ndarray, rng: np.random.Generator | Any = np.random) -> np.ndarray:
    """
    ``argmax_a q(s, a)`` with ties between actions of exactly equal value broken uniformly at random.

    A zero-initialised table ties in every state it has not learned: a behaviour policy that always takes the first
    action there walks the same way until a wall stops it, and its greedy steps explore nothing.

    :param q_values: shape ``(batch, n_actions)``
    :param rng: what draws the tie-breaks: a ``numpy.random.Generator`` or the ``numpy.random`` module (seeded by
        SB3's ``set_random_seed``)
    :return: actions, shape ``(batch,)``
    """
    best = q_values == q_values.max(axis=1, keepdims=True)
    if best.sum() == len(best):  # no ties anywhere: no random numbers drawn
        return best.argmax(axis=1)
    return np.where(best, rng.random(best.shape), -1.0).argmax(axis=1)


class SFNetwork(BasePolicy):
    """
    MLP successor-feature network: features, then one MLP (``sf_net``) to ``ψ(s, ·)``.

    :param observation_space: Observation space
    :param action_space: Action space (Discrete)
    :param features_extractor: Features extractor
    :param features_dim: Number of features
    :param reward_dim: Number of objectives ``d``
    :param net_arch: Hidden layer sizes
    :param activation_fn: Activation function
    :param normalize_images: Whether to divide images by 255
    """

    action_space: spaces.Discrete
    #: the hidden layers when ``net_arch`` is None
    default_net_arch: tuple[int, ...] = (64, 64)

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        reward_dim: int,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.net_arch = list(self.default_net_arch if net_arch is None else net_arch)
        self.activation_fn = activation_fn
        self.features_dim = features_dim
        self.reward_dim = reward_dim
        self.n_actions = int(action_space.n)
        self.sf_net = self._make_layers()

    def _make_layers(self) -> nn.Sequential:
        """The layers from the features to ``ψ``: an MLP of ``net_arch``."""
        return nn.Sequential(
            *create_mlp(self.features_dim, self.n_actions * self.reward_dim, self.net_arch, self.activation_fn)
        )

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """
        :param obs: Observation batch
        :return: ``ψ(s, ·)``, shape ``(batch, n_actions, d)``
        """
        features = self.extract_features(obs, self.features_extractor)
        return self.sf_net(features).view(-1, self.n_actions, self.reward_dim)

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        raise NotImplementedError("an SF network has no weights: use SFDQNPolicy or GPIPolicy to act")

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            features_dim=self.features_dim,
            reward_dim=self.reward_dim,
            activation_fn=self.activation_fn,
            features_extractor=self.features_extractor,
        )
        return data


def non_finite_key(state: Mapping[str, th.Tensor]) -> str | None:
    """
    The first tensor of a network's state dict that is not finite in float32, the networks' and tables' dtype (a
    float64 1e39 is finite, and inf once loaded), or None.
    """
    for key, value in state.items():
        if value.is_floating_point() and not bool(th.isfinite(value.to(th.float32)).all()):
            return key
    return None
