"""Monte-Carlo rollouts of a joint policy in a PettingZoo ParallelEnv with vector rewards."""

from __future__ import annotations

import numbers
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from sb3_sfgpi.common.action_masks import ACTION_MASK, info_mask
from sb3_sfgpi.common.checks import check_parallel_reset, check_parallel_step

#: Maps the observations of the live agents to their actions: ``policy(observations)``, or, where the env gives
#: action masks (:mod:`~sb3_sfgpi.common.action_masks`), ``policy(observations, action_masks=masks)`` with the live
#: agents' masks (every action allowed for an agent whose info has none).
JointPolicy = Callable[..., dict[str, Any]]


@dataclass
class EpisodeReturns:
    """
    Vector returns of every agent over several episodes.

    :param discounted: agent -> array ``(n_episodes, d)`` of discounted returns
    :param undiscounted: agent -> array ``(n_episodes, d)`` of plain sums of rewards
    :param final_infos: per episode, the last info dict of every agent
    :param step_infos: per episode (when recorded), agent -> info key -> its value after every step; only the
        numeric entries of the infos are kept
    """

    discounted: dict[str, np.ndarray]
    undiscounted: dict[str, np.ndarray]
    final_infos: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    step_infos: list[dict[str, dict[str, list[float]]]] = field(default_factory=list)

    def mean_discounted(self, agent: str) -> np.ndarray:
        """Mean discounted vector return of ``agent``: the Monte-Carlo estimate of ``V^π``."""
        return self.discounted[agent].mean(axis=0)

    def mean_discounted_over(self, agents: Iterable[str] | None = None) -> np.ndarray:
        """Mean over ``agents`` (default: all of them) of their mean discounted vector returns."""
        return np.mean(
            [self.mean_discounted(agent) for agent in (self.discounted if agents is None else agents)], axis=0
        )

    def mean_undiscounted(self, agent: str) -> np.ndarray:
        """Mean undiscounted vector return of ``agent``."""
        return self.undiscounted[agent].mean(axis=0)


def run_episodes(
    env: ParallelEnv,
    policy: JointPolicy,
    n_episodes: int,
    gamma: float,
    seed: int | None = None,
    record_infos: bool = False,
) -> EpisodeReturns:
    """
    Run full episodes of a PettingZoo ParallelEnv with vector rewards and collect each agent's returns.

    :param env: the env (it is reset, once per episode)
    :param policy: maps the live agents' observations to their actions (and their action masks, where the env
        gives any: :data:`JointPolicy`)
    :param n_episodes: number of episodes
    :param gamma: discount factor of the discounted returns
    :param seed: seed of the first reset (episode ``i`` uses ``seed + i``)
    :param record_infos: also keep the numeric entries of every agent's info after every step
        (:attr:`EpisodeReturns.step_infos`), e.g. waiting times over a traffic episode
    :return: the returns of every agent that was present at reset
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be at least 1, got {n_episodes}")
    discounted: dict[str, list[np.ndarray]] = {}
    undiscounted: dict[str, list[np.ndarray]] = {}
    final_infos = []
    step_infos: list[dict[str, dict[str, list[float]]]] = []
    for episode in range(n_episodes):
        obs, infos = env.reset(seed=None if seed is None else seed + episode)
        check_parallel_reset(env, 0, obs, env.possible_agents)
        agents = list(env.agents)
        dims = {agent: env.reward_space(agent).shape[0] for agent in agents}  # type: ignore[attr-defined]
        disc = {agent: np.zeros(dims[agent]) for agent in agents}
        total = {agent: np.zeros(dims[agent]) for agent in agents}
        last_infos = dict(infos)
        trace: dict[str, dict[str, list[float]]] = {}
        discount = 1.0
        step = 0
        while env.agents:
            live = list(env.agents)
            masks = _live_masks(env, live, infos)
            observations = {agent: obs[agent] for agent in live}
            actions = policy(observations) if masks is None else policy(observations, action_masks=masks)
            obs, rewards, terminations, truncations, infos = env.step(actions)
            step += 1
            check_parallel_step(env, 0, live, (obs, rewards, terminations, truncations), env.agents, step)
            for agent, reward in rewards.items():
                disc[agent] += discount * np.asarray(reward, dtype=np.float64)
                total[agent] += reward
            last_infos.update(infos)
            if record_infos:
                _record_step(trace, infos)
            discount *= gamma
        for agent in agents:
            discounted.setdefault(agent, []).append(disc[agent])
            undiscounted.setdefault(agent, []).append(total[agent])
        final_infos.append(last_infos)
        if record_infos:
            step_infos.append(trace)
    return EpisodeReturns(
        {agent: np.array(values) for agent, values in discounted.items()},
        {agent: np.array(values) for agent, values in undiscounted.items()},
        final_infos,
        step_infos,
    )


def _live_masks(
    env: ParallelEnv, live: list[str], infos: Mapping[str, Mapping[str, Any]]
) -> dict[str, np.ndarray] | None:
    """The live agents' action masks from their last infos, or None where no agent has one."""
    if not any(ACTION_MASK in infos.get(agent, ()) for agent in live):
        return None
    masks = {agent: info_mask(infos.get(agent, {}), env.action_space(agent).n, f"agent {agent!r}") for agent in live}
    return {
        agent: np.ones(env.action_space(agent).n, dtype=bool) if mask is None else mask for agent, mask in masks.items()
    }


def _record_step(trace: dict[str, dict[str, list[float]]], infos: Mapping[str, Mapping[str, Any]]) -> None:
    for agent, info in infos.items():
        columns = trace.setdefault(agent, {})
        for key, value in info.items():
            if isinstance(value, (numbers.Real, np.bool_)):  # bool and numpy scalars included
                columns.setdefault(key, []).append(float(value))
