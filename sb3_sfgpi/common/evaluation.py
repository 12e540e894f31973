"""Monte-Carlo evaluation in multi-agent envs, expected utility and hypervolume."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

#: Maps the observations of the live agents to their actions.
JointPolicy = Callable[[dict[str, Any]], dict[str, Any]]


@dataclass
class EpisodeReturns:
    """
    Vector returns of every agent over several episodes.

    :param discounted: agent -> array ``(n_episodes, d)`` of discounted returns
    :param undiscounted: agent -> array ``(n_episodes, d)`` of plain sums of rewards
    :param final_infos: per episode, the last info dict of every agent
    """

    discounted: dict[str, np.ndarray]
    undiscounted: dict[str, np.ndarray]
    final_infos: list[dict[str, dict[str, Any]]] = field(default_factory=list)

    def mean_discounted(self, agent: str) -> np.ndarray:
        """Mean discounted vector return of ``agent``: the Monte-Carlo estimate of ``V^π``."""
        return self.discounted[agent].mean(axis=0)

    def mean_undiscounted(self, agent: str) -> np.ndarray:
        """Mean undiscounted vector return of ``agent``."""
        return self.undiscounted[agent].mean(axis=0)


def run_episodes(
    env: ParallelEnv,
    policy: JointPolicy,
    n_episodes: int,
    gamma: float,
    seed: int | None = None,
) -> EpisodeReturns:
    """
    Run full episodes of a PettingZoo ParallelEnv with vector rewards and collect each agent's returns.

    :param env: the env (it is reset, once per episode)
    :param policy: maps the live agents' observations to their actions
    :param n_episodes: number of episodes
    :param gamma: discount factor of the discounted returns
    :param seed: seed of the first reset (episode ``i`` uses ``seed + i``)
    :return: the returns of every agent that was present at reset
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be at least 1, got {n_episodes}")
    discounted: dict[str, list[np.ndarray]] = {}
    undiscounted: dict[str, list[np.ndarray]] = {}
    final_infos = []
    for episode in range(n_episodes):
        obs, infos = env.reset(seed=None if seed is None else seed + episode)
        agents = list(env.agents)
        dims = {agent: env.reward_space(agent).shape[0] for agent in agents}  # type: ignore[attr-defined]
        disc = {agent: np.zeros(dims[agent]) for agent in agents}
        total = {agent: np.zeros(dims[agent]) for agent in agents}
        last_infos = dict(infos)
        discount = 1.0
        while env.agents:
            actions = policy({agent: obs[agent] for agent in env.agents})
            obs, rewards, _, _, infos = env.step(actions)
            for agent, reward in rewards.items():
                disc[agent] += discount * np.asarray(reward, dtype=np.float64)
                total[agent] += reward
            last_infos.update(infos)
            discount *= gamma
        for agent in agents:
            discounted.setdefault(agent, []).append(disc[agent])
            undiscounted.setdefault(agent, []).append(total[agent])
        final_infos.append(last_infos)
    return EpisodeReturns(
        {agent: np.array(values) for agent, values in discounted.items()},
        {agent: np.array(values) for agent, values in undiscounted.items()},
        final_infos,
    )


def expected_utility(weights: np.ndarray, returns: np.ndarray) -> float:
    """
    Mean scalarised return ``mean_i w_i · G_i`` over test weights.

    :param weights: shape ``(n, d)``
    :param returns: the vector return obtained for each weight, shape ``(n, d)``
    """
    weights, returns = np.asarray(weights, dtype=np.float64), np.asarray(returns, dtype=np.float64)
    if weights.shape != returns.shape:
        raise ValueError(f"weights {weights.shape} and returns {returns.shape} must have the same shape")
    return float(np.mean(np.sum(weights * returns, axis=1)))


def hypervolume(points: Sequence[np.ndarray] | np.ndarray, reference: Sequence[float] | np.ndarray) -> float:
    """
    Volume dominated by ``points`` (maximisation) and bounded below by ``reference``.

    Exact, by slicing along the last objective; meant for the few dozen points of a coverage set.

    :param points: shape ``(n, d)``
    :param reference: shape ``(d,)``; points not strictly above it in every objective add nothing
    """
    ref = np.asarray(reference, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, ref.shape[0])
    pts = pts[np.all(pts > ref, axis=1)]
    return _hypervolume(pts - ref)


def _hypervolume(pts: np.ndarray) -> float:
    # Points are relative to the reference (all coordinates > 0).
    if len(pts) == 0:
        return 0.0
    if pts.shape[1] == 1:
        return float(pts.max())
    order = np.argsort(-pts[:, -1])
    pts = pts[order]
    volume = 0.0
    for i in range(len(pts)):
        lower = pts[i + 1, -1] if i + 1 < len(pts) else 0.0
        height = pts[i, -1] - lower
        if height > 0:
            volume += height * _hypervolume(pts[: i + 1, :-1])
    return volume
