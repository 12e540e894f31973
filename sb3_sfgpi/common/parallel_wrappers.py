"""PettingZoo ParallelEnv wrappers that let SF learners train on environments as they come (MOMAland's included)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask
from sb3_sfgpi.common.single_agent import SingleAgentParallelEnv
from sb3_sfgpi.common.supersuit_wrappers import prepared

#: Observation spaces SB3's replay buffers and policies take as they are.
FLAT_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
#: Attributes under which PettingZoo and MOMAland envs keep their episode's number of steps.
TIME_LIMIT_ATTRIBUTES = ("num_timesteps", "max_cycles")


def needs_flattening(env: Any) -> bool:
    """Whether some agent's observation space is composite (``Tuple``, ``Dict``), which SB3 cannot store."""
    return any(not isinstance(env.observation_space(agent), FLAT_SPACES) for agent in env.possible_agents)


class _ObservationWrapper(BaseParallelWrapper):
    """A ParallelEnv wrapper that changes each agent's observation (:meth:`_observation`) at reset and at every step,
    and nothing else."""

    def _observation(self, agent: str, observation: Any) -> Any:
        raise NotImplementedError

    def _observations(self, observations: dict[str, Any]) -> dict[str, Any]:
        return {agent: self._observation(agent, obs) for agent, obs in observations.items()}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return self._observations(observations), infos

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return self._observations(observations), rewards, terminations, truncations, infos


class FlattenObservations(_ObservationWrapper):
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

    def _observation(self, agent: str, observation: Any) -> Any:
        return spaces.flatten(self._spaces[agent], observation)


def as_parallel_env(env: Any) -> Any:
    """
    ``env`` as the runner trains on it: a single-agent Gymnasium env becomes a
    :class:`~sb3_sfgpi.common.single_agent.SingleAgentParallelEnv` (SFOLS is MA-SFOLS with one agent), a ParallelEnv
    wrapped with SuperSuit gets back what its wrappers took (:mod:`~sb3_sfgpi.common.supersuit_wrappers`), and
    :class:`FlattenObservations` wraps an env whose observation spaces are composite.

    :raises ValueError: a turn-based (AEC) env, or something that is neither a ParallelEnv nor a Gymnasium env
    """
    if isinstance(env, gym.Env):
        env = SingleAgentParallelEnv(env)
    elif isinstance(env, AECEnv):
        raise ValueError(
            f"{env} is a turn-based (AEC) env: MA-SFOLS steps agents that act together in a ParallelEnv and has no "
            "runner that takes turns; use the game's parallel version where it has one (docs: environments, MOMAland)"
        )
    elif isinstance(env, gym.vector.VectorEnv) or hasattr(env, "num_envs"):
        raise ValueError(
            f"{env!r} is a vectorised env (SuperSuit's pettingzoo_env_to_vec_env_v1 / concat_vec_envs_v1, a Gymnasium "
            "or SB3 VecEnv): MA-SFOLS takes the ParallelEnv itself (wrapped with SuperSuit's other wrappers as you "
            "like) and steps copies of it together with n_envs=k"
        )
    elif not hasattr(env, "possible_agents"):
        raise ValueError(f"{env!r} is neither a PettingZoo ParallelEnv nor a Gymnasium env")
    else:
        env = prepared(env)
    return FlattenObservations(env) if needs_flattening(env) else env


