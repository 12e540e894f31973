"""Environments shared by the benchmarks: MO-Gymnasium's Four-Room, vector and scalarised, and its "xy" view."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class XYObservation(gym.ObservationWrapper):
    """Four-Room observed as the agent's cell ``[row, col]`` only (the paper's "xy"): ``MultiDiscrete([13, 13])``."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.observation_space = spaces.MultiDiscrete([13, 13])

    def observation(self, observation: Any) -> np.ndarray:
        return np.asarray(observation[:2], dtype=np.int64)


def four_room(xy: bool = False) -> gym.Env:
    """MO-Gymnasium's ``four-room-v0`` (vector rewards, 200-step time limit), optionally with "xy" observations."""
    import mo_gymnasium as mo

    env = mo.make("four-room-v0")
    return XYObservation(env) if xy else env


def scalarized_four_room(weights: np.ndarray) -> gym.Env:
    """``four-room-v0`` with the scalar reward ``w · r`` (MO-Gymnasium's ``LinearReward``), for SB3's DQN."""
    import mo_gymnasium as mo

    return mo.wrappers.LinearReward(mo.make("four-room-v0"), weight=np.asarray(weights, dtype=np.float32))
