"""A multi-agent version of the paper's Fig. 1 MOMDP, for exact tests of the multi-agent loop.

Every agent walks its own copy of the chain s0 → s1 → s2 → s3 → s4 (terminal); the action only chooses the
vector reward. ``max_steps`` truncates episodes before the terminal state, to exercise time limits; ``staggered``
starts agent ``i`` at state ``i``, so that agents finish one after the other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces
from momdp import N_STATES, REWARDS, optimal_value
from pettingzoo import ParallelEnv

if TYPE_CHECKING:  # imported where used: env copies' processes import this module without torch
    from sb3_sfgpi.multiagent import MultiAgentRunner

__all__ = ["CHAIN_LEARNER", "FailingChain", "ParallelChainEnv", "make_chain_runner", "optimal_value"]

#: Tabular SFDQN settings that solve the chain in a few hundred steps per agent.
CHAIN_LEARNER = dict(
    policy="TabularPolicy",
    learning_rate=0.3,
    gamma=1.0,
    exploration_initial_eps=1.0,
    exploration_fraction=0.6,
    exploration_final_eps=0.1,
    learning_starts=0,
    train_freq=1,
    batch_size=16,
    buffer_size=10_000,
)


class ParallelChainEnv(ParallelEnv):
    """``n_agents`` agents, each on its own Fig. 1 chain; Discrete(5) observations, reward vectors of shape (2,)."""

    metadata = {"name": "parallel_chain_v0", "render_modes": []}

    def __init__(self, n_agents: int = 2, max_steps: int | None = None, staggered: bool = False):
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.max_steps = max_steps
        self.staggered = staggered
        self._reward_space = spaces.Box(0.0, 9.0, shape=(2,), dtype=np.float32)
        self._observation_space = spaces.Discrete(N_STATES)
        self._action_space = spaces.Discrete(3)

    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Space:
        return self._action_space

    def reward_space(self, agent: str) -> spaces.Box:
        return self._reward_space

    @property
    def reward_spaces(self) -> dict[str, spaces.Box]:
        return {agent: self._reward_space for agent in self.possible_agents}

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self.state = {agent: i * self.staggered for i, agent in enumerate(self.agents)}
        self.steps = 0
        return dict(self.state), {agent: {} for agent in self.agents}

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


class FailingChain(ParallelChainEnv):
    """A chain whose simulator breaks at its third step (here, not in a test module: its copies' processes import
    this light module)."""

    def step(self, actions):
        if self.steps == 2:
            raise ValueError("the simulator broke")
        return super().step(actions)


def make_chain_runner(n_agents: int = 2, seed: int = 0, max_steps: int | None = None) -> MultiAgentRunner:
    """Independent tabular learners (:data:`CHAIN_LEARNER`) on a :class:`ParallelChainEnv`."""
    from sb3_sfgpi.learners import default_learner_factory
    from sb3_sfgpi.multiagent import MultiAgentRunner

    return MultiAgentRunner(
        ParallelChainEnv(n_agents, max_steps=max_steps), default_learner_factory(**CHAIN_LEARNER), seed=seed
    )
