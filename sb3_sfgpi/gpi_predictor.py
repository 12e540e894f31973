"""A GPI set bound to one preference weight, acting through SB3's ``predict`` signature.

:meth:`sb3_sfgpi.gpi.GPIPolicy.predict` takes the weight ``w`` as its second argument, so SB3's tools, which call
``predict(observation, state=..., episode_start=..., deterministic=...)``, cannot use a set directly.
:meth:`~sb3_sfgpi.gpi.GPIPolicy.for_weights` returns a :class:`GPIPredictor` instead: a set and a weight, with SB3's
signature.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from sb3_sfgpi.common.weights import validate_weights


class WeightedPolicySet(Protocol):
    """What a :class:`GPIPredictor` needs of its set (:class:`~sb3_sfgpi.gpi.GPIPolicy` is one)."""

    @property
    def reward_dim(self) -> int: ...

    def __len__(self) -> int: ...

    def predict(self, observation: np.ndarray, w: np.ndarray, *args: Any, **kwargs: Any) -> Any: ...


class GPIPredictor:
    """
    GPI for one preference weight: ``π(s) = argmax_a max_{π ∈ Π} w · ψ^π(s, a)``.

    It holds the set itself, not a copy: policies added to the set later take part in its decisions.

    :param policy_set: the GPI set
    :param w: preference weights of length ``d`` (normalised to sum to one)
    :raises ValueError: bad weights or an empty set
    """

    def __init__(self, policy_set: WeightedPolicySet, w: np.ndarray | Sequence[float]):
        self.policy_set = policy_set
        self._weights = validate_weights(w, policy_set.reward_dim)

    @property
    def weights(self) -> np.ndarray:
        """The preference weights ``w`` it acts for (a copy)."""
        return self._weights.copy()

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
        action_masks: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        The GPI action for ``w``, as SB3's ``predict`` (see :meth:`sb3_sfgpi.gpi.GPIPolicy.predict`).

        :param observation: one observation or a batch
        :param state: unused, returned as is
        :param episode_start: unused
        :param deterministic: GPI is deterministic; kept for SB3 compatibility
        :param action_masks: the actions each observation has (0/1, one row per observation), as sb3-contrib's
            maskable algorithms take them; None: every action
        :return: the actions (a scalar array for one observation) and ``state``
        """
        return self.policy_set.predict(
            observation, self._weights, state, episode_start, deterministic, action_masks=action_masks
        )

    def __repr__(self) -> str:
        return f"GPIPredictor({len(self.policy_set)} policies, w={self._weights.tolist()})"
