"""A single-agent Gymnasium env with vector rewards (MO-Gymnasium's convention) as a PettingZoo ParallelEnv of one
agent, so that SFOLS is MA-SFOLS with one agent: the same runner, run directory, evaluation and command line."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from sb3_sfgpi.common.reward_space import env_reward_dim

#: The name of the one agent.
AGENT = "agent_0"


class SingleAgentParallelEnv(ParallelEnv):
    """
    ``env`` as a ParallelEnv whose one agent, ``"agent_0"``, takes its actions and gets its observations, vector
    rewards (``reward_space(agent)`` is the env's ``reward_space``) and infos. The agent leaves when the episode
    terminates or is truncated, as PettingZoo's agents do.

    :param env: a Gymnasium env following MO-Gymnasium's convention (a ``reward_space`` Box of shape ``(d,)``)
    :raises ValueError: an env without a vector ``reward_space``
    """

    def __init__(self, env: gym.Env):
        env_reward_dim(env)
        self.env = env
        self.possible_agents = [AGENT]
        self.agents: list[str] = []
        self.metadata = dict(getattr(env, "metadata", {}))
        self.render_mode = env.render_mode

    def __str__(self) -> str:
        return f"SingleAgentParallelEnv<{self.env}>"

    def observation_space(self, agent: str) -> spaces.Space:
        return self.env.observation_space

    def action_space(self, agent: str) -> spaces.Space:
        return self.env.action_space

    def reward_space(self, agent: str) -> spaces.Box:
        """The env's ``reward_space`` (the same for its one agent)."""
        return self.env.get_wrapper_attr("reward_space")

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        self.agents = [AGENT]
        return {AGENT: observation}, {AGENT: info}

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        if set(actions) != {AGENT}:
            raise ValueError(f"{self} has the one agent {AGENT!r}; got actions for {sorted(actions)}")
        observation, reward, terminated, truncated, info = self.env.step(actions[AGENT])
        if terminated or truncated:
            self.agents = []
        reward = np.asarray(reward, dtype=np.float32)
        return {AGENT: observation}, {AGENT: reward}, {AGENT: terminated}, {AGENT: truncated}, {AGENT: info}

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()
