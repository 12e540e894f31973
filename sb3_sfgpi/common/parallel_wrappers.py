"""PettingZoo ParallelEnv wrappers that let SF learners train on environments as they come (MOMAland's included)."""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
from pettingzoo.utils.wrappers import BaseParallelWrapper

#: Observation spaces SB3's replay buffers and policies take as they are.
FLAT_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
#: Attributes under which PettingZoo and MOMAland envs keep their episode's number of steps.
TIME_LIMIT_ATTRIBUTES = ("num_timesteps", "max_cycles")


def needs_flattening(env: Any) -> bool:
    """Whether some agent's observation space is composite (``Tuple``, ``Dict``), which SB3 cannot store."""
    return any(not isinstance(env.observation_space(agent), FLAT_SPACES) for agent in env.possible_agents)


class FlattenObservations(BaseParallelWrapper):
    """
    Every agent's observations flattened into one ``Box`` (gymnasium's ``flatten_space`` and ``flatten``: discrete
    parts one-hot, the others concatenated), e.g. MOMAland's item gathering, whose observations are
    ``Tuple(Discrete, Box)``. :class:`~sb3_sfgpi.multiagent.MultiAgentRunner` applies it where it is needed; a
    policy set learned on it acts on the flattened observations (wrap the env the same way to use it).
    """

    def __init__(self, env: Any):
        super().__init__(env)
        self._spaces = {agent: env.observation_space(agent) for agent in env.possible_agents}
        self._flat = {agent: spaces.flatten_space(space) for agent, space in self._spaces.items()}

    def observation_space(self, agent: str) -> spaces.Box:
        return self._flat[agent]

    def _flatten(self, observations: dict[str, Any]) -> dict[str, Any]:
        return {agent: spaces.flatten(self._spaces[agent], obs) for agent, obs in observations.items()}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return self._flatten(observations), infos

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return self._flatten(observations), rewards, terminations, truncations, infos


def flattened(env: Any) -> Any:
    """``env`` itself, or :class:`FlattenObservations` of it where some observation space is composite."""
    return FlattenObservations(env) if needs_flattening(env) else env


class SwapTerminationsTruncations(BaseParallelWrapper):
    """
    Hands back ``terminations`` and ``truncations`` in their places, for envs that return them swapped: MOMAland
    0.2's item gathering and beach return ``observations, rewards, truncations, terminations, infos``. Use it only
    on such an env: ``MASFOLS(SwapTerminationsTruncations(moitem_gathering_v0.parallel_env()), ...)``.
    """

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return observations, rewards, truncations, terminations, infos


def time_limit(env: Any) -> int | None:
    """The episode length an env declares (MOMAland's ``num_timesteps``, PettingZoo's ``max_cycles``), if any."""
    for name in TIME_LIMIT_ATTRIBUTES:
        value = getattr(env.unwrapped, name, None)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
    return None
