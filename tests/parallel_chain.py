"""A multi-agent version of the paper's Fig. 1 MOMDP, for exact tests of the multi-agent loop.

Every agent walks its own copy of the chain s0 → s1 → s2 → s3 → s4 (terminal); the action only chooses the
vector reward. Agent ``i`` may have a longer chain (it finishes later), to exercise early-finishing agents.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

# REWARDS[state][action] = (objective 0, objective 1); actions A, B, C.
REWARDS = np.array(
    [
        [(1, 9), (8, 9), (1, 5)],
        [(8, 7), (7, 7), (5, 2)],
        [(3, 6), (9, 0), (6, 1)],
        [(1, 0), (4, 8), (0, 5)],
    ],
    dtype=np.float32,
)
N_STATES = 5


def policy_values() -> np.ndarray:
    """Undiscounted value vectors of all 3^4 deterministic policies, shape (81, 2)."""
    return np.array([sum(REWARDS[s, a] for s, a in enumerate(actions)) for actions in itertools.product(range(3), repeat=4)])


def optimal_value(w: np.ndarray) -> float:
    """max_π w · V^π by brute force."""
    return float(np.max(policy_values() @ np.asarray(w)))


class ParallelChainEnv(ParallelEnv):
    """``n_agents`` agents, each on its own Fig. 1 chain; Discrete(5) observations, reward vectors of shape (2,)."""

    metadata = {"name": "parallel_chain_v0", "render_modes": []}

    def __init__(self, n_agents: int = 2, max_steps: int | None = None):
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.max_steps = max_steps
        self._reward_space = spaces.Box(0.0, 9.0, shape=(2,), dtype=np.float32)

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(N_STATES)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(3)

    def reward_space(self, agent: str) -> spaces.Box:
        return self._reward_space

    @property
    def reward_spaces(self) -> dict[str, spaces.Box]:
        return {agent: self._reward_space for agent in self.possible_agents}

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self.state = {agent: 0 for agent in self.agents}
        self.steps = 0
        return {agent: 0 for agent in self.agents}, {agent: {} for agent in self.agents}

    def step(self, actions):
        self.steps += 1
        obs, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in self.agents:
            s = self.state[agent]
            rewards[agent] = REWARDS[s, actions[agent]].copy()
            self.state[agent] = s + 1
            obs[agent] = s + 1
            terminations[agent] = s + 1 == N_STATES - 1
            truncations[agent] = self.max_steps is not None and self.steps >= self.max_steps and not terminations[agent]
            infos[agent] = {}
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos
