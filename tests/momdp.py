"""The MOMDP of the paper's Fig. 1 as a Gymnasium env, with exact (brute-force) values.

States ``s0 → s1 → s2 → s3 → s4`` (terminal), whatever the action; the action (A, B or C) only chooses the
vector reward. A deterministic policy is a tuple of 4 actions, one for each of ``s0..s3``: there are
``3**4 = 81`` of them, so every value and every optimum here is computed exactly.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
from gymnasium import spaces

if TYPE_CHECKING:  # imported where used: env copies' processes import this module without torch
    from sb3_sfgpi.sfdqn import TabularSFNetwork

#: REWARDS[state, action] = (objective 0, objective 1); actions A, B, C.
REWARDS = np.array(
    [
        [(1, 9), (8, 9), (1, 5)],
        [(8, 7), (7, 7), (5, 2)],
        [(3, 6), (9, 0), (6, 1)],
        [(1, 0), (4, 8), (0, 5)],
    ],
    dtype=np.float32,
)
N_STATES = 5  # s0..s3 and the terminal s4
N_ACTIONS = 3
REWARD_DIM = 2
TERMINAL = N_STATES - 1

#: Every deterministic policy, as a tuple (action in s0, ..., action in s3).
ALL_POLICIES: list[tuple[int, ...]] = list(itertools.product(range(N_ACTIONS), repeat=TERMINAL))


class Fig1MOMDP(gym.Env):
    """
    The Fig. 1 chain with vector rewards (MO-Gymnasium convention).

    :param one_hot: observe a one-hot float32 vector of length 5 instead of the ``Discrete(5)`` state
    """

    metadata = {"render_modes": []}

    def __init__(self, one_hot: bool = False):
        self.one_hot = one_hot
        if one_hot:
            self.observation_space = spaces.Box(0.0, 1.0, shape=(N_STATES,), dtype=np.float32)
        else:
            self.observation_space = spaces.Discrete(N_STATES)
        self.action_space = spaces.Discrete(N_ACTIONS)
        self.reward_space = spaces.Box(0.0, 9.0, shape=(REWARD_DIM,), dtype=np.float32)
        self.state = 0

    def _obs(self):
        if self.one_hot:
            return np.eye(N_STATES, dtype=np.float32)[self.state]
        return self.state

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.state = 0
        return self._obs(), {}

    def step(self, action):
        if self.state == TERMINAL:
            raise RuntimeError("step() called on a terminated episode: call reset()")
        reward = REWARDS[self.state, int(action)].copy()
        self.state += 1
        return self._obs(), reward, self.state == TERMINAL, False, {}


def observation(state: int, one_hot: bool = False):
    """The observation the env emits in ``state``."""
    return np.eye(N_STATES, dtype=np.float32)[state] if one_hot else state


def all_observations(one_hot: bool = False) -> np.ndarray:
    """A batch of the observations of ``s0..s4``."""
    return np.eye(N_STATES, dtype=np.float32) if one_hot else np.arange(N_STATES)


def policy_value(actions: Sequence[int], gamma: float = 1.0, start: int = 0) -> np.ndarray:
    """Exact value vector ``V^π(s_start)`` of the deterministic policy ``actions`` (one action per state)."""
    value = np.zeros(REWARD_DIM)
    for k, s in enumerate(range(start, TERMINAL)):
        value += gamma**k * REWARDS[s, actions[s]]
    return value


def all_policy_values(gamma: float = 1.0) -> np.ndarray:
    """``V^π(s0)`` of all 81 deterministic policies, shape ``(81, 2)`` (ordered as :data:`ALL_POLICIES`)."""
    return np.array([policy_value(p, gamma) for p in ALL_POLICIES])


def optimal_value(w: Sequence[float], gamma: float = 1.0) -> float:
    """``max_π w · V^π(s0)`` by brute force over all deterministic policies."""
    return float(np.max(all_policy_values(gamma) @ np.asarray(w, dtype=np.float64)))


def optimal_policy(w: Sequence[float], gamma: float = 1.0) -> tuple[int, ...]:
    """A deterministic policy reaching :func:`optimal_value` (the first in :data:`ALL_POLICIES` order)."""
    return ALL_POLICIES[int(np.argmax(all_policy_values(gamma) @ np.asarray(w, dtype=np.float64)))]


def successor_features(actions: Sequence[int], gamma: float = 1.0) -> np.ndarray:
    """
    Exact ``ψ^π(s, a)`` of a deterministic policy, shape ``(5, 3, 2)`` (zero in the terminal state).

    ``ψ^π(s, a) = r(s, a) + γ ψ^π(s + 1, π(s + 1))``.
    """
    psi = np.zeros((N_STATES, N_ACTIONS, REWARD_DIM))
    for s in reversed(range(TERMINAL)):
        continuation = psi[s + 1, actions[s + 1]] if s + 1 < TERMINAL else np.zeros(REWARD_DIM)
        psi[s] = REWARDS[s] + gamma * continuation
    return psi


def convex_coverage_values(gamma: float = 1.0) -> np.ndarray:
    """The distinct value vectors that are optimal for some weight (the CCS values), found on a fine grid."""
    values = all_policy_values(gamma)
    found = set()
    for t in np.linspace(0.0, 1.0, 2001):
        scalar = values @ np.array([1 - t, t])
        found.update(tuple(v) for v in values[np.isclose(scalar, scalar.max())])
    # Drop weakly dominated ties (e.g. (16, 30) next to (23, 30) at w = (0, 1)).
    ccs = [v for v in found if not any(np.all(np.array(u) >= v) and u != v for u in found)]
    return np.array(sorted(ccs))


def policy_of(act: Callable[[int], int]) -> tuple[int, ...]:
    """The deterministic policy (one action per state ``s0..s3``) of a state → action function."""
    return tuple(int(act(s)) for s in range(TERMINAL))


def rollout_return(act: Callable[[object], int], gamma: float = 1.0, one_hot: bool = False) -> np.ndarray:
    """Discounted vector return of one episode of the env acting with ``act(observation)``."""
    env = Fig1MOMDP(one_hot=one_hot)
    obs, _ = env.reset(seed=0)
    total, discount, done = np.zeros(REWARD_DIM), 1.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(act(obs))
        total += discount * reward
        discount *= gamma
        done = terminated or truncated
    return total


def exact_tabular_network(actions: Sequence[int], gamma: float = 1.0) -> TabularSFNetwork:
    """A tabular SF network of the Fig. 1 MOMDP holding the exact ``ψ^π`` of the deterministic policy ``actions``."""
    from sb3_sfgpi.sfdqn import TabularSFNetwork

    net = TabularSFNetwork(spaces.Discrete(N_STATES), spaces.Discrete(N_ACTIONS), REWARD_DIM)
    net.table.set_dense(successor_features(actions, gamma).reshape(N_STATES, -1))
    return net
