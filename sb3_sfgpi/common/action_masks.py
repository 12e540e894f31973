"""Action masks: which actions an agent has in a state, as Gymnasium and PettingZoo envs give them.

The convention is ``info["action_mask"]``: one 0/1 entry per action of the (possibly padded) ``Discrete`` space, 1
where the action exists (Gymnasium's ``Taxi``, PettingZoo's parallel envs; the ``action_mask`` of PettingZoo's
turn-based games and of sb3-contrib's maskable algorithms has the same meaning). An env without masks has every
action everywhere. Learners explore, act and bootstrap only on the actions a mask allows, and GPI acts only on them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

#: The info key of an action mask.
ACTION_MASK = "action_mask"


def info_mask(info: Mapping[str, Any], n_actions: int, where: str = "the env") -> np.ndarray | None:
    """
    The action mask an info carries, checked, or None where it has none.

    :param info: one agent's (or env's) info of a reset or step
    :param n_actions: the size of the ``Discrete`` action space
    :param where: who gave the info (for the error message)
    :return: a boolean array of shape ``(n_actions,)``, True where the action exists
    :raises ValueError: a mask of another shape, with entries other than 0/1, or with no action allowed
    """
    mask = info.get(ACTION_MASK)
    if mask is None:
        return None
    array = np.asarray(mask)
    if array.shape != (n_actions,) or not _zeros_and_ones(array):
        raise ValueError(f"{where}'s info['{ACTION_MASK}'] must be {n_actions} entries of 0 or 1, got {mask!r}")
    if not array.any():
        raise ValueError(f"{where}'s info['{ACTION_MASK}'] allows no action: {mask!r}")
    return array.astype(bool)


def stacked_masks(masks: Sequence[np.ndarray | None], n_actions: int) -> np.ndarray | None:
    """
    One mask per row, or None where no row has one (a row without a mask has every action).

    :param masks: per row, its mask or None
    :param n_actions: the number of actions
    :return: shape ``(len(masks), n_actions)``, or None
    """
    if all(mask is None for mask in masks):
        return None
    return np.stack([np.ones(n_actions, dtype=bool) if mask is None else mask for mask in masks])


def checked_masks(action_masks: Any, batch: int, n_actions: int) -> np.ndarray | None:
    """
    ``action_masks`` given to a ``predict``, as a boolean array of shape ``(batch, n_actions)`` (None stays None).

    :raises ValueError: another shape, entries other than 0/1, or a row that allows no action
    """
    if action_masks is None:
        return None
    array = np.asarray(action_masks)
    if array.ndim == 1:
        array = array[None]
    if array.shape != (batch, n_actions) or not _zeros_and_ones(array):
        raise ValueError(
            f"action_masks must be 0/1 of shape ({batch}, {n_actions}) (one row per observation), got "
            f"shape {array.shape}"
        )
    if not array.any(axis=1).all():
        raise ValueError("action_masks allows no action for some observation")
    return array.astype(bool)


def _zeros_and_ones(array: np.ndarray) -> bool:
    """Whether every entry of a numeric (or boolean) array is 0 or 1."""
    return array.dtype.kind in "biuf" and bool(np.isin(array, (0, 1)).all())


def masked(q_values: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """``q_values`` with ``-inf`` where the mask does not allow the action (``q_values`` itself without masks)."""
    return q_values if masks is None else np.where(masks, q_values, -np.inf)


def sample_allowed(action_space: Any, mask: np.ndarray | None) -> int:
    """
    A uniformly random action among those ``mask`` allows (of the whole space without a mask: the draws of an env
    without masks are unchanged).
    """
    return action_space.sample() if mask is None else action_space.sample(mask=mask.astype(np.int8))
