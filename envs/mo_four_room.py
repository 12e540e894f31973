"""MO-Gymnasium's single-agent ``four-room-v0`` with the observation space a table can index."""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import mo_gymnasium
import numpy as np
from gymnasium import spaces

__all__ = ["FullObservation", "make_four_room"]


class FullObservation(gym.ObservationWrapper):
    """
    Declare four-room's true observation space: the cell (row, column) and one collected-flag per object.

    MO-Gymnasium declares it as ``Box(0, 13, (14,))``, which would make a table of 14**14 rows; on the default layout
    it is ``MultiDiscrete([13, 13] + [2] * 12)`` (692,224 rows).
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        n_objects = env.observation_space.shape[0] - 2
        height, width = env.unwrapped.maze.shape
        self.observation_space = spaces.MultiDiscrete([height, width] + [2] * n_objects)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.asarray(observation, dtype=np.int64)


def make_four_room(maze: Sequence[str] | None = None) -> gym.Env:
    """
    ``four-room-v0`` (200-step time limit) with :class:`FullObservation`.

    :param maze: another layout, one string per row in MO-Gymnasium's characters (``X`` wall, ``G`` goal, ``_``
        start, ``1``/``2``/``3`` objects); default: ``four-room-v0``'s
    """
    kwargs = {} if maze is None else {"maze": np.array([list(row) for row in maze])}
    return FullObservation(mo_gymnasium.make("four-room-v0", **kwargs))