class PadActions(BaseParallelWrapper):
    """
    Agents whose ``Discrete`` action spaces differ (in size or ``start``) given one ``Discrete(n)``, ``n`` the largest,
    with action masks: an agent's action ``i`` is its own ``start + i``, and ``info["action_mask"]`` allows its own
    ``n`` actions only (and, where the env gives masks of its own, only those of them). Learners and GPI act within the
    masks (:mod:`~sb3_sfgpi.common.action_masks`); an action a mask forbids is refused. ``reward_space`` and the env's
    other attributes pass through. E.g. MOMAland's gem mining (``Discrete(3, start=1)`` beside ``Discrete(4)``):
    ``MASFOLS(PadActions(mogem_mining_v0.parallel_env()), ...)``.

    :raises ValueError: an agent whose action space is not ``Discrete``
    """

    def __init__(self, env: Any):
        super().__init__(env)
        self._own: dict[str, spaces.Discrete] = {}
        for agent in env.possible_agents:
            space = env.action_space(agent)
            if not isinstance(space, spaces.Discrete):
                raise ValueError(f"PadActions pads Discrete action spaces; {agent!r} has {space}")
            self._own[agent] = space
        self._space = spaces.Discrete(max(int(space.n) for space in self._own.values()))

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._space

    def _masked(self, infos: dict[str, Any]) -> dict[str, Any]:
        masked_infos = {}
        for agent, info in infos.items():
            mask = np.zeros(self._space.n, dtype=np.int8)
            own = info_mask(info, int(self._own[agent].n), f"agent {agent!r}")
            mask[: self._own[agent].n] = 1 if own is None else own
            masked_infos[agent] = {**info, ACTION_MASK: mask}
        return masked_infos

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return observations, self._masked(infos)

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        own_actions = {}
        for agent, action in actions.items():
            space = self._own[agent]
            if not 0 <= int(action) < space.n:
                raise ValueError(f"action {action} of {agent!r} is a padded one (it has {space.n} actions)")
            own_actions[agent] = int(space.start) + int(action)
        observations, rewards, terminations, truncations, infos = self.env.step(own_actions)
        return observations, rewards, terminations, truncations, self._masked(infos)


class SwapTerminationsTruncations(BaseParallelWrapper):
    """
    Hands back ``terminations`` and ``truncations`` in their places, for envs that return them swapped: MOMAland
    0.2's item gathering and beach return ``observations, rewards, truncations, terminations, infos``. Use it only
    on such an env: ``MASFOLS(SwapTerminationsTruncations(moitem_gathering_v0.parallel_env()), ...)``.
    """

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return observations, rewards, truncations, terminations, infos


class SelfFirstAgentIds(_ObservationWrapper):
    """
    Each agent's observation as the first agent would see it, for envs that mark agents by their index: MOMAland's
    item gathering hands each agent ``(its id, the map)``, agent ``i`` being ``-(i + 1)`` in both. Wrapped, an agent
    sees itself as ``-1`` and the others as ``-2, -3, …`` in their order, so that a policy can act for any agent (one
    Π over homogeneous agents, MA-SFOLS's; a learner shared by the agents, ``sharing="shared"``, then learns from all
    of them); unwrapped, a member learned by agent 0 reads agent 1's observations as if agent 1 were the other agent.
    Spaces, rewards and the rest pass through:
    ``MASFOLS(SelfFirstAgentIds(SwapTerminationsTruncations(moitem_gathering_v0.parallel_env())), ...)``.

    :raises ValueError: an agent whose observation space is not ``Tuple(Discrete(n, start=-n), Box)``, ``n`` the
        number of agents
    """

    def __init__(self, env: Any):
        super().__init__(env)
        n = len(env.possible_agents)
        for agent in env.possible_agents:
            space = env.observation_space(agent)
            parts = space.spaces if isinstance(space, spaces.Tuple) else ()
            if not (
                len(parts) == 2 and isinstance(parts[0], spaces.Discrete) and isinstance(parts[1], spaces.Box)
                and int(parts[0].n) == n and int(parts[0].start) == -n
            ):  # fmt: skip
                raise ValueError(
                    f"SelfFirstAgentIds takes (agent id, map) observations with ids -1 to -{n}; {agent!r} has {space}"
                )

    def _observation(self, agent: str, observation: tuple[Any, np.ndarray]) -> tuple[int, np.ndarray]:
        own, board = -int(observation[0]), np.asarray(observation[1])
        relabelled = board.copy()
        relabelled[board == -own] = -1
        relabelled[(board < 0) & (board > -own)] -= 1  # the agents before it, one place later
        return -1, relabelled


def time_limit(env: Any) -> int | None:
    """The episode length an env declares (MOMAland's ``num_timesteps``, PettingZoo's ``max_cycles``), if any."""
    for name in TIME_LIMIT_ATTRIBUTES:
        value = getattr(env.unwrapped, name, None)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
    return None
