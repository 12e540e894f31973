"""What a learner that goes on across iterations needs to go on exactly after a resume, as tensors and plain data.

A learner conditioned on the weights (``ConditionedMlpPolicy``) is not rebuilt every iteration: its network, its
optimizer and its replay buffer carry what it learned to the next one. A run's checkpoint keeps them in a file of
tensors and plain numbers (read with ``weights_only=True``: nothing in it is executed), checked against the learner
that takes them. Its random generators are seeded again at the start of every iteration, so they need no saving.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

from sb3_sfgpi.sfdqn.networks import non_finite_key
from sb3_sfgpi.sfdqn.sfdqn import SFDQN

#: The replay buffer's arrays a state holds (those the buffer has), their stored rows only.
BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts", "next_forbidden")


def training_state(learner: SFDQN) -> dict[str, Any]:
    """
    The state of a learner between two iterations: network and target, optimizer, replay buffer, step counters and
    weight support.

    :return: tensors and plain numbers (``torch.save`` writes it, ``torch.load(weights_only=True)`` reads it)
    """
    buffer = learner.replay_buffer
    rows = buffer.buffer_size if buffer.full else buffer.pos + 1
    replay = {
        name: th.from_numpy(getattr(buffer, name)[:rows].copy())  # a snapshot, not a view of the buffer
        for name in BUFFER_ARRAYS
        if getattr(buffer, name, None) is not None
    }
    support = learner.weight_support
    return {
        "policy": {key: value.clone() for key, value in learner.policy.state_dict().items()},
        "optimizer": learner.policy.optimizer.state_dict(),
        "replay": replay,
        "replay_position": [int(buffer.pos), int(buffer.full), int(buffer._rows_at_pos)],
        "counters": [
            int(c) for c in (learner.num_timesteps, learner._n_calls, learner._n_updates, learner._episode_num)
        ],
        "weight_support": None if support is None else th.as_tensor(support),
        "exploration_rate": float(learner.exploration_rate),  # the next step's: set by the last one
    }


def restore_training_state(learner: SFDQN, state: Any) -> None:
    """
    Give ``learner`` (built with the run's settings) the state :func:`training_state` took.

    :raises ValueError: a state that does not fit the learner (keys, shapes, types, non-finite numbers)
    """
    try:
        replay, position, counters = state["replay"], state["replay_position"], state["counters"]
        _check_replay(learner, replay, position)
        if len(counters) != 4 or not all(isinstance(c, int) and c >= 0 for c in counters):
            raise ValueError(f"the step counters must be 4 non-negative integers, got {counters!r}")
        key = non_finite_key(state["policy"])
        if key is not None:
            raise ValueError(f"the saved network holds non-finite values in {key!r}")
        exploration_rate = state["exploration_rate"]
        if not isinstance(exploration_rate, float) or not 0.0 <= exploration_rate <= 1.0:
            raise ValueError(f"the exploration rate must be a number in [0, 1], got {exploration_rate!r}")
        learner.policy.load_state_dict(state["policy"])
        learner.policy.optimizer.load_state_dict(state["optimizer"])
    except (KeyError, TypeError, RuntimeError) as error:
        raise ValueError(f"the learner's saved state does not fit it: {error!r}") from None
    buffer = learner.replay_buffer
    for name, array in replay.items():
        getattr(buffer, name)[: len(array)] = array.numpy()
    buffer.pos, buffer.full, buffer._rows_at_pos = position[0], bool(position[1]), position[2]
    learner.num_timesteps, learner._n_calls, learner._n_updates, learner._episode_num = counters
    learner.exploration_rate = exploration_rate
    if state["weight_support"] is not None:
        learner.set_weight_support(state["weight_support"].numpy())


def _check_replay(learner: SFDQN, replay: dict[str, th.Tensor], position: list[int]) -> None:
    """Refuse saved replay arrays of other shapes or types than the learner's buffer, or of non-finite numbers."""
    buffer = learner.replay_buffer
    if not isinstance(replay, dict) or set(replay) - set(BUFFER_ARRAYS):
        raise ValueError(f"the saved replay buffer holds unknown arrays: {sorted(replay)}")
    if len(position) != 3 or not 0 <= position[0] < buffer.buffer_size or position[1] not in (0, 1):
        raise ValueError(f"the saved replay position {position!r} does not fit a buffer of {buffer.buffer_size}")
    for name, array in replay.items():
        mine = getattr(buffer, name, None)
        if mine is None and name == "next_forbidden":  # masks: the buffer makes its array when it stores the first
            buffer._store_masks(slice(0, 0), np.zeros((0, int(learner.action_space.n)), dtype=bool))  # type: ignore[attr-defined]
            mine = buffer.next_forbidden
        if mine is None or not isinstance(array, th.Tensor) or array.shape[1:] != mine.shape[1:]:
            raise ValueError(f"the saved replay array {name!r} does not fit the learner's buffer")
        if len(array) > len(mine) or array.numpy().dtype != mine.dtype:
            raise ValueError(f"the saved replay array {name!r} has {len(array)} rows of {array.dtype}")
        if array.is_floating_point() and not bool(th.isfinite(array).all()):
            raise ValueError(f"the saved replay array {name!r} holds non-finite values")
